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

/* The formats are the frame ring's (enum vlff_pixfmt of vlff/shm.h), so a
 * raw camera format and a ring plane format are one vocabulary. */
#include <vlff/shm.h>
#define VLFF_PIX_INVALID VLFF_PIX_NONE
typedef enum vlff_pixfmt vlff_pix_t;

vlff_pix_t vlff_pix_from_name(const char *name);
const char *vlff_pix_name(vlff_pix_t pix);
/* Bytes per pixel of the packed format (Bayer: one sample). 0 for INVALID. */
size_t vlff_pix_bytes(vlff_pix_t pix);
/* Comma-separated list of accepted names, for error messages. */
const char *vlff_pix_names(void);

#endif
