#include "vlm_fixture.h"

#include <setjmp.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include <cmocka.h>

static char dir[128];

bool fixture_have_torch(void) {
  if (system("/usr/bin/python3 -c 'import torch, onnx, numpy' >/dev/null 2>&1") == 0) return true;
  print_message("\n*** SKIPPED: /usr/bin/python3 cannot import torch/onnx/numpy (apt install python3-torch "
                "python3-onnx): the OpenCV-vs-PyTorch checks did NOT run ***\n\n");
  return false;
}

const char *fixture_dir(const char *tag) {
  snprintf(dir, sizeof dir, "/tmp/vlff-vlm-%s-%d", tag, (int)getpid());
  char cmd[400];
  snprintf(cmd, sizeof cmd, "rm -rf '%s' && mkdir -p '%s'", dir, dir);
  if (system(cmd) != 0) fail_msg("cannot create %s", dir);
  return dir;
}

void fixture_run(const char *cmd) {
  char full[4096];
  snprintf(full, sizeof full, "( %s ) > '%s/cmd.log' 2>&1", cmd, dir);
  if (system(full) != 0) {
    char log[300];
    snprintf(log, sizeof log, "cat '%s/cmd.log'", dir);
    if (system(log) != 0) print_message("(no log)\n");
    fail_msg("command failed: %s", cmd);
  }
}

void fixture_cleanup(void) {
  if (!dir[0]) return;
  char cmd[300];
  snprintf(cmd, sizeof cmd, "rm -rf '%s'", dir);
  if (system(cmd) != 0) print_message("could not remove %s\n", dir);
}

char *fixture_read(const char *path, size_t *len) {
  FILE *f = fopen(path, "rb");
  if (!f) fail_msg("cannot open %s", path);
  fseek(f, 0, SEEK_END);
  long n = ftell(f);
  fseek(f, 0, SEEK_SET);
  char *buf = malloc((size_t)n + 1);
  if (fread(buf, 1, (size_t)n, f) != (size_t)n) fail_msg("short read %s", path);
  fclose(f);
  buf[n] = 0;
  *len = (size_t)n;
  return buf;
}
