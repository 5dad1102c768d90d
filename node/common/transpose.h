/*
 * Transposes a rows x cols matrix of 16-bit values (row-major) into
 * dst[c * rows + r] = src[r * cols + c]. Feature maps cross module borders
 * in both layouts: the feature ring carries [D][h][w], the sim and the
 * keyframe store use [h][w][D]. src and dst must not overlap.
 */
#ifndef VLFF_TRANSPOSE_H
#define VLFF_TRANSPOSE_H

#include <stddef.h>
#include <stdint.h>

void vlff_transpose_u16(const uint16_t *src, size_t rows, size_t cols, uint16_t *dst);

#endif
