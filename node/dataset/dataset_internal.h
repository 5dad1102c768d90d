/* Shared between the dataset module's files; not installed. */
#ifndef VLFF_DATASET_INTERNAL_H
#define VLFF_DATASET_INTERNAL_H

#include <stddef.h>
#include <stdint.h>

void vlff_ds_seterr(char *err, size_t errlen, const char *fmt, ...) __attribute__((format(printf, 3, 4)));

/* JPEG decoding through OpenCV (jpeg_cv.cpp): RGB8 rows, malloc'd. */
int vlff_cv_decode_jpeg(const uint8_t *buf, size_t len, int max_side, int *w, int *h, uint8_t **rgb,
                        char *err, size_t errlen);

#endif
