/*
 * Label hold: the label a published voxel shows, from the label it showed
 * before and the one the map gives it now.
 *
 * Why: the field is one shared decoder trained on every keyframe, so
 * training on the views of one room moves its features a little
 * everywhere, and a voxel near a decision boundary flipped between classes
 * from one publish to the next although nothing new was seen there. A
 * controller reading the map cannot tell that churn from a changing world.
 *
 * Rule (vlff_hold_label): the voxel's published label becomes the map's
 * new label when
 *  - it has none yet (never decided since create or reset), or
 *  - new evidence for it arrived: a keyframe observed the voxel
 *    (vlff_hold_observed: a measured ray passed through it or ended in it)
 *    after its label was last decided, or
 *  - the new label is a class and the held one another class, and the new
 *    label's margin (best minus second-best score: a lower bound of the
 *    best's lead over the held label's score, which is at most the second)
 *    is above the hysteresis h (publish.label_hysteresis; 0: the map's
 *    label always), or
 *  - one of the two is FREE or UNKNOWN: whether a voxel no measured surface
 *    ended in is occupied follows the field's density (h is a margin between
 *    classes' scores, not between densities).
 * Otherwise the held label stays. Each decision counts whether the label
 * changed (a flip: a voxel that had a label, class or FREE, and now shows
 * another; a voxel labelled for the first time is new, not a flip), and
 * whether that happened without new evidence ("elsewhere": the camera
 * looked elsewhere): the flips a reader sees where nothing was seen again.
 *
 * The held labels and their evidence stamps are learned state: saved with
 * the observation grid (vlff_hold_save, 3 bytes a voxel: the label and
 * whether the voxel was observed, and observed since its label was
 * decided), so a restarted node holds the labels it published before.
 *
 * Contract: one owner thread (the publisher's). Voxel indices are below the
 * nvox given at create (not checked).
 */
#ifndef VLFF_HOLD_H
#define VLFF_HOLD_H

#include <stddef.h>
#include <stdint.h>

struct vlff_hold;

/* The counts of the decisions since the last vlff_hold_begin. */
struct vlff_hold_stats {
  size_t decided;           /* voxels labelled */
  size_t changed;           /* their label differs from the one they had (not counting new ones) */
  size_t mapped_elsewhere;  /* labelled (class or FREE) before, and no evidence since */
  size_t changed_elsewhere; /* of those, changed (a flip without new evidence) */
};

/* NULL when out of memory. */
struct vlff_hold *vlff_hold_create(size_t nvox, double hysteresis);
void vlff_hold_destroy(struct vlff_hold *h);
/* The map's grid grew or was refitted on its lattice (lattice.h): each
 * voxel's held label and stamps move with it (from dims, shifted by sh, into
 * nd; a voxel beyond nd is dropped, which the map does only to voxels that
 * hold nothing); new voxels hold none. -1 (h unchanged) when out of
 * memory. */
int vlff_hold_grow(struct vlff_hold *h, const uint32_t dims[3], const int32_t sh[3], const uint32_t nd[3]);
/* Forget every held label and evidence stamp (mapping reset, a load). */
void vlff_hold_reset(struct vlff_hold *h);

/* A new keyframe's observations begin: its vlff_hold_observed calls are
 * new evidence for every label decided before them. */
void vlff_hold_keyframe(struct vlff_hold *h);
/* The current keyframe observed voxel vi. */
void vlff_hold_observed(struct vlff_hold *h, size_t vi);

/* A publish's decisions begin: zeroes the stats. */
void vlff_hold_begin(struct vlff_hold *h);
/* The label to publish at voxel vi, given the map's label now (a class,
 * VLFF_LABEL_FREE or VLFF_LABEL_UNKNOWN) and its margin (ignored unless it
 * is a class); remembered as the voxel's held label. */
uint16_t vlff_hold_label(struct vlff_hold *h, size_t vi, uint16_t label, float margin);
/* The voxel forgets its held label: it is decided afresh next time (a
 * voxel no longer observed). */
void vlff_hold_forget(struct vlff_hold *h, size_t vi);
const struct vlff_hold_stats *vlff_hold_stats(const struct vlff_hold *h);

/* Saved state: vlff_hold_save_size bytes, written by vlff_hold_save into
 * out. vlff_hold_load takes them back into a hold of the same nvox: 0, or
 * -1 with err naming the first value out of bounds (a label neither a class
 * of at most VLFF_SHM_MAX_PROMPTS prompts, FREE nor UNKNOWN, or unknown
 * flags) and the hold untouched. The hold's own keyframe count starts over;
 * only which voxels have evidence newer than their label matters. */
size_t vlff_hold_save_size(const struct vlff_hold *h);
void vlff_hold_save(const struct vlff_hold *h, uint8_t *out);
int vlff_hold_load(struct vlff_hold *h, const uint8_t *in, size_t len, char *err, size_t errlen);

#endif
