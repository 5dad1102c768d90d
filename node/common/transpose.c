#include "transpose.h"

/* In tiles of 16 output rows x 64 output columns: the tile's source lines
 * stay cached while each output row is written contiguously. Wider tiles put
 * the strided source lines into the same cache sets; both row by row and
 * square tiles were slower on feature maps. */
void vlff_transpose_u16(const uint16_t *src, size_t rows, size_t cols, uint16_t *dst) {
  enum { TILE_C = 16, TILE_R = 64 };
  for (size_t c0 = 0; c0 < cols; c0 += TILE_C) {
    size_t c1 = cols - c0 < TILE_C ? cols : c0 + TILE_C;
    for (size_t r0 = 0; r0 < rows; r0 += TILE_R) {
      size_t r1 = rows - r0 < TILE_R ? rows : r0 + TILE_R;
      for (size_t c = c0; c < c1; c++) {
        uint16_t *out = dst + c * rows;
        for (size_t r = r0; r < r1; r++) out[r] = src[r * cols + c];
      }
    }
  }
}
