/* Keyframe store: budget, redundancy eviction, protection of new views, weights. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
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

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(test_budget_and_copy), cmocka_unit_test(test_redundant_view_goes),
    cmocka_unit_test(test_newest_protected_and_weights), cmocka_unit_test(test_pose_distance),
    cmocka_unit_test(test_contradicted_retired))
