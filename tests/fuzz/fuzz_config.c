/* libFuzzer target: any byte string must parse or be rejected cleanly,
 * the limits' pre-pass (depth, events, anchors, aliases, directives) and
 * the loader alike; seeds with anchors, aliases, %TAG directives, duplicate
 * keys, NUL escapes and leading zeros start it on each. */
#include <stddef.h>
#include <stdint.h>
#include <string.h>

#include "config.h"
#include "vlff/shm.h"

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  struct vlff_config cfg;
  char err[512];
  err[0] = 0;
  int rc = vlff_config_load_mem((const char *)data, size, "fuzz", &cfg, err, sizeof err);
  /* A rejection must always say why; an acceptance must be self-consistent. */
  if (rc != 0 && strncmp(err, "fuzz:", 5) != 0) __builtin_trap();
  /* What the file says is quoted escaped: a NUL in a key, a control byte
   * in a value, never reach the message raw. */
  for (const char *c = err; *c; c++)
    if ((unsigned char)*c < 0x20 || *c == 0x7f) __builtin_trap();
  if (rc == 0 && cfg.prompts.active >= cfg.prompts.set_count) __builtin_trap();
  /* Every prompt set taken is one the mailbox would take. */
  for (int s = 0; rc == 0 && s < cfg.prompts.set_count; s++) {
    const char *texts[VLFF_MAX_PROMPTS];
    for (int i = 0; i < cfg.prompts.sets[s].count; i++) texts[i] = cfg.prompts.sets[s].text[i];
    if (vlff_prompt_check(texts, cfg.prompts.sets[s].count) != 0) __builtin_trap();
  }
  return 0;
}
