/*
 * The drivers' only contact with OpenCV: a plain C interface over a C++
 * file, so the rest of the drivers stay C17.
 *
 * Contract
 *  - Every function returns 0 on success, or -1 with err filled with one
 *    line naming what failed. No C++ exception ever crosses this header:
 *    each entry point catches everything OpenCV throws.
 *  - Buffers are caller-owned; functions write only within [dst, dst +
 *    dstride * h). Destination strides may differ from source strides.
 *  - Objects from *_new() are owned by the caller and freed with their
 *    *_free(); NULL is accepted by *_free(). An object is immutable after
 *    *_new() and may be used from one thread at a time (OpenCV scratch
 *    memory lives inside it).
 */
#ifndef VLFF_CVSHIM_H
#define VLFF_CVSHIM_H

#include <stddef.h>
#include <stdint.h>

#include "pixfmt.h"

#ifdef __cplusplus
extern "C" {
#endif

/* Convert one image of format fmt to packed RGB8. Bayer patterns are named
 * the GenICam way (the colour of the first two pixels of the first row).
 * Mono16 is not a colour format and is refused. */
int vlff_cv_to_rgb(const void *src, size_t sstride, int w, int h, vlff_pix_t fmt, uint8_t *dst,
                   size_t dstride, char *err, size_t errlen);

/* Compress a packed RGB8 image (stride bytes a row) as JPEG (png 0, quality
 * 1..100) or PNG (png 1, quality ignored) into a malloc'd buffer *out of *len
 * bytes, which the caller frees. */
int vlff_cv_compress_rgb(const uint8_t *rgb, size_t stride, int w, int h, int png, int quality, uint8_t **out,
                         size_t *len, char *err, size_t errlen);

/* Resample a packed RGB8 image from sw x sh to dw x dh, pixel centres on
 * pixel centres (output pixel (u, v) samples input (u + 0.5) * sw / dw - 0.5,
 * likewise in v): area averaging when both sides shrink (no aliasing of fine
 * texture), bilinear otherwise. */
int vlff_cv_resize_rgb(const uint8_t *src, size_t sstride, int sw, int sh, uint8_t *dst, size_t dstride, int dw,
                       int dh, char *err, size_t errlen);

/* A pinhole + Brown-Conrady (k1 k2 p1 p2 k3) undistortion for a fixed image
 * size. The output keeps the input's camera matrix. */
struct vlff_cv_undistort;
struct vlff_cv_undistort *vlff_cv_undistort_new(int w, int h, const double k[4], const double dist[5],
                                                char *err, size_t errlen);
/* channels: 1 (uint8), 3 (RGB8); 2-byte single channel when bytes_per_sample
 * is 2 (uint16 depth: nearest-neighbour so no depth is invented). */
int vlff_cv_undistort_apply(struct vlff_cv_undistort *u, const void *src, size_t sstride, void *dst,
                            size_t dstride, int channels, int bytes_per_sample, char *err,
                            size_t errlen);
void vlff_cv_undistort_free(struct vlff_cv_undistort *u);

/* Calibration as read from an OpenCV FileStorage YAML: camera_matrix and
 * distortion_coefficients (and image_width/image_height when present), or
 * the stereo keys M1 D1 M2 D2 R T of OpenCV's stereo_calib. */
struct vlff_cv_calib {
  int has_mono, has_stereo;
  int width, height;       /* 0 when the file does not say */
  double k[9], dist[5];    /* mono: camera_matrix, distortion_coefficients */
  double k1[9], d1[5], k2[9], d2[5], r[9], t[3]; /* stereo */
};
int vlff_cv_calib_load(const char *path, struct vlff_cv_calib *out, char *err, size_t errlen);

/* The raw contents of a depth-to-colour calibration file (depthreg.h lists
 * the keys): matrices as written, T in the file's units, *t_unit_m the
 * file's translation_unit_m (1 when absent). No bounds are checked here
 * beyond shapes and finiteness: vlff_rgbd_calib_load does that. */
struct vlff_rgbd_calib;
int vlff_cv_rgbd_calib_read(const char *path, struct vlff_rgbd_calib *out, double *t_unit_m, char *err,
                            size_t errlen);

/* Stereo depth from a rectifiable pair: rectification from the calibration,
 * then semi-global block matching. Each eye is w x h. */
struct vlff_cv_stereo;
struct vlff_cv_stereo *vlff_cv_stereo_new(const struct vlff_cv_calib *c, int w, int h,
                                          int disparities, char *err, size_t errlen);
/* Rectified left eye's intrinsics (fx fy cx cy) and the baseline in metres. */
void vlff_cv_stereo_geometry(const struct vlff_cv_stereo *s, double k[4], double *baseline_m);
/* left/right: RGB8 eyes (strides may differ). Writes the rectified left
 * RGB8 image and the depth in metres (0 = no valid disparity). */
int vlff_cv_stereo_compute(struct vlff_cv_stereo *s, const uint8_t *left, size_t lstride,
                           const uint8_t *right, size_t rstride, uint8_t *rect_left, size_t rect_stride,
                           float *depth_m, size_t depth_stride, char *err, size_t errlen);
void vlff_cv_stereo_free(struct vlff_cv_stereo *s);

#ifdef __cplusplus
}
#endif

#endif
