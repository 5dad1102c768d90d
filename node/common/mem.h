/*
 * Freeing the plain buffers a struct owns, in one statement.
 *
 * Destructors of structs that own many malloc'd arrays otherwise spell one
 * free() per member; VLFF_FREE_ALL(p->a, p->b, ...) frees each in order.
 *
 * Contract: every argument is a pointer returned by malloc, calloc or
 * realloc, or NULL; none is freed twice. Header-only, thread-safe.
 */
#ifndef VLFF_MEM_H
#define VLFF_MEM_H

#include <stddef.h>
#include <stdlib.h>

static inline void vlff_free_each(void *const *ptrs, size_t n) {
  for (size_t i = 0; i < n; i++) free(ptrs[i]);
}

#define VLFF_FREE_ALL(...)                          \
  vlff_free_each((void *const[]){__VA_ARGS__},      \
                 sizeof((void *const[]){__VA_ARGS__}) / sizeof(void *))

#endif
