/*
 * Depth registration: a depth camera's range image re-expressed in the
 * colour camera, so that one frame record holds colour and depth of the
 * same pixels although two devices took them.
 *
 * Each depth pixel is undistorted, back-projected at its range, moved by
 * the depth-to-colour extrinsic and projected into the colour camera. It
 * covers the colour pixels whose centres fall inside the projection of its
 * own footprint (so upsampling leaves no cracks on a continuous surface),
 * nearest range wins (a z-buffer: a foreground object hides what the depth
 * camera saw behind it), and colour pixels nothing lands on stay 0
 * (invalid): disocclusions are holes, never interpolated.
 *
 * Conventions
 *  - Calibration as OpenCV's stereoCalibrate writes it, camera 1 = depth,
 *    camera 2 = colour: X_colour = R X_depth + T. Pixel coordinates are
 *    OpenCV's (the centre of pixel (0,0) is at (0,0)); distortion is
 *    OpenCV's Brown-Conrady model k1 k2 p1 p2 [k3 [k4 k5 k6]].
 *  - The output is at the colour camera's resolution or any other of about
 *    the same aspect (within VLFF_DEPTHREG_ASPECT_TOL), for the UNDISTORTED
 *    colour camera: the colour plane must be undistorted with the colour
 *    camera matrix kept (vlff_cv_undistort does that) and, at another size,
 *    resampled with pixel centres kept on pixel centres (vlff_cv_resize_rgb).
 *    Each axis scales by its own ratio (fx by out_w / colour_w, fy by
 *    out_h / colour_h, the principal point as (c + 0.5) * s - 0.5): exact
 *    for any size, the pixels non-square by the aspects' difference.
 *    vlff_depthreg_intrinsics gives the output camera.
 *  - Depth in is uint16 counts times unit_m metres (0 = invalid); depth out
 *    is uint16 millimetres along the colour camera's optical axis, 0 =
 *    invalid (VLFF_PIX_DEPTH_U16_MM).
 *
 * Calibration file (OpenCV FileStorage, YAML or XML, as cv::FileStorage
 * writes it):
 *    K1 (or M1, cameraMatrix1)   3x3  depth camera matrix
 *    D1 (or distCoeffs1)         4, 5 or 8 depth distortion coefficients
 *    K2 (or M2, cameraMatrix2)   3x3  colour camera matrix
 *    D2 (or distCoeffs2)         4, 5 or 8 colour distortion coefficients
 *    R                           3x3 rotation (or a 3x1 rotation vector)
 *    T                           3x1 translation, depth -> colour
 *    translation_unit_m          optional: metres per unit of T (the
 *                                calibration target's unit; default 1)
 *    depth_width depth_height color_width color_height   optional sizes
 *
 * Contract
 *  - int functions return 0 (or a documented count) on success and -1 on
 *    error with one line in err naming the file, the key and the bound
 *    that was broken. Every number read is checked against physical bounds
 *    (vlff_rgbd_calib_check) before anything uses it.
 *  - vlff_depthreg_new returns a registration for fixed image sizes, owned
 *    by the caller (vlff_depthreg_free, NULL accepted). It is immutable
 *    after creation except for its output scratch; one thread at a time.
 *  - Buffers are caller-owned; apply writes only the out_h rows of out.
 */
#ifndef VLFF_DEPTHREG_H
#define VLFF_DEPTHREG_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

#define VLFF_DIST_MAX 8
/* The largest relative difference between the output's aspect and the
 * colour images' that registration accepts: enough for a size rounded to
 * whole pixels (1280x720 -> 426x240), too little to hide a stretched image
 * (640x480 -> 640x360 is a crop, which the camera's ROI does). */
#define VLFF_DEPTHREG_ASPECT_TOL 0.01

struct vlff_rgbd_calib {
  double kd[9], dd[VLFF_DIST_MAX]; /* depth camera matrix (row-major) and distortion */
  int nd;                          /* distortion coefficients given: 4, 5 or 8 */
  double kc[9], dc[VLFF_DIST_MAX]; /* colour camera */
  int nc;
  double r[9];                     /* depth -> colour rotation, row-major */
  double t[3];                     /* depth -> colour translation, metres */
  int depth_w, depth_h, color_w, color_h; /* 0 when the file does not say */
};

/* Reads and checks a calibration file (the format above). */
int vlff_rgbd_calib_load(const char *path, struct vlff_rgbd_calib *c, char *err, size_t errlen);
/* The physical bounds every calibration must meet: focal lengths 1..1e5
 * px, aspect fx/fy within 0.2..5, no skew, a [0 0 1] last row, finite
 * distortion of magnitude < 1000, R orthonormal with det +1 (to 1e-4), T
 * finite and under 1 m (two cameras of one rig); when image sizes are given,
 * sizes 1..16384, bounds.h's field of view and aspect, and principal points
 * inside the images. name prefixes the message. */
int vlff_rgbd_calib_check(const struct vlff_rgbd_calib *c, const char *name, char *err, size_t errlen);

struct vlff_depthreg;
/* For depth images of depth_w x depth_h and colour images of color_w x
 * color_h; out_w x out_h = 0 x 0 means the colour size, otherwise its
 * aspect must be the colour images' within VLFF_DEPTHREG_ASPECT_TOL. Fails when a size disagrees with the
 * calibration's, a principal point lies outside its image, or a distortion
 * does not invert over the image. */
struct vlff_depthreg *vlff_depthreg_new(const struct vlff_rgbd_calib *c, int depth_w, int depth_h, int color_w,
                                        int color_h, int out_w, int out_h, char *err, size_t errlen);
void vlff_depthreg_free(struct vlff_depthreg *r);
/* Whether an output of out_w x out_h has the aspect of color_w x color_h
 * images within VLFF_DEPTHREG_ASPECT_TOL (all sizes positive). */
bool vlff_depthreg_aspect_ok(int out_w, int out_h, int color_w, int color_h);
/* The output camera: fx fy cx cy (OpenCV pixel convention) and its size. */
void vlff_depthreg_intrinsics(const struct vlff_depthreg *r, double k[4], int *out_w, int *out_h);
/* Registers one depth image (depth_w x depth_h uint16, rows stride bytes
 * apart, value * unit_m = metres, unit_m in (0, 1]) into out (out_w x
 * out_h uint16 mm, rows out_stride bytes apart). Returns the number of
 * valid output pixels, or -1 (bad unit or strides). */
long vlff_depthreg_apply(struct vlff_depthreg *r, const uint16_t *depth, size_t stride, double unit_m,
                         uint16_t *out, size_t out_stride, char *err, size_t errlen);

/* The distortion model, exposed for tests and tools: normalised
 * undistorted (x, y) -> distorted, and its inverse (0, or -1 when the
 * iteration does not converge). */
void vlff_distort_point(const double *dist, int n, double x, double y, double *xd, double *yd);
int vlff_undistort_point(const double *dist, int n, double xd, double yd, double *x, double *y);

#ifdef __cplusplus
}
#endif

#endif
