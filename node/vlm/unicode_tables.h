/*
 * Unicode facts for the CLIP tokenizer (generated tables, see
 * gen_unicode_tables.py): letter (\p{L}) and number (\p{N}) code-point
 * ranges and the simple lower-case mapping, all sorted for binary search.
 * Read-only data: safe from any thread.
 */
#ifndef VLFF_UNICODE_TABLES_H
#define VLFF_UNICODE_TABLES_H

#include <stddef.h>
#include <stdint.h>

struct vlff_uni_range {
  uint32_t lo, hi;
};
struct vlff_uni_pair {
  uint32_t from, to;
};

extern const struct vlff_uni_range vlff_uni_letters[];
extern const size_t vlff_uni_letters_count;
extern const struct vlff_uni_range vlff_uni_numbers[];
extern const size_t vlff_uni_numbers_count;
extern const struct vlff_uni_pair vlff_uni_lower[];
extern const size_t vlff_uni_lower_count;

#endif
