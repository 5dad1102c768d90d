/* The labelled point set (PLY) parser. */
#include <stddef.h>
#include <stdint.h>

#include "dataset.h"

static volatile float sink;

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  struct vlff_points p;
  char err[256];
  if (vlff_ply_parse(data, size, "fuzz.ply", &p, err, sizeof err) == 0) {
    for (size_t i = 0; i < p.n; i++) sink += p.xyz[3 * i + 2] + p.label[i];
    vlff_points_free(&p);
  }
  return 0;
}
