/*
 * Why bounds on the field of view rather than on fx alone: a focal length
 * means nothing without the image size it is given at (the node rescales
 * frames for training), while a field of view is a property of the lens.
 */
#include "bounds.h"

#include <math.h>
#include <stdio.h>

#include "config.h"

static int say(char *why, size_t whylen, const char *msg, double v, double lo, double hi) {
  if (why && whylen) snprintf(why, whylen, msg, v, lo, hi);
  return -1;
}

/* Focal length range, in pixels, for an axis of n pixels. */
static void focal_range(int n, double *lo, double *hi) {
  const double deg = M_PI / 180.0;
  *lo = n / (2.0 * tan(VLFF_MAX_FOV_DEG * 0.5 * deg));
  *hi = n / (2.0 * tan(VLFF_MIN_FOV_DEG * 0.5 * deg));
}

int vlff_skew_plausible(double fx, double skew, char *why, size_t whylen) {
  if (fabs(skew) <= VLFF_MAX_SKEW_FRAC * fx) return 0;
  if (why && whylen) snprintf(why, whylen, "skew %g is more than %g %% of fx=%g; the camera model has none", skew,
                              100 * VLFF_MAX_SKEW_FRAC, fx);
  return -1;
}

int vlff_intrinsics_plausible(int width, int height, double fx, double fy, double cx, double cy, char *why,
                              size_t whylen) {
  if (width < 1 || height < 1 || width > VLFF_MAX_IMAGE_SIDE || height > VLFF_MAX_IMAGE_SIDE) {
    if (why && whylen)
      snprintf(why, whylen, "image size %dx%d outside 1..%d pixels per side", width, height, VLFF_MAX_IMAGE_SIDE);
    return -1;
  }
  double lo, hi;
  focal_range(width, &lo, &hi);
  if (!(fx >= lo && fx <= hi))
    return say(why, whylen, "fx %g outside [%g, %g] (a field of view of 1 to 170 degrees at this width)", fx, lo, hi);
  focal_range(height, &lo, &hi);
  if (!(fy >= lo && fy <= hi))
    return say(why, whylen, "fy %g outside [%g, %g] (a field of view of 1 to 170 degrees at this height)", fy, lo, hi);
  double aspect = fx / fy;
  if (!(aspect >= 1.0 / VLFF_MAX_PIXEL_ASPECT && aspect <= VLFF_MAX_PIXEL_ASPECT))
    return say(why, whylen, "pixel aspect fx/fy %g outside [%g, %g]", aspect, 1.0 / VLFF_MAX_PIXEL_ASPECT,
               VLFF_MAX_PIXEL_ASPECT);
  if (!(cx >= -0.5 * width && cx <= 1.5 * width))
    return say(why, whylen, "cx %g outside [%g, %g] (the image grown by half its width)", cx, -0.5 * width,
               1.5 * width);
  if (!(cy >= -0.5 * height && cy <= 1.5 * height))
    return say(why, whylen, "cy %g outside [%g, %g] (the image grown by half its height)", cy, -0.5 * height,
               1.5 * height);
  return 0;
}

static int pose_in_world(const double c2w[16], double limit, char *why, size_t whylen) {
  const char axis[3] = {'x', 'y', 'z'};
  for (int i = 0; i < 3; i++) {
    double t = c2w[i * 4 + 3];
    if (!(fabs(t) <= limit)) {
      if (why && whylen)
        snprintf(why, whylen, "camera %c = %g m outside [%g, %g] (field.world_limit_m)", axis[i], t, -limit, limit);
      return -1;
    }
  }
  return 0;
}

int vlff_field_pose_plausible(const struct vlff_cfg_field *field, const double c2w[16], char *why, size_t whylen) {
  return field->grow ? pose_in_world(c2w, field->world_limit_m, why, whylen)
                     : vlff_pose_plausible(c2w, field->scene_min, field->scene_max, why, whylen);
}

int vlff_pose_step_plausible(const double prev_c2w[16], double prev_depth_max_m, const double c2w[16],
                             double depth_max_m, char *why, size_t whylen) {
  double dx = c2w[3] - prev_c2w[3], dy = c2w[7] - prev_c2w[7], dz = c2w[11] - prev_c2w[11];
  double step = sqrt(dx * dx + dy * dy + dz * dz);
  double bound = fmin(VLFF_MAX_POSE_STEP_M, fmax(VLFF_MIN_POSE_STEP_M, fmax(prev_depth_max_m, depth_max_m)));
  if (step <= bound) return 0;
  if (why && whylen)
    snprintf(why, whylen, "camera moved %g m since the keyframe candidate before, farther than the %g m either "
             "frame's depth reaches", step, bound);
  return -1;
}

int vlff_pose_plausible(const double c2w[16], const double lo[3], const double hi[3], char *why, size_t whylen) {
  const char axis[3] = {'x', 'y', 'z'};
  double grow = 0;
  if (lo && hi)
    for (int i = 0; i < 3; i++) grow = fmax(grow, hi[i] - lo[i]);
  for (int i = 0; i < 3; i++) {
    double t = c2w[i * 4 + 3];
    double a = lo && hi ? lo[i] - grow : -VLFF_MAX_POSE_ABS_M, b = lo && hi ? hi[i] + grow : VLFF_MAX_POSE_ABS_M;
    if (!(t >= a && t <= b)) {
      if (why && whylen)
        snprintf(why, whylen, "camera %c = %g m outside [%g, %g] (%s)", axis[i], t, a, b,
                 lo && hi ? "the scene box grown by its largest extent" : "no scene box: an absolute bound");
      return -1;
    }
  }
  return 0;
}
