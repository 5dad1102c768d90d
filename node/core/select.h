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
#include <stdint.h>

/* Time admission is a credit, not a minimum gap: a camera at exactly
 * keyframes.rate_hz delivers frames a few ms early or late, and a gap of
 * one interval from the last keyframe refused every early one (a 5 Hz
 * stream at rate_hz 5 kept 3 frames a second; a 30 Hz one at 5 kept 4.3).
 * Credit accrues with time since the last keyframe, up to 1.5 intervals,
 * and a keyframe spends one interval of it: the long-run rate never
 * exceeds rate_hz, while a frame up to half an interval early once one was
 * late (or skipped) is taken. */
struct vlff_kf_selector {
  double min_interval_s;      /* 1 / keyframes.rate_hz */
  double min_translation_m;   /* 0 with min_rotation_deg 0: time alone decides */
  double min_rotation_deg;
  bool have_last;
  long long last_t_ns;
  double credit_s;            /* credit left at last_t_ns */
  double last_c2w[16];
};

void vlff_kf_selector_init(struct vlff_kf_selector *s, double rate_hz, double min_translation_m,
                           double min_rotation_deg);

/* True when a frame at t_ns has the time credit to become a keyframe
 * (motion is judged by vlff_kf_selector_offer). */
bool vlff_kf_selector_due(const struct vlff_kf_selector *s, long long t_ns);

/* True when the frame should become a keyframe (time credit, then motion
 * from the last keyframe); then it is remembered as the last one and spends
 * one interval of credit. A frame older than the last keyframe is refused. */
bool vlff_kf_selector_offer(struct vlff_kf_selector *s, long long t_ns, const double c2w[16]);

/* Angle in radians between two poses' rotations (trace(Ra^T Rb) = 1 + 2 cos). */
double vlff_pose_angle(const double a[16], const double b[16]);

/* World point seen at pixel (u, v) (continuous coordinates, pixel centres at
 * +0.5) at depth d along the camera z axis of a camera with these
 * intrinsics and camera-to-world pose. */
void vlff_unproject(const double c2w[16], double fx, double fy, double cx, double cy, double u, double v, double d,
                    double out[3]);

/* The surface-mode split of a label grid of lw x lh cells over a width x
 * height camera (depth in metres, [height][width], may be NULL): a cell
 * whose depth pixel (the one under the cell's centre) holds a valid depth
 * gets that measured surface point, world xyz[3 i], and its index pix[i];
 * the other cells' indices go to holes (NULL: not wanted), *nholes of them
 * (nholes may be NULL). Returns the surface cells. The publisher's label
 * image and vlff-eval's 2D score read the same cells. */
size_t vlff_label_surface(const double c2w[16], double fx, double fy, double cx, double cy, int width, int height,
                          const float *depth, int lw, int lh, float *xyz, uint32_t *pix, uint32_t *holes,
                          size_t *nholes);

/* Median of n values (n > 0); reorders v. */
float vlff_medianf(float *v, size_t n);

/* A pose is usable: finite, rotation orthonormal with det +1 (within 1e-3),
 * last row 0 0 0 1. */
bool vlff_pose_valid(const double c2w[16]);

enum vlff_posecheck { VLFF_POSE_UNKNOWN, VLFF_POSE_OK, VLFF_POSE_BAD };

struct vlff_pose_evidence {
  double residual_m;   /* median |rendered - measured| over usable pixels (m), -1 if none */
  double residual;     /* median of each pixel's |rendered - measured| / s(d), -1 if none */
  double inlier_frac;  /* usable pixels with a scaled residual under 2, -1 if none */
  size_t usable;
};

/* Compare depth rendered from the map at a frame's pose with the frame's
 * measured depth, over pixels where the map is confident (hit != 0) and the
 * measurement is valid. Each pixel's residual is scaled by what a good
 * frame shows at its measured range d: s(d) = sqrt(floor_m^2 + sigma(d)^2),
 * the map's own error (floor_m) and the sensor's noise sigma(d) = noise_1m
 * d^2 (a stereo camera's grows with range squared) in quadrature, so a view
 * down a long sight line is not judged by near views' residuals. Fewer than
 * min_frac of the pixels usable: UNKNOWN (the map cannot judge yet). */
enum vlff_posecheck vlff_pose_evidence(const float *rendered, const unsigned char *hit, const float *measured,
                                       size_t n, double min_frac, double floor_m, double noise_1m,
                                       struct vlff_pose_evidence *ev);

/* The verdict on the scaled residual, relative to recently admitted
 * keyframes (recent_residual, recent_inliers: their medians; <= 0 when there
 * are too few). A residual up to 1 (what a good frame shows) is OK. Above
 * it a frame is BAD when it disagrees with the map clearly more than good
 * frames do: residual > 1.6x theirs and inliers < 0.8x theirs (a young map
 * disagrees with every frame; a wrong pose with most of it). Without history
 * only a residual above 3 is BAD. */
enum vlff_posecheck vlff_pose_verdict(const struct vlff_pose_evidence *ev, double recent_residual,
                                      double recent_inliers);

#endif
