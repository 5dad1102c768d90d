/* Image and text encoders: small random LSeg / CLIP-text models exported
 * by our scripts, run in OpenCV through our C code, compared with PyTorch.
 * Also bad model files and the shape/D validation. */
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include <sys/stat.h>
#include <cmocka.h>

#include "config.h"
#include "field.h"
#include "image_encoder.h"
#include "text_encoder.h"
#include "tokenizer.h"
#include "unit.h"
#include "vlm_fixture.h"

static bool have_torch;
static const char *dir;
static char export_dir[512];

static int setup(void **state) {
  have_torch = fixture_have_torch();
  if (!have_torch) return 0;
  dir = fixture_dir("enc");
  snprintf(export_dir, sizeof export_dir, "%s/node/vlm/export", getenv("VLFF_SOURCE_DIR"));
  return 0;
}

static int teardown(void **state) {
  if (have_torch) fixture_cleanup();
  return 0;
}

#define SKIP_WITHOUT_TORCH() \
  do {                       \
    if (!have_torch) skip(); \
  } while (0)

static void image_config(struct vlff_config *cfg) {
  vlff_config_defaults(cfg);
  snprintf(cfg->vlm.image_model, sizeof cfg->vlm.image_model, "%s/lseg.onnx", dir);
  cfg->vlm.input_width = cfg->vlm.input_height = 64;
  for (int c = 0; c < 3; c++) cfg->vlm.mean[c] = cfg->vlm.std[c] = 0.5;
  cfg->field.feature_dim = 32;
}

static void export_image(void) {
  char cmd[2048];
  snprintf(cmd, sizeof cmd, "/usr/bin/python3 %s/export_lseg.py --random --small --seed 3 --out %s/lseg.onnx --reference %s/ref",
           export_dir, dir, dir);
  fixture_run(cmd);
}

/* PyTorch's [D,h,w] against our float16 [h][w][D]. */
static void compare_image(const uint16_t *got, const float *ref, int d, int h, int w, bool normalize) {
  double worst = 0;
  for (int p = 0; p < h * w; p++) {
    double ss = 0;
    for (int c = 0; c < d; c++) ss += (double)ref[c * h * w + p] * ref[c * h * w + p];
    double s = normalize ? 1.0 / sqrt(ss) : 1.0;
    for (int c = 0; c < d; c++) {
      double want = ref[c * h * w + p] * s, have = vlff_f16_to_f32(got[p * d + c]);
      double err = fabs(want - have) / (1e-3 + 1e-3 * fabs(want)); /* float16 keeps ~4.9e-4 relative */
      if (err > worst) worst = err;
    }
  }
  print_message("image encoder vs PyTorch: worst error %.3f of tolerance (normalize=%d)\n", worst, normalize);
  assert_true(worst <= 1.0);
}

static void test_image_matches_pytorch(void **state) {
  SKIP_WITHOUT_TORCH();
  export_image();
  char path[600];
  size_t n;
  snprintf(path, sizeof path, "%s/ref/image.rgb", dir);
  uint8_t *img = (uint8_t *)fixture_read(path, &n);
  assert_int_equal(n, 64 * 64 * 3);
  snprintf(path, sizeof path, "%s/ref/image_ref.f32", dir);
  float *ref = (float *)fixture_read(path, &n);
  assert_int_equal(n, 32 * 32 * 32 * sizeof(float));

  struct vlff_config cfg;
  image_config(&cfg);
  char err[512];
  uint16_t *out = malloc(32 * 32 * 32 * sizeof *out), *out2 = malloc(32 * 32 * 32 * sizeof *out);
  for (int norm = 0; norm < 2; norm++) {
    cfg.vlm.normalize = norm;
    struct vlff_image_encoder *e = vlff_image_encoder_open(&cfg.vlm, cfg.field.feature_dim, err, sizeof err);
    if (!e) fail_msg("%s", err);
    int d, h, w;
    vlff_image_encoder_shape(e, &d, &h, &w);
    assert_int_equal(d, 32);
    assert_int_equal(h, 32);
    assert_int_equal(w, 32);
    assert_int_equal(vlff_image_encoder_run(e, img, 64, 64, 64 * 3, out, err, sizeof err), 0);
    compare_image(out, ref, 32, 32, 32, norm);
    /* A padded row stride gives the same features. */
    uint8_t *padded = calloc(64 * 200, 1);
    for (int y = 0; y < 64; y++) memcpy(padded + y * 200, img + y * 192, 192);
    assert_int_equal(vlff_image_encoder_run(e, padded, 64, 64, 200, out2, err, sizeof err), 0);
    assert_memory_equal(out, out2, 32 * 32 * 32 * sizeof *out);
    free(padded);
    /* Other frame sizes are resized to the model's input. */
    uint8_t *big = malloc(100 * 80 * 3);
    for (int i = 0; i < 100 * 80 * 3; i++) big[i] = (uint8_t)(i * 7);
    assert_int_equal(vlff_image_encoder_run(e, big, 100, 80, 300, out2, err, sizeof err), 0);
    free(big);
    assert_int_equal(vlff_image_encoder_run(e, img, 0, 64, 0, out2, err, sizeof err), -1);
    vlff_image_encoder_close(e);
  }
  /* BGR order with swapped statistics feeds the model the same tensor. */
  cfg.vlm.bgr = true;
  cfg.vlm.mean[0] = 0.25;
  cfg.vlm.std[0] = 0.7;
  struct vlff_image_encoder *e = vlff_image_encoder_open(&cfg.vlm, cfg.field.feature_dim, err, sizeof err);
  assert_non_null(e);
  uint8_t *swapped = malloc(64 * 64 * 3);
  for (int i = 0; i < 64 * 64; i++)
    swapped[i * 3] = img[i * 3 + 2], swapped[i * 3 + 1] = img[i * 3 + 1], swapped[i * 3 + 2] = img[i * 3];
  assert_int_equal(vlff_image_encoder_run(e, swapped, 64, 64, 192, out2, err, sizeof err), 0);
  vlff_image_encoder_close(e);
  cfg.vlm.bgr = false;
  cfg.vlm.mean[0] = 0.5, cfg.vlm.std[0] = 0.5;
  cfg.vlm.mean[2] = 0.25, cfg.vlm.std[2] = 0.7;
  e = vlff_image_encoder_open(&cfg.vlm, cfg.field.feature_dim, err, sizeof err);
  assert_non_null(e);
  assert_int_equal(vlff_image_encoder_run(e, img, 64, 64, 192, out, err, sizeof err), 0);
  vlff_image_encoder_close(e);
  assert_memory_equal(out, out2, 32 * 32 * 32 * sizeof *out);
  free(swapped);
  free(out);
  free(out2);
  free(img);
  free(ref);
}

static void expect_image_refused(struct vlff_config *cfg, const char *what) {
  char err[512] = "";
  struct vlff_image_encoder *e = vlff_image_encoder_open(&cfg->vlm, cfg->field.feature_dim, err, sizeof err);
  if (e) fail_msg("accepted a bad image model (expected: %s)", what);
  if (!strstr(err, what)) fail_msg("error '%s' lacks '%s'", err, what);
  print_message("refused as expected: %s\n", err);
}

static void test_image_bad_models(void **state) {
  SKIP_WITHOUT_TORCH();
  struct vlff_config cfg;
  image_config(&cfg);
  cfg.field.feature_dim = 64;
  expect_image_refused(&cfg, "D=32, but field.feature_dim is 64");
  image_config(&cfg);
  cfg.vlm.input_width = 96; /* the model's position grid is fixed at 64x64 */
  expect_image_refused(&cfg, "probe inference at 96x64");
  image_config(&cfg);
  snprintf(cfg.vlm.image_model, sizeof cfg.vlm.image_model, "%s/missing.onnx", dir);
  expect_image_refused(&cfg, "missing.onnx");
  char path[600];
  snprintf(path, sizeof path, "%s/lseg.onnx", dir);
  size_t n;
  char *model = fixture_read(path, &n);
  snprintf(cfg.vlm.image_model, sizeof cfg.vlm.image_model, "%s/truncated.onnx", dir);
  FILE *f = fopen(cfg.vlm.image_model, "wb");
  fwrite(model, 1, n / 2, f);
  fclose(f);
  expect_image_refused(&cfg, "truncated.onnx");
  snprintf(cfg.vlm.image_model, sizeof cfg.vlm.image_model, "%s/garbage.onnx", dir);
  f = fopen(cfg.vlm.image_model, "wb");
  for (size_t i = 0; i < 5000; i++) fputc((int)(i * 131 % 251), f);
  fclose(f);
  expect_image_refused(&cfg, "garbage.onnx");
  free(model);
  /* A FIFO or a directory at the model's name: refused, never waited on. */
  snprintf(cfg.vlm.image_model, sizeof cfg.vlm.image_model, "%s/fifo.onnx", dir);
  assert_int_equal(mkfifo(cfg.vlm.image_model, 0600), 0);
  expect_image_refused(&cfg, "fifo.onnx: is a FIFO, expected a regular file");
  unlink(cfg.vlm.image_model);
  snprintf(cfg.vlm.image_model, sizeof cfg.vlm.image_model, "%s", dir);
  expect_image_refused(&cfg, "is a directory, expected a regular file");
  /* The text model is a valid ONNX file with the wrong contract. */
  image_config(&cfg);
  snprintf(cfg.vlm.image_model, sizeof cfg.vlm.image_model, "%s/text.onnx", dir);
  expect_image_refused(&cfg, "text.onnx");
}

static const char *prompts[] = {"chair", "a photo of a chair.", "there's a red mug on the desk, isn't there?",
                                "shower curtain", "a photo of a table."};
#define NPROMPTS 5

static void text_config(struct vlff_config *cfg) {
  vlff_config_defaults(cfg);
  snprintf(cfg->vlm.text_model, sizeof cfg->vlm.text_model, "%s/text.onnx", dir);
  snprintf(cfg->vlm.bpe_vocab, sizeof cfg->vlm.bpe_vocab, "%s/bpe_simple_vocab_16e6.txt.gz",
           getenv("VLFF_DATA_DIR"));
  cfg->field.feature_dim = 32;
}

static void test_text_matches_pytorch(void **state) {
  SKIP_WITHOUT_TORCH();
  struct vlff_config cfg;
  text_config(&cfg);
  char err[512];
  struct vlff_tokenizer *tok = vlff_tokenizer_open(cfg.vlm.bpe_vocab, err, sizeof err);
  assert_non_null(tok);
  char path[600];
  snprintf(path, sizeof path, "%s/tokens.txt", dir);
  FILE *f = fopen(path, "w");
  for (int i = 0; i < NPROMPTS; i++) {
    int32_t ids[VLFF_CLIP_CONTEXT];
    assert_true(vlff_tokenizer_context(tok, prompts[i], ids, err, sizeof err) > 0);
    for (int j = 0; j < VLFF_CLIP_CONTEXT; j++) fprintf(f, "%d%c", ids[j], j + 1 < VLFF_CLIP_CONTEXT ? ' ' : '\n');
  }
  fclose(f);
  vlff_tokenizer_close(tok);
  char cmd[2048];
  snprintf(cmd, sizeof cmd,
           "/usr/bin/python3 %s/export_clip_text.py --random --small --seed 5 --out %s/text.onnx "
           "--reference-tokens %s --reference-out %s/text_ref.f32",
           export_dir, dir, path, dir);
  fixture_run(cmd);
  snprintf(path, sizeof path, "%s/text_ref.f32", dir);
  size_t n;
  float *ref = (float *)fixture_read(path, &n);
  assert_int_equal(n, NPROMPTS * 32 * sizeof(float));

  struct vlff_text_encoder *e = vlff_text_encoder_open(&cfg.vlm, cfg.prompts.templ, cfg.field.feature_dim, err, sizeof err);
  if (!e) fail_msg("%s", err);
  assert_int_equal(vlff_text_encoder_dim(e), 32);
  float emb[32];
  double worst = 0;
  for (int i = 0; i < NPROMPTS; i++) {
    assert_int_equal(vlff_text_encoder_encode(e, prompts[i], emb, err, sizeof err), 0);
    double ss = 0;
    for (int j = 0; j < 32; j++) ss += (double)ref[i * 32 + j] * ref[i * 32 + j];
    for (int j = 0; j < 32; j++) {
      double d = fabs(emb[j] - ref[i * 32 + j] / sqrt(ss));
      if (d > worst) worst = d;
    }
  }
  print_message("text encoder vs PyTorch: worst abs error %.2e on unit vectors\n", worst);
  assert_true(worst < 1e-4);
  /* Distinct prompts give distinct embeddings (a constant output fails). */
  float other[32];
  assert_int_equal(vlff_text_encoder_encode(e, "chair", emb, err, sizeof err), 0);
  assert_int_equal(vlff_text_encoder_encode(e, "shower curtain", other, err, sizeof err), 0);
  double dot = 0;
  for (int j = 0; j < 32; j++) dot += emb[j] * other[j];
  assert_true(dot < 0.999);
  long hits, misses;
  vlff_text_encoder_cache_stats(e, &hits, &misses);
  assert_int_equal(hits, 2);
  assert_int_equal(misses, NPROMPTS);
  assert_int_equal(vlff_text_encoder_encode(e, "chair <|endoftext|> table", emb, err, sizeof err), -1);
  assert_non_null(strstr(err, "special token"));
  assert_int_equal(vlff_text_encoder_encode(e, "bad \xff utf8", emb, err, sizeof err), -1);
  vlff_text_encoder_close(e);

  /* Template: "a photo of a {}." + "chair" is the second reference prompt. */
  snprintf(cfg.prompts.templ, sizeof cfg.prompts.templ, "a photo of a {}.");
  e = vlff_text_encoder_open(&cfg.vlm, cfg.prompts.templ, cfg.field.feature_dim, err, sizeof err);
  assert_non_null(e);
  assert_int_equal(vlff_text_encoder_encode(e, "chair", emb, err, sizeof err), 0);
  double ss = 0;
  for (int j = 0; j < 32; j++) ss += (double)ref[32 + j] * ref[32 + j];
  for (int j = 0; j < 32; j++) assert_true(fabs(emb[j] - ref[32 + j] / sqrt(ss)) < 1e-4);
  vlff_text_encoder_close(e);
  free(ref);
}

static void expect_text_refused(struct vlff_config *cfg, const char *what) {
  char err[512] = "";
  struct vlff_text_encoder *e = vlff_text_encoder_open(&cfg->vlm, cfg->prompts.templ, cfg->field.feature_dim, err, sizeof err);
  if (e) fail_msg("accepted a bad text model (expected: %s)", what);
  if (!strstr(err, what)) fail_msg("error '%s' lacks '%s'", err, what);
  print_message("refused as expected: %s\n", err);
}

static void test_text_bad_models(void **state) {
  SKIP_WITHOUT_TORCH();
  struct vlff_config cfg;
  text_config(&cfg);
  cfg.field.feature_dim = 512;
  expect_text_refused(&cfg, "D=32, but field.feature_dim is 512");
  text_config(&cfg);
  snprintf(cfg.vlm.bpe_vocab, sizeof cfg.vlm.bpe_vocab, "%s/nope.gz", dir);
  expect_text_refused(&cfg, "nope.gz");
  /* The image model with the text table beside it: wrong contract. */
  text_config(&cfg);
  char cmd[1400];
  snprintf(cmd, sizeof cmd, "cp %s/text.onnx.tokemb %s/lseg.onnx.tokemb", dir, dir);
  fixture_run(cmd);
  snprintf(cfg.vlm.text_model, sizeof cfg.vlm.text_model, "%s/lseg.onnx", dir);
  expect_text_refused(&cfg, "probe inference failed");
  /* Truncated token table. */
  snprintf(cmd, sizeof cmd, "cp %s/text.onnx %s/t2.onnx && head -c 100000 %s/text.onnx.tokemb > %s/t2.onnx.tokemb", dir,
           dir, dir, dir);
  fixture_run(cmd);
  snprintf(cfg.vlm.text_model, sizeof cfg.vlm.text_model, "%s/t2.onnx", dir);
  expect_text_refused(&cfg, "truncated token-embedding table");
  snprintf(cmd, sizeof cmd, "rm %s/t2.onnx.tokemb", dir);
  fixture_run(cmd);
  expect_text_refused(&cfg, "cannot open token-embedding table");
  /* A FIFO in place of the token table and of the BPE merges. */
  char fifo[700];
  snprintf(fifo, sizeof fifo, "%s/t2.onnx.tokemb", dir);
  assert_int_equal(mkfifo(fifo, 0600), 0);
  expect_text_refused(&cfg, "t2.onnx.tokemb: is a FIFO, expected a regular file");
  unlink(fifo);
  text_config(&cfg);
  snprintf(cfg.vlm.bpe_vocab, sizeof cfg.vlm.bpe_vocab, "%s/fifo.gz", dir);
  assert_int_equal(mkfifo(cfg.vlm.bpe_vocab, 0600), 0);
  expect_text_refused(&cfg, "fifo.gz: is a FIFO, expected a regular file");
  unlink(cfg.vlm.bpe_vocab);
}

VLFF_UNIT_MAIN(setup, teardown,
    cmocka_unit_test(test_image_matches_pytorch), cmocka_unit_test(test_text_matches_pytorch),
    cmocka_unit_test(test_image_bad_models), cmocka_unit_test(test_text_bad_models))
