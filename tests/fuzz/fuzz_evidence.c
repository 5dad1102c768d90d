/* Saved per-voxel evidence (part of the publisher's observation file). */
#include <stddef.h>
#include <stdint.h>

#include "evidence.h"

static volatile float sink;

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  static struct vlff_evidence *e;
  static const double origin[3] = {-1, -1, 0};
  static const uint32_t dims[3] = {4, 4, 4};
  char err[256];
  if (!e) e = vlff_evidence_create(origin, dims, 0.5, 4, VLFF_MAX_PROMPTS, 4096, err, sizeof err);
  if (!e) return 0;
  if (vlff_evidence_load(e, data, size, err, sizeof err) == 0) {
    float f[4];
    for (long vi = 0; vi < 64; vi++)
      if (vlff_evidence_get(e, vi, f)) sink += f[0] + f[3];
  }
  return 0;
}
