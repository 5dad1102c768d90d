/*
 * Keyframe admission: which frames become keyframes, and which poses are
 * trusted. Pure functions over plain arrays, so the policy is testable
 * without a camera or a trained field.
 *
 * Contract: no allocation, no global state, thread-safe.
 */
#ifndef VLFF_SELECT_H
#define VLFF_SELECT_H

#include <stdbool.h>
#include <stddef.h>

struct vlff_kf_selector {
  double min_interval_s;      /* 1 / keyframes.rate_hz */
  double min_translation_m;   /* 0 with min_rotation_deg 0: time alone decides */
  double min_rotation_deg;
  bool have_last;
  long long last_t_ns;
  double last_c2w[16];
};

void vlff_kf_selector_init(struct vlff_kf_selector *s, double rate_hz, double min_translation_m,
                           double min_rotation_deg);

/* True when the frame should become a keyframe; then it is remembered as the
 * last one. */
bool vlff_kf_selector_offer(struct vlff_kf_selector *s, long long t_ns, const double c2w[16]);

/* A pose is usable: finite, rotation orthonormal with det +1 (within 1e-3),
 * last row 0 0 0 1. */
bool vlff_pose_valid(const double c2w[16]);

enum vlff_posecheck { VLFF_POSE_UNKNOWN, VLFF_POSE_OK, VLFF_POSE_BAD };

/* Compare depth rendered from the map at a frame's pose with the frame's
 * measured depth, over pixels where the map is confident (hit != 0) and the
 * measurement is valid. Fewer than min_frac of the pixels usable: UNKNOWN
 * (the map cannot judge yet). Otherwise BAD when the median absolute residual
 * exceeds threshold_m. *residual_m receives the median (or -1). */
enum vlff_posecheck vlff_posecheck(const float *rendered, const unsigned char *hit,
                                   const float *measured, size_t n, double threshold_m,
                                   double min_frac, double *residual_m);

#endif
