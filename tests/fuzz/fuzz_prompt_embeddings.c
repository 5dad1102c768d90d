/* The prompt embeddings file parser. */
#include <stddef.h>
#include <stdint.h>

#include "dataset.h"

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  struct vlff_prompt_embeddings e;
  char err[256];
  if (vlff_prompt_embeddings_parse((const char *)data, size, "fuzz.txt", 0, &e, err, sizeof err) == 0) {
    (void)vlff_prompt_embeddings_find(&e, "chair");
    vlff_prompt_embeddings_free(&e);
  }
  return 0;
}
