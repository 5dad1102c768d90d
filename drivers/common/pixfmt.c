/* GenICam pixel format names <-> enum vlff_pix. */
#include "pixfmt.h"

#include <string.h>

static const struct {
  vlff_pix_t pix;
  const char *name;
  size_t bytes;
} table[] = {
    {VLFF_PIX_MONO8, "Mono8", 1},         {VLFF_PIX_MONO16, "Mono16", 2},
    {VLFF_PIX_RGB8, "RGB8", 3},           {VLFF_PIX_BGR8, "BGR8", 3},
    {VLFF_PIX_BAYER_RG8, "BayerRG8", 1},  {VLFF_PIX_BAYER_BG8, "BayerBG8", 1},
    {VLFF_PIX_BAYER_GR8, "BayerGR8", 1},  {VLFF_PIX_BAYER_GB8, "BayerGB8", 1},
    /* GenICam's 3D range component: 16-bit unsigned, laid out as Mono16. */
    {VLFF_PIX_MONO16, "Coord3D_C16", 2},
};

#define N (sizeof table / sizeof table[0])

vlff_pix_t vlff_pix_from_name(const char *name) {
  for (size_t i = 0; i < N; i++)
    if (!strcmp(table[i].name, name)) return table[i].pix;
  return VLFF_PIX_INVALID;
}

const char *vlff_pix_name(vlff_pix_t pix) {
  for (size_t i = 0; i < N; i++)
    if (table[i].pix == pix) return table[i].name;
  return "invalid";
}

size_t vlff_pix_bytes(vlff_pix_t pix) {
  for (size_t i = 0; i < N; i++)
    if (table[i].pix == pix) return table[i].bytes;
  return 0;
}

const char *vlff_pix_names(void) {
  return "Mono8, Mono16, RGB8, BGR8, BayerRG8, BayerBG8, BayerGR8, BayerGB8, Coord3D_C16";
}
