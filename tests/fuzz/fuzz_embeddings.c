/* Fuzz the embeddings-file parser: any bytes parse into a consistent set
 * or are refused with a message naming the file. */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include "embeddings.h"

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  char err[256] = "";
  struct vlff_embeddings *e = vlff_embeddings_parse((const char *)data, size, "fuzz", 0, err, sizeof err);
  if (!e) {
    if (strncmp(err, "fuzz", 4)) abort();
    return 0;
  }
  int d = vlff_embeddings_dim(e), n = vlff_embeddings_count(e);
  if (d < 1 || n < 1) abort();
  for (int i = 0; i < n; i++) {
    const float *v = vlff_embeddings_vector(e, i);
    for (int k = 0; k < d; k++)
      if (!isfinite(v[k])) abort();
    if (vlff_embeddings_lookup(e, vlff_embeddings_prompt(e, i)) != v) abort(); /* unique prompts */
  }
  vlff_embeddings_free(e);
  return 0;
}
