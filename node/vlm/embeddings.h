/*
 * vlff_embeddings: the prompt -> vector file, for deployments that
 * precompute text embeddings instead of running the text encoder
 * (config key prompts.embeddings).
 *
 * Format (UTF-8 text, one record a line, '\n' line ends):
 *     vlff-embeddings 1
 *     dim 512
 *     # comment lines and empty lines are ignored
 *     chair<TAB>0.0123 -0.0456 ... (exactly dim numbers, single spaces)
 * A prompt is 1..63 bytes of valid UTF-8 without control characters,
 * unique in the file; the numbers are finite, and the vector's length is
 * VLFF_EMBEDDINGS_MIN_NORM to VLFF_EMBEDDINGS_MAX_NORM (only its direction
 * is used, but a length far outside any encoder's is not an embedding, and
 * its products overflow or flush to zero in float). At most
 * VLFF_EMBEDDINGS_MAX prompts. Vectors are stored as given (the field
 * normalises).
 *
 * Contract
 *  - Loaders return NULL with one line "file:line: what" in err on any
 *    violation; nothing partial is ever returned.
 *  - The object is immutable after loading: lookups may run from any
 *    thread. The caller frees it with vlff_embeddings_free().
 *  - vlff_embeddings_save() writes atomically (temp file, fsync, rename).
 */
#ifndef VLFF_EMBEDDINGS_H
#define VLFF_EMBEDDINGS_H

#include <stddef.h>

#define VLFF_EMBEDDINGS_MAX 4096
#define VLFF_EMBEDDINGS_MAX_BYTES (64u << 20)
#define VLFF_EMBEDDINGS_MIN_NORM 1e-6
#define VLFF_EMBEDDINGS_MAX_NORM 1e6

struct vlff_embeddings;

/* expected_dim: the field's D, or 0 to accept any dimension. */
struct vlff_embeddings *vlff_embeddings_load(const char *path, int expected_dim, char *err, size_t errlen);
struct vlff_embeddings *vlff_embeddings_parse(const char *buf, size_t len, const char *name, int expected_dim,
                                              char *err, size_t errlen);
void vlff_embeddings_free(struct vlff_embeddings *e);

int vlff_embeddings_dim(const struct vlff_embeddings *e);
int vlff_embeddings_count(const struct vlff_embeddings *e);
const char *vlff_embeddings_prompt(const struct vlff_embeddings *e, int i);
const float *vlff_embeddings_vector(const struct vlff_embeddings *e, int i);
/* The vector of prompt (exact match), or NULL. Valid while e lives. */
const float *vlff_embeddings_lookup(const struct vlff_embeddings *e, const char *prompt);

/* Write count prompts with vectors [count][dim]. 0 or -1 with err. */
int vlff_embeddings_save(const char *path, int dim, int count, const char *const *prompts, const float *vectors,
                         char *err, size_t errlen);

#endif
