/* Shared between the dataset module's files; not installed. */
#ifndef VLFF_DATASET_INTERNAL_H
#define VLFF_DATASET_INTERNAL_H

#include <stddef.h>
#include <stdint.h>

#include "log.h" /* vlff_errf for error messages */

/* JPEG decoding through OpenCV (jpeg_cv.cpp): RGB8 rows, malloc'd. */
int vlff_cv_decode_jpeg(const uint8_t *buf, size_t len, int max_side, int *w, int *h, uint8_t **rgb,
                        char *err, size_t errlen);

/* ScanNet (scannet.c). */
struct vlff_dataset;
struct vlff_image;
int vlff_scannet_labels_load(struct vlff_dataset *ds, const char *path, int set, char *err, size_t errlen);
/* Sets the output geometry from both cameras (see scannet.c's comment). */
int vlff_scannet_geometry(struct vlff_dataset *ds, const double Kc[16], int cw, int ch, const double Kd[16],
                          int dw, int dh, const double Ec[16], const double Ed[16], const char *where, char *err,
                          size_t errlen);
void vlff_scannet_resample_rgb(const struct vlff_dataset *ds, const uint8_t *src, uint8_t *dst);
/* dmm: [depth_height][depth_width] stored units; scale: metres per unit. */
void vlff_scannet_register_depth(const struct vlff_dataset *ds, const uint16_t *dmm, double scale, float *out);
int vlff_scannet_map_labels(const struct vlff_dataset *ds, const struct vlff_image *im, const char *path,
                            uint8_t *label, char *err, size_t errlen);
int vlff_sens_open(struct vlff_dataset *ds, const char *path, char *err, size_t errlen);
/* Frame i's colour (RGB8 at the colour size) and depth (stored units at the
 * depth size), malloc'd; either output may be NULL. */
int vlff_sens_read(const struct vlff_dataset *ds, int i, uint8_t **rgb, uint16_t **depth, char *err,
                   size_t errlen);
float vlff_sens_depth_scale(const struct vlff_dataset *ds);
/* The labelled mesh's path for a scene directory of a layout (sens: the
 * .sens file's path or NULL), checked to open (see vlff_dataset_points_path). */
int vlff_scannet_points_path(const char *dir, int layout, const char *sens, char *path, size_t cap, char *err,
                             size_t errlen);
/* Frame i's colour timestamp as the file stores it (microseconds). */
int vlff_sens_stamp_us(const struct vlff_dataset *ds, int i, uint64_t *us);
void vlff_sens_close(struct vlff_sens *s);

#endif
