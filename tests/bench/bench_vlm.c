/* Vision-language models on this machine: image encoder per frame, text
 * encoder per prompt, tokenizer throughput. Models are the small test
 * configurations with random weights (exported here by the user-facing
 * scripts); VLFF_BENCH_FULL=1 adds LSeg ViT-B/16 at 320x256 and CLIP ViT-B
 * text with random weights. Baselines measured in the same run: a bare
 * OpenCV forward of the same model on a prepared blob (what our
 * preprocessing, L2 normalisation and float16 packing add), and for the
 * tokenizer the text transformer's own forward (its share of a prompt). */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include "config.h"
#include "dnn_shim.h"
#include "image_encoder.h"
#include "log.h"
#include "text_encoder.h"
#include "tokenizer.h"

static double now(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (double)ts.tv_sec + ts.tv_nsec * 1e-9;
}

static char dir[128];

static int sh(const char *cmd) {
  char full[2048];
  snprintf(full, sizeof full, "(%s) > %s/export.log 2>&1", cmd, dir);
  int rc = system(full);
  if (rc) fprintf(stderr, "bench_vlm: failed: %s (see %s/export.log)\n", cmd, dir);
  return rc;
}

/* ms per frame of the encoder, and of a bare forward of the same model. */
static int bench_image(const char *model, int w, int h, int dim, int reps, double *ms, double *bare_ms) {
  struct vlff_config cfg;
  vlff_config_defaults(&cfg);
  snprintf(cfg.vlm.image_model, sizeof cfg.vlm.image_model, "%s", model);
  cfg.vlm.input_width = w, cfg.vlm.input_height = h;
  cfg.field.feature_dim = dim;
  char err[512];
  struct vlff_image_encoder *e = vlff_image_encoder_open(&cfg.vlm, cfg.field.feature_dim, err, sizeof err);
  if (!e) {
    fprintf(stderr, "bench_vlm: %s\n", err);
    return -1;
  }
  int d, oh, ow;
  vlff_image_encoder_shape(e, &d, &oh, &ow);
  /* A camera-sized frame, so the resize is part of what is timed. */
  int fw = 640, fh = 480;
  uint8_t *frame = malloc((size_t)fw * fh * 3);
  for (size_t i = 0; i < (size_t)fw * fh * 3; i++) frame[i] = (uint8_t)(i * 2654435761u >> 13);
  uint16_t *out = malloc((size_t)d * oh * ow * sizeof *out);
  vlff_image_encoder_run(e, frame, fw, fh, (size_t)fw * 3, out, err, sizeof err);
  double t0 = now();
  for (int i = 0; i < reps; i++)
    if (vlff_image_encoder_run(e, frame, fw, fh, (size_t)fw * 3, out, err, sizeof err)) return -1;
  *ms = (now() - t0) * 1e3 / reps;
  vlff_image_encoder_close(e);

  struct vlff_dnn *net = vlff_dnn_open(model, false, NULL, err, sizeof err);
  float *blob = calloc((size_t)3 * w * h, sizeof *blob);
  int shape[4] = {1, 3, h, w};
  struct vlff_tensor t;
  vlff_dnn_run(net, blob, shape, 4, &t, 1, err, sizeof err);
  t0 = now();
  for (int i = 0; i < reps; i++) vlff_dnn_run(net, blob, shape, 4, &t, 1, err, sizeof err);
  *bare_ms = (now() - t0) * 1e3 / reps;
  vlff_dnn_close(net);
  printf("image %s: %dx%d -> [%d,%d,%d]: %.2f ms/frame (bare forward %.2f ms)\n", model, w, h, d, oh, ow, *ms,
         *bare_ms);
  free(frame);
  free(out);
  free(blob);
  return 0;
}

static const char *prompts[] = {"wall", "floor", "cabinet", "bed", "chair", "sofa", "table", "door", "window",
                                "bookshelf", "picture", "counter", "desk", "curtain", "refrigerator",
                                "shower curtain", "toilet", "sink", "bathtub", "other furniture"};
#define NP (int)(sizeof prompts / sizeof prompts[0])

static int bench_text(const char *model, const char *bpe, int dim, int width, double *ms, double *hit_us,
                      double *bare_ms) {
  struct vlff_config cfg;
  vlff_config_defaults(&cfg);
  snprintf(cfg.vlm.text_model, sizeof cfg.vlm.text_model, "%s", model);
  snprintf(cfg.vlm.bpe_vocab, sizeof cfg.vlm.bpe_vocab, "%s", bpe);
  snprintf(cfg.prompts.templ, sizeof cfg.prompts.templ, "a photo of a {}.");
  cfg.field.feature_dim = dim;
  char err[512];
  struct vlff_text_encoder *e = vlff_text_encoder_open(&cfg.vlm, cfg.prompts.templ, cfg.field.feature_dim, err, sizeof err);
  if (!e) {
    fprintf(stderr, "bench_vlm: %s\n", err);
    return -1;
  }
  float *emb = malloc((size_t)dim * sizeof *emb);
  double t0 = now();
  for (int i = 0; i < NP; i++)
    if (vlff_text_encoder_encode(e, prompts[i], emb, err, sizeof err)) return -1;
  *ms = (now() - t0) * 1e3 / NP;
  int hits = 0;
  t0 = now();
  for (int r = 0; r < 50; r++)
    for (int i = 0; i < NP; i++, hits++) vlff_text_encoder_encode(e, prompts[i], emb, err, sizeof err);
  *hit_us = (now() - t0) * 1e6 / hits;
  vlff_text_encoder_close(e);

  struct vlff_dnn *net = vlff_dnn_open(model, false, NULL, err, sizeof err);
  float *x = calloc((size_t)77 * width, sizeof *x);
  int shape[3] = {1, 77, width};
  struct vlff_tensor t;
  vlff_dnn_run(net, x, shape, 3, &t, 1, err, sizeof err);
  t0 = now();
  for (int i = 0; i < NP; i++) vlff_dnn_run(net, x, shape, 3, &t, 1, err, sizeof err);
  *bare_ms = (now() - t0) * 1e3 / NP;
  vlff_dnn_close(net);
  printf("text %s: %.2f ms/prompt uncached (bare forward %.2f ms), %.2f us cached\n", model, *ms, *bare_ms, *hit_us);
  free(emb);
  free(x);
  return 0;
}

int main(void) {
  vlff_log_set_level(VLFF_LOG_WARN);
  const char *src = getenv("VLFF_SOURCE_DIR") ? getenv("VLFF_SOURCE_DIR") : VLFF_SOURCE_DEFAULT;
  char bpe[512], cmd[1024];
  snprintf(bpe, sizeof bpe, "%s/node/vlm/data/bpe_simple_vocab_16e6.txt.gz", src);
  snprintf(dir, sizeof dir, "/tmp/vlff-bench-vlm-%d", (int)getpid());
  snprintf(cmd, sizeof cmd, "mkdir -p %s", dir);
  if (system(cmd)) return 1;
  int full = getenv("VLFF_BENCH_FULL") && atoi(getenv("VLFF_BENCH_FULL"));

  /* Tokenizer: every prompt of the reference vectors, many times. */
  char err[512];
  struct vlff_tokenizer *tok = vlff_tokenizer_open(bpe, err, sizeof err);
  if (!tok) {
    fprintf(stderr, "bench_vlm: %s\n", err);
    return 1;
  }
  int32_t ids[77];
  long tokens = 0;
  int reps = 200;
  double t0 = now();
  for (int r = 0; r < reps; r++)
    for (int i = 0; i < NP; i++) tokens += vlff_tokenizer_encode(tok, prompts[i], strlen(prompts[i]), ids, 77, NULL, 0);
  double tok_us = (now() - t0) * 1e6 / (reps * NP);
  vlff_tokenizer_close(tok);
  printf("tokenizer: %.2f us/prompt, %.0f prompts/s, %.0f tokens/s\n", tok_us, 1e6 / tok_us,
         tokens / ((now() - t0)));

  double ims, ibare, tms, thit, tbare;
  snprintf(cmd, sizeof cmd, "/usr/bin/python3 %s/node/vlm/export/export_lseg.py --random --small --out %s/lseg.onnx", src, dir);
  if (sh(cmd) || bench_image(strcat(strcpy(err, dir), "/lseg.onnx"), 64, 64, 32, 50, &ims, &ibare)) return 1;
  snprintf(cmd, sizeof cmd, "/usr/bin/python3 %s/node/vlm/export/export_clip_text.py --random --small --out %s/text.onnx", src, dir);
  if (sh(cmd) || bench_text(strcat(strcpy(err, dir), "/text.onnx"), bpe, 32, 64, &tms, &thit, &tbare)) return 1;
  char extra[512] = "";
  if (full) {
    double fims, fibare, ftms, fthit, ftbare;
    snprintf(cmd, sizeof cmd, "/usr/bin/python3 %s/node/vlm/export/export_lseg.py --random --arch vitb16 --width 320 --height 256 --out %s/lseg-b.onnx", src, dir);
    if (sh(cmd) || bench_image(strcat(strcpy(err, dir), "/lseg-b.onnx"), 320, 256, 512, 3, &fims, &fibare)) return 1;
    snprintf(cmd, sizeof cmd, "/usr/bin/python3 %s/node/vlm/export/export_clip_text.py --random --out %s/text-b.onnx", src, dir);
    if (sh(cmd) || bench_text(strcat(strcpy(err, dir), "/text-b.onnx"), bpe, 512, 512, &ftms, &fthit, &ftbare)) return 1;
    snprintf(extra, sizeof extra, " image_vitb16_320x256_ms=%.1f text_vitb_ms=%.2f", fims, ftms);
  }
  snprintf(cmd, sizeof cmd, "rm -rf %s", dir);
  sh(cmd);
  printf("RESULT image_small_ms=%.3f image_vs_bare_forward=%.3f text_small_ms=%.3f text_vs_bare_forward=%.3f "
         "text_cached_us=%.2f tokenizer_us=%.2f tokenizer_vs_text_forward=%.4f%s\n",
         ims, ims / ibare, tms, tms / tbare, thit, tok_us, tok_us * 1e-3 / tbare, extra);
  return 0;
}
