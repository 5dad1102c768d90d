/*
 * The label palette every picture vlff draws uses: snapshots, vlff-eval's
 * strips and PLY files, so that one class has one colour everywhere.
 */
#ifndef VLFF_PALETTE_H
#define VLFF_PALETTE_H

#include <stdint.h>

/* The colour vlff draws label k in (ScanNet's benchmark palette for the 20
 * classes, cycling beyond); black for k < 0 (no label). Pointer to 3 bytes. */
const uint8_t *vlff_label_color(int k);

#endif
