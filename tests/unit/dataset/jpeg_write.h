/* test_scannet's JPEG writer (OpenCV builds): RGB8 w x h at quality into a
 * malloc'd *out of *len bytes. 0, or -1. */
#ifndef VLFF_TEST_JPEG_WRITE_H
#define VLFF_TEST_JPEG_WRITE_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

int test_jpeg_encode(const uint8_t *rgb, int w, int h, int quality, uint8_t **out, size_t *len);

#ifdef __cplusplus
}
#endif

#endif
