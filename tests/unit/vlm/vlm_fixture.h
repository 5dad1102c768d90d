/* Test fixture shared by the vlm tests: export small random models with
 * the user-facing scripts (python3-torch) into a per-process directory. */
#ifndef VLFF_TEST_VLM_FIXTURE_H
#define VLFF_TEST_VLM_FIXTURE_H

#include <stdbool.h>
#include <stddef.h>

/* true when /usr/bin/python3 can import torch and onnx; otherwise prints
 * a loud notice (the caller then skips). */
bool fixture_have_torch(void);
/* /tmp/vlff-vlm-<tag>-<pid>, created. */
const char *fixture_dir(const char *tag);
/* Run a command, failing the test with its output on error. */
void fixture_run(const char *cmd);
void fixture_cleanup(void);
char *fixture_read(const char *path, size_t *len);

#endif
