/*
 * Pixel formats the drivers accept from cameras, by GenICam name.
 *
 * Contract
 *  - vlff_pix_from_name() maps a GenICam PixelFormat name ("BayerRG8") to
 *    the enum; unknown names give VLFF_PIX_INVALID. Names are case-sensitive
 *    because GenICam's are.
 *  - Pure functions; thread-safe.
 */
#ifndef VLFF_PIXFMT_H
#define VLFF_PIXFMT_H

#include <stddef.h>

enum vlff_pix {
  VLFF_PIX_INVALID = 0,
  VLFF_PIX_MONO8,
  VLFF_PIX_MONO16,
  VLFF_PIX_RGB8,
  VLFF_PIX_BGR8,
  VLFF_PIX_BAYER_RG8,
  VLFF_PIX_BAYER_BG8,
  VLFF_PIX_BAYER_GR8,
  VLFF_PIX_BAYER_GB8,
};

enum vlff_pix vlff_pix_from_name(const char *name);
const char *vlff_pix_name(enum vlff_pix pix);
/* Bytes per pixel of the packed format (Bayer: one sample). 0 for INVALID. */
size_t vlff_pix_bytes(enum vlff_pix pix);
int vlff_pix_is_bayer(enum vlff_pix pix);
/* Comma-separated list of accepted names, for error messages. */
const char *vlff_pix_names(void);

#endif
