/* Fuzz the CLIP tokenizer's prompt path: any bytes must give ids in the
 * vocabulary or a clean error, never a crash. */
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "tokenizer.h"

static struct vlff_tokenizer *tok;

int LLVMFuzzerInitialize(int *argc, char ***argv) {
  const char *dir = getenv("VLFF_DATA_DIR");
  char path[1024];
  snprintf(path, sizeof path, "%s/bpe_simple_vocab_16e6.txt.gz", dir ? dir : VLFF_DATA_DEFAULT);
  char err[512];
  tok = vlff_tokenizer_open(path, err, sizeof err);
  if (!tok) {
    fprintf(stderr, "fuzz_tokenizer: %s\n", err);
    abort();
  }
  return 0;
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  int32_t ids[VLFF_CLIP_CONTEXT];
  char err[256];
  long n = vlff_tokenizer_encode(tok, (const char *)data, size, ids, VLFF_CLIP_CONTEXT, err, sizeof err);
  for (long i = 0; i < n && i < VLFF_CLIP_CONTEXT; i++)
    if (ids[i] < 0 || ids[i] >= VLFF_CLIP_VOCAB) abort();
  if (n < 0 && !err[0]) abort();
  /* Cleaning grows text by at most 3 bytes for 2 (U+0130 -> i + U+0307). */
  if (n > 2 * (long)size) abort();
  return 0;
}
