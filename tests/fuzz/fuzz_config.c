/* libFuzzer target: any byte string must parse or be rejected cleanly. */
#include <stddef.h>
#include <stdint.h>
#include <string.h>

#include "config.h"

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  struct vlff_config cfg;
  char err[512];
  err[0] = 0;
  int rc = vlff_config_load_mem((const char *)data, size, "fuzz", &cfg, err, sizeof err);
  /* A rejection must always say why; an acceptance must be self-consistent. */
  if (rc != 0 && strncmp(err, "fuzz:", 5) != 0) __builtin_trap();
  if (rc == 0 && cfg.prompts.active >= cfg.prompts.set_count) __builtin_trap();
  return 0;
}
