/* The text parsers of scene directories: pose/intrinsics matrices (and the
 * pose check and the physical bounds of bounds.h) and bbox.txt. */
#include <stddef.h>
#include <stdint.h>

#include "bounds.h"
#include "dataset.h"

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  char err[256];
  double m[16], lo[3], hi[3];
  if (vlff_parse_matrix((const char *)data, size, "fuzz.txt", m, err, sizeof err) == 0) {
    (void)vlff_check_pose(m, "fuzz.txt", err, sizeof err);
    /* The same matrix read as intrinsics (at 640x480) and as a pose. */
    (void)vlff_intrinsics_plausible(640, 480, m[0], m[5], m[2], m[6], err, sizeof err);
    (void)vlff_pose_plausible(m, NULL, NULL, err, sizeof err);
  }
  (void)vlff_parse_bbox((const char *)data, size, "bbox.txt", lo, hi, err, sizeof err);
  return 0;
}
