/*
 * Forged and diverged learned state (issue 51 item 7). A checkpoint written
 * by the real trainer, then forged (a NaN parameter, a negative Adam second
 * moment, 3e38 values, a step count near INT64_MAX) with its checksum
 * recomputed the way the format does, is refused with the file, the tensor
 * and the index named, and the field it was loaded into stays as it was;
 * the genuine file still loads. Before, each one resumed: the loss went NaN
 * (the status read PSNR 100.000) and the huge step overflowed the step
 * counter. A live field whose own parameters go non-finite applies no
 * update, says so, is never checkpointed, and rolls back to the newest
 * checkpoint that loads (or re-initialises), after which it trains and
 * checkpoints finite values again.
 */
#include <fcntl.h>
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#include <cmocka.h>

#include "field_internal.h"
#include "small_field.h"
#include "unit.h"

/* The checkpoint's checksum as docs/field.md states it: 64-bit words (host
 * order, the tail zero-padded and tagged with its length) mixed as h ^= w,
 * h *= FNV prime, h ^= h >> 29, from the FNV offset basis. */
static uint64_t ckpt_sum(const unsigned char *p, size_t n) {
  uint64_t h = 0xcbf29ce484222325ull;
  for (size_t i = 0;; i += 8) {
    uint64_t w = 0;
    size_t k = n - i < 8 ? n - i : 8;
    memcpy(&w, p + i, k);
    if (k < 8) w ^= (uint64_t)k << 56;
    h ^= w;
    h *= 0x100000001b3ull;
    h ^= h >> 29;
    if (k < 8) return h;
  }
}

static unsigned char *read_file(const char *path, size_t *len) {
  FILE *in = fopen(path, "rb");
  assert_non_null(in);
  assert_int_equal(fseek(in, 0, SEEK_END), 0);
  long size = ftell(in);
  assert_true(size > 0);
  rewind(in);
  unsigned char *b = malloc((size_t)size);
  assert_non_null(b);
  assert_int_equal(fread(b, 1, (size_t)size, in), (size_t)size);
  fclose(in);
  *len = (size_t)size;
  return b;
}

/* Writes b with len - 8 bytes of body and its checksum recomputed into the
 * last 8, as a forger who knows the format would. */
static void write_forged(const char *path, unsigned char *b, size_t len) {
  uint64_t sum = ckpt_sum(b, len - 8);
  memcpy(b + len - 8, &sum, 8);
  FILE *out = fopen(path, "wb");
  assert_non_null(out);
  assert_int_equal(fwrite(b, 1, len, out), len);
  assert_int_equal(fclose(out), 0);
}

/* The file layout (checkpoint.c): an 80-byte header (the step at byte 48),
 * params, Adam m, Adam v (float32 each), the occupancy density (float32),
 * ... then the averaged MLP weights. */
enum { HDR = 128, STEP_AT = 48 }; /* the header, the box and the cells' size (version 7) */

struct forgery {
  const char *what;
  size_t at;       /* byte offset in the file */
  int is_step;     /* an int64 step, else a float */
  float value;
  long long step;
  const char *named[3]; /* what the error must say besides the file */
};

static void test_forged(void **state) {
  (void)state;
  struct vlff_config cfg;
  cfg_small(&cfg);
  struct vlff_field *f = trained(&cfg, 20);
  char good[512], path[512], err[1024];
  tmp_path(good, sizeof good, "good");
  tmp_path(path, sizeof path, "forged");
  assert_int_equal(vlff_field_save(f, good, err, sizeof err), 0);
  size_t len;
  unsigned char *b = read_file(good, &len);
  const size_t np = f->nparams, nc = vlff_occ_cells(&f->occ), fs = sizeof(float);
  const size_t p0 = HDR, m0 = p0 + np * fs, v0 = m0 + np * fs, d0 = v0 + np * fs;
  const size_t avg0 = d0 + nc * fs + nc + nc * sizeof(uint16_t);
  /* The step sits where the layout says. */
  int64_t step;
  memcpy(&step, b + STEP_AT, 8);
  assert_int_equal(step, 20);
  const size_t tab = 37, mlp = f->ntable + 5; /* an index in the hash table, one in the MLPs */
  char ti[32], mi[32], mi_avg[32];
  snprintf(ti, sizeof ti, "[%zu] (hash table)", tab);
  snprintf(mi, sizeof mi, "[%zu] (MLP weights)", mlp);
  snprintf(mi_avg, sizeof mi_avg, "avg[%d] (MLP weights)", 5);
  const struct forgery forged[] = {
      {"NaN parameter", p0 + tab * fs, 0, NAN, 0, {"params", ti, "not finite"}},
      {"3e38 parameter", p0 + mlp * fs, 0, 3e38f, 0, {"params", mi, "outside [-1e+06, 1e+06]"}},
      {"infinite parameter", p0 + mlp * fs, 0, -INFINITY, 0, {"params", mi, "not finite"}},
      {"3e38 first moment", m0 + tab * fs, 0, 3e38f, 0, {"adam_m", ti, "= 3e+38"}},
      {"NaN first moment", m0 + mlp * fs, 0, NAN, 0, {"adam_m", mi, "not finite"}},
      {"negative second moment", v0 + mlp * fs, 0, -1.0f, 0, {"adam_v", mi, "= -1, outside [0, 1e+16]"}},
      {"3e38 second moment", v0 + tab * fs, 0, 3e38f, 0, {"adam_v", ti, "outside [0, 1e+16]"}},
      {"NaN averaged weight", avg0 + 5 * fs, 0, NAN, 0, {mi_avg, "not finite", ""}},
      {"NaN occupancy density", d0 + 3 * fs, 0, NAN, 0, {"occupancy density[3]", "not finite", ""}},
      {"step near INT64_MAX", STEP_AT, 1, 0, INT64_MAX - 5, {"step 9223372036854775802 outside [0, 1099511627776]", "", ""}},
      {"step just past 2^40", STEP_AT, 1, 0, (1LL << 40) + 1, {"step 1099511627777 outside", "", ""}},
      {"negative step", STEP_AT, 1, 0, -3, {"step -3 outside", "", ""}},
  };
  struct vlff_field *young = trained(&cfg, 3), *ref = trained(&cfg, 3);
  unsigned char *bad = malloc(len);
  assert_non_null(bad);
  for (size_t q = 0; q < sizeof forged / sizeof forged[0]; q++) {
    const struct forgery *fg = &forged[q];
    memcpy(bad, b, len);
    if (fg->is_step) {
      int64_t s = fg->step;
      memcpy(bad + fg->at, &s, 8);
    } else {
      memcpy(bad + fg->at, &fg->value, fs);
    }
    write_forged(path, bad, len);
    err[0] = 0;
    int rc = vlff_field_load(young, path, err, sizeof err);
    print_message("%s: %s\n", fg->what, rc ? err : "LOADED");
    assert_int_equal(rc, -1);
    assert_non_null(strstr(err, path));
    assert_non_null(strstr(err, "refused"));
    for (int k = 0; k < 3; k++) assert_non_null(strstr(err, fg->named[k]));
    /* Left as it was: the same steps, the same answers, and it trains on. */
    assert_int_equal(vlff_field_steps(young), 3);
    assert_true(same_queries(young, ref));
  }
  struct vlff_train_stats st;
  assert_int_equal(vlff_field_step(young, views, NV, NULL, &st, err, sizeof err), 0);
  assert_int_equal(vlff_field_steps(young), 4);
  assert_true(isfinite(st.loss));
  /* The genuine file, unchanged, loads. */
  assert_int_equal(vlff_field_load(young, good, err, sizeof err), 0);
  assert_int_equal(vlff_field_steps(young), 20);
  assert_true(same_queries(young, f));
  unlink(good);
  unlink(path);
  free(bad);
  free(b);
  vlff_field_destroy(young);
  vlff_field_destroy(ref);
  vlff_field_destroy(f);
}

/* What an absurd but allowed learning rate makes (the demo at train.lr 10 held
 * |Adam m| of 1.2e4 after 1,200 steps, with a finite loss and a useful map) is
 * no forgery: it saves and resumes. The first bounds (1e4) threw such a field
 * away at the node's stop. */
static void test_large_state_kept(void **state) {
  (void)state;
  struct vlff_config cfg;
  cfg_small(&cfg);
  struct vlff_field *f = trained(&cfg, 5);
  char err[512], path[256];
  tmp_path(path, sizeof path, "large");
  const size_t tab = 37, mlp = f->ntable + 5;
  f->params[tab] = 5e4f;
  f->params[mlp] = -2e4f;
  f->adam_m[tab] = -1.2e4f;
  f->adam_v[mlp] = 1.5e8f;
  assert_int_equal(vlff_field_check(f, err, sizeof err), 0);
  if (vlff_field_save(f, path, err, sizeof err) != 0)
    fail_msg("save: %s", err);
  struct vlff_field *back = trained(&cfg, 0);
  if (vlff_field_load(back, path, err, sizeof err) != 0)
    fail_msg("load: %s", err);
  assert_true(back->params[tab] == 5e4f && back->adam_m[tab] == -1.2e4f && back->adam_v[mlp] == 1.5e8f);
  vlff_field_destroy(back);
  vlff_field_destroy(f);
  unlink(path);
}

/* Every value of the field's state within the bounds of field.h. */
static void assert_state_finite(const struct vlff_field *f) {
  for (size_t i = 0; i < f->nparams; i++) {
    assert_true(isfinite(f->params[i]) && fabsf(f->params[i]) <= VLFF_FIELD_MAX_PARAM);
    assert_true(isfinite(f->adam_m[i]) && fabsf(f->adam_m[i]) <= VLFF_FIELD_MAX_MOMENT1);
    assert_true(f->adam_v[i] >= 0 && f->adam_v[i] <= VLFF_FIELD_MAX_MOMENT2);
  }
  for (size_t i = 0; i < f->nmlp; i++) assert_true(isfinite(f->avg[i]));
}

/* Make sure a file's modification time orders after an earlier one's, on
 * file systems with coarse timestamps. */
static void set_mtime(const char *path, time_t t) {
  struct timespec ts[2] = {{t, 0}, {t, 0}};
  assert_int_equal(utimensat(AT_FDCWD, path, ts, 0), 0);
}

static void test_rollback(void **state) {
  (void)state;
  struct vlff_config cfg;
  cfg_small(&cfg);
  char older[512], newer[512], err[1024];
  tmp_path(older, sizeof older, "older");
  tmp_path(newer, sizeof newer, "newer");
  unlink(older);
  unlink(newer);
  struct vlff_field *f = trained(&cfg, 10);
  assert_int_equal(vlff_field_save(f, older, err, sizeof err), 0);
  for (int i = 0; i < 5; i++) assert_int_equal(vlff_field_step(f, views, NV, NULL, NULL, err, sizeof err), 0);
  assert_int_equal(vlff_field_save(f, newer, err, sizeof err), 0);
  set_mtime(older, time(NULL) - 20);
  set_mtime(newer, time(NULL) - 10);
  struct vlff_field *at15 = trained(&cfg, 15);
  assert_true(same_queries(f, at15));
  for (int i = 0; i < 3; i++) assert_int_equal(vlff_field_step(f, views, NV, NULL, NULL, err, sizeof err), 0);

  /* A non-finite bias of the colour head's output, which every shaded
   * sample passes through: the next step's loss is NaN. No update is applied (no NaN
   * moment anywhere), the step count stays, and the PSNR says NaN rather
   * than the 100 dB its floor gave a NaN error. */
  const size_t poisoned = f->ntable + f->m2.boff[f->m2.nl - 1] + 1;
  f->params[poisoned] = NAN;
  struct vlff_train_stats st;
  memset(&st, 0, sizeof st);
  float m_before = f->adam_m[f->ntable + 7];
  assert_int_equal(vlff_field_step(f, views, NV, NULL, &st, err, sizeof err), -2);
  print_message("poisoned step: %s (loss %g, psnr %g)\n", err, st.loss, st.psnr);
  assert_non_null(strstr(err, "loss is not finite"));
  assert_non_null(strstr(err, "no update applied"));
  assert_false(isfinite(st.loss));
  assert_false(st.psnr > 99.0);
  assert_true(isnan(st.psnr));
  assert_int_equal(vlff_field_steps(f), 18);
  assert_true(f->adam_m[f->ntable + 7] == m_before);
  for (size_t i = 0; i < f->nparams; i++) assert_true(isfinite(f->adam_m[i]) && isfinite(f->adam_v[i]));
  /* The scan names it; the field is never checkpointed. */
  assert_int_equal(vlff_field_check(f, err, sizeof err), -1);
  char idx[64];
  snprintf(idx, sizeof idx, "params[%zu] (MLP weights) = nan, not finite", poisoned);
  assert_non_null(strstr(err, idx));
  char fresh[512];
  tmp_path(fresh, sizeof fresh, "fresh");
  unlink(fresh);
  assert_int_equal(vlff_field_save(f, fresh, err, sizeof err), -1);
  assert_non_null(strstr(err, "not written"));
  assert_non_null(strstr(err, idx));
  assert_int_equal(access(fresh, F_OK), -1);
  assert_int_equal(vlff_field_save(f, newer, err, sizeof err), -1); /* the good one stays */

  /* Rolled back to the newest checkpoint (step 15), which trains on and
   * checkpoints finite values. */
  const char *paths[3] = {older, fresh, newer};
  assert_int_equal(vlff_field_rollback(f, paths, 3, err, sizeof err), 2);
  assert_string_equal(err, "");
  assert_int_equal(vlff_field_steps(f), 15);
  assert_true(same_queries(f, at15));
  assert_int_equal(vlff_field_check(f, err, sizeof err), 0);
  for (int i = 0; i < 5; i++) {
    assert_int_equal(vlff_field_step(f, views, NV, NULL, &st, err, sizeof err), 0);
    assert_true(isfinite(st.loss) && isfinite(st.psnr));
  }
  assert_int_equal(vlff_field_save(f, fresh, err, sizeof err), 0);
  struct vlff_field *back = trained(&cfg, 0);
  assert_int_equal(vlff_field_load(back, fresh, err, sizeof err), 0);
  assert_int_equal(vlff_field_steps(back), 20);
  assert_state_finite(back);
  vlff_field_destroy(back);
  unlink(fresh);

  /* A poisoned second moment of a table entry no ray may reach: the steps'
   * losses stay finite, the checkpoint-time scan finds it. With the newest
   * file now refused, the rollback takes the older one and says why. */
  f->adam_v[11] = -1.0f;
  assert_int_equal(vlff_field_check(f, err, sizeof err), -1);
  assert_non_null(strstr(err, "adam_v[11] (hash table) = -1"));
  {
    size_t len;
    unsigned char *b = read_file(newer, &len);
    float nan = NAN;
    memcpy(b + HDR + 2 * sizeof(float), &nan, sizeof nan);
    write_forged(newer, b, len);
    free(b);
    set_mtime(newer, time(NULL) - 10);
  }
  assert_int_equal(vlff_field_rollback(f, paths, 3, err, sizeof err), 0);
  assert_non_null(strstr(err, newer));
  assert_non_null(strstr(err, "params[2] (hash table) = nan"));
  assert_int_equal(vlff_field_steps(f), 10);
  assert_int_equal(vlff_field_check(f, err, sizeof err), 0);

  /* No checkpoint loads: re-initialised, the field a new one is, and it
   * trains. */
  unlink(older);
  f->params[poisoned] = INFINITY;
  assert_int_equal(vlff_field_rollback(f, paths, 3, err, sizeof err), -1);
  struct vlff_field *new_field = trained(&cfg, 0);
  assert_int_equal(vlff_field_steps(f), 0);
  assert_true(same_queries(f, new_field));
  assert_memory_equal(f->params, new_field->params, f->nparams * sizeof(float));
  assert_memory_equal(f->adam_v, new_field->adam_v, f->nparams * sizeof(float));
  for (int i = 0; i < 3; i++) assert_int_equal(vlff_field_step(f, views, NV, NULL, NULL, err, sizeof err), 0);
  assert_int_equal(vlff_field_check(f, err, sizeof err), 0);
  vlff_field_destroy(new_field);
  unlink(newer);
  vlff_field_destroy(at15);
  vlff_field_destroy(f);
}

VLFF_UNIT_MAIN(setup, teardown, cmocka_unit_test(test_forged), cmocka_unit_test(test_rollback), cmocka_unit_test(test_large_state_kept))
