/*
 * ScanNet as users have it: the exporter's layout with its separate depth
 * camera, ScanNet's label ids mapped through scannetv2-labels.combined.tsv,
 * the *_vh_clean_2.labels.ply ground truth, and the raw .sens stream read
 * directly (no Python export step).
 *
 * ScanNet's colour (1296x968) and depth (640x480) cameras differ in size,
 * aspect and intrinsics, so no single set of intrinsics serves both images.
 * Frames are returned in the colour camera's geometry at the depth camera's
 * resolution: the colour image is box-filtered down to it, the labels are
 * sampled nearest, and the depth is registered into it -- each depth pixel
 * back-projected with the depth intrinsics, moved by the depth-to-colour
 * extrinsic and projected with the scaled colour intrinsics, the nearest
 * surface winning where several land on one pixel and pixels that none
 * reaches left invalid (0). Features computed on the colour image stay
 * aligned, since the output covers the colour camera's whole field of view.
 */
#include <errno.h>
#include <dirent.h>
#include <fcntl.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>
#include <zlib.h>

#include "bounds.h"
#include "dataset.h"
#include "files.h"
#include "vlff/escape.h"
#include "dataset_internal.h"

#define seterr vlff_errf

/* ScanNet v2's 20 benchmark classes, by NYU40 id, in the benchmark's order. */
static const int bench20_nyu40[20] = {1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 14, 16, 24, 28, 33, 34, 36, 39};
static const char *const bench20_name[20] = {
    "wall",    "floor",   "cabinet", "bed",          "chair",          "sofa",   "table",
    "door",    "window",  "bookshelf", "picture",    "counter",        "desk",   "curtain",
    "refrigerator", "shower curtain", "toilet", "sink", "bathtub", "otherfurniture"};
static const char *const nyu40_name[40] = {
    "wall",        "floor",       "cabinet",      "bed",           "chair",       "sofa",
    "table",       "door",        "window",       "bookshelf",     "picture",     "counter",
    "blinds",      "desk",        "shelves",      "curtain",       "dresser",     "pillow",
    "mirror",      "floor mat",   "clothes",      "ceiling",       "books",       "refrigerator",
    "television",  "paper",       "towel",        "shower curtain", "box",        "whiteboard",
    "person",      "night stand", "toilet",       "sink",          "lamp",        "bathtub",
    "bag",         "otherstructure", "otherfurniture", "otherprop"};

int vlff_label_set_classes(int set) { return set == VLFF_LABELS_NYU40 ? 40 : 20; }

const char *vlff_label_set_name(int set, int k) {
  if (k < 0 || k >= vlff_label_set_classes(set)) return NULL;
  return set == VLFF_LABELS_NYU40 ? nyu40_name[k] : bench20_name[k];
}

/* NYU40 id -> class index of the set, 255 = not one of its classes. */
static uint8_t nyu40_class(int set, long nyu) {
  if (set == VLFF_LABELS_NYU40) return nyu >= 1 && nyu <= 40 ? (uint8_t)(nyu - 1) : 255;
  for (int k = 0; k < 20; k++)
    if (bench20_nyu40[k] == nyu) return (uint8_t)k;
  return 255;
}

/* ---- label TSV ---------------------------------------------------------- */

#define TSV_MAX_ID 65535

/* Column index of name in a tab-separated header, or -1. */
static int tsv_column(const char *hdr, const char *name) {
  int col = 0;
  const char *s = hdr;
  for (;;) {
    size_t n = strcspn(s, "\t\r\n");
    if (n == strlen(name) && !strncmp(s, name, n)) return col;
    if (s[n] != '\t') return -1;
    s += n + 1, col++;
  }
}

/* Tab-separated fields of a line (its end at '\n', a '\r' before it not a
 * field's). */
static size_t tsv_fields(const char *line) {
  size_t n = 1;
  for (const char *c = line; *c && *c != '\n'; c++) n += *c == '\t';
  return n;
}

/* Field col of a line as an integer in [lo, hi]; -1 when absent or bad. */
static int tsv_int(const char *line, int col, long lo, long hi, long *out) {
  const char *s = line;
  for (int c = 0; c < col; c++) {
    s = strchr(s, '\t');
    if (!s) return -1;
    s++;
  }
  /* digits only: strtol skips white space, so an empty field read the
   * next column's number, and it takes a sign */
  if (*s < '0' || *s > '9') return -1;
  char *end;
  errno = 0;
  long v = strtol(s, &end, 10);
  if (end == s || errno || (*end && *end != '\t' && *end != '\r' && *end != '\n') || v < lo || v > hi)
    return -1;
  *out = v;
  return 0;
}

int vlff_scannet_labels_load(struct vlff_dataset *ds, const char *path, int set, char *err, size_t errlen) {
  uint8_t *buf;
  size_t len;
  if (vlff_read_file(path, (size_t)16 << 20, &buf, &len, err, errlen) < 0) return -1;
  char *text = (char *)buf;
  const char *nul = memchr(buf, 0, len);
  if (nul) {
    int at = 1;
    for (const char *c = text; c < nul; c++) at += *c == '\n';
    seterr(err, errlen, "%s:%d: NUL byte", VLFF_Q(path), at);
    free(buf);
    return -1;
  }
  char *save = NULL, *line = strtok_r(text, "\n", &save);
  int cid = line ? tsv_column(line, "id") : -1, cnyu = line ? tsv_column(line, "nyu40id") : -1;
  const size_t ncols = line ? tsv_fields(line) : 0;
  if (cid < 0 || cnyu < 0) {
    seterr(err, errlen, "%s:1: header lacks the columns 'id' and 'nyu40id' (scannetv2-labels.combined.tsv)",
           VLFF_Q(path));
    free(buf);
    return -1;
  }
  uint8_t *map = malloc(TSV_MAX_ID + 1);
  if (!map) {
    free(buf);
    seterr(err, errlen, "%s: out of memory", VLFF_Q(path));
    return -1;
  }
  memset(map, 255, TSV_MAX_ID + 1);
  int lineno = 1, rows = 0;
  while ((line = strtok_r(NULL, "\n", &save))) {
    lineno++;
    if (!line[strspn(line, " \t\r")]) continue;
    long id, nyu;
    /* More fields than the header names is no row of the file (rows whose
     * line ends were lost read as one); fewer, empty last columns, as
     * pandas reads them. */
    if (tsv_fields(line) > ncols) {
      seterr(err, errlen, "%s:%d: %zu fields, more than the header's %zu", VLFF_Q(path), lineno, tsv_fields(line),
             ncols);
      goto fail;
    }
    if (tsv_int(line, cid, 1, TSV_MAX_ID, &id) < 0 || tsv_int(line, cnyu, 0, 40, &nyu) < 0) {
      seterr(err, errlen, "%s:%d: 'id' must be an integer in [1, %d] and 'nyu40id' one in [0, 40]", VLFF_Q(path),
             lineno,
             TSV_MAX_ID);
      goto fail;
    }
    if (map[id] != 255 && map[id] != nyu40_class(set, nyu)) {
      seterr(err, errlen, "%s:%d: id %ld is listed twice with different classes", VLFF_Q(path), lineno, id);
      goto fail;
    }
    map[id] = nyu40_class(set, nyu);
    rows++;
  }
  if (rows == 0) {
    seterr(err, errlen, "%s: no label rows", VLFF_Q(path));
    goto fail;
  }
  free(buf);
  free(ds->label_map);
  ds->label_map = map;
  ds->label_set = set;
  return 0;
fail:
  free(map);
  free(buf);
  return -1;
}

/* ---- geometry ----------------------------------------------------------- */

static int check_camera(const double K[16], int w, int h, const char *path, char *err, size_t errlen) {
  double fx = K[0], fy = K[5], cx = K[2], cy = K[6];
  /* the physical bounds every camera in vlff is held to (bounds.h) */
  char why[200];
  if (vlff_intrinsics_plausible(w, h, fx, fy, cx, cy, why, sizeof why)) {
    seterr(err, errlen, "%s: implausible camera for a %dx%d image: %s", VLFF_Q(path), w, h, why);
    return -1;
  }
  if (!(cx > 0 && cx < w) || !(cy > 0 && cy < h)) {
    seterr(err, errlen, "%s: principal point (%g, %g) lies outside the %dx%d image", VLFF_Q(path), cx, cy, w, h);
    return -1;
  }
  if (vlff_skew_plausible(fx, K[1], why, sizeof why)) {
    seterr(err, errlen, "%s: %s", VLFF_Q(path), why);
    return -1;
  }
  return 0;
}

int vlff_scannet_geometry(struct vlff_dataset *ds, const double Kc[16], int cw, int ch, const double Kd[16],
                          int dw, int dh, const double Ec[16], const double Ed[16], const char *where, char *err,
                          size_t errlen) {
  if (cw < 1 || ch < 1 || dw < 1 || dh < 1 || cw > 16384 || ch > 16384 || dw > 16384 || dh > 16384) {
    seterr(err, errlen, "%s: image sizes colour %dx%d, depth %dx%d out of range", VLFF_Q(where), cw, ch, dw, dh);
    return -1;
  }
  if (check_camera(Kc, cw, ch, where, err, errlen) < 0 || check_camera(Kd, dw, dh, where, err, errlen) < 0)
    return -1;
  if (vlff_check_pose(Ec, where, err, errlen) < 0 || vlff_check_pose(Ed, where, err, errlen) < 0) return -1;
  /* depth camera -> rig -> colour camera: extrinsics are sensor-to-rig */
  double ci[16];
  vlff_pose_invert(Ec, ci);
  for (int r = 0; r < 4; r++)
    for (int c = 0; c < 4; c++) {
      double s = 0;
      for (int k = 0; k < 4; k++) s += ci[4 * r + k] * Ed[4 * k + c];
      ds->d2c[4 * r + c] = s;
    }
  const double apart = hypot(hypot(ds->d2c[3], ds->d2c[7]), ds->d2c[11]);
  if (apart > 1) {
    seterr(err, errlen, "%s: depth and colour cameras are %.2f m apart, more than 1 m", VLFF_Q(where), apart);
    return -1;
  }
  ds->registered = 1;
  ds->color_width = cw, ds->color_height = ch;
  ds->depth_width = dw, ds->depth_height = dh;
  ds->dfx = Kd[0], ds->dfy = Kd[5], ds->dcx = Kd[2], ds->dcy = Kd[6];
  /* output: the colour camera scaled to the depth camera's pixel count, its
   * principal point in the field's convention (pixel u centred at u + 0.5;
   * ScanNet's, OpenCV's, at u) */
  ds->width = dw, ds->height = dh;
  double sx = (double)dw / cw, sy = (double)dh / ch;
  ds->fx = Kc[0] * sx, ds->fy = Kc[5] * sy;
  ds->cx = (Kc[2] + 0.5) * sx, ds->cy = (Kc[6] + 0.5) * sy;
  return 0;
}

void vlff_scannet_resample_rgb(const struct vlff_dataset *ds, const uint8_t *src, uint8_t *dst) {
  const int cw = ds->color_width, ch = ds->color_height, W = ds->width, H = ds->height;
  for (int v = 0; v < H; v++) {
    int y0 = (int)((double)v * ch / H), y1 = (int)((double)(v + 1) * ch / H);
    if (y1 <= y0) y1 = y0 + 1;
    if (y1 > ch) y1 = ch;
    for (int u = 0; u < W; u++) {
      int x0 = (int)((double)u * cw / W), x1 = (int)((double)(u + 1) * cw / W);
      if (x1 <= x0) x1 = x0 + 1;
      if (x1 > cw) x1 = cw;
      unsigned s[3] = {0, 0, 0}, n = 0;
      for (int y = y0; y < y1; y++)
        for (int x = x0; x < x1; x++, n++)
          for (int c = 0; c < 3; c++) s[c] += src[((size_t)y * cw + x) * 3 + c];
      for (int c = 0; c < 3; c++) dst[((size_t)v * W + u) * 3 + c] = (uint8_t)((s[c] + n / 2) / n);
    }
  }
}

void vlff_scannet_register_depth(const struct vlff_dataset *ds, const uint16_t *dmm, double scale, float *out) {
  const int dw = ds->depth_width, dh = ds->depth_height, W = ds->width, H = ds->height;
  const double *T = ds->d2c;
  for (size_t k = 0; k < (size_t)W * H; k++) out[k] = 0;
  for (int v = 0; v < dh; v++)
    for (int u = 0; u < dw; u++) {
      uint16_t raw = dmm[(size_t)v * dw + u];
      if (!raw) continue;
      double z = raw * scale;
      double x = (u - ds->dcx) / ds->dfx * z, y = (v - ds->dcy) / ds->dfy * z;
      double X = T[0] * x + T[1] * y + T[2] * z + T[3];
      double Y = T[4] * x + T[5] * y + T[6] * z + T[7];
      double Z = T[8] * x + T[9] * y + T[10] * z + T[11];
      if (!(Z > 1e-6)) continue;
      /* the output pixel the point falls in (pixel u spans [u, u+1)) */
      double pu = ds->fx * X / Z + ds->cx, pv = ds->fy * Y / Z + ds->cy;
      if (!(pu >= 0 && pu < W && pv >= 0 && pv < H)) continue;
      size_t o = (size_t)(int)pv * W + (size_t)(int)pu;
      if (out[o] == 0 || Z < out[o]) out[o] = (float)Z;
    }
}

int vlff_scannet_map_labels(const struct vlff_dataset *ds, const struct vlff_image *im, const char *path,
                            uint8_t *label, char *err, size_t errlen) {
  if (im->channels != 1) {
    seterr(err, errlen, "%s: labels must be a single-channel image", VLFF_Q(path));
    return -1;
  }
  if ((long long)im->width * ds->height != (long long)im->height * ds->width &&
      (long long)im->width * ds->color_height != (long long)im->height * ds->color_width) {
    seterr(err, errlen, "%s: %dx%d has neither the colour nor the output images' aspect", VLFF_Q(path), im->width,
           im->height);
    return -1;
  }
  const int W = ds->width, H = ds->height;
  for (int v = 0; v < H; v++)
    for (int u = 0; u < W; u++) {
      int su = (int)((u + 0.5) * im->width / W), sv = (int)((v + 0.5) * im->height / H);
      size_t s = (size_t)sv * im->width + su;
      unsigned id = im->depth16 ? ((const uint16_t *)im->data)[s] : ((const uint8_t *)im->data)[s];
      label[(size_t)v * W + u] = ds->label_map ? ds->label_map[id] : (uint8_t)(id < 255 ? id : 255);
    }
  return 0;
}

/* ---- .sens -------------------------------------------------------------- */

enum { SENS_COLOR_RAW = 0, SENS_COLOR_PNG = 1, SENS_COLOR_JPEG = 2 };
enum { SENS_DEPTH_RAW = 0, SENS_DEPTH_ZLIB = 1 };
#define SENS_MAX_BLOB ((uint64_t)64 << 20)

struct vlff_sens {
  int fd;
  char *path; /* whole: the mesh and labels are looked for beside it */
  int color_type, depth_type;
  float depth_shift;
  uint64_t *off; /* [n][4]: colour offset, colour bytes, depth offset, depth bytes */
};

static int rd(int fd, void *p, size_t n, off_t *at) {
  ssize_t r = pread(fd, p, n, *at);
  if (r != (ssize_t)n) return -1;
  *at += (off_t)n;
  return 0;
}

static void mat_from_f32(const float f[16], double m[16]) {
  for (int i = 0; i < 16; i++) m[i] = f[i];
}

void vlff_sens_close(struct vlff_sens *s) {
  if (!s) return;
  if (s->fd >= 0) close(s->fd);
  free(s->path);
  free(s->off);
  free(s);
}

int vlff_sens_open(struct vlff_dataset *ds, const char *path, char *err, size_t errlen) {
  struct vlff_sens *s = calloc(1, sizeof *s);
  if (!s || !(s->path = strdup(path))) {
    free(s);
    seterr(err, errlen, "%s: out of memory", VLFF_Q(path));
    return -1;
  }
  s->fd = open(path, O_RDONLY | O_NONBLOCK | O_CLOEXEC);
  struct stat st;
  if (s->fd < 0 || fstat(s->fd, &st) < 0 || !S_ISREG(st.st_mode)) {
    seterr(err, errlen, "%s: %s", VLFF_Q(path), s->fd < 0 ? strerror(errno) : "not a regular file");
    vlff_sens_close(s);
    return -1;
  }
  const uint64_t size = (uint64_t)st.st_size;
  off_t at = 0;
  uint32_t version;
  uint64_t namelen;
  if (rd(s->fd, &version, 4, &at) < 0 || version != 4) {
    seterr(err, errlen, "%s: not a ScanNet .sens file of version 4", VLFF_Q(path));
    goto fail;
  }
  if (rd(s->fd, &namelen, 8, &at) < 0 || namelen > 4096) {
    seterr(err, errlen, "%s: sensor name length is implausible", VLFF_Q(path));
    goto fail;
  }
  at += (off_t)namelen;
  float kf[4][16];
  int32_t ctype, dtype;
  uint32_t dims[4];
  uint64_t nframes;
  if (rd(s->fd, kf, sizeof kf, &at) < 0 || rd(s->fd, &ctype, 4, &at) < 0 || rd(s->fd, &dtype, 4, &at) < 0 ||
      rd(s->fd, dims, sizeof dims, &at) < 0 || rd(s->fd, &s->depth_shift, 4, &at) < 0 ||
      rd(s->fd, &nframes, 8, &at) < 0) {
    seterr(err, errlen, "%s: truncated header", VLFF_Q(path));
    goto fail;
  }
  if (ctype < SENS_COLOR_RAW || ctype > SENS_COLOR_JPEG) {
    seterr(err, errlen, "%s: colour compression type %d is not raw, PNG or JPEG", VLFF_Q(path), ctype);
    goto fail;
  }
  if (dtype != SENS_DEPTH_RAW && dtype != SENS_DEPTH_ZLIB) {
    seterr(err, errlen, "%s: depth compression type %d is not raw or zlib (occi is not supported)", VLFF_Q(path),
           dtype);
    goto fail;
  }
  /* depth_shift converts metres to stored units: 1000 for millimetres */
  if (!(s->depth_shift >= 1 && s->depth_shift <= 100000)) {
    seterr(err, errlen, "%s: depth shift %g is outside [1, 100000] units per metre", VLFF_Q(path), s->depth_shift);
    goto fail;
  }
  /* a frame record is at least its pose, stamps and sizes */
  if (nframes == 0 || nframes > (uint64_t)INT_MAX || nframes > (size - (uint64_t)at) / (64 + 32)) {
    seterr(err, errlen, "%s: %llu frames do not fit in %llu bytes", VLFF_Q(path), (unsigned long long)nframes,
           (unsigned long long)size);
    goto fail;
  }
  s->color_type = ctype, s->depth_type = dtype;
  double Kc[16], Ec[16], Kd[16], Ed[16];
  mat_from_f32(kf[0], Kc), mat_from_f32(kf[1], Ec), mat_from_f32(kf[2], Kd), mat_from_f32(kf[3], Ed);
  if (vlff_scannet_geometry(ds, Kc, (int)dims[0], (int)dims[1], Kd, (int)dims[2], (int)dims[3], Ec, Ed, path,
                            err, errlen) < 0)
    goto fail;
  const uint64_t raw_color = (uint64_t)dims[0] * dims[1] * 3, raw_depth = (uint64_t)dims[2] * dims[3] * 2;
  s->off = malloc(nframes * 4 * sizeof *s->off);
  ds->c2w = malloc(nframes * 16 * sizeof(double));
  ds->stem = malloc(nframes * sizeof *ds->stem);
  ds->listed = malloc(nframes * sizeof *ds->listed);
  ds->n_listed = (int)nframes;
  ds->last_number = (long)nframes - 1;
  if (!s->off || !ds->c2w || !ds->stem || !ds->listed) {
    seterr(err, errlen, "%s: out of memory for %llu frames", VLFF_Q(path), (unsigned long long)nframes);
    goto fail;
  }
  ds->n = 0;
  for (uint64_t i = 0; i < nframes; i++) {
    float pose[16];
    uint64_t stamps[2], sz[2];
    if (rd(s->fd, pose, sizeof pose, &at) < 0 || rd(s->fd, stamps, sizeof stamps, &at) < 0 ||
        rd(s->fd, sz, sizeof sz, &at) < 0) {
      seterr(err, errlen, "%s: frame %llu: truncated record", VLFF_Q(path), (unsigned long long)i);
      goto fail;
    }
    if (sz[0] == 0 || sz[0] > SENS_MAX_BLOB || sz[1] == 0 || sz[1] > SENS_MAX_BLOB ||
        sz[0] + sz[1] > size - (uint64_t)at || (ctype == SENS_COLOR_RAW && sz[0] != raw_color) ||
        (dtype == SENS_DEPTH_RAW && sz[1] != raw_depth)) {
      seterr(err, errlen, "%s: frame %llu: colour %llu and depth %llu bytes do not fit the file or the format",
             VLFF_Q(path), (unsigned long long)i, (unsigned long long)sz[0], (unsigned long long)sz[1]);
      goto fail;
    }
    uint64_t *o = s->off + (size_t)ds->n * 4;
    o[0] = (uint64_t)at, o[1] = sz[0], o[2] = (uint64_t)at + sz[0], o[3] = sz[1];
    at += (off_t)(sz[0] + sz[1]);
    double m[16];
    int finite = 1;
    for (int k = 0; k < 16; k++) {
      m[k] = pose[k];
      if (!isfinite(pose[k])) finite = 0;
    }
    if (!finite) { /* ScanNet marks lost tracking with -inf */
      ds->skipped++;
      continue;
    }
    char name[48], why[256];
    snprintf(name, sizeof name, "frame %llu pose", (unsigned long long)i);
    if (vlff_check_pose(m, name, why, sizeof why) < 0) {
      seterr(err, errlen, "%s: %s", VLFF_Q(path), why);
      goto fail;
    }
    memcpy(ds->c2w + (size_t)ds->n * 16, m, sizeof m);
    snprintf(ds->stem[ds->n], VLFF_DS_NAME, "%llu", (unsigned long long)i);
    ds->listed[ds->n++] = (int)i;
  }
  if (ds->n == 0) {
    seterr(err, errlen, "%s: every frame's pose is invalid", VLFF_Q(path));
    goto fail;
  }
  ds->sens = s;
  return 0;
fail:
  vlff_sens_close(s);
  return -1;
}

int vlff_sens_read(const struct vlff_dataset *ds, int i, uint8_t **rgb, uint16_t **depth, char *err,
                   size_t errlen) {
  const struct vlff_sens *s = ds->sens;
  const uint64_t *o = s->off + (size_t)i * 4;
  const size_t draw = (size_t)ds->depth_width * ds->depth_height * 2;
  uint8_t *blob = NULL;
  if (rgb) *rgb = NULL;
  if (depth) *depth = NULL;
  if (rgb) {
    blob = malloc(o[1] + 1);
    off_t at = (off_t)o[0];
    if (!blob || rd(s->fd, blob, o[1], &at) < 0) {
      seterr(err, errlen, "%s: frame %s: cannot read the colour image", VLFF_Q(s->path), VLFF_Q(ds->stem[i]));
      goto fail;
    }
    if (s->color_type == SENS_COLOR_RAW) {
      *rgb = blob, blob = NULL;
    } else {
      struct vlff_image im;
      char name[4200];
      snprintf(name, sizeof name, "%s frame %s colour", s->path, ds->stem[i]);
      if (vlff_image_decode(blob, o[1], name, &im, err, errlen) < 0) goto fail;
      if (im.width != ds->color_width || im.height != ds->color_height || im.channels != 3 || im.depth16) {
        seterr(err, errlen, "%s: %dx%d, %d channels; the header says %dx%d RGB", VLFF_Q(name), im.width, im.height,
               im.channels, ds->color_width, ds->color_height);
        vlff_image_free(&im);
        goto fail;
      }
      *rgb = im.data;
      free(blob), blob = NULL;
    }
  }
  if (depth) {
    blob = malloc(o[3]);
    *depth = malloc(draw);
    off_t at = (off_t)o[2];
    if (!blob || !*depth || rd(s->fd, blob, o[3], &at) < 0) {
      seterr(err, errlen, "%s: frame %s: cannot read the depth image", VLFF_Q(s->path), VLFF_Q(ds->stem[i]));
      goto fail;
    }
    if (s->depth_type == SENS_DEPTH_RAW) {
      memcpy(*depth, blob, draw);
    } else {
      uLongf n = (uLongf)draw;
      if (uncompress((Bytef *)*depth, &n, blob, (uLong)o[3]) != Z_OK || n != draw) {
        seterr(err, errlen, "%s: frame %s: depth is not %zu bytes of zlib-compressed uint16", VLFF_Q(s->path),
               VLFF_Q(ds->stem[i]), draw);
        goto fail;
      }
    }
    free(blob), blob = NULL;
  }
  return 0;
fail:
  free(blob);
  if (rgb) free(*rgb), *rgb = NULL;
  if (depth) free(*depth), *depth = NULL;
  return -1;
}

float vlff_sens_depth_scale(const struct vlff_dataset *ds) { return 1.0f / ds->sens->depth_shift; }

/* A frame record is pose (64 bytes), colour and depth stamps (2 x uint64,
 * microseconds), sizes (2 x uint64), then the colour blob at off[0]. */
int vlff_sens_stamp_us(const struct vlff_dataset *ds, int i, uint64_t *us) {
  uint64_t st[2];
  off_t at = (off_t)ds->sens->off[(size_t)i * 4] - 32;
  if (rd(ds->sens->fd, st, sizeof st, &at) < 0) return -1;
  *us = st[0];
  return 0;
}

/* ---- 3D ground truth ---------------------------------------------------- */

/* The *_vh_clean_2.labels.ply files in dir: how many, the first's path in out. */
static int find_labels_ply(const char *dir, char *out, size_t cap) {
  static const char suffix[] = "_vh_clean_2.labels.ply";
  DIR *d = opendir(dir);
  if (!d) return 0;
  int found = 0;
  struct dirent *e;
  while ((e = readdir(d))) {
    size_t l = strlen(e->d_name), sl = sizeof suffix - 1;
    if (l > sl && !strcmp(e->d_name + l - sl, suffix)) {
      if (!found) snprintf(out, cap, "%s/%s", dir, e->d_name);
      found++;
    }
  }
  closedir(d);
  return found;
}

/* A ScanNet scene's name: the .sens file's without ".sens", else the scene
 * directory's (scans/scene0000_00). */
static void scene_name(const char *dir, const char *sens, char *out, size_t cap) {
  const char *p = sens && sens[0] ? sens : dir;
  size_t l = strlen(p);
  while (l > 1 && p[l - 1] == '/') l--;
  size_t b = l;
  while (b > 0 && p[b - 1] != '/') b--;
  size_t n = l - b;
  if (sens && sens[0] && n > 5 && !strncmp(p + l - 5, ".sens", 5)) n -= 5;
  if (n == 0 || (n == 1 && p[b] == '.') || (n == 2 && !strncmp(p + b, "..", 2))) snprintf(out, cap, "<scene>");
  else snprintf(out, cap, "%.*s", (int)n, p + b);
}

int vlff_scannet_points_path(const char *dir, int layout, const char *sens, char *path, size_t cap, char *err,
                             size_t errlen) {
  int found = 0;
  char where[4200] = "";
  if (layout != VLFF_DS_REFERENCE) {
    char up[4200];
    snprintf(up, sizeof up, "%s/..", dir);
    snprintf(where, sizeof where, "%s", dir);
    found = find_labels_ply(dir, path, cap);
    if (!found) snprintf(where, sizeof where, "%s", up), found = find_labels_ply(up, path, cap);
    if (found > 1) {
      seterr(err, errlen, "%s: %d *_vh_clean_2.labels.ply files; keep the scene's own", VLFF_Q(where), found);
      return -1;
    }
  }
  if (!found) { /* the reference layout's names (a ScanNet scene may have them instead) */
    snprintf(path, cap, "%s/points.ply", dir);
    if (access(path, F_OK) != 0) snprintf(path, cap, "%s/mesh.ply", dir);
    if (access(path, F_OK) != 0) {
      if (layout == VLFF_DS_REFERENCE) {
        seterr(err, errlen, "%s/points.ply: missing (nor mesh.ply): the labelled 3D ground truth", VLFF_Q(dir));
      } else {
        char name[VLFF_DS_NAME + 32];
        scene_name(dir, sens, name, sizeof name);
        seterr(err, errlen, "%s/%s_vh_clean_2.labels.ply: missing: ScanNet's labelled mesh (the 3D ground truth) is "
                            "neither in the scene directory nor in its parent", VLFF_Q(dir), VLFF_Q(name));
      }
      return -1;
    }
  }
  int fd = vlff_open_regular(path, err, errlen);
  if (fd < 0) return -1;
  close(fd);
  return 0;
}

int vlff_dataset_points_path(const struct vlff_dataset *ds, char *path, size_t cap, char *err, size_t errlen) {
  return vlff_scannet_points_path(ds->dir, ds->layout, ds->sens ? ds->sens->path : NULL, path, cap, err, errlen);
}

int vlff_dataset_read_points(const struct vlff_dataset *ds, struct vlff_points *p, char *err, size_t errlen) {
  char path[4400];
  if (vlff_dataset_points_path(ds, path, sizeof path, err, errlen) < 0) return -1;
  if (vlff_ply_read(path, p, err, errlen) < 0) return -1;
  size_t l = strlen(path), sl = strlen("_vh_clean_2.labels.ply");
  if (l > sl && !strcmp(path + l - sl, "_vh_clean_2.labels.ply")) /* vertex labels are NYU40 ids */
    for (size_t k = 0; k < p->n; k++) p->label[k] = nyu40_class(ds->label_set, p->label[k]);
  return 0;
}
