/*
 * vlff metrics: confusion matrices, the two evaluation protocols, and the
 * baselines every field result is compared against.
 *
 * Labels: ground truth is a class id 0..K-1; any other value (255 in our
 * datasets) is "unlabelled" and ignored. A prediction is 0..K-1, or -1 for
 * "no prediction" (a ray that hit nothing, a point no view saw, a point
 * outside the field's box): it counts as a false negative of the true class
 * and a false positive of no class.
 *
 * Standard protocol (ScanNet benchmark style): per-class TP/FP/FN summed over
 * every pixel (or point) of the scene; IoU_c = TP/(TP+FP+FN); mIoU and mAcc
 * (per-class recall TP/(TP+FN)) are means over the classes present in the
 * scene's ground truth (TP+FN > 0). Classes absent from the ground truth are
 * left out of the means; wrongly predicting them still lowers the present
 * classes' recall and IoU.
 * Reference-code protocol (the paper's implementation): the same summed IoU;
 * in 2D its "accuracy" is per-class precision TP/(TP+FP) (0 when the class is
 * never predicted), averaged over present classes; in 3D features are the
 * average of 10 queries jittered by up to 2 cm and "accuracy" is recall;
 * scores are computed per scene and averaged over scenes.
 *
 * Contract: functions returning int give 0 or -1 with err filled; the caller
 * owns every buffer; no global state (thread-safe on distinct objects).
 */
#ifndef VLFF_METRICS_H
#define VLFF_METRICS_H

#include <stddef.h>
#include <stdint.h>

#define VLFF_METRICS_MAX_CLASSES 256

/* K x (K+1) counts: row = ground truth, column = prediction, column K =
 * no prediction. */
struct vlff_confusion {
  int k;
  uint64_t *m;
  uint64_t ignored;   /* samples with an unlabelled ground truth */
};

struct vlff_class_score {
  uint64_t tp, fp, fn;
  double iou, recall, precision;
  int present;        /* TP+FN > 0 */
};

struct vlff_summary {
  double miou, macc, mprec;  /* means over present classes */
  double pixel_acc;          /* all correct / all labelled */
  int present;               /* number of present classes */
  uint64_t labelled;
};

int vlff_confusion_init(struct vlff_confusion *c, int k, char *err, size_t errlen);
void vlff_confusion_free(struct vlff_confusion *c);
void vlff_confusion_reset(struct vlff_confusion *c);
/* Add n samples; gt values outside 0..K-1 are ignored, pred outside 0..K-1
 * is "no prediction". */
void vlff_confusion_add(struct vlff_confusion *c, const uint8_t *gt, const int *pred, size_t n);
void vlff_confusion_add_one(struct vlff_confusion *c, int gt, int pred);
/* c += o (same K). */
int vlff_confusion_merge(struct vlff_confusion *c, const struct vlff_confusion *o);

void vlff_confusion_class(const struct vlff_confusion *c, int cls, struct vlff_class_score *out);
void vlff_confusion_summary(const struct vlff_confusion *c, struct vlff_summary *out);

/* L2-normalised copies of K embeddings (rows that are zero stay zero). */
void vlff_normalize_rows(const float *in, float *out, int k, int d);

/* Argmax over K unit embeddings of each of n feature vectors (float16 or
 * float32, [n][D]); a zero or non-finite feature gets -1. score (may be
 * NULL) receives the winning cosine similarity. */
void vlff_classify_f16(const uint16_t *feat, size_t n, int d, const float *emb_unit, int k,
                       int *label, float *score);
void vlff_classify_f32(const float *feat, size_t n, int d, const float *emb_unit, int k,
                       int *label, float *score);

/* One posed view with its features, for the fusion baseline. */
struct vlff_fusion_view {
  int width, height;              /* depth image size */
  double fx, fy, cx, cy;          /* at width x height */
  double c2w[16];                 /* camera-to-world, OpenCV camera */
  const float *depth;             /* metres, 0 = invalid */
  int feat_width, feat_height;
  const uint16_t *features;       /* float16 [fh][fw][D] */
};

/* OpenScene-style multi-view fusion: project each point into every view;
 * where it lands inside the image on a valid depth within `tol` metres of
 * its own depth (the visibility test), take the nearest feature-map pixel;
 * average those features. out[n][D] (zero for points no view saw),
 * count[n] (may be NULL) receives the number of views used. */
int vlff_fusion(const float *xyz, size_t n, const struct vlff_fusion_view *views, int nviews, int d,
                double tol, float *out, int *count, char *err, size_t errlen);

/* The same fusion one view at a time, in the prompts' K dimensions
 * instead of the features' D: a point the view sees (the same visibility
 * test and cell as vlff_fusion) adds that cell's feature projected on the
 * K unit embeddings to acc[n][k] and 1 to count[n] (both zeroed by the
 * caller). The projection is linear, so the argmax of the summed
 * projections (vlff_fusion_labels: -1 for a point no view saw) is the
 * argmax of the averaged feature's cosines, the label vlff_fusion and
 * vlff_classify_f32 give (up to rounding), from [n][K] sums instead of
 * [n][D] and with one view in memory at a time. */
int vlff_fusion_add(const float *xyz, size_t n, const struct vlff_fusion_view *view, int d, const float *emb_unit,
                    int k, double tol, double *acc, int *count, char *err, size_t errlen);
void vlff_fusion_labels(const double *acc, const int *count, size_t n, int k, int *label);

/* Ground-truth label at the centre of feature-map cell (i, j) of an image
 * labelled [h][w]: the label image nearest-sampled to the evaluation grid. */
void vlff_downsample_labels(const uint8_t *label, int w, int h, uint8_t *out, int ow, int oh);

#endif
