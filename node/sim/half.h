/*
 * float16 helpers of the sim/dataset/eval modules: node/field's conversion
 * (IEEE binary16, round to nearest even), so every module that handles
 * features agrees bit for bit.
 */
#ifndef VLFF_HALF_H
#define VLFF_HALF_H

#include <stdint.h>

#include "field.h"

static inline uint16_t vlff_half_from_f32(float x) { return vlff_f32_to_f16(x); }
static inline float vlff_half_to_f32(uint16_t h) { return vlff_f16_to_f32(h); }

#endif
