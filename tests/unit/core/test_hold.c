/* The label hold (hold.h): a published voxel's label changes only with new
 * evidence for it or past the hysteresis margin, and the flips are counted
 * as a reader sees them. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>
#include <cmocka.h>

#include "hold.h"
#include "unit.h"
#include "vlff/shm.h"

enum { CHAIR = 4, TABLE = 6 };

/* A voxel near a decision boundary, the camera elsewhere: the field's
 * label wobbles between two classes with small margins and the published
 * label stays; a clear lead, or a keyframe that sees it again, changes it. */
static void test_held_without_evidence(void **state) {
  (void)state;
  struct vlff_hold *h = vlff_hold_create(8, 0.05);
  assert_non_null(h);
  vlff_hold_keyframe(h);
  vlff_hold_observed(h, 3);
  vlff_hold_begin(h);
  assert_int_equal(vlff_hold_label(h, 3, CHAIR, 0.01f), CHAIR); /* first label: taken */
  assert_int_equal(vlff_hold_stats(h)->changed, 0);              /* new, not a flip */
  assert_int_equal(vlff_hold_stats(h)->decided, 1);
  assert_int_equal(vlff_hold_stats(h)->mapped_elsewhere, 0);
  for (int i = 0; i < 10; i++) {
    vlff_hold_begin(h);
    assert_int_equal(vlff_hold_label(h, 3, i % 2 ? CHAIR : TABLE, 0.04f), CHAIR);
    assert_int_equal(vlff_hold_stats(h)->changed_elsewhere, 0);
    assert_int_equal(vlff_hold_stats(h)->mapped_elsewhere, 1);
  }
  /* Past the hysteresis: changed, and counted as a flip elsewhere. */
  vlff_hold_begin(h);
  assert_int_equal(vlff_hold_label(h, 3, TABLE, 0.06f), TABLE);
  assert_int_equal(vlff_hold_stats(h)->changed_elsewhere, 1);
  /* A keyframe that observed it again: the map's label, whatever its margin. */
  vlff_hold_keyframe(h);
  vlff_hold_observed(h, 3);
  vlff_hold_begin(h);
  assert_int_equal(vlff_hold_label(h, 3, CHAIR, 0.001f), CHAIR);
  assert_int_equal(vlff_hold_stats(h)->changed, 1); /* TABLE -> CHAIR: a flip */
  assert_int_equal(vlff_hold_stats(h)->mapped_elsewhere, 0);
  /* ... once: the next publish without evidence holds again. */
  vlff_hold_begin(h);
  assert_int_equal(vlff_hold_label(h, 3, TABLE, 0.01f), CHAIR);
  /* A keyframe that saw other voxels is no evidence for this one. */
  vlff_hold_keyframe(h);
  vlff_hold_observed(h, 5);
  assert_int_equal(vlff_hold_label(h, 3, TABLE, 0.01f), CHAIR);
  vlff_hold_destroy(h);
}

/* Free space and occupancy follow the field's density; a reset forgets the
 * held labels; hysteresis 0 publishes the map's label always. */
static void test_free_reset_and_off(void **state) {
  (void)state;
  struct vlff_hold *h = vlff_hold_create(4, 0.05);
  vlff_hold_keyframe(h);
  vlff_hold_observed(h, 0);
  assert_int_equal(vlff_hold_label(h, 0, CHAIR, 0.2f), CHAIR);
  assert_int_equal(vlff_hold_label(h, 0, VLFF_LABEL_FREE, 0), VLFF_LABEL_FREE);
  assert_int_equal(vlff_hold_label(h, 0, TABLE, 0.0f), TABLE);
  assert_int_equal(vlff_hold_label(h, 0, CHAIR, 0.0f), TABLE);
  vlff_hold_reset(h);
  assert_int_equal(vlff_hold_label(h, 0, CHAIR, 0.0f), CHAIR);
  vlff_hold_destroy(h);
  h = vlff_hold_create(4, 0);
  vlff_hold_keyframe(h);
  vlff_hold_observed(h, 1);
  assert_int_equal(vlff_hold_label(h, 1, CHAIR, 0.01f), CHAIR);
  assert_int_equal(vlff_hold_label(h, 1, TABLE, 0.01f), TABLE);
  vlff_hold_destroy(h);
}

/* Saved and loaded (a restart): held labels stay held, evidence that came
 * after a label was decided is still new evidence, a voxel never observed
 * has none; forged labels and flags are refused naming the voxel, and the
 * hold keeps what it had. */
static void test_save_load(void **state) {
  (void)state;
  struct vlff_hold *h = vlff_hold_create(4, 0.05), *g = vlff_hold_create(4, 0.05);
  assert_true(h && g);
  vlff_hold_keyframe(h);
  vlff_hold_observed(h, 0);
  vlff_hold_observed(h, 1);
  assert_int_equal(vlff_hold_label(h, 0, CHAIR, 0.2f), CHAIR);
  assert_int_equal(vlff_hold_label(h, 1, TABLE, 0.2f), TABLE);
  vlff_hold_keyframe(h);
  vlff_hold_observed(h, 1); /* seen again after its label: new evidence */
  uint8_t buf[12];
  assert_int_equal(vlff_hold_save_size(h), sizeof buf);
  vlff_hold_save(h, buf);
  char err[200];
  assert_int_equal(vlff_hold_load(g, buf, sizeof buf, err, sizeof err), 0);
  vlff_hold_begin(g);
  assert_int_equal(vlff_hold_label(g, 0, TABLE, 0.01f), CHAIR); /* held */
  assert_int_equal(vlff_hold_label(g, 1, CHAIR, 0.01f), CHAIR); /* new evidence: the map's */
  assert_int_equal(vlff_hold_label(g, 2, TABLE, 0.01f), TABLE); /* never labelled: taken */
  assert_int_equal(vlff_hold_stats(g)->changed, 1);
  assert_int_equal(vlff_hold_stats(g)->mapped_elsewhere, 1);
  /* A keyframe after the load is new evidence for voxel 0. */
  vlff_hold_keyframe(g);
  vlff_hold_observed(g, 0);
  assert_int_equal(vlff_hold_label(g, 0, TABLE, 0.01f), TABLE);
  /* Forged: a label past the prompts, flags no hold writes, a short buffer. */
  uint8_t bad[12];
  memcpy(bad, buf, sizeof bad);
  bad[3 * 2] = 40, bad[3 * 2 + 1] = 0;
  assert_int_equal(vlff_hold_load(g, bad, sizeof bad, err, sizeof err), -1);
  assert_non_null(strstr(err, "voxel 2 holds label 40"));
  memcpy(bad, buf, sizeof bad);
  bad[3 * 3 + 2] = 2; /* fresh without seen */
  assert_int_equal(vlff_hold_load(g, bad, sizeof bad, err, sizeof err), -1);
  assert_non_null(strstr(err, "voxel 3 has flags 0x02"));
  assert_int_equal(vlff_hold_load(g, buf, sizeof buf - 1, err, sizeof err), -1);
  assert_non_null(strstr(err, "expected 12"));
  vlff_hold_begin(g);
  assert_int_equal(vlff_hold_label(g, 0, CHAIR, 0.01f), TABLE); /* kept what it had */
  vlff_hold_destroy(h);
  vlff_hold_destroy(g);
}

VLFF_UNIT_MAIN(NULL, NULL, cmocka_unit_test(test_held_without_evidence), cmocka_unit_test(test_free_reset_and_off),
               cmocka_unit_test(test_save_load))
