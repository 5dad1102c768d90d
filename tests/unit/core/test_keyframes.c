/* Keyframe store: budget, redundancy eviction, protection of new views, weights. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/resource.h>
#include <unistd.h>
#include <cmocka.h>

#include "keyframes.h"
#include "unit.h"

enum { W = 8, H = 6, FW = 2, FH = 2, D = 4 };
static uint8_t rgb[W * H * 3];
static float depth[W * H];
static uint16_t feat[FW * FH * D];

static struct vlff_keyframe_in make(long long id, double x, double y) {
  struct vlff_keyframe_in k;
  memset(&k, 0, sizeof k);
  k.id = id;
  k.feature_dim = D;
  k.view.width = W;
  k.view.height = H;
  k.view.rgb = rgb;
  k.view.depth = depth;
  k.view.feat_width = FW;
  k.view.feat_height = FH;
  k.view.features = feat;
  for (int i = 0; i < 4; i++) k.view.c2w[i * 5] = 1;
  k.view.c2w[3] = x;
  k.view.c2w[7] = y;
  memset(rgb, (int)id, sizeof rgb);
  return k;
}

static int has_id(struct vlff_kfstore *s, long long id) {
  for (int i = 0; i < vlff_kfstore_count(s); i++)
    if (vlff_kfstore_id(s, i) == id) return 1;
  return 0;
}

static void test_budget_and_copy(void **st) {
  (void)st;
  size_t cost = vlff_kfstore_cost(W, H, FW, FH, D, 1);
  struct vlff_kfstore *s = vlff_kfstore_create(cost * 3, 100, 1);
  assert_non_null(s);
  for (int i = 0; i < 10; i++) {
    struct vlff_keyframe_in k = make(i, i, 0);
    assert_int_equal(vlff_kfstore_add(s, &k), 0);
    assert_true(vlff_kfstore_bytes(s) <= cost * 3);
  }
  assert_int_equal(vlff_kfstore_count(s), 3);
  assert_int_equal(vlff_kfstore_evicted(s), 7);
  const struct vlff_view *v;
  const float *w;
  int n = vlff_kfstore_views(s, 1, &v, &w);
  assert_int_equal(n, 3);
  /* The store copied the pixels: the newest keeps its own value. */
  assert_int_equal(v[2].rgb[0], 9);
  assert_ptr_not_equal(v[2].rgb, rgb);
  /* A keyframe larger than the budget is refused. */
  struct vlff_kfstore *tiny = vlff_kfstore_create(10, 10, 1);
  struct vlff_keyframe_in k = make(1, 0, 0);
  assert_int_equal(vlff_kfstore_add(tiny, &k), -1);
  vlff_kfstore_destroy(tiny);
  vlff_kfstore_destroy(s);
}

static void test_redundant_view_goes(void **st) {
  (void)st;
  struct vlff_kfstore *s = vlff_kfstore_create(1 << 20, 4, 1);
  /* Views at x = 0, 5, 5.1, 10: the pair 5 / 5.1 is redundant. */
  double xs[] = {0, 5, 5.1, 10};
  for (int i = 0; i < 4; i++) {
    struct vlff_keyframe_in k = make(i, xs[i], 0);
    assert_int_equal(vlff_kfstore_add(s, &k), 0);
  }
  struct vlff_keyframe_in k = make(4, 20, 0);
  assert_int_equal(vlff_kfstore_add(s, &k), 0);
  assert_int_equal(vlff_kfstore_count(s), 4);
  /* One of the redundant pair went (the older, id 1); coverage kept. */
  assert_false(has_id(s, 1));
  assert_true(has_id(s, 0) && has_id(s, 2) && has_id(s, 3) && has_id(s, 4));
  vlff_kfstore_destroy(s);
}

static void test_newest_protected_and_weights(void **st) {
  (void)st;
  struct vlff_kfstore *s = vlff_kfstore_create(1 << 20, 5, 2);
  for (int i = 0; i < 5; i++) {
    struct vlff_keyframe_in k = make(i, i * 3.0, 0);
    vlff_kfstore_add(s, &k);
  }
  /* The newest lands on top of id 4: still id 4 and 5 are protected. */
  struct vlff_keyframe_in k = make(5, 12.01, 0);
  vlff_kfstore_add(s, &k);
  assert_true(has_id(s, 4) && has_id(s, 5));
  const struct vlff_view *v;
  const float *w;
  int n = vlff_kfstore_views(s, 2, &v, &w);
  float sum = 0, recent = 0;
  for (int i = 0; i < n; i++) {
    assert_true(w[i] > 0);
    sum += w[i];
    if (i >= n - 2) recent += w[i];
  }
  assert_float_equal(sum, 1.0f, 1e-5);
  assert_float_equal(recent, 0.5f, 1e-5);
  vlff_kfstore_destroy(s);
}

static void test_pose_distance(void **st) {
  (void)st;
  double a[16] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};
  double b[16] = {0, -1, 0, 3, 1, 0, 0, 4, 0, 0, 1, 0, 0, 0, 0, 1}; /* 90 deg about z, 5 m away */
  assert_float_equal(vlff_pose_distance(a, a), 0, 1e-9);
  assert_float_equal(vlff_pose_distance(a, b), 5 + 0.5 * 1.5707963267948966, 1e-9);
}

/* Views whose camera stands at x >= 2 "show what is gone" here. */
static bool shows_gone(void *ctx, const struct vlff_view *v) {
  (*(int *)ctx)++;
  return v->c2w[3] >= 2;
}

/* Keyframes newer depth contradicts are retired whatever their age, the
 * rest keep their place and bytes; the newest stays even when
 * contradicted (its depth is the newest there is). */
static void test_contradicted_retired(void **st) {
  (void)st;
  size_t cost = vlff_kfstore_cost(W, H, FW, FH, D, 1);
  struct vlff_kfstore *s = vlff_kfstore_create(cost * 10, 10, 1);
  for (int i = 0; i < 5; i++) {
    struct vlff_keyframe_in k = make(i, i, 0);
    assert_int_equal(vlff_kfstore_add(s, &k), 0);
  }
  int calls = 0;
  assert_int_equal(vlff_kfstore_retire(s, shows_gone, &calls), 2);
  assert_int_equal(calls, 4);
  assert_int_equal(vlff_kfstore_count(s), 3);
  assert_int_equal(vlff_kfstore_retired(s), 2);
  assert_int_equal(vlff_kfstore_bytes(s), 3 * cost);
  assert_true(has_id(s, 0) && has_id(s, 1) && has_id(s, 4) && !has_id(s, 2) && !has_id(s, 3));
  assert_int_equal(vlff_kfstore_id(s, 2), 4);
  vlff_kfstore_destroy(s);
}

/* Keyframe id's pixels, depth and features all say id. */
static struct vlff_keyframe_in make_marked(long long id, double x) {
  struct vlff_keyframe_in k = make(id, x, 0);
  for (int i = 0; i < W * H; i++) depth[i] = (float)id + 0.5f;
  for (int i = 0; i < FW * FH * D; i++) feat[i] = (uint16_t)(1000 + id);
  return k;
}

static const struct vlff_view *view_of(struct vlff_kfstore *s, long long id) {
  const struct vlff_view *v;
  const float *w;
  int n = vlff_kfstore_views(s, 1, &v, &w);
  for (int i = 0; i < n; i++)
    if (vlff_kfstore_id(s, i) == id) return &v[i];
  return NULL;
}

static char page_dir[64];
static char page_path[96];

static int page_setup(void **st) {
  (void)st;
  snprintf(page_dir, sizeof page_dir, "/tmp/vlff-kfpage-XXXXXX");
  if (!mkdtemp(page_dir)) return -1;
  snprintf(page_path, sizeof page_path, "%s/keyframes.pages", page_dir);
  return 0;
}

static int page_teardown(void **st) {
  (void)st;
  unlink(page_path);
  return rmdir(page_dir);
}

/* A page file record: a keyframe's depth, features and pixels. */
static size_t record_len(void) {
  return (size_t)W * H * (3 + sizeof(float)) + (size_t)FW * FH * D * sizeof(uint16_t);
}

/* A store holding `held` keyframes, the newest `protect` of them never
 * evicted, paging to page_path (1 MiB). */
static struct vlff_kfstore *paging_store(int held, int protect) {
  struct vlff_kfstore *s = vlff_kfstore_create(vlff_kfstore_cost(W, H, FW, FH, D, 1) * (size_t)held, 100, protect);
  char err[256];
  assert_non_null(s);
  assert_int_equal(vlff_kfstore_page_to(s, page_path, 1 << 20, err, sizeof err), 0);
  return s;
}

/* A full store pages its evicted keyframes out whole; a camera back near
 * one brings it back, pixels, depth and features as they were, as the
 * oldest view, and the view that leaves for it goes to the page file. A
 * paged view that would be the next to go stays there (no thrashing). */
static void test_paged_and_back(void **st) {
  (void)st;
  size_t cost = vlff_kfstore_cost(W, H, FW, FH, D, 1);
  struct vlff_kfstore *s = paging_store(3, 1);
  /* Views 1 m apart along x: on these ties the oldest goes, so 17, 18, 19
   * stay and 10..16 are paged. */
  for (int i = 0; i < 10; i++) {
    struct vlff_keyframe_in k = make_marked(10 + i, i);
    assert_int_equal(vlff_kfstore_add(s, &k), 0);
  }
  assert_int_equal(vlff_kfstore_count(s), 3);
  assert_int_equal(vlff_kfstore_evicted(s), 7);
  assert_int_equal(vlff_kfstore_paged(s), 7);
  assert_int_equal(vlff_kfstore_paged_out(s), 7);
  assert_int_equal(vlff_kfstore_dropped(s), 0);
  const size_t len = vlff_kfstore_page_bytes(s) / 7;
  assert_true(len > 0 && vlff_kfstore_page_bytes(s) == 7 * len);
  /* Far from every paged view: nothing comes back. */
  double c2w[16] = {1, 0, 0, 50, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};
  assert_int_equal(vlff_kfstore_page_in(s, c2w, 1.5), 0);
  /* Back at x = 0: keyframe 10 returns; 17 (the most redundant) leaves. */
  c2w[3] = 0;
  assert_int_equal(vlff_kfstore_page_in(s, c2w, 1.5), 1);
  assert_true(has_id(s, 10) && has_id(s, 18) && has_id(s, 19) && !has_id(s, 17));
  assert_int_equal(vlff_kfstore_id(s, 0), 10); /* the oldest: not protected, not recent */
  assert_int_equal(vlff_kfstore_paged_in(s), 1);
  assert_int_equal(vlff_kfstore_paged_out(s), 8);
  assert_int_equal(vlff_kfstore_paged(s), 7);
  assert_int_equal(vlff_kfstore_bytes(s), 3 * cost);
  assert_true(vlff_kfstore_page_bytes(s) == 7 * len); /* 17 took 10's place */
  const struct vlff_view *v = view_of(s, 10);
  assert_non_null(v);
  assert_int_equal(v->rgb[0], 10);
  assert_int_equal(v->rgb[W * H * 3 - 1], 10);
  assert_float_equal(v->depth[W * H - 1], 10.5, 0);
  assert_int_equal(v->features[FW * FH * D - 1], 1010);
  assert_float_equal(v->c2w[3], 0, 0);
  /* At x = 1: keyframe 11 would come back for 18 (the most redundant), but
   * then sit 1 m from 10, as near as 10 from it, and as the oldest go next:
   * it stays paged. */
  c2w[3] = 1;
  assert_int_equal(vlff_kfstore_page_in(s, c2w, 1.5), 0);
  assert_int_equal(vlff_kfstore_paged_in(s), 1);
  /* A second store paging to the same name makes its own file; the first
   * one's destroy leaves that alone (a mapping reset does this). */
  struct vlff_kfstore *u = paging_store(3, 1);
  vlff_kfstore_destroy(s);
  assert_int_equal(access(page_path, F_OK), 0);
  /* Views at 0, 10, 20, 30: 0 paged. Back at 0 it would come back for 10,
   * but the page file is cut short: dropped, counted, the store as it was. */
  for (int i = 0; i < 4; i++) {
    struct vlff_keyframe_in k = make_marked(i, 10.0 * i);
    assert_int_equal(vlff_kfstore_add(u, &k), 0);
  }
  assert_int_equal(vlff_kfstore_paged(u), 1);
  assert_int_equal(truncate(page_path, 0), 0);
  c2w[3] = 0;
  assert_int_equal(vlff_kfstore_page_in(u, c2w, 1.5), -1);
  assert_int_equal(vlff_kfstore_dropped(u), 1);
  assert_int_equal(vlff_kfstore_paged(u), 0);
  assert_int_equal(vlff_kfstore_count(u), 3);
  assert_true(has_id(u, 1) && has_id(u, 2) && has_id(u, 3));
  assert_non_null(strstr(vlff_kfstore_page_error(u), "short read"));
  vlff_kfstore_destroy(u);
  assert_int_equal(access(page_path, F_OK), -1); /* its own file goes with it */
}

/* A page file's budget: what does not fit is dropped and counted, with the
 * reason; without a page file every evicted keyframe is dropped. */
static void test_page_file_full(void **st) {
  (void)st;
  size_t cost = vlff_kfstore_cost(W, H, FW, FH, D, 1);
  struct vlff_kfstore *s = vlff_kfstore_create(cost * 3, 100, 1);
  struct vlff_kfstore *none = vlff_kfstore_create(cost * 3, 100, 1);
  char err[256];
  struct vlff_keyframe_in k = make_marked(1, 0);
  const size_t len = record_len();
  assert_int_equal(vlff_kfstore_page_to(s, page_path, 2 * len + len / 2, err, sizeof err), 0);
  for (int i = 0; i < 10; i++) {
    k = make_marked(i, i);
    assert_int_equal(vlff_kfstore_add(s, &k), 0);
    assert_int_equal(vlff_kfstore_add(none, &k), 0);
  }
  assert_int_equal(vlff_kfstore_paged(s), 2);
  assert_int_equal(vlff_kfstore_dropped(s), 5);
  assert_non_null(strstr(vlff_kfstore_page_error(s), "is full"));
  assert_int_equal(vlff_kfstore_dropped(none), 7);
  assert_int_equal(vlff_kfstore_paged(none), 0);
  double c2w[16] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};
  assert_int_equal(vlff_kfstore_page_in(none, c2w, 1.5), 0);
  /* A page file where none can be made. */
  assert_int_equal(vlff_kfstore_page_to(none, "/nonexistent-dir/keyframes.pages", 1 << 20, err, sizeof err), -1);
  assert_non_null(strstr(err, "keyframe page file /nonexistent-dir/keyframes.pages: "));
  vlff_kfstore_destroy(s);
  vlff_kfstore_destroy(none);
}

/* Views of one place count once: an evicted view of the place of a kept
 * one is not paged, and a newer view of a paged place overwrites it (a
 * robot on a loop does not fill the file with copies). */
static void test_same_place_once(void **st) {
  (void)st;
  struct vlff_kfstore *s = paging_store(2, 1);
  /* Two held, one protected: each add evicts the older (A at x = 0 first). */
  const double xs[] = {0, 10, 20, 0, 30, 40};
  for (int i = 0; i < 6; i++) {
    struct vlff_keyframe_in k = make_marked(i, xs[i]);
    assert_int_equal(vlff_kfstore_add(s, &k), 0);
  }
  /* 0, 1, 2 paged; then 3 (at 0's place) overwrote 0's record. */
  assert_int_equal(vlff_kfstore_paged_out(s), 4);
  assert_int_equal(vlff_kfstore_paged(s), 3);
  const size_t len = record_len();
  assert_true(vlff_kfstore_page_bytes(s) == 3 * len);
  /* 0's record (the file's first) holds 3's pixels now: depth, features, rgb. */
  FILE *f = fopen(page_path, "rb");
  assert_non_null(f);
  uint8_t px[W * H * 3];
  assert_int_equal(fseek(f, (long)(W * H * sizeof(float) + FW * FH * D * sizeof(uint16_t)), SEEK_SET), 0);
  assert_int_equal(fread(px, 1, sizeof px, f), sizeof px);
  fclose(f);
  assert_int_equal(px[0], 3);
  assert_int_equal(px[sizeof px - 1], 3);
  /* With one view to evict, a paged view brought back would be the next to
   * go: it stays paged. */
  double c2w[16] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};
  assert_int_equal(vlff_kfstore_page_in(s, c2w, 1.5), 0);
  /* A view on top of a kept one: that one goes, and is not paged. */
  struct vlff_kfstore *t = paging_store(2, 0);
  for (int i = 0; i < 3; i++) {
    struct vlff_keyframe_in k = make_marked(i, i == 2 ? 0.01 : 5.0 * i);
    assert_int_equal(vlff_kfstore_add(t, &k), 0);
  }
  assert_int_equal(vlff_kfstore_evicted(t), 1);
  assert_int_equal(vlff_kfstore_paged(t), 0);
  assert_int_equal(vlff_kfstore_dropped(t), 0);
  vlff_kfstore_destroy(t);
  vlff_kfstore_destroy(s);
}

/* A write the kernel refuses (the file-size limit, as a full disk would):
 * the keyframe is dropped, counted, with the kernel's reason; the records
 * written before stay readable. */
static void test_page_write_fails(void **st) {
  (void)st;
  struct vlff_kfstore *s = paging_store(3, 1);
  const size_t len = record_len();
  struct rlimit old, lim;
  assert_int_equal(getrlimit(RLIMIT_FSIZE, &old), 0);
  lim = old;
  lim.rlim_cur = (rlim_t)(2 * len + len / 2);
  void (*was)(int) = signal(SIGXFSZ, SIG_IGN);
  assert_int_equal(setrlimit(RLIMIT_FSIZE, &lim), 0);
  for (int i = 0; i < 6; i++) {
    struct vlff_keyframe_in k = make_marked(i, i);
    assert_int_equal(vlff_kfstore_add(s, &k), 0);
  }
  assert_int_equal(setrlimit(RLIMIT_FSIZE, &old), 0);
  signal(SIGXFSZ, was);
  /* 0 and 1 written whole; 2 cut short by the limit. */
  assert_int_equal(vlff_kfstore_paged(s), 2);
  assert_int_equal(vlff_kfstore_dropped(s), 1);
  assert_non_null(strstr(vlff_kfstore_page_error(s), "File too large"));
  double c2w[16] = {1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};
  assert_int_equal(vlff_kfstore_page_in(s, c2w, 1.5), 1);
  const struct vlff_view *v = view_of(s, 0);
  assert_non_null(v);
  assert_float_equal(v->depth[W * H - 1], 0.5, 0);
  vlff_kfstore_destroy(s);
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(test_budget_and_copy), cmocka_unit_test(test_redundant_view_goes),
    cmocka_unit_test(test_newest_protected_and_weights), cmocka_unit_test(test_pose_distance),
    cmocka_unit_test(test_contradicted_retired),
    cmocka_unit_test_setup_teardown(test_paged_and_back, page_setup, page_teardown),
    cmocka_unit_test_setup_teardown(test_page_file_full, page_setup, page_teardown),
    cmocka_unit_test_setup_teardown(test_same_place_once, page_setup, page_teardown),
    cmocka_unit_test_setup_teardown(test_page_write_fails, page_setup, page_teardown))
