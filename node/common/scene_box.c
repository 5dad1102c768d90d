/* A scene's box file into field.scene_min/max (scene_box.h). */
#include "scene_box.h"

#include <ctype.h>
#include <errno.h>
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "files.h"
#include "vlff/escape.h"

int vlff_scene_box_parse(const char *text, const char *name, double lo[3], double hi[3], char *err, size_t errlen) {
  double v[6];
  const char *s = text;
  for (int i = 0; i < 6; i++) {
    /* Commas separate like white space, as the scene reader takes bbox.txt
     * (formats.c), so a file vlff-eval reads the node reads too. */
    while (*s == ',' || isspace((unsigned char)*s)) s++;
    char *end;
    errno = 0;
    v[i] = strtod(s, &end);
    if (end == s) {
      snprintf(err, errlen, "%s: expected 6 numbers (min x y z, max x y z), got %d", VLFF_Q(name), i);
      return -1;
    }
    if (errno == ERANGE || !isfinite(v[i]) || fabs(v[i]) > 1e4) {
      snprintf(err, errlen, "%s: number %d is not a finite coordinate within 10 km", VLFF_Q(name), i + 1);
      return -1;
    }
    s = end;
  }
  while (*s == ',' || isspace((unsigned char)*s)) s++;
  if (*s) {
    snprintf(err, errlen, "%s: expected 6 numbers (min x y z, max x y z) and nothing after them", VLFF_Q(name));
    return -1;
  }
  for (int a = 0; a < 3; a++) {
    if (!(v[a] < v[a + 3])) {
      snprintf(err, errlen, "%s: axis %d has min %g >= max %g", VLFF_Q(name), a, v[a], v[a + 3]);
      return -1;
    }
  }
  for (int a = 0; a < 3; a++) lo[a] = v[a], hi[a] = v[a + 3];
  return 0;
}

int vlff_scene_box_read(const char *path, double lo[3], double hi[3], char *err, size_t errlen) {
  uint8_t *buf;
  size_t len;
  if (vlff_read_file(path, 4096, &buf, &len, err, errlen)) return -1;
  if (strlen((const char *)buf) != len) {
    free(buf);
    snprintf(err, errlen, "%s: holds a NUL byte; expected 6 numbers as text", VLFF_Q(path));
    return -1;
  }
  int rc = vlff_scene_box_parse((const char *)buf, path, lo, hi, err, errlen);
  free(buf);
  return rc;
}
