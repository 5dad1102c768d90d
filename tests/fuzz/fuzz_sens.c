/* ScanNet's .sens stream reader: any bytes as a .sens file must open with a
 * clean error or give frames whose reads succeed or fail cleanly. */
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "dataset.h"

static char path[64];

int LLVMFuzzerInitialize(int *argc, char ***argv) {
  (void)argc, (void)argv;
  snprintf(path, sizeof path, "/tmp/vlff-fuzz-%ld.sens", (long)getpid());
  return 0;
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  FILE *f = fopen(path, "wb");
  if (!f) abort();
  fwrite(data, 1, size, f);
  fclose(f);
  struct vlff_dataset ds;
  char err[512];
  if (vlff_dataset_open(&ds, path, VLFF_DS_SENS, err, sizeof err) == 0) {
    /* frames as large as a real camera's; the reader's own caps are wider */
    if ((size_t)ds.width * ds.height <= (1u << 20) &&
        (size_t)ds.color_width * ds.color_height <= (1u << 22)) {
      size_t px = (size_t)ds.width * ds.height;
      uint8_t *rgb = malloc(px * 3);
      float *depth = malloc(px * sizeof *depth);
      if (rgb && depth) vlff_dataset_read_frame(&ds, 0, rgb, depth, NULL, err, sizeof err);
      free(rgb), free(depth);
    }
    vlff_dataset_close(&ds);
  }
  unlink(path);
  return 0;
}
