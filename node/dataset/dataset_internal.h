/* Shared between the dataset module's files; not installed. */
#ifndef VLFF_DATASET_INTERNAL_H
#define VLFF_DATASET_INTERNAL_H

#include <stddef.h>
#include <stdint.h>

#include "log.h" /* vlff_errf for error messages */

/* JPEG decoding through OpenCV (jpeg_cv.cpp): RGB8 rows, malloc'd. */
int vlff_cv_decode_jpeg(const uint8_t *buf, size_t len, int max_side, int *w, int *h, uint8_t **rgb,
                        char *err, size_t errlen);

#endif
