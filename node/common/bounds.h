/*
 * Physical bounds of a camera: what intrinsics and poses can be, whatever
 * file, ring or dataset they came from.
 *
 * One place decides what is plausible, so the frame ingest, the map
 * publisher and the dataset reader refuse the same values for the same
 * reason. The bounds are wide (any real lens and any room- to
 * building-sized scene passes); they exist so that a corrupt or hostile
 * value is refused with a message instead of making a loop over pixels or
 * rays run for ever or a result silently wrong.
 *
 * Intrinsics (pinhole, at the image size they are given for):
 *  - width and height in [1, VLFF_MAX_IMAGE_SIDE];
 *  - fx, fy finite, with the field of view on each axis between
 *    VLFF_MIN_FOV_DEG and VLFF_MAX_FOV_DEG (fx in about [0.044, 57] x width);
 *  - fx / fy within [1 / VLFF_MAX_PIXEL_ASPECT, VLFF_MAX_PIXEL_ASPECT];
 *  - the principal point inside the image grown by half its size on every
 *    side (cx in [-width/2, 3 width/2], likewise cy).
 * Poses (camera-to-world, row-major 4x4, metres):
 *  - the translation finite, and the camera centre no further outside the
 *    scene box than the box's largest extent (a camera may look into the
 *    scene from as far away as the scene is big); with no box known, every
 *    coordinate within VLFF_MAX_POSE_ABS_M.
 *  (Orthonormality of the rotation is vlff_pose_valid's / vlff_check_pose's.)
 *
 * Contract: pure functions, no allocation, thread-safe. Each returns 0 when
 * plausible, or -1 with one line in why (when why is not NULL) naming the
 * value and the bound it broke.
 */
#ifndef VLFF_BOUNDS_H
#define VLFF_BOUNDS_H

#include <stddef.h>

#define VLFF_MAX_IMAGE_SIDE 65536
#define VLFF_MIN_FOV_DEG 1.0
#define VLFF_MAX_FOV_DEG 170.0
#define VLFF_MAX_PIXEL_ASPECT 4.0
#define VLFF_MAX_POSE_ABS_M 1e4

int vlff_intrinsics_plausible(int width, int height, double fx, double fy, double cx, double cy, char *why,
                              size_t whylen);
/* A camera matrix's skew against the field's cameras, which have square
 * pixel axes: a skew would be dropped, every ray off by it. Calibrations give
 * 0, or rounding's worth: at most VLFF_MAX_SKEW_FRAC of fx. 0 when
 * plausible, -1 with *why set. */
#define VLFF_MAX_SKEW_FRAC 1e-3
int vlff_skew_plausible(double fx, double skew, char *why, size_t whylen);

/* lo and hi: the scene box (lo < hi on every axis), or both NULL. */
int vlff_pose_plausible(const double c2w[16], const double lo[3], const double hi[3], char *why, size_t whylen);
/* The node's bound for a camera pose by its field section: with a fixed box
 * as vlff_pose_plausible over field.scene_min/max; with field.grow, within
 * +-field.world_limit_m of the origin on every axis. */
struct vlff_cfg_field;
int vlff_field_pose_plausible(const struct vlff_cfg_field *field, const double c2w[16], char *why, size_t whylen);

/* The farthest depth a frame's pixel may give, metres: no RGB-D sensor
 * measures beyond it (structured light and stereo stop near 10-20 m). A
 * farther pixel is no measurement (a 16-bit sensor's 65535, a float 1e30)
 * and is taken as invalid: all-65.5 m depth passed the bad-pose check as
 * 100 % inliers and cleared the map's surfaces. */
#define VLFF_DEPTH_MAX_M 40.0

/* The largest magnitude a vision-language feature value may have: no
 * model's come near it, and a map of float16's 65504s drove the feature loss
 * from 0.05 to 1800 and into the checkpoint. In float16 bits, |x| above it
 * is (bits & 0x7FFF) > VLFF_FEATURE_MAX_ABS_F16 (NaN and Inf are above too). */
#define VLFF_FEATURE_MAX_ABS 1000.0
#define VLFF_FEATURE_MAX_ABS_F16 0x63D0u

/* A box-free check of a pose's units. A camera that moves farther between
 * two frames than the farthest depth either measured shares no surface
 * between them, and no tracker follows it across that: such a step says the
 * poses are not in metres (in millimetres every step is 1000 times too
 * long) or the tracker jumped. The bound is never under
 * VLFF_MIN_POSE_STEP_M, so that a camera facing a wall at arm's length is
 * not held to its depth, and never over VLFF_MAX_POSE_STEP_M, so that one
 * wild depth pixel does not switch the check off. 0 when plausible, -1
 * with *why set. */
#define VLFF_MIN_POSE_STEP_M 1.0
#define VLFF_MAX_POSE_STEP_M 100.0
int vlff_pose_step_plausible(const double prev_c2w[16], double prev_depth_max_m, const double c2w[16],
                             double depth_max_m, char *why, size_t whylen);

#endif
