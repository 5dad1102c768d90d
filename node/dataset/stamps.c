/* A recording's frame times (dataset.h: vlff_dataset_stamps). */
#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "dataset.h"
#include "dataset_internal.h"
#include "files.h"
#include "vlff/escape.h"

/* A gap longer than this is no frame rate: a replay would sit idle for it. */
#define MAX_GAP_S 60.0

static int check(const struct vlff_dataset *ds, const double *abs_t, const char *name, double *t, char *err,
                 size_t errlen) {
  for (int i = 0; i < ds->n; i++) {
    if (!isfinite(abs_t[i])) {
      snprintf(err, errlen, "%s: frame %s: stamp is not a finite number", VLFF_Q(name), VLFF_Q(ds->stem[i]));
      return -1;
    }
    double d = i ? abs_t[i] - abs_t[i - 1] : 0;
    if (d < 0 || d > MAX_GAP_S) {
      snprintf(err, errlen, "%s: frame %s: stamp %.6f s is %.6f s after the previous frame's; expected 0 to %g",
               VLFF_Q(name), VLFF_Q(ds->stem[i]), abs_t[i], d, MAX_GAP_S);
      return -1;
    }
  }
  for (int i = 0; i < ds->n; i++) t[i] = abs_t[i] - abs_t[0];
  return 1;
}

static int from_sens(const struct vlff_dataset *ds, double *t, char *err, size_t errlen) {
  double *a = malloc((size_t)ds->n * sizeof *a);
  if (!a) return snprintf(err, errlen, "out of memory"), -1;
  int any = 0;
  for (int i = 0; i < ds->n; i++) {
    uint64_t us;
    if (vlff_sens_stamp_us(ds, i, &us) < 0) {
      free(a);
      snprintf(err, errlen, "%s: frame %s: cannot read its stamps", VLFF_Q(ds->dir), VLFF_Q(ds->stem[i]));
      return -1;
    }
    any |= us != 0;
    a[i] = (double)us * 1e-6;
  }
  int rc = any ? check(ds, a, ds->dir, t, err, errlen) : 0;
  free(a);
  return rc;
}

static int from_file(const struct vlff_dataset *ds, const char *path, double *t, char *err, size_t errlen) {
  uint8_t *buf;
  size_t len;
  if (vlff_read_file(path, 64u << 20, &buf, &len, err, errlen)) return -1;
  double *a = malloc((size_t)ds->n * sizeof *a);
  char *seen = calloc((size_t)ds->n, 1);
  int rc = -1, line = 0;
  if (!a || !seen) {
    snprintf(err, errlen, "out of memory");
    goto out;
  }
  if (strlen((char *)buf) != len) {
    snprintf(err, errlen, "%s: holds a NUL byte", VLFF_Q(path));
    goto out;
  }
  for (char *save = NULL, *l = strtok_r((char *)buf, "\n", &save); l; l = strtok_r(NULL, "\n", &save)) {
    line++;
    while (*l == ' ' || *l == '\t') l++;
    if (!*l || *l == '#' || *l == '\r') continue;
    char stem[VLFF_DS_NAME + 1];
    double v;
    int used = 0;
    char secs[64];
    char *vend = NULL;
    if (sscanf(l, "%64s %63s %n", stem, secs, &used) != 2 || (l[used] && l[used] != '\r') ||
        strspn(secs, "0123456789.eE+-") != strlen(secs) || (v = strtod(secs, &vend), *vend)) {
      /* decimal seconds only: sscanf's %lf read 0x1p-2 and nan */
      snprintf(err, errlen, "%s:%d: expected \"STEM SECONDS\" (decimal seconds)", VLFF_Q(path), line);
      goto out;
    }
    int found = 0;
    for (int i = 0; i < ds->n && !found; i++) /* stems are few enough (thousands) to search */
      if (!strcmp(ds->stem[i], stem)) {
        if (seen[i]) {
          snprintf(err, errlen, "%s:%d: frame %s listed twice", VLFF_Q(path), line, VLFF_Q(stem));
          goto out;
        }
        seen[i] = 1, a[i] = v, found = 1;
      }
    /* a stem of no frame: a typo, or another scene's file; a frame the
     * scene lists but skipped (no pose) may keep its stamp */
    char *end;
    errno = 0;
    long long num = strtoll(stem, &end, 10);
    if (!found && !(ds->skipped > 0 && !*end && !errno && num >= 0 && num <= ds->last_number)) {
      snprintf(err, errlen, "%s:%d: the scene has no frame %s", VLFF_Q(path), line, VLFF_Q(stem));
      goto out;
    }
  }
  for (int i = 0; i < ds->n; i++)
    if (!seen[i]) {
      snprintf(err, errlen, "%s: frame %s has no stamp", VLFF_Q(path), VLFF_Q(ds->stem[i]));
      goto out;
    }
  rc = check(ds, a, path, t, err, errlen);
out:
  free(a);
  free(seen);
  free(buf);
  return rc;
}

int vlff_dataset_stamps(const struct vlff_dataset *ds, double *t, char *err, size_t errlen) {
  char path[4200];
  snprintf(path, sizeof path, "%s/timestamps.txt", ds->dir);
  if (access(path, F_OK) == 0 || errno != ENOENT) return from_file(ds, path, t, err, errlen);
  if (ds->layout == VLFF_DS_SENS) return from_sens(ds, t, err, errlen);
  return 0;
}

int vlff_dataset_write_stamps(const char *dir, int n, const double *t, char *err, size_t errlen) {
  size_t cap = 64 + (size_t)n * 40, len = 0;
  char *b = malloc(cap);
  if (!b) return snprintf(err, errlen, "out of memory"), -1;
  len += (size_t)snprintf(b, cap, "# frame stem, seconds in the recording\n");
  for (int i = 0; i < n; i++) len += (size_t)snprintf(b + len, cap - len, "%05d %.6f\n", i, t[i]);
  char path[4200];
  snprintf(path, sizeof path, "%s/timestamps.txt", dir);
  int rc = vlff_write_file_atomic(path, b, len, err, errlen);
  free(b);
  return rc;
}
