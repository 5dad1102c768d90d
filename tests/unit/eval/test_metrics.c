/* Metrics against hand-computed confusion matrices; classification and the
 * fusion baseline on hand-made geometry. */
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>

#include <cmocka.h>

#include "field.h"
#include "metrics.h"
#include "unit.h"

#define NEAR(a, b) assert_true(fabs((a) - (b)) < 1e-12)

/* gt   0 0 0 1  1 2 255 255
 * pred 0 0 1 1 -1 2   0   1
 * class 0: TP 2, FN 1 (->1), FP 0       IoU 2/3, recall 2/3, precision 1
 * class 1: TP 1, FN 1 (none), FP 1      IoU 1/3, recall 1/2, precision 1/2
 * class 2: TP 1                         IoU 1,   recall 1,   precision 1 */
static void test_hand_computed(void **state) {
  (void)state;
  struct vlff_confusion c;
  char err[128];
  assert_int_equal(vlff_confusion_init(&c, 3, err, sizeof err), 0);
  const uint8_t gt[] = {0, 0, 0, 1, 1, 2, 255, 255};
  const int pred[] = {0, 0, 1, 1, -1, 2, 0, 1};
  vlff_confusion_add(&c, gt, pred, 8);
  assert_int_equal(c.ignored, 2);
  struct vlff_class_score s;
  vlff_confusion_class(&c, 0, &s);
  assert_int_equal(s.tp, 2), assert_int_equal(s.fp, 0), assert_int_equal(s.fn, 1);
  NEAR(s.iou, 2.0 / 3), NEAR(s.recall, 2.0 / 3), NEAR(s.precision, 1);
  vlff_confusion_class(&c, 1, &s);
  assert_int_equal(s.tp, 1), assert_int_equal(s.fp, 1), assert_int_equal(s.fn, 1);
  NEAR(s.iou, 1.0 / 3), NEAR(s.recall, 0.5), NEAR(s.precision, 0.5);
  vlff_confusion_class(&c, 2, &s);
  NEAR(s.iou, 1);
  struct vlff_summary m;
  vlff_confusion_summary(&c, &m);
  assert_int_equal(m.present, 3);
  assert_int_equal(m.labelled, 6);
  NEAR(m.miou, (2.0 / 3 + 1.0 / 3 + 1) / 3);
  NEAR(m.macc, (2.0 / 3 + 0.5 + 1) / 3);
  NEAR(m.mprec, (1 + 0.5 + 1) / 3);
  NEAR(m.pixel_acc, 4.0 / 6);
  /* merging doubles counts, leaves ratios */
  struct vlff_confusion d;
  assert_int_equal(vlff_confusion_init(&d, 3, err, sizeof err), 0);
  vlff_confusion_add(&d, gt, pred, 8);
  assert_int_equal(vlff_confusion_merge(&d, &c), 0);
  vlff_confusion_class(&d, 1, &s);
  assert_int_equal(s.tp, 2), assert_int_equal(s.fp, 2), assert_int_equal(s.fn, 2);
  struct vlff_summary m2;
  vlff_confusion_summary(&d, &m2);
  NEAR(m2.miou, m.miou);
  vlff_confusion_reset(&d);
  vlff_confusion_summary(&d, &m2);
  assert_int_equal(m2.present, 0);
  NEAR(m2.miou, 0);
  vlff_confusion_free(&d);
  vlff_confusion_free(&c);
}

/* Classes absent from the ground truth are left out of the means even when
 * predicted; their false positives still cost the true class. */
static void test_absent_classes(void **state) {
  (void)state;
  struct vlff_confusion c;
  char err[128];
  assert_int_equal(vlff_confusion_init(&c, 4, err, sizeof err), 0);
  const uint8_t gt[] = {0, 0, 2, 2, 2, 2};
  const int pred[] = {3, 0, 2, 2, 2, 7};
  vlff_confusion_add(&c, gt, pred, 6);
  struct vlff_class_score s;
  vlff_confusion_class(&c, 3, &s);
  assert_false(s.present);
  assert_int_equal(s.fp, 1);
  NEAR(s.iou, 0);
  struct vlff_summary m;
  vlff_confusion_summary(&c, &m);
  assert_int_equal(m.present, 2);
  NEAR(m.miou, (0.5 + 0.75) / 2);
  NEAR(m.macc, (0.5 + 0.75) / 2);
  NEAR(m.mprec, (1 + 1) / 2.0);
  vlff_confusion_free(&c);
  assert_int_equal(vlff_confusion_init(&c, 0, err, sizeof err), -1);
  assert_non_null(strstr(err, "class count"));
}

static void test_classify(void **state) {
  (void)state;
  const float emb[] = {2, 0, 0, 0, 0, 3, 0, 0, 0, 0, 0, 1};
  float unit[12];
  vlff_normalize_rows(emb, unit, 3, 4);
  NEAR(unit[0], 1), NEAR(unit[6], 0);
  const float f[] = {1, 0.2f, 0, 0, 0.1f, -5, 0, 0.3f, 0, 0, 0, 0, NAN, 0, 0, 0};
  int lab[4];
  float score[4];
  vlff_classify_f32(f, 4, 4, unit, 3, lab, score);
  assert_int_equal(lab[0], 0);
  assert_int_equal(lab[1], 2);
  assert_int_equal(lab[2], -1);
  assert_int_equal(lab[3], -1);
  assert_true(fabs(score[0] - 1 / sqrt(1.04)) < 1e-6);
  uint16_t h[16];
  for (int i = 0; i < 16; i++) h[i] = vlff_f32_to_f16(f[i]);
  int lab2[4];
  vlff_classify_f16(h, 4, 4, unit, 3, lab2, NULL);
  assert_memory_equal(lab, lab2, sizeof lab);
}

/* One camera at the origin looking down +z (identity pose), 4x4 image,
 * 2x2 feature map with D=2. A point in front whose depth matches the depth
 * map is fused; an occluded one and one behind the camera are not. */
static void test_fusion(void **state) {
  (void)state;
  float depth[16];
  for (int i = 0; i < 16; i++) depth[i] = 2.0f;
  uint16_t feat[2 * 2 * 2];
  const float fv[8] = {1, 0, 0, 1, 0.5f, 0.5f, -1, 0};
  for (int i = 0; i < 8; i++) feat[i] = vlff_f32_to_f16(fv[i]);
  struct vlff_fusion_view v[2];
  memset(v, 0, sizeof v);
  for (int k = 0; k < 2; k++) {
    v[k].width = 4, v[k].height = 4, v[k].fx = v[k].fy = 4, v[k].cx = v[k].cy = 2;
    for (int i = 0; i < 4; i++) v[k].c2w[5 * i] = 1;
    v[k].depth = depth, v[k].feat_width = 2, v[k].feat_height = 2, v[k].features = feat;
  }
  /* second view moved 1 m back along z: the same point is 3 m away */
  v[1].c2w[11] = -1;
  for (int i = 0; i < 16; i++) depth[i] = 2.0f;
  float depth2[16];
  for (int i = 0; i < 16; i++) depth2[i] = 3.0f;
  v[1].depth = depth2;
  /* (1, 1, 2) projects to u = 4*1/2+2 = 4 -> outside; use (0.5, 0.5, 2): u = v = 3 -> cell (1,1) */
  const float pts[] = {0.5f, 0.5f, 2.0f, -0.5f, -0.5f, 4.0f, 0, 0, -1.0f};
  float out[6];
  int cnt[3];
  char err[128];
  assert_int_equal(vlff_fusion(pts, 3, v, 2, 2, 0.05, out, cnt, err, sizeof err), 0);
  assert_int_equal(cnt[0], 2);
  assert_true(out[0] == -1.0f && out[1] == 0.0f);
  /* at u = v = 1 (cell 0,0) but 4 m away where the depth map says 2 (occluded) in view 0, and 5 m vs 3 in view 1 */
  assert_int_equal(cnt[1], 0);
  assert_true(out[2] == 0 && out[3] == 0);
  assert_int_equal(cnt[2], 0);
  v[0].fx = 0;
  assert_int_equal(vlff_fusion(pts, 3, v, 2, 2, 0.05, out, cnt, err, sizeof err), -1);
  assert_non_null(strstr(err, "view 0"));
}

static double lcg(uint64_t *s) {
  *s = *s * 6364136223846793005ull + 1442695040888963407ull;
  return (double)(*s >> 11) / (double)(1ull << 53);
}

/* Fusion one view at a time in the prompts' K dimensions gives the labels
 * (and counts) of fusion in D dimensions followed by the argmax of the
 * cosines: three views of a plane 2-3 m away, random features and
 * prompts, points on the plane and off it. */
static void test_fusion_streamed(void **state) {
  (void)state;
  enum { W = 16, H = 12, FW = 8, FH = 6, D = 8, K = 4, NV = 3, NP = 400 };
  uint64_t rs = 7;
  static float depth[NV][W * H];
  static uint16_t feat[NV][FW * FH * D];
  struct vlff_fusion_view v[NV];
  memset(v, 0, sizeof v);
  for (int k = 0; k < NV; k++) {
    v[k].width = W, v[k].height = H, v[k].fx = v[k].fy = 12, v[k].cx = W / 2.0, v[k].cy = H / 2.0;
    for (int i = 0; i < 4; i++) v[k].c2w[5 * i] = 1;
    v[k].c2w[3] = 0.3 * (k - 1), v[k].c2w[11] = -0.5 * k; /* the plane z = 2 is 2 + 0.5 k m away */
    for (int i = 0; i < W * H; i++) depth[k][i] = (float)(2 + 0.5 * k);
    for (int i = 0; i < FW * FH * D; i++) feat[k][i] = vlff_f32_to_f16((float)(lcg(&rs) * 2 - 1));
    v[k].depth = depth[k], v[k].feat_width = FW, v[k].feat_height = FH, v[k].features = feat[k];
  }
  float emb[K * D], unit_emb[K * D];
  for (int i = 0; i < K * D; i++) emb[i] = (float)(lcg(&rs) * 2 - 1);
  vlff_normalize_rows(emb, unit_emb, K, D);
  static float pts[NP * 3];
  for (int i = 0; i < NP; i++) {
    pts[3 * i] = (float)(lcg(&rs) * 2.4 - 1.2), pts[3 * i + 1] = (float)(lcg(&rs) * 1.8 - 0.9);
    pts[3 * i + 2] = i % 5 == 0 ? 2.5f : 2.0f; /* every fifth off the plane: no view sees it */
  }
  static float avg[NP * D];
  static double acc[NP * K];
  int cnt[NP], cnt2[NP] = {0}, want[NP], got[NP];
  char err[128];
  assert_int_equal(vlff_fusion(pts, NP, v, NV, D, 0.05, avg, cnt, err, sizeof err), 0);
  vlff_classify_f32(avg, NP, D, unit_emb, K, want, NULL);
  memset(acc, 0, sizeof acc);
  for (int k = 0; k < NV; k++)
    assert_int_equal(vlff_fusion_add(pts, NP, &v[k], D, unit_emb, K, 0.05, acc, cnt2, err, sizeof err), 0);
  vlff_fusion_labels(acc, cnt2, NP, K, got);
  int seen = 0, multi = 0;
  for (int i = 0; i < NP; i++) {
    assert_int_equal(cnt[i], cnt2[i]);
    assert_int_equal(want[i], got[i]);
    seen += cnt[i] > 0, multi += cnt[i] > 1;
    if (i % 5 == 0) assert_int_equal(got[i], -1);
  }
  /* the comparison covers points seen by one view and by several */
  assert_true(seen > NP / 2 && multi > NP / 4);
  v[1].fx = 0;
  assert_int_equal(vlff_fusion_add(pts, NP, &v[1], D, unit_emb, K, 0.05, acc, cnt2, err, sizeof err), -1);
  assert_non_null(strstr(err, "fusion: invalid view"));
}

static void test_downsample_labels(void **state) {
  (void)state;
  uint8_t img[4 * 4], out[2 * 2];
  for (int i = 0; i < 16; i++) img[i] = (uint8_t)i;
  vlff_downsample_labels(img, 4, 4, out, 2, 2);
  /* centres of 2x2 cells land on pixel (1,1), (3,1), (1,3), (3,3) */
  assert_int_equal(out[0], 5);
  assert_int_equal(out[1], 7);
  assert_int_equal(out[2], 13);
  assert_int_equal(out[3], 15);
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(test_hand_computed), cmocka_unit_test(test_absent_classes),
    cmocka_unit_test(test_classify), cmocka_unit_test(test_fusion), cmocka_unit_test(test_fusion_streamed),
    cmocka_unit_test(test_downsample_labels))
