/* PNG (and JPEG) decoding of dataset images from arbitrary bytes. */
#include <stddef.h>
#include <stdint.h>

#include "dataset.h"

static volatile uint8_t sink;

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  struct vlff_image im;
  char err[256];
  /* JPEG decoding is OpenCV's own code: fuzz only what we parse (PNG via our
   * libpng wrapper) */
  if (size >= 2 && data[0] == 0xff && data[1] == 0xd8) return 0;
  if (vlff_image_decode(data, size, "fuzz.png", &im, err, sizeof err) == 0) {
    /* touch every byte so a short allocation would be caught by ASan */
    size_t n = (size_t)im.width * im.height * im.channels * (im.depth16 ? 2 : 1);
    for (size_t i = 0; i < n; i++) sink ^= ((uint8_t *)im.data)[i];
    vlff_image_free(&im);
  }
  return 0;
}
