/*
 * File formats of scene directories: PNG (libpng), text matrices, bbox,
 * PLY point sets, prompt embeddings, and atomic file writes.
 *
 * Every parser works on a memory buffer so the fuzz targets exercise exactly
 * the code the loaders run, and reports "name: what" (with a line number
 * where there is one).
 */
#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <stdbool.h>
#include <png.h>
#include <setjmp.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "dataset.h"
#include "dataset_internal.h"
#include "files.h"
#include "vlff/escape.h"

#define MAX_IMAGE_SIDE 16384
#define MAX_IMAGE_BYTES (256 << 20)

#define seterr vlff_errf

/* ---- PNG ---------------------------------------------------------------- */

struct membuf {
  const uint8_t *p;
  size_t len, pos;
};

struct png_err {
  jmp_buf jb;
  char msg[160];
};

static void png_on_error(png_structp png, png_const_charp msg) {
  struct png_err *e = png_get_error_ptr(png);
  snprintf(e->msg, sizeof e->msg, "%s", msg);
  longjmp(e->jb, 1);
}

static void png_on_warning(png_structp png, png_const_charp msg) {
  (void)png, (void)msg;
}

static void png_mem_read(png_structp png, png_bytep out, png_size_t n) {
  struct membuf *m = png_get_io_ptr(png);
  if (m->len - m->pos < n) png_error(png, "truncated file");
  memcpy(out, m->p + m->pos, n);
  m->pos += n;
}

void vlff_image_free(struct vlff_image *im) {
  if (!im) return;
  free(im->data);
  memset(im, 0, sizeof *im);
}

static int is_little_endian(void) {
  uint16_t x = 1;
  return *(uint8_t *)&x == 1;
}

static int png_decode(const uint8_t *buf, size_t len, const char *name, struct vlff_image *im,
                      char *err, size_t errlen) {
  struct membuf m = {buf, len, 0};
  struct png_err pe = {.msg = ""};
  png_structp png = png_create_read_struct(PNG_LIBPNG_VER_STRING, &pe, png_on_error, png_on_warning);
  if (!png) {
    seterr(err, errlen, "%s: out of memory", VLFF_Q(name));
    return -1;
  }
  png_infop info = png_create_info_struct(png);
  /* volatile: modified between setjmp and a possible longjmp */
  uint8_t *volatile data = NULL;
  png_bytep *volatile rows = NULL;
  if (!info || setjmp(pe.jb)) {
    free(data);
    free(rows);
    png_destroy_read_struct(&png, info ? &info : NULL, NULL);
    seterr(err, errlen, "%s: bad PNG: %s", VLFF_Q(name), VLFF_Q(pe.msg[0] ? pe.msg : "out of memory"));
    return -1;
  }
  png_set_read_fn(png, &m, png_mem_read);
  png_set_user_limits(png, MAX_IMAGE_SIDE, MAX_IMAGE_SIDE);
  png_set_chunk_malloc_max(png, 8u << 20);
  png_read_info(png, info);
  png_uint_32 w, h;
  int bit, ctype;
  png_get_IHDR(png, info, &w, &h, &bit, &ctype, NULL, NULL, NULL);
  if (ctype == PNG_COLOR_TYPE_PALETTE) png_set_palette_to_rgb(png);
  if (ctype == PNG_COLOR_TYPE_GRAY && bit < 8) png_set_expand_gray_1_2_4_to_8(png);
  if (png_get_valid(png, info, PNG_INFO_tRNS)) png_set_tRNS_to_alpha(png);
  if (ctype & PNG_COLOR_MASK_ALPHA || png_get_valid(png, info, PNG_INFO_tRNS)) png_set_strip_alpha(png);
  if (bit == 16 && is_little_endian()) png_set_swap(png);
  png_read_update_info(png, info);
  int channels = png_get_channels(png, info);
  int obit = png_get_bit_depth(png, info);
  if ((channels != 1 && channels != 3) || (obit != 8 && obit != 16)) {
    pe.msg[0] = 0;
    snprintf(pe.msg, sizeof pe.msg, "unsupported layout (%d channels, %d bit)", channels, obit);
    longjmp(pe.jb, 1);
  }
  size_t rowbytes = png_get_rowbytes(png, info);
  if ((size_t)h * rowbytes > MAX_IMAGE_BYTES) {
    snprintf(pe.msg, sizeof pe.msg, "%ux%u image is larger than %d MiB", (unsigned)w, (unsigned)h,
             MAX_IMAGE_BYTES >> 20);
    longjmp(pe.jb, 1);
  }
  if (rowbytes != (size_t)w * channels * (obit / 8)) {
    snprintf(pe.msg, sizeof pe.msg, "unexpected row size");
    longjmp(pe.jb, 1);
  }
  data = malloc(rowbytes * h);
  rows = malloc(h * sizeof *rows);
  if (!data || !rows) {
    snprintf(pe.msg, sizeof pe.msg, "out of memory for %ux%u", (unsigned)w, (unsigned)h);
    longjmp(pe.jb, 1);
  }
  for (png_uint_32 y = 0; y < h; y++) rows[y] = data + y * rowbytes;
  png_read_image(png, rows);
  png_read_end(png, NULL);
  png_destroy_read_struct(&png, &info, NULL);
  free(rows);
  im->width = (int)w, im->height = (int)h, im->channels = channels, im->depth16 = obit == 16;
  im->data = data;
  return 0;
}

int vlff_image_decode(const uint8_t *buf, size_t len, const char *name, struct vlff_image *im,
                      char *err, size_t errlen) {
  memset(im, 0, sizeof *im);
  if (len >= 8 && !png_sig_cmp(buf, 0, 8)) return png_decode(buf, len, name, im, err, errlen);
  if (len >= 3 && buf[0] == 0xff && buf[1] == 0xd8 && buf[2] == 0xff) {
#ifdef VLFF_HAVE_OPENCV
    int w, h;
    uint8_t *rgb;
    char e2[160];
    if (vlff_cv_decode_jpeg(buf, len, MAX_IMAGE_SIDE, &w, &h, &rgb, e2, sizeof e2) < 0) {
      seterr(err, errlen, "%s: bad JPEG: %s", VLFF_Q(name), VLFF_Q(e2));
      return -1;
    }
    im->width = w, im->height = h, im->channels = 3, im->depth16 = 0, im->data = rgb;
    return 0;
#else
    seterr(err, errlen, "%s: JPEG needs OpenCV, which this build was configured without", VLFF_Q(name));
    return -1;
#endif
  }
  seterr(err, errlen, "%s: neither PNG nor JPEG", VLFF_Q(name));
  return -1;
}

int vlff_image_read(const char *path, struct vlff_image *im, char *err, size_t errlen) {
  uint8_t *buf;
  size_t len;
  memset(im, 0, sizeof *im);
  if (vlff_read_file(path, (size_t)1 << 30, &buf, &len, err, errlen) < 0) return -1;
  int rc = vlff_image_decode(buf, len, path, im, err, errlen);
  free(buf);
  return rc;
}

struct growbuf {
  uint8_t *p;
  size_t len, cap;
  int oom;
};

static void png_mem_write(png_structp png, png_bytep data, png_size_t n) {
  struct growbuf *g = png_get_io_ptr(png);
  if (g->len + n > g->cap) {
    size_t cap = g->cap ? g->cap : 1 << 16;
    while (cap < g->len + n) cap *= 2;
    uint8_t *p = realloc(g->p, cap);
    if (!p) {
      g->oom = 1;
      png_error(png, "out of memory");
    }
    g->p = p, g->cap = cap;
  }
  memcpy(g->p + g->len, data, n);
  g->len += n;
}

static void png_mem_flush(png_structp png) { (void)png; }

int vlff_png_write(const char *path, const void *data, int width, int height, int channels,
                   int depth16, char *err, size_t errlen) {
  if (width < 1 || height < 1 || width > MAX_IMAGE_SIDE || height > MAX_IMAGE_SIDE ||
      (channels != 1 && channels != 3)) {
    seterr(err, errlen, "%s: cannot write a %dx%d %d-channel PNG", VLFF_Q(path), width, height, channels);
    return -1;
  }
  struct growbuf g = {0};
  struct png_err pe = {.msg = ""};
  png_structp png = png_create_write_struct(PNG_LIBPNG_VER_STRING, &pe, png_on_error, png_on_warning);
  png_infop info = png ? png_create_info_struct(png) : NULL;
  png_bytep *volatile rows = NULL;
  if (!png || !info || setjmp(pe.jb)) {
    free(rows);
    free(g.p);
    png_destroy_write_struct(png ? &png : NULL, info ? &info : NULL);
    seterr(err, errlen, "%s: PNG encoding failed: %s", VLFF_Q(path), pe.msg[0] ? pe.msg : "out of memory");
    return -1;
  }
  png_set_write_fn(png, &g, png_mem_write, png_mem_flush);
  /* fast, still much smaller than raw: datasets are written in bulk */
  png_set_compression_level(png, 1);
  png_set_IHDR(png, info, (png_uint_32)width, (png_uint_32)height, depth16 ? 16 : 8,
               channels == 3 ? PNG_COLOR_TYPE_RGB : PNG_COLOR_TYPE_GRAY, PNG_INTERLACE_NONE,
               PNG_COMPRESSION_TYPE_DEFAULT, PNG_FILTER_TYPE_DEFAULT);
  png_write_info(png, info);
  if (depth16 && is_little_endian()) png_set_swap(png);
  rows = malloc((size_t)height * sizeof *rows);
  if (!rows) {
    snprintf(pe.msg, sizeof pe.msg, "out of memory");
    longjmp(pe.jb, 1);
  }
  size_t rowbytes = (size_t)width * channels * (depth16 ? 2 : 1);
  for (int y = 0; y < height; y++) rows[y] = (png_bytep)data + (size_t)y * rowbytes;
  png_write_image(png, rows);
  png_write_end(png, NULL);
  png_destroy_write_struct(&png, &info);
  free(rows);
  int rc = vlff_write_file_atomic(path, g.p, g.len, err, errlen);
  free(g.p);
  return rc;
}

/* ---- text numbers ------------------------------------------------------- */

/* Parse up to max whitespace-separated numbers; returns the count, or -1
 * (err set) on a token that is not a number. */
static int parse_numbers(const char *buf, size_t len, const char *name, double *out, int max,
                         char *err, size_t errlen) {
  int n = 0, line = 1;
  size_t i = 0;
  char tok[64];
  while (i < len) {
    char c = buf[i];
    if (c == '\n') line++;
    if (c == ' ' || c == '\t' || c == '\n' || c == '\r' || c == ',') {
      i++;
      continue;
    }
    size_t j = i;
    while (j < len && buf[j] != ' ' && buf[j] != '\t' && buf[j] != '\n' && buf[j] != '\r' && buf[j] != ',')
      j++;
    if (j - i >= sizeof tok) {
      seterr(err, errlen, "%s:%d: token too long to be a number", VLFF_Q(name), line);
      return -1;
    }
    memcpy(tok, buf + i, j - i);
    tok[j - i] = 0;
    char *end;
    errno = 0;
    double v = strtod(tok, &end);
    if (end == tok || *end) {
      seterr(err, errlen, "%s:%d: '%s' is not a number", VLFF_Q(name), line, VLFF_Q(tok));
      return -1;
    }
    if (n == max) {
      seterr(err, errlen, "%s:%d: more than %d numbers", VLFF_Q(name), line, max);
      return -1;
    }
    out[n++] = v;
    i = j;
  }
  return n;
}

int vlff_parse_matrix(const char *buf, size_t len, const char *name, double m[16], char *err,
                      size_t errlen) {
  double v[16];
  int n = parse_numbers(buf, len, name, v, 16, err, errlen);
  if (n < 0) return -1;
  if (n == 9) {
    double o[16] = {v[0], v[1], v[2], 0, v[3], v[4], v[5], 0, v[6], v[7], v[8], 0, 0, 0, 0, 1};
    memcpy(m, o, sizeof o);
  } else if (n == 16) {
    memcpy(m, v, sizeof v);
  } else {
    seterr(err, errlen, "%s: expected a 4x4 (16 numbers) or 3x3 (9) matrix, got %d numbers", VLFF_Q(name), n);
    return -1;
  }
  for (int i = 0; i < 16; i++)
    if (!isfinite(m[i])) {
      seterr(err, errlen, "%s: element (%d,%d) is not finite", VLFF_Q(name), i / 4, i % 4);
      return -1;
    }
  return 0;
}

int vlff_check_pose(const double m[16], const char *name, char *err, size_t errlen) {
  for (int i = 0; i < 16; i++)
    if (!isfinite(m[i])) {
      seterr(err, errlen, "%s: pose element (%d,%d) is not finite", VLFF_Q(name), i / 4, i % 4);
      return -1;
    }
  if (fabs(m[12]) > 1e-6 || fabs(m[13]) > 1e-6 || fabs(m[14]) > 1e-6 || fabs(m[15] - 1) > 1e-6) {
    seterr(err, errlen, "%s: last row is [%g %g %g %g], not [0 0 0 1]", VLFF_Q(name), m[12], m[13], m[14], m[15]);
    return -1;
  }
  double worst = 0;
  for (int a = 0; a < 3; a++)
    for (int b = 0; b < 3; b++) {
      double d = 0;
      for (int k = 0; k < 3; k++) d += m[k * 4 + a] * m[k * 4 + b];
      worst = fmax(worst, fabs(d - (a == b)));
    }
  if (worst > 1e-3) {
    seterr(err, errlen, "%s: rotation is not orthonormal (|R^T R - I| = %.3g)", VLFF_Q(name), worst);
    return -1;
  }
  double det = m[0] * (m[5] * m[10] - m[6] * m[9]) - m[1] * (m[4] * m[10] - m[6] * m[8]) +
               m[2] * (m[4] * m[9] - m[5] * m[8]);
  if (det < 0) {
    seterr(err, errlen, "%s: rotation is a reflection (det %.3f)", VLFF_Q(name), det);
    return -1;
  }
  return 0;
}

void vlff_pose_invert(const double m[16], double o[16]) {
  for (int r = 0; r < 3; r++) {
    for (int c = 0; c < 3; c++) o[r * 4 + c] = m[c * 4 + r];
    o[r * 4 + 3] = -(m[0 * 4 + r] * m[3] + m[1 * 4 + r] * m[7] + m[2 * 4 + r] * m[11]);
  }
  o[12] = o[13] = o[14] = 0, o[15] = 1;
}

int vlff_parse_bbox(const char *buf, size_t len, const char *name, double lo[3], double hi[3],
                    char *err, size_t errlen) {
  double v[6];
  int n = parse_numbers(buf, len, name, v, 6, err, errlen);
  if (n < 0) return -1;
  if (n != 6) {
    seterr(err, errlen, "%s: expected 6 numbers (min xyz, max xyz), got %d", VLFF_Q(name), n);
    return -1;
  }
  for (int k = 0; k < 3; k++) {
    if (!isfinite(v[k]) || !isfinite(v[k + 3]) || fabs(v[k]) > 1e5 || fabs(v[k + 3]) > 1e5) {
      seterr(err, errlen, "%s: axis %d bounds are not finite numbers of sane size", VLFF_Q(name), k);
      return -1;
    }
    if (!(v[k] < v[k + 3])) {
      seterr(err, errlen, "%s: axis %d has min %g >= max %g", VLFF_Q(name), k, v[k], v[k + 3]);
      return -1;
    }
    lo[k] = v[k], hi[k] = v[k + 3];
  }
  return 0;
}

/* ---- PLY ---------------------------------------------------------------- */

enum ply_type { PT_NONE, PT_I8, PT_U8, PT_I16, PT_U16, PT_I32, PT_U32, PT_F32, PT_F64 };

/* The PLY type names, each type's own first, then its sized alias. */
static const struct {
  const char *n;
  int t;
} ply_types[] = {{"char", PT_I8},    {"int8", PT_I8},     {"uchar", PT_U8},   {"uint8", PT_U8},
                 {"short", PT_I16},  {"int16", PT_I16},   {"ushort", PT_U16}, {"uint16", PT_U16},
                 {"int", PT_I32},    {"int32", PT_I32},   {"uint", PT_U32},   {"uint32", PT_U32},
                 {"float", PT_F32},  {"float32", PT_F32}, {"double", PT_F64}, {"float64", PT_F64}};

static int ply_type_of(const char *s) {
  for (size_t i = 0; i < sizeof ply_types / sizeof ply_types[0]; i++)
    if (!strcmp(ply_types[i].n, s)) return ply_types[i].t;
  return PT_NONE;
}

static const int ply_size[] = {0, 1, 1, 2, 2, 4, 4, 4, 8};

/* An integer type's range into lo..hi (false for the float types). */
static bool ply_int_range(int t, double *lo, double *hi) {
  static const double r[][2] = {{0, 0},          {-128, 127},          {0, 255},          {-32768, 32767},
                                {0, 65535},      {-2147483648.0, 2147483647.0}, {0, 4294967295.0}};
  if (t < PT_I8 || t > PT_U32) return false;
  *lo = r[t][0], *hi = r[t][1];
  return true;
}

static const char *ply_type_name(int t) {
  for (size_t i = 0; i < sizeof ply_types / sizeof ply_types[0]; i++)
    if (ply_types[i].t == t) return ply_types[i].n;
  return "?";
}

static double ply_get(const uint8_t *p, int t) {
  /* binary_little_endian on any host */
  uint64_t u = 0;
  for (int i = ply_size[t] - 1; i >= 0; i--) u = (u << 8) | p[i];
  switch (t) {
  case PT_I8: return (int8_t)u;
  case PT_U8: return (uint8_t)u;
  case PT_I16: return (int16_t)u;
  case PT_U16: return (uint16_t)u;
  case PT_I32: return (int32_t)u;
  case PT_U32: return (uint32_t)u;
  case PT_F32: {
    uint32_t b = (uint32_t)u;
    float f;
    memcpy(&f, &b, 4);
    return f;
  }
  case PT_F64: {
    double d;
    memcpy(&d, &u, 8);
    return d;
  }
  default: return 0;
  }
}

void vlff_points_free(struct vlff_points *p) {
  if (!p) return;
  free(p->xyz), free(p->label);
  memset(p, 0, sizeof *p);
}

#define PLY_MAX_PROPS 32
#define PLY_MAX_POINTS (64u << 20)

/* What the header says about the vertex element. */
struct ply_header {
  int format; /* 0 ascii, 1 binary_little_endian */
  size_t nvert, pos; /* pos: the first byte after end_header */
  int nprop, ptype[PLY_MAX_PROPS];
  int ix, iy, iz, il; /* property indices of x, y, z, label */
  int more;           /* elements follow the vertices (faces): bytes after them are theirs */
};

/* One "property" line of the vertex element. */
static int ply_property(struct ply_header *h, const char *b, const char *c, int nt, const char *name, int line,
                        char *err, size_t errlen) {
  if (!strcmp(b, "list")) {
    seterr(err, errlen, "%s:%d: list property in the vertex element is not supported", VLFF_Q(name), line);
    return -1;
  }
  int t = ply_type_of(b);
  if (t == PT_NONE || nt < 3) {
    seterr(err, errlen, "%s:%d: unknown property type '%s'", VLFF_Q(name), line, VLFF_Q(b));
    return -1;
  }
  if (h->nprop == PLY_MAX_PROPS) {
    seterr(err, errlen, "%s:%d: more than %d vertex properties", VLFF_Q(name), line, PLY_MAX_PROPS);
    return -1;
  }
  if (!strcmp(c, "x")) h->ix = h->nprop;
  else if (!strcmp(c, "y")) h->iy = h->nprop;
  else if (!strcmp(c, "z")) h->iz = h->nprop;
  else if (!strcmp(c, "label")) h->il = h->nprop;
  h->ptype[h->nprop++] = t;
  return 0;
}

static int ply_header(const uint8_t *buf, size_t len, const char *name, struct ply_header *h, char *err,
                      size_t errlen) {
  if (len < 4 || memcmp(buf, "ply\n", 4)) {
    seterr(err, errlen, "%s: not a PLY file (no 'ply' magic line)", VLFF_Q(name));
    return -1;
  }
  *h = (struct ply_header){.format = -1, .ix = -1, .iy = -1, .iz = -1, .il = -1};
  size_t pos = 4;
  long long nvert = -1;
  int in_vertex = 0, seen_other_before = 0, line = 1;
  for (;;) {
    line++;
    size_t e = pos;
    while (e < len && buf[e] != '\n') e++;
    if (e >= len) {
      seterr(err, errlen, "%s:%d: header not terminated by end_header", VLFF_Q(name), line);
      return -1;
    }
    char l[256];
    size_t ll = e - pos;
    if (ll >= sizeof l) {
      seterr(err, errlen, "%s:%d: header line too long", VLFF_Q(name), line);
      return -1;
    }
    memcpy(l, buf + pos, ll);
    l[ll] = 0;
    if (ll && l[ll - 1] == '\r') l[--ll] = 0;
    pos = e + 1;
    char a[64] = "", b[64] = "", c[64] = "", d[64] = "";
    int nt = sscanf(l, "%63s %63s %63s %63s", a, b, c, d);
    if (nt <= 0) continue;
    if (!strcmp(a, "end_header")) break;
    if (!strcmp(a, "comment") || !strcmp(a, "obj_info")) continue;
    if (!strcmp(a, "format")) {
      if (!strcmp(b, "ascii")) h->format = 0;
      else if (!strcmp(b, "binary_little_endian")) h->format = 1;
      else {
        seterr(err, errlen, "%s:%d: format '%s' not supported (ascii, binary_little_endian)", VLFF_Q(name), line,
               VLFF_Q(b));
        return -1;
      }
    } else if (!strcmp(a, "element")) {
      if (in_vertex || nvert >= 0) {
        in_vertex = 0; /* elements after the vertices are never read */
        h->more = 1;
        continue;
      }
      if (!strcmp(b, "vertex")) {
        char *end;
        long long v = strtoll(c, &end, 10);
        if (nt < 3 || *end || v < 0 || v > PLY_MAX_POINTS) {
          seterr(err, errlen, "%s:%d: bad vertex count '%s' (0..%u)", VLFF_Q(name), line, VLFF_Q(c), PLY_MAX_POINTS);
          return -1;
        }
        nvert = v, in_vertex = 1;
      } else {
        seen_other_before = 1;
      }
    } else if (!strcmp(a, "property")) {
      if (in_vertex && ply_property(h, b, c, nt, name, line, err, errlen) < 0) return -1;
    } else {
      seterr(err, errlen, "%s:%d: unexpected header keyword '%s'", VLFF_Q(name), line, VLFF_Q(a));
      return -1;
    }
  }
  if (h->format < 0) {
    seterr(err, errlen, "%s: no format line", VLFF_Q(name));
    return -1;
  }
  if (seen_other_before) {
    seterr(err, errlen, "%s: the vertex element must come first", VLFF_Q(name));
    return -1;
  }
  if (nvert < 0 || h->ix < 0 || h->iy < 0 || h->iz < 0 || h->il < 0) {
    seterr(err, errlen, "%s: needs a vertex element with properties x, y, z and label", VLFF_Q(name));
    return -1;
  }
  if (nvert == 0) {
    seterr(err, errlen, "%s: the vertex element holds no vertices: no labelled point to score", VLFF_Q(name));
    return -1;
  }
  h->nvert = (size_t)nvert, h->pos = pos;
  return 0;
}

/* Vertex k from its property values v. */
static void ply_store(const struct ply_header *h, const double *v, size_t k, struct vlff_points *p) {
  p->xyz[3 * k] = (float)v[h->ix], p->xyz[3 * k + 1] = (float)v[h->iy], p->xyz[3 * k + 2] = (float)v[h->iz];
  p->label[k] = v[h->il] >= 0 && v[h->il] < 255 ? (uint8_t)v[h->il] : 255;
}

static int ply_body_binary(const struct ply_header *h, const uint8_t *buf, size_t len, const char *name,
                           struct vlff_points *p, char *err, size_t errlen) {
  size_t stride = 0, n = h->nvert;
  for (int i = 0; i < h->nprop; i++) stride += (size_t)ply_size[h->ptype[i]];
  if ((len - h->pos) / stride < n) {
    seterr(err, errlen, "%s: truncated: %zu vertices of %zu bytes need %zu bytes, %zu present", VLFF_Q(name), n, stride,
           n * stride, len - h->pos);
    return -1;
  }
  if (!h->more && len - h->pos != n * stride) {
    seterr(err, errlen, "%s: %zu bytes after the %zu vertices the header declares, and no element after them",
           VLFF_Q(name), len - h->pos - n * stride, n);
    return -1;
  }
  double v[PLY_MAX_PROPS];
  for (size_t k = 0; k < n; k++) {
    size_t o = h->pos + k * stride;
    for (int i = 0; i < h->nprop; i++) {
      v[i] = ply_get(buf + o, h->ptype[i]);
      o += (size_t)ply_size[h->ptype[i]];
    }
    ply_store(h, v, k, p);
  }
  return 0;
}

static int ply_body_ascii(const struct ply_header *h, const uint8_t *buf, size_t len, const char *name,
                          struct vlff_points *p, char *err, size_t errlen) {
  const char *s = (const char *)buf + h->pos, *end = (const char *)buf + len;
  double v[PLY_MAX_PROPS];
  for (size_t k = 0; k < h->nvert; k++) {
    for (int i = 0; i < h->nprop; i++) {
      while (s < end && (*s == ' ' || *s == '\t' || *s == '\n' || *s == '\r')) s++;
      char tok[64];
      size_t tl = 0;
      while (s < end && *s != ' ' && *s != '\t' && *s != '\n' && *s != '\r' && tl < sizeof tok - 1) tok[tl++] = *s++;
      tok[tl] = 0;
      char *e2;
      v[i] = strtod(tok, &e2);
      if (!tl || *e2) {
        seterr(err, errlen, "%s: vertex %zu property %d: '%s' is not a number", VLFF_Q(name), k, i, VLFF_Q(tok));
        return -1;
      }
      double lo, hi;
      if (ply_int_range(h->ptype[i], &lo, &hi) && !(v[i] >= lo && v[i] <= hi && v[i] == floor(v[i]))) {
        seterr(err, errlen, "%s: vertex %zu property %d: '%s' is not a %s (%.0f..%.0f)", VLFF_Q(name), k, i,
               VLFF_Q(tok), ply_type_name(h->ptype[i]), lo, hi);
        return -1;
      }
    }
    ply_store(h, v, k, p);
  }
  while (s < end && (*s == ' ' || *s == '\t' || *s == '\n' || *s == '\r')) s++;
  if (!h->more && s < end) {
    seterr(err, errlen, "%s: data after the %zu vertices the header declares, and no element after them",
           VLFF_Q(name), h->nvert);
    return -1;
  }
  return 0;
}

int vlff_ply_parse(const uint8_t *buf, size_t len, const char *name, struct vlff_points *p,
                   char *err, size_t errlen) {
  memset(p, 0, sizeof *p);
  struct ply_header h;
  if (ply_header(buf, len, name, &h, err, errlen) < 0) return -1;
  size_t n = h.nvert;
  p->xyz = malloc((n ? n : 1) * 3 * sizeof(float));
  p->label = malloc(n ? n : 1);
  if (!p->xyz || !p->label) {
    vlff_points_free(p);
    seterr(err, errlen, "%s: out of memory for %zu points", VLFF_Q(name), n);
    return -1;
  }
  int rc = h.format == 1 ? ply_body_binary(&h, buf, len, name, p, err, errlen)
                         : ply_body_ascii(&h, buf, len, name, p, err, errlen);
  for (size_t k = 0; rc == 0 && k < n; k++)
    if (!isfinite(p->xyz[3 * k]) || !isfinite(p->xyz[3 * k + 1]) || !isfinite(p->xyz[3 * k + 2])) {
      seterr(err, errlen, "%s: vertex %zu has a non-finite coordinate", VLFF_Q(name), k);
      rc = -1;
    }
  if (rc < 0) {
    vlff_points_free(p);
    return -1;
  }
  p->n = n;
  return 0;
}

int vlff_ply_read(const char *path, struct vlff_points *p, char *err, size_t errlen) {
  uint8_t *buf;
  size_t len;
  memset(p, 0, sizeof *p);
  if (vlff_read_file(path, (size_t)4 << 30, &buf, &len, err, errlen) < 0) return -1;
  int rc = vlff_ply_parse(buf, len, path, p, err, errlen);
  free(buf);
  return rc;
}

int vlff_ply_write(const char *path, const float *xyz, const uint8_t *rgb, const uint8_t *label,
                   size_t n, char *err, size_t errlen) {
  char hdr[512];
  int hl = snprintf(hdr, sizeof hdr,
                    "ply\nformat binary_little_endian 1.0\ncomment vlff labelled point set; label 255 = "
                    "unlabelled\nelement vertex %zu\nproperty float x\nproperty float y\nproperty float "
                    "z\n%sproperty uchar label\nend_header\n",
                    n, rgb ? "property uchar red\nproperty uchar green\nproperty uchar blue\n" : "");
  size_t stride = 12 + (rgb ? 3 : 0) + 1;
  size_t total = (size_t)hl + n * stride;
  uint8_t *b = malloc(total);
  if (!b) {
    seterr(err, errlen, "%s: out of memory", VLFF_Q(path));
    return -1;
  }
  memcpy(b, hdr, (size_t)hl);
  uint8_t *o = b + hl;
  for (size_t k = 0; k < n; k++) {
    for (int i = 0; i < 3; i++) {
      uint32_t u;
      memcpy(&u, &xyz[3 * k + i], 4);
      for (int j = 0; j < 4; j++) *o++ = (uint8_t)(u >> (8 * j));
    }
    if (rgb)
      for (int i = 0; i < 3; i++) *o++ = rgb[3 * k + i];
    *o++ = label[k];
  }
  int rc = vlff_write_file_atomic(path, b, total, err, errlen);
  free(b);
  return rc;
}
