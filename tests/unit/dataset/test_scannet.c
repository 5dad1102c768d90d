/* ScanNet as users have it, from files this test writes in ScanNet's own
 * formats: the exporter's layout with its own depth camera, label-filt/ ids
 * mapped through scannetv2-labels.combined.tsv, *_vh_clean_2.labels.ply, and
 * the raw .sens stream (header, JPEG colour, zlib depth, -inf poses).
 *
 * The scene, in the colour camera's frame: a plate at Z = 1 m over a wall
 * at Z = 2 m; the depth camera sits 10 cm to the right. Registered depth
 * must put the plate where the colour camera sees it (sub-pixel), keep the
 * plate where the wall behind it, seen only by the depth camera, lands on
 * the same pixels (z-buffer), and leave unseen pixels invalid. */
#define _XOPEN_SOURCE 700
#include <ftw.h>
#include <math.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <signal.h>
#include <spawn.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>
#include <zlib.h>
#ifdef VLFF_HAVE_HDF5
#include <hdf5.h>
#endif

#include <cmocka.h>

#include "dataset.h"
#include "files.h"
#include "dataset_internal.h"
#ifdef VLFF_HAVE_OPENCV
#include "jpeg_write.h"
#endif
#include "unit.h"
#include "vlff/shm.h"

#define CW 162
#define CH 121
#define DW 80
#define DH 60
#define BASE 0.10 /* depth camera's offset along x, metres */
static const double Kc[4] = {150, 150, 80.5, 60.2}; /* fx fy cx cy */
static const double Kd[4] = {74, 74, 39.6, 29.7};
static const double plate[4] = {-0.25, 0.15, -0.2, 0.2}; /* x0 x1 y0 y1 at Z = 1 */

static char root[256];

static int rm_one(const char *p, const struct stat *st, int flag, struct FTW *ftw) {
  (void)st, (void)flag, (void)ftw;
  return remove(p);
}

static void put(const char *path, const void *data, size_t n) {
  FILE *f = fopen(path, "wb");
  assert_non_null(f);
  assert_int_equal(fwrite(data, 1, n, f), n);
  fclose(f);
}

static void putf(const char *path, const char *fmt, ...) {
  char b[4096];
  va_list ap;
  va_start(ap, fmt);
  int n = vsnprintf(b, sizeof b, fmt, ap);
  va_end(ap);
  put(path, b, (size_t)n);
}

/* Z of the first surface along the ray o + t d (d has z = 1). */
static double cast(double ox, double dx, double dy) {
  double x = ox + dx, y = dy;
  if (x >= plate[0] && x <= plate[1] && y >= plate[2] && y <= plate[3]) return 1.0;
  return 2.0;
}

static void depth_image(uint16_t *d) {
  for (int v = 0; v < DH; v++)
    for (int u = 0; u < DW; u++)
      d[v * DW + u] = (uint16_t)lround(1000 * cast(BASE, (u - Kd[2]) / Kd[0], (v - Kd[3]) / Kd[1]));
}

/* Colour: red left of x = 81, green bands split at y = 60. Labels: ScanNet
 * ids 1 (wall) left, 2 (chair) top right, 7 (blinds) bottom right, rows 0-3
 * unannotated. */
static void colour_image(uint8_t *rgb, uint16_t *ids) {
  for (int y = 0; y < CH; y++)
    for (int x = 0; x < CW; x++) {
      uint8_t *p = rgb + (y * CW + x) * 3;
      p[0] = x < 81 ? 230 : 20, p[1] = y < 60 ? 200 : 40, p[2] = 100;
      ids[y * CW + x] = y < 4 ? 0 : x < 81 ? 1 : y < 60 ? 2 : 7;
    }
}

static const char tsv[] =
    "id\traw_category\tcategory\tcount\tnyu40id\teigen13id\tnyuClass\tnyu40class\teigen13class\n"
    "1\twall\twall\t8277\t1\t12\twall\twall\tWall\n"
    "2\tchair\tchair\t4646\t5\t4\tchair\tchair\tChair\n"
    "7\tblinds\tblinds\t170\t13\t13\tblinds\tblinds\tWindow\n";

static void write_tsv_and_ply(const char *scene) {
  char p[1024];
  snprintf(p, sizeof p, "%s/scannetv2-labels.combined.tsv", root);
  put(p, tsv, sizeof tsv - 1);
  /* binary little-endian, as ScanNet ships it: labels are NYU40 ids */
  snprintf(p, sizeof p, "%s/scene_vh_clean_2.labels.ply", scene);
  FILE *f = fopen(p, "wb");
  assert_non_null(f);
  fputs("ply\nformat binary_little_endian 1.0\ncomment MLIB generated\nelement vertex 4\n"
        "property float x\nproperty float y\nproperty float z\nproperty uchar red\nproperty uchar green\n"
        "property uchar blue\nproperty uchar alpha\nproperty ushort label\nelement face 1\n"
        "property list uchar int vertex_indices\nend_header\n",
        f);
  const uint16_t nyu[4] = {5, 13, 50, 39};
  for (int k = 0; k < 4; k++) {
    float xyz[3] = {(float)k, 0.5f, 1.0f};
    uint8_t c[4] = {1, 2, 3, 255};
    fwrite(xyz, 4, 3, f), fwrite(c, 1, 4, f), fwrite(&nyu[k], 2, 1, f);
  }
  uint8_t three = 3;
  int32_t idx[3] = {0, 1, 2};
  fwrite(&three, 1, 1, f), fwrite(idx, 4, 3, f);
  fclose(f);
}

static void mat_text(char *b, size_t n, const double K[4]) {
  snprintf(b, n, "%f 0 %f 0\n0 %f %f 0\n0 0 1 0\n0 0 0 1\n", K[0], K[2], K[1], K[3]);
}

static void write_png16(const char *path, const uint16_t *d, int w, int h) {
  char err[256];
  if (vlff_png_write(path, d, w, h, 1, 1, err, sizeof err) < 0) fail_msg("%s", err);
}

/* Colour as the format wants it: JPEG with OpenCV, else PNG. */
static uint8_t *colour_blob(const uint8_t *rgb, size_t *len) {
  char err[256];
  uint8_t *b = NULL;
#ifdef VLFF_HAVE_OPENCV
  (void)err;
  if (test_jpeg_encode(rgb, CW, CH, 95, &b, len) < 0) fail_msg("JPEG encoding failed");
#else
  char p[1024];
  snprintf(p, sizeof p, "%s/tmp.png", root);
  if (vlff_png_write(p, rgb, CW, CH, 3, 0, err, sizeof err) < 0) fail_msg("%s", err);
  if (vlff_read_file(p, 1 << 24, &b, len, err, sizeof err) < 0) fail_msg("%s", err);
  unlink(p);
#endif
  return b;
}

/* The scene's images as an export stores them: colour (and encoded as the
 * export's colour files), label ids at colour resolution, and depth. */
struct images {
  uint8_t *rgb, *blob;
  uint16_t *ids, *depth;
  size_t blob_len;
};

static void images_make(struct images *im) {
  im->rgb = malloc(CW * CH * 3);
  im->ids = malloc(CW * CH * 2), im->depth = malloc(DW * DH * 2);
  assert_true(im->rgb && im->ids && im->depth);
  colour_image(im->rgb, im->ids);
  depth_image(im->depth);
  im->blob = colour_blob(im->rgb, &im->blob_len);
}

static void images_free(struct images *im) { free(im->blob), free(im->rgb), free(im->ids), free(im->depth); }

/* A ScanNet export of n frames; frame `lost` (if in range) has ScanNet's
 * lost-tracking pose, all -inf. */
static void write_export(const char *scene, int n, int lost) {
  char p[1024], b[512];
  const char *subs[] = {"", "/color", "/depth", "/pose", "/intrinsic", "/label-filt"};
  for (int k = 0; k < 6; k++) {
    snprintf(p, sizeof p, "%s%s", scene, subs[k]);
    assert_int_equal(mkdir(p, 0755), 0);
  }
  struct images im;
  images_make(&im);
  for (int i = 0; i < n; i++) {
    snprintf(p, sizeof p, "%s/color/%d.jpg", scene, i);
    put(p, im.blob, im.blob_len);
    snprintf(p, sizeof p, "%s/depth/%d.png", scene, i);
    write_png16(p, im.depth, DW, DH);
    snprintf(p, sizeof p, "%s/label-filt/%d.png", scene, i);
    write_png16(p, im.ids, CW, CH);
    snprintf(p, sizeof p, "%s/pose/%d.txt", scene, i);
    if (i == lost)
      putf(p, "-inf -inf -inf -inf\n-inf -inf -inf -inf\n-inf -inf -inf -inf\n-inf -inf -inf -inf\n");
    else
      putf(p, "1 0 0 %d\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", i);
  }
  mat_text(b, sizeof b, Kc);
  snprintf(p, sizeof p, "%s/intrinsic/intrinsic_color.txt", scene);
  putf(p, "%s", b);
  mat_text(b, sizeof b, Kd);
  snprintf(p, sizeof p, "%s/intrinsic/intrinsic_depth.txt", scene);
  putf(p, "%s", b);
  snprintf(p, sizeof p, "%s/intrinsic/extrinsic_depth.txt", scene);
  putf(p, "1 0 0 %f\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", BASE);
  write_tsv_and_ply(scene);
  images_free(&im);
}

struct sens_opts {
  uint32_t version;
  int32_t dtype;
  uint64_t nframes_claimed;
  long truncate_to; /* < 0: bytes cut from the end */
  int skewed_frame; /* > 0: that frame's rotation is not orthonormal */
  double apart;     /* > 0: the depth camera this far from the colour camera on every axis */
};

static void write_sens(const char *path, const struct sens_opts *o) {
  FILE *f = fopen(path, "wb");
  assert_non_null(f);
  uint64_t namelen = 6;
  fwrite(&o->version, 4, 1, f), fwrite(&namelen, 8, 1, f), fwrite("struct", 1, 6, f);
  float m[4][16] = {{0}};
  const double *K[2] = {Kc, Kd};
  for (int c = 0; c < 2; c++) {
    float *k = m[2 * c], *e = m[2 * c + 1];
    k[0] = (float)K[c][0], k[2] = (float)K[c][2], k[5] = (float)K[c][1], k[6] = (float)K[c][3], k[10] = k[15] = 1;
    e[0] = e[5] = e[10] = e[15] = 1;
  }
  m[3][3] = (float)BASE;
  if (o->apart > 0) m[3][3] = m[3][7] = m[3][11] = (float)o->apart;
  fwrite(m, 4, 64, f);
  int32_t ctype = 2;
#ifndef VLFF_HAVE_OPENCV
  ctype = 1; /* PNG */
#endif
  uint32_t dims[4] = {CW, CH, DW, DH};
  float shift = 1000;
  fwrite(&ctype, 4, 1, f), fwrite(&o->dtype, 4, 1, f), fwrite(dims, 4, 4, f), fwrite(&shift, 4, 1, f);
  fwrite(&o->nframes_claimed, 8, 1, f);
  struct images im;
  images_make(&im);
  uLongf zn = compressBound(DW * DH * 2);
  uint8_t *z = malloc(zn);
  assert_int_equal(compress2(z, &zn, (const Bytef *)im.depth, DW * DH * 2, 6), Z_OK);
  for (int i = 0; i < 3; i++) {
    float pose[16] = {1, 0, 0, 0.1f * i, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};
    if (i == 1) pose[0] = -INFINITY; /* lost tracking */
    if (o->skewed_frame && i == o->skewed_frame) pose[1] = 0.5f;
    uint64_t st[2] = {1000u * i, 1000u * i}, sz[2] = {im.blob_len, zn};
    fwrite(pose, 4, 16, f), fwrite(st, 8, 2, f), fwrite(sz, 8, 2, f), fwrite(im.blob, 1, im.blob_len, f);
    fwrite(z, 1, zn, f);
  }
  long size = ftell(f);
  fclose(f);
  if (o->truncate_to) assert_int_equal(truncate(path, size + o->truncate_to), 0); /* cut the last frame */
  free(z);
  images_free(&im);
}

/* root/<name>/<name>.sens (three frames, the second lost) with the label
 * TSV and the labelled mesh; dir and path filled. */
static void sens_scene(char *dir, size_t dcap, char *path, size_t pcap, const char *name) {
  snprintf(dir, dcap, "%s/%s", root, name);
  assert_int_equal(mkdir(dir, 0755), 0);
  snprintf(path, pcap, "%s/%s.sens", dir, name);
  struct sens_opts good = {.version = 4, .dtype = 1, .nframes_claimed = 3};
  write_sens(path, &good);
  write_tsv_and_ply(dir);
}

/* Registered depth against the geometry, colour and labels resampled. */
static void check_frame(const struct vlff_dataset *ds, int set) {
  assert_true(ds->registered);
  assert_int_equal(ds->width, DW);
  assert_int_equal(ds->height, DH);
  uint8_t *rgb = malloc(DW * DH * 3), *lab = malloc(DW * DH);
  float *z = malloc(DW * DH * sizeof *z);
  char err[512];
  if (vlff_dataset_read_frame(ds, 0, rgb, z, lab, err, sizeof err) < 0) fail_msg("%s", err);
  double su = 0, sv = 0, eu = 0, ev = 0;
  int got = 0, want = 0, wrong = 0, interior = 0, interior_valid = 0;
  for (int v = 0; v < DH; v++)
    for (int u = 0; u < DW; u++) {
      /* the field's pixel centres: u + 0.5 */
      double dx = (u + 0.5 - ds->cx) / ds->fx, dy = (v + 0.5 - ds->cy) / ds->fy;
      double expect = cast(0, dx, dy), Z = z[v * DW + u];
      /* 2 px from the plate's outline, the surface is unambiguous */
      int near_edge = 0;
      for (int a = -2; a <= 2; a++)
        for (int b = -2; b <= 2; b++)
          if (cast(0, (u + a + 0.5 - ds->cx) / ds->fx, (v + b + 0.5 - ds->cy) / ds->fy) != expect) near_edge = 1;
      if (expect == 1.0) eu += u, ev += v, want++;
      if (Z > 0 && fabs(Z - 1.0) < 1e-3) su += u, sv += v, got++;
      if (!near_edge) {
        interior++;
        if (Z > 0) {
          interior_valid++;
          if (fabs(Z - expect) > 1e-3) wrong++;
        }
      }
    }
  assert_int_equal(wrong, 0);
  assert_true(interior_valid >= 0.9 * interior);
  assert_true(got > 0 && want > 0);
  assert_true(fabs(su / got - eu / want) < 0.5);
  assert_true(fabs(sv / got - ev / want) < 0.5);
  /* colour: box-filtered, JPEG's ringing stays at the edges */
  const uint8_t *p = rgb + (10 * DW + 10) * 3, *q = rgb + (50 * DW + 70) * 3;
  assert_true(abs(p[0] - 230) < 12 && abs(p[1] - 200) < 12 && abs(p[2] - 100) < 12);
  assert_true(abs(q[0] - 20) < 12 && abs(q[1] - 40) < 12);
  /* labels: id 1 -> wall, 2 -> chair, 7 -> blinds, 0 -> none */
  assert_int_equal(lab[0], 255);
  assert_int_equal(lab[10 * DW + 10], 0);
  assert_int_equal(lab[10 * DW + 70], 4);
  assert_int_equal(lab[50 * DW + 70], set == VLFF_LABELS_NYU40 ? 12 : 255);
  free(rgb), free(lab), free(z);
}

static void check_points(const struct vlff_dataset *ds, int set) {
  struct vlff_points pts;
  char err[512];
  if (vlff_dataset_read_points(ds, &pts, err, sizeof err) < 0) fail_msg("%s", err);
  assert_int_equal(pts.n, 4);
  /* NYU40 5 chair, 13 blinds, 50 (invalid, as in scene0270_00), 39 otherfurniture */
  const uint8_t want20[4] = {4, 255, 255, 19}, want40[4] = {4, 12, 255, 38};
  for (int k = 0; k < 4; k++) assert_int_equal(pts.label[k], set == VLFF_LABELS_NYU40 ? want40[k] : want20[k]);
  vlff_points_free(&pts);
}

/* root/scans/<name>, its parent created: a scene directory as ScanNet's
 * download script lays them out. */
static void scene_path(char *scene, size_t cap, const char *name) {
  snprintf(scene, cap, "%s/scans", root);
  mkdir(scene, 0755);
  snprintf(scene, cap, "%s/scans/%s", root, name);
}

static void test_export_layout(void **state) {
  (void)state;
  char scene[400], err[512];
  scene_path(scene, sizeof scene, "scene0000_00");
  write_export(scene, 2, -1);
  for (int set = VLFF_LABELS_SCANNET20; set <= VLFF_LABELS_NYU40; set++) {
    struct vlff_dataset ds;
    struct vlff_dataset_options o = {.layout = VLFF_DS_AUTO, .label_set = set};
    if (vlff_dataset_open_opts(&ds, scene, &o, err, sizeof err) < 0) fail_msg("%s", err);
    assert_int_equal(ds.layout, VLFF_DS_SCANNET);
    assert_int_equal(ds.n, 2);
    assert_true(ds.has_labels);
    check_frame(&ds, set);
    check_points(&ds, set);
    vlff_dataset_close(&ds);
  }
  assert_string_equal(vlff_label_set_name(VLFF_LABELS_SCANNET20, 19), "otherfurniture");
  assert_null(vlff_label_set_name(VLFF_LABELS_SCANNET20, 20));
  char p[600], moved[640];
  /* a FIFO or a directory at a camera file's name is refused, not taken
   * for absent (the depth camera was then taken for the colour camera) */
  const char *cams[2] = {"intrinsic_depth.txt", "extrinsic_depth.txt"};
  for (int k = 0; k < 2; k++) {
    snprintf(p, sizeof p, "%s/intrinsic/%s", scene, cams[k]);
    snprintf(moved, sizeof moved, "%s.kept", p);
    int had = rename(p, moved) == 0;
    assert_int_equal(mkfifo(p, 0600), 0);
    struct vlff_dataset dk;
    assert_int_equal(vlff_dataset_open(&dk, scene, VLFF_DS_AUTO, err, sizeof err), -1);
    if (!strstr(err, cams[k]) || !strstr(err, "is a FIFO")) fail_msg("%s: %s", cams[k], err);
    unlink(p);
    if (had) assert_int_equal(rename(moved, p), 0);
  }
  /* without the TSV, label ids cannot be classes: say where it looked */
  snprintf(p, sizeof p, "%s/scannetv2-labels.combined.tsv", root);
  unlink(p);
  struct vlff_dataset ds;
  assert_int_equal(vlff_dataset_open(&ds, scene, VLFF_DS_AUTO, err, sizeof err), -1);
  assert_non_null(strstr(err, "scannetv2-labels.combined.tsv"));
  /* a TSV without ScanNet's columns, or with a bad row, names file and line */
  put(p, "id\tname\n1\twall\n", 15);
  assert_int_equal(vlff_dataset_open(&ds, scene, VLFF_DS_AUTO, err, sizeof err), -1);
  assert_non_null(strstr(err, ":1: header lacks"));
  putf(p, "%s9\tx\tx\t1\t41\n", tsv);
  assert_int_equal(vlff_dataset_open(&ds, scene, VLFF_DS_AUTO, err, sizeof err), -1);
  assert_non_null(strstr(err, "combined.tsv:5:"));
  /* An empty nyu40id read the next column's number (strtol skips the tab);
   * a sign or a space was taken; rows run together read as one; a NUL cut
   * a field short. */
  static const char *const bad[][2] = {
      {"9\tx\tx\t1\t\t3\n", "combined.tsv:5: 'id' must be an integer"},
      {"9\tx\tx\t1\t 3\n", "combined.tsv:5: 'id' must be an integer"},
      {"+9\tx\tx\t1\t3\n", "combined.tsv:5: 'id' must be an integer"},
      {"9\tx\tx\t1\t3\t1\t1\t1\t1\t9\tx\tx\t1\t3\n", "combined.tsv:5: 14 fields, more than the header's 9"},
  };
  for (size_t k = 0; k < sizeof bad / sizeof bad[0]; k++) {
    putf(p, "%s%s", tsv, bad[k][0]);
    assert_int_equal(vlff_dataset_open(&ds, scene, VLFF_DS_AUTO, err, sizeof err), -1);
    if (!strstr(err, bad[k][1])) fail_msg("case %zu: %s", k, err);
  }
  char withnul[sizeof tsv + 16];
  memcpy(withnul, tsv, sizeof tsv - 1);
  memcpy(withnul + sizeof tsv - 1, "9\tx\tx\t1\t3\0x\n", 13);
  put(p, withnul, sizeof tsv - 1 + 13);
  assert_int_equal(vlff_dataset_open(&ds, scene, VLFF_DS_AUTO, err, sizeof err), -1);
  if (!strstr(err, "combined.tsv:5: NUL byte")) fail_msg("NUL: %s", err);
  /* fewer fields than the header (empty last columns) are a row */
  putf(p, "%s9\tx\tx\t1\t3\n", tsv);
  if (vlff_dataset_open(&ds, scene, VLFF_DS_AUTO, err, sizeof err) < 0) fail_msg("%s", err);
  vlff_dataset_close(&ds);
}

static void test_sens(void **state) {
  (void)state;
  char dir[400], path[600], err[512];
  sens_scene(dir, sizeof dir, path, sizeof path, "scene0001_00");
  char p[600];
  snprintf(p, sizeof p, "%s/label-filt", dir);
  assert_int_equal(mkdir(p, 0755), 0);
  uint8_t *rgb = malloc(CW * CH * 3);
  uint16_t *ids = malloc(CW * CH * 2);
  colour_image(rgb, ids);
  for (int i = 0; i < 3; i += 2) {
    snprintf(p, sizeof p, "%s/label-filt/%d.png", dir, i);
    write_png16(p, ids, CW, CH);
  }
  free(rgb), free(ids);
  /* the directory and the file itself both open it */
  const char *names[2] = {dir, path};
  for (int k = 0; k < 2; k++) {
    struct vlff_dataset ds;
    if (vlff_dataset_open(&ds, names[k], VLFF_DS_AUTO, err, sizeof err) < 0) fail_msg("%s", err);
    assert_int_equal(ds.layout, VLFF_DS_SENS);
    assert_int_equal(ds.n, 2);
    assert_int_equal(ds.skipped, 1);
    assert_string_equal(ds.stem[1], "2");
    assert_true(fabs(ds.c2w[16 + 3] - 0.2) < 1e-6);
    check_frame(&ds, VLFF_LABELS_SCANNET20);
    check_points(&ds, VLFF_LABELS_SCANNET20);
    vlff_dataset_close(&ds);
  }
  /* hostile files: each refused naming the file and what is wrong */
  struct {
    struct sens_opts o;
    const char *says;
  } bad[] = {
      {{.version = 3, .dtype = 1, .nframes_claimed = 3}, "version 4"},
      {{.version = 4, .dtype = 2, .nframes_claimed = 3}, "occi"},
      {{.version = 4, .dtype = 1, .nframes_claimed = 1ull << 40}, "do not fit"},
      {{.version = 4, .dtype = 1, .nframes_claimed = 3, .truncate_to = -10}, "frame 2"},
      /* 0.7 m on every axis: under 1 m on each, 1.21 m apart */
      {{.version = 4, .dtype = 1, .nframes_claimed = 3, .apart = 0.7}, "cameras are 1.21 m apart, more than 1 m"},
  };
  for (size_t k = 0; k < sizeof bad / sizeof *bad; k++) {
    write_sens(path, &bad[k].o);
    struct vlff_dataset ds;
    assert_int_equal(vlff_dataset_open(&ds, path, VLFF_DS_AUTO, err, sizeof err), -1);
    if (!strstr(err, bad[k].says) || !strstr(err, "scene0001_00.sens")) fail_msg("case %zu: %s", k, err);
  }
}

/* A .sens deep in long directory names: a bad pose is named with the whole
 * path and the frame (the message was formed in 48 bytes, which kept the
 * path's first 47 and lost the frame); paths longer than the reader takes
 * are refused naming their length, not cut short. */
static void test_sens_long_path(void **state) {
  (void)state;
  char dir[1024], path[1200], err[2048], seg[201];
  memset(seg, 'd', 200), seg[200] = 0;
  snprintf(dir, sizeof dir, "%s/%s", root, seg);
  assert_int_equal(mkdir(dir, 0755), 0);
  size_t l = strlen(dir);
  snprintf(dir + l, sizeof dir - l, "/%s", "scene0003_00");
  assert_int_equal(mkdir(dir, 0755), 0);
  snprintf(path, sizeof path, "%s/scene0003_00.sens", dir);
  struct sens_opts skew = {.version = 4, .dtype = 1, .nframes_claimed = 3, .skewed_frame = 2};
  write_sens(path, &skew);
  write_tsv_and_ply(dir);
  struct vlff_dataset ds;
  assert_int_equal(vlff_dataset_open(&ds, path, VLFF_DS_AUTO, err, sizeof err), -1);
  if (strncmp(err, path, strlen(path)) || !strstr(err, ": frame 2 pose: rotation is not orthonormal"))
    fail_msg("%s", err);
  /* 4001 bytes: one more than a dataset path may have */
  char *lng = malloc(VLFF_DS_PATH_MAX + 2);
  assert_non_null(lng);
  memset(lng, 'x', VLFF_DS_PATH_MAX + 1), lng[VLFF_DS_PATH_MAX + 1] = 0;
  lng[0] = '/';
  assert_int_equal(vlff_dataset_open(&ds, lng, VLFF_DS_AUTO, err, sizeof err), -1);
  if (!strstr(err, "dataset path of 4001 bytes is longer than the 4000")) fail_msg("%s", err);
  struct vlff_dataset_options o = {.layout = VLFF_DS_AUTO, .label_set = VLFF_LABELS_SCANNET20, .label_tsv = lng};
  assert_int_equal(vlff_dataset_open_opts(&ds, path, &o, err, sizeof err), -1);
  if (!strstr(err, "label table path of 4001 bytes")) fail_msg("%s", err);
  free(lng);
}

#ifdef VLFF_HAVE_HDF5
/* A feature file at path: rows maps of h x w x c floats, every value of row
 * r = base + r + 1; rank 3 writes one map as [h,w,c]. With nframes > 0 a root
 * dataset "frames" of those numbers (as int64, or as float when as_float)
 * names each row's frame. */
/* The name write_feats gives its map, features/<feat_dset>. */
static const char *feat_dset = "lseg";

static void write_feats(const char *path, float base, int rows, int h, int w, int c, int rank,
                        const long long *frames, int nframes, int as_float) {
  H5Eset_auto2(H5E_DEFAULT, NULL, NULL);
  hid_t f = H5Fcreate(path, H5F_ACC_TRUNC, H5P_DEFAULT, H5P_DEFAULT);
  assert_true(f >= 0);
  hid_t g = H5Gcreate2(f, "features", H5P_DEFAULT, H5P_DEFAULT, H5P_DEFAULT);
  hsize_t dims[4] = {(hsize_t)rows, (hsize_t)h, (hsize_t)w, (hsize_t)c};
  size_t per = (size_t)h * w * c;
  float *v = malloc((size_t)rows * per * sizeof *v);
  assert_non_null(v);
  for (int r = 0; r < rows; r++)
    for (size_t k = 0; k < per; k++) v[r * per + k] = base + (float)(r + 1);
  hid_t sp = rank == 3 ? H5Screate_simple(3, dims + 1, NULL) : H5Screate_simple(4, dims, NULL);
  hid_t d = H5Dcreate2(g, feat_dset, H5T_IEEE_F32LE, sp, H5P_DEFAULT, H5P_DEFAULT, H5P_DEFAULT);
  assert_true(d >= 0);
  assert_true(H5Dwrite(d, H5T_NATIVE_FLOAT, H5S_ALL, H5S_ALL, H5P_DEFAULT, v) >= 0);
  H5Dclose(d), H5Sclose(sp), H5Gclose(g);
  if (nframes > 0) {
    hsize_t n = (hsize_t)nframes;
    double fv[64];
    for (int k = 0; k < nframes && k < 64; k++) fv[k] = (double)frames[k];
    sp = H5Screate_simple(1, &n, NULL);
    d = H5Dcreate2(f, "frames", as_float ? H5T_IEEE_F64LE : H5T_STD_I64LE, sp, H5P_DEFAULT, H5P_DEFAULT, H5P_DEFAULT);
    assert_true(d >= 0);
    assert_true(H5Dwrite(d, as_float ? H5T_NATIVE_DOUBLE : H5T_NATIVE_LLONG, H5S_ALL, H5S_ALL, H5P_DEFAULT,
                         as_float ? (const void *)fv : (const void *)frames) >= 0);
    H5Dclose(d), H5Sclose(sp);
  }
  H5Fclose(f);
  free(v);
}

/* features.hdf with rows maps of 2x2x4 floats, every value of row r = r + 1. */
static void write_features(const char *scene, int rows) {
  char p[600];
  snprintf(p, sizeof p, "%s/features.hdf", scene);
  write_feats(p, 0, rows, 2, 2, 4, 4, NULL, 0, 0);
}

/* Frame i's first feature as half-float bits. */
static uint16_t first_feature(const struct vlff_dataset *ds, int i) {
  uint16_t out[16];
  char err[512];
  if (vlff_dataset_read_features(ds, i, out, err, sizeof err) < 0) fail_msg("%s", err);
  return out[0];
}
#endif

/* A scene with a lost-tracking frame: the frame is skipped, the others keep
 * their ScanNet frame numbers, and features.hdf may hold a map per usable
 * frame or one per frame the scene lists (an extractor run over every
 * exported image); any other count is refused naming both. */
static void test_lost_tracking(void **state) {
  (void)state;
  char scene[400], err[512];
  scene_path(scene, sizeof scene, "scene0002_00");
  write_export(scene, 3, 1);
  char p[600];
  snprintf(p, sizeof p, "%s/scannetv2-labels.combined.tsv", root);
  put(p, tsv, sizeof tsv - 1);
  struct vlff_dataset ds;
  if (vlff_dataset_open(&ds, scene, VLFF_DS_AUTO, err, sizeof err) < 0) fail_msg("%s", err);
  assert_int_equal(ds.n, 2);
  assert_int_equal(ds.skipped, 1);
  assert_int_equal(ds.n_listed, 3);
  assert_string_equal(ds.stem[1], "2");
  assert_int_equal(ds.listed[1], 2);
  vlff_dataset_close(&ds);
#ifdef VLFF_HAVE_HDF5
  /* 1, 2 and 3 as half floats: the value of row 0, 1 and 2 */
  const int rows[3] = {3, 2, 4};
  const uint16_t one = 0x3c00, want_frame1[3] = {0x4200, 0x4000, 0};
  for (int k = 0; k < 3; k++) {
    write_features(scene, rows[k]);
    int rc = vlff_dataset_open(&ds, scene, VLFF_DS_AUTO, err, sizeof err);
    if (!want_frame1[k]) {
      assert_int_equal(rc, -1);
      if (!strstr(err, "expected N=2 frames (or 3, every frame listed, 1 of them skipped"))
        fail_msg("refusal does not name both counts: %s", err);
      continue;
    }
    if (rc < 0) fail_msg("%d rows: %s", rows[k], err);
    assert_int_equal(first_feature(&ds, 0), one);
    assert_int_equal(first_feature(&ds, 1), want_frame1[k]); /* ScanNet frame 2 */
    vlff_dataset_close(&ds);
  }
#endif
}

#ifdef VLFF_HAVE_HDF5
/* The usable frame whose stem is stem. */
static int frame_of(const struct vlff_dataset *ds, const char *stem) {
  for (int i = 0; i < ds->n; i++)
    if (!strcmp(ds->stem[i], stem)) return i;
  fail_msg("no frame %s", stem);
  return -1;
}
#endif

/* What a caller requires is checked before any frame is listed and named
 * as ScanNet names it: the labelled mesh <scene>_vh_clean_2.labels.ply (the
 * .sens file's scene name), label-filt/, features.hdf. A reader that needs
 * none of them (vlff-replay) still opens the scene. */
static void test_required_files(void **state) {
  (void)state;
  char dir[400], path[600], p[700], err[512];
  sens_scene(dir, sizeof dir, path, sizeof path, "scene0010_00");
  snprintf(p, sizeof p, "%s/scene_vh_clean_2.labels.ply", dir);
  assert_int_equal(unlink(p), 0);
  struct vlff_dataset ds;
  struct vlff_dataset_options o = {.layout = VLFF_DS_AUTO, .require = VLFF_DS_REQUIRE_POINTS};
  assert_int_equal(vlff_dataset_open_opts(&ds, path, &o, err, sizeof err), -1);
  if (!strstr(err, "scene0010_00/scene0010_00_vh_clean_2.labels.ply: missing") || strstr(err, "mesh.ply"))
    fail_msg("%s", err);
  if (vlff_dataset_open(&ds, path, VLFF_DS_AUTO, err, sizeof err) < 0) fail_msg("%s", err);
  struct vlff_points pts;
  assert_int_equal(vlff_dataset_read_points(&ds, &pts, err, sizeof err), -1);
  if (!strstr(err, "scene0010_00_vh_clean_2.labels.ply: missing")) fail_msg("%s", err);
  vlff_dataset_close(&ds);
  /* the export layout names it after the scene directory; a FIFO there is refused, not waited on */
  char scene[400];
  scene_path(scene, sizeof scene, "scene0011_00");
  write_export(scene, 2, -1);
  snprintf(p, sizeof p, "%s/scene_vh_clean_2.labels.ply", scene);
  assert_int_equal(unlink(p), 0);
  assert_int_equal(vlff_dataset_open_opts(&ds, scene, &o, err, sizeof err), -1);
  if (!strstr(err, "scans/scene0011_00/scene0011_00_vh_clean_2.labels.ply: missing")) fail_msg("%s", err);
  snprintf(p, sizeof p, "%s/scene0011_00_vh_clean_2.labels.ply", scene);
  assert_int_equal(mkfifo(p, 0644), 0);
  assert_int_equal(vlff_dataset_open_opts(&ds, scene, &o, err, sizeof err), -1);
  if (!strstr(err, "scene0011_00_vh_clean_2.labels.ply")) fail_msg("%s", err);
  unlink(p);
  write_tsv_and_ply(scene);
  /* the 2D labels and the features */
  o.require = VLFF_DS_REQUIRE_POINTS | VLFF_DS_REQUIRE_LABELS | VLFF_DS_REQUIRE_FEATURES;
  assert_int_equal(vlff_dataset_open_opts(&ds, scene, &o, err, sizeof err), -1);
  if (!strstr(err, "scene0011_00/features.hdf: missing")) fail_msg("%s", err);
  snprintf(p, sizeof p, "rm -r %s/label-filt", scene);
  assert_int_equal(system(p), 0);
  assert_int_equal(vlff_dataset_open_opts(&ds, scene, &o, err, sizeof err), -1);
  if (!strstr(err, "scene0011_00/label-filt: missing: ScanNet's 2D labels")) fail_msg("%s", err);
}

#ifdef VLFF_HAVE_HDF5
/* Features for some frames only (a whole ScanNet scene's maps at D = 512
 * are about 110 GB): features.hdf naming its rows' frames in "frames", or
 * features/<frame>.hdf, one file per frame. A frame without features is
 * refused when read, naming the file and the frame; frame numbers out of
 * order, beyond the scene or not matching the rows, and a file naming no
 * frame of the scene, are refused at open naming the file and the row. */
static void test_features_some_frames(void **state) {
  (void)state;
  char scene[400], err[512], p[700];
  scene_path(scene, sizeof scene, "scene0006_00");
  write_export(scene, 7, 4); /* frames 0..6, 4 lost */
  snprintf(p, sizeof p, "%s/features.hdf", scene);
  const long long every2[4] = {0, 2, 4, 6};
  write_feats(p, 0, 4, 2, 2, 4, 4, every2, 4, 0);
  struct vlff_dataset ds;
  uint16_t out[16];
  if (vlff_dataset_open(&ds, scene, VLFF_DS_AUTO, err, sizeof err) < 0) fail_msg("%s", err);
  assert_int_equal(ds.n, 6);
  assert_int_equal(ds.feat_frames, 3); /* 0, 2 and 6; 4 is lost */
  assert_int_equal(first_feature(&ds, frame_of(&ds, "0")), 0x3c00); /* row 0: 1 */
  assert_int_equal(first_feature(&ds, frame_of(&ds, "2")), 0x4000); /* row 1: 2 */
  assert_int_equal(first_feature(&ds, frame_of(&ds, "6")), 0x4400); /* row 3: 4 */
  assert_int_equal(vlff_dataset_read_features(&ds, frame_of(&ds, "1"), out, err, sizeof err), -1);
  if (!strstr(err, "scene0006_00/features.hdf: holds no features for frame 1")) fail_msg("%s", err);
  vlff_dataset_close(&ds);
  struct {
    long long f[4];
    int n, as_float;
    const char *says;
  } bad[] = {
      {{0, 4, 2, 6}, 4, 0, "frames[2] = 2 after frame 4: frame numbers must increase"},
      {{0, 2, 2, 6}, 4, 0, "frames[2] = 2 after frame 2"},
      {{0, 2, 4, 7}, 4, 0, "frames[3] = 7: the scene's frames run 0..6"},
      {{-1, 2, 4, 6}, 4, 0, "frames[0] = -1"},
      {{0, 2, 4}, 3, 0, "'frames' names 3 frames but features/lseg holds 4"},
      {{0, 2, 4, 6}, 4, 1, "'frames' must be a 1-D integer dataset"},
  };
  for (size_t k = 0; k < sizeof bad / sizeof *bad; k++) {
    write_feats(p, 0, 4, 2, 2, 4, 4, bad[k].f, bad[k].n, bad[k].as_float);
    assert_int_equal(vlff_dataset_open(&ds, scene, VLFF_DS_AUTO, err, sizeof err), -1);
    if (!strstr(err, bad[k].says) || !strstr(err, "scene0006_00/features.hdf")) fail_msg("case %zu: %s", k, err);
  }
  /* without "frames", a count that fits no rule says how to name them */
  write_feats(p, 0, 4, 2, 2, 4, 4, NULL, 0, 0);
  assert_int_equal(vlff_dataset_open(&ds, scene, VLFF_DS_AUTO, err, sizeof err), -1);
  if (!strstr(err, "holds 4 frames; expected N=6") || !strstr(err, "'frames' dataset")) fail_msg("%s", err);
  /* one file per frame, [H,W,C] or [1,H,W,C]; the lost frame's is passed over */
  unlink(p);
  snprintf(p, sizeof p, "%s/features", scene);
  assert_int_equal(mkdir(p, 0755), 0);
  const int have[4] = {0, 2, 4, 6};
  for (int k = 0; k < 4; k++) {
    snprintf(p, sizeof p, "%s/features/%d.hdf", scene, have[k]);
    write_feats(p, (float)have[k], 1, 2, 2, 4, k % 2 ? 4 : 3, NULL, 0, 0);
  }
  if (vlff_dataset_open(&ds, scene, VLFF_DS_AUTO, err, sizeof err) < 0) fail_msg("%s", err);
  assert_true(ds.feat_files);
  assert_int_equal(ds.feat_frames, 3);
  assert_int_equal(first_feature(&ds, frame_of(&ds, "0")), 0x3c00); /* 1 */
  assert_int_equal(first_feature(&ds, frame_of(&ds, "2")), 0x4200); /* 3 */
  assert_int_equal(first_feature(&ds, frame_of(&ds, "6")), 0x4700); /* 7 */
  assert_int_equal(vlff_dataset_read_features(&ds, frame_of(&ds, "5"), out, err, sizeof err), -1);
  if (!strstr(err, "scene0006_00/features/5.hdf: holds no features for frame 5")) fail_msg("%s", err);
  vlff_dataset_close(&ds);
  /* a file of another shape is refused when read, naming it */
  snprintf(p, sizeof p, "%s/features/6.hdf", scene);
  write_feats(p, 6, 1, 2, 2, 8, 3, NULL, 0, 0);
  if (vlff_dataset_open(&ds, scene, VLFF_DS_AUTO, err, sizeof err) < 0) fail_msg("%s", err);
  assert_int_equal(vlff_dataset_read_features(&ds, frame_of(&ds, "6"), out, err, sizeof err), -1);
  if (!strstr(err, "features/6.hdf: features/lseg is 2x2x8; the scene's are 2x2x4")) fail_msg("%s", err);
  vlff_dataset_close(&ds);
  /* a frame's file with two maps, or its map under another name than the
   * other files': the first by name was read, silently */
  for (int k = 0; k < 2; k++) {
    if (k == 0) {
      write_feats(p, 6, 1, 2, 2, 4, 3, NULL, 0, 0);
      hid_t f = H5Fopen(p, H5F_ACC_RDWR, H5P_DEFAULT);
      assert_true(f >= 0);
      hsize_t dd[3] = {2, 2, 4};
      hid_t sp = H5Screate_simple(3, dd, NULL);
      hid_t d = H5Dcreate2(f, "features/aaa", H5T_IEEE_F32LE, sp, H5P_DEFAULT, H5P_DEFAULT, H5P_DEFAULT);
      assert_true(d >= 0);
      float zero[16] = {0};
      assert_true(H5Dwrite(d, H5T_NATIVE_FLOAT, H5S_ALL, H5S_ALL, H5P_DEFAULT, zero) >= 0);
      H5Dclose(d), H5Sclose(sp), H5Fclose(f);
    } else {
      feat_dset = "other";
      write_feats(p, 6, 1, 2, 2, 4, 3, NULL, 0, 0);
      feat_dset = "lseg";
    }
    if (vlff_dataset_open(&ds, scene, VLFF_DS_AUTO, err, sizeof err) < 0) fail_msg("%s", err);
    assert_int_equal(vlff_dataset_read_features(&ds, frame_of(&ds, "6"), out, err, sizeof err), -1);
    const char *want = k ? "features/6.hdf: holds features/other; the scene's other frame files hold features/lseg"
                         : "features/6.hdf: group 'features' holds 2 datasets ('aaa', 'lseg'...), a frame's file one map";
    if (!strstr(err, want)) fail_msg("%s", err);
    vlff_dataset_close(&ds);
  }
  /* a file naming no frame of the scene, or two maps in one frame's file */
  snprintf(p, sizeof p, "%s/features/9.hdf", scene);
  write_feats(p, 0, 1, 2, 2, 4, 3, NULL, 0, 0);
  assert_int_equal(vlff_dataset_open(&ds, scene, VLFF_DS_AUTO, err, sizeof err), -1);
  if (!strstr(err, "features/9.hdf: the scene has no frame 9")) fail_msg("%s", err);
  unlink(p);
  snprintf(p, sizeof p, "%s/features/0.hdf", scene);
  write_feats(p, 0, 2, 2, 2, 4, 4, NULL, 0, 0);
  assert_int_equal(vlff_dataset_open(&ds, scene, VLFF_DS_AUTO, err, sizeof err), -1);
  if (!strstr(err, "features/0.hdf: features/lseg has shape [2,2,2,4]; expected one frame")) fail_msg("%s", err);
  /* both forms at once: which one is meant? */
  write_feats(p, 0, 1, 2, 2, 4, 4, NULL, 0, 0);
  snprintf(p, sizeof p, "%s/features.hdf", scene);
  write_feats(p, 0, 6, 2, 2, 4, 4, NULL, 0, 0);
  assert_int_equal(vlff_dataset_open(&ds, scene, VLFF_DS_AUTO, err, sizeof err), -1);
  if (!strstr(err, "both features.hdf and features/")) fail_msg("%s", err);
}
#define FEATURES_TEST , cmocka_unit_test(test_features_some_frames)
#else
#define FEATURES_TEST
#endif

#if defined(VLFF_HAVE_HDF5) && (defined(VLFF_EVAL_BUILT) || defined(VLFF_REPLAY_BUILT))
/* grep -q for text (a fixed string) in root/<log>.log. */
static int log_has(const char *log, const char *text) {
  char cmd[1200];
  snprintf(cmd, sizeof cmd, "grep -qF -- '%s' %s/%s.log", text, root, log);
  return system(cmd) == 0;
}

static void show_log(const char *log) {
  char cmd[700];
  snprintf(cmd, sizeof cmd, "cat %s/%s.log >&2", root, log);
  (void)!system(cmd);
}
#endif

#if defined(VLFF_HAVE_HDF5) && defined(VLFF_EVAL_BUILT)
/* prompt_embeddings.txt in dir naming every class of the label set, D = dim
 * (>= 4; the first four distinguish the classes). */
static void write_embeddings_dim(const char *dir, int set, int dim) {
  char p[600];
  snprintf(p, sizeof p, "%s/prompt_embeddings.txt", dir);
  FILE *f = fopen(p, "w");
  assert_non_null(f);
  fprintf(f, "vlff-embeddings 1\ndim %d\n", dim);
  for (int k = 0; vlff_label_set_name(set, k); k++) {
    fprintf(f, "%s\t%d %d %d 1", vlff_label_set_name(set, k), k % 3, k / 3 % 3, k / 9);
    for (int j = 4; j < dim; j++) fputs(" 0", f);
    fputc('\n', f);
  }
  fclose(f);
}

static void write_embeddings(const char *dir, int set) { write_embeddings_dim(dir, set, 4); }

/* report.json's source frames as "n n ...": train_frames, then test_frames. */
static void report_frames(const char *out, char *train, char *test, size_t cap) {
  char cmd[900];
  snprintf(cmd, sizeof cmd,
           "python3 -c 'import json,sys; s=json.load(open(sys.argv[1]))[\"source\"]; "
           "print(*s[\"train_frames\"]); print(*s[\"test_frames\"])' %s/report.json",
           out);
  FILE *p = popen(cmd, "r");
  assert_non_null(p);
  assert_non_null(fgets(train, (int)cap, p));
  assert_non_null(fgets(test, (int)cap, p));
  assert_int_equal(pclose(p), 0);
}


/* vlff-eval on ScanNet as users have it: an export with a lost-tracking
 * frame and features.hdf holding a map per listed frame, its NYU40 labels
 * through a TSV given by --label-tsv; and the raw .sens file. The report
 * names frames by their ScanNet numbers and scores every label set. */
static void test_eval_reads_scannet(void **state) {
  (void)state;
  char scene[400], eval[600], cmd[3000], train[64], test[64];
  scene_path(scene, sizeof scene, "scene0003_00");
  write_export(scene, 4, 1);
  write_features(scene, 4);
  vlff_test_prog(eval, sizeof eval, "node/eval/vlff-eval");
  char tsvp[600], moved[600];
  snprintf(tsvp, sizeof tsvp, "%s/scannetv2-labels.combined.tsv", root);
  snprintf(moved, sizeof moved, "%s/labels.tsv", root);
  put(moved, tsv, sizeof tsv - 1);
  unlink(tsvp);
  const char *sets[2] = {"scannet20", "nyu40"};
  for (int set = VLFF_LABELS_SCANNET20; set <= VLFF_LABELS_NYU40; set++) {
    write_embeddings(scene, set);
    snprintf(cmd, sizeof cmd,
             "%s --dataset %s --iters 0 --quiet --holdout 2 --label-set %s --label-tsv %s --out %s/out-%s "
             ">%s/eval-%s.log 2>&1",
             eval, scene, sets[set], moved, root, sets[set], root, sets[set]);
    if (system(cmd) != 0) {
      snprintf(cmd, sizeof cmd, "cat %s/eval-%s.log >&2", root, sets[set]);
      (void)!system(cmd);
      fail_msg("vlff-eval --label-set %s failed", sets[set]);
    }
    snprintf(cmd, sizeof cmd, "%s/out-%s", root, sets[set]);
    report_frames(cmd, train, test, sizeof train);
    assert_string_equal(train, "0 3\n"); /* usable frames 0, 2, 3: the 2nd held out */
    assert_string_equal(test, "2\n");
    /* the lost frame is counted, in the log and the report */
    char logname[32];
    snprintf(logname, sizeof logname, "eval-%s", sets[set]);
    if (!log_has(logname, "1 more frames without a pose (lost tracking) skipped")) fail_msg("no count of the lost frame");
    snprintf(cmd, sizeof cmd, "grep -q '\"frames_without_pose\": *1' %s/out-%s/report.json", root, sets[set]);
    assert_int_equal(system(cmd), 0);
  }
  /* without --label-tsv the labels cannot be mapped: the refusal says where it looked */
  snprintf(cmd, sizeof cmd, "%s --dataset %s --iters 0 --quiet --out %s/out-none >%s/none.log 2>&1", eval, scene,
           root, root);
  assert_int_not_equal(system(cmd), 0);
  snprintf(cmd, sizeof cmd, "grep -q 'scannetv2-labels.combined.tsv' %s/none.log", root);
  assert_int_equal(system(cmd), 0);
  /* the raw .sens beside the same labels and features: frames 0 and 2 (1 is lost) */
  char dir[400], path[600];
  sens_scene(dir, sizeof dir, path, sizeof path, "scene0004_00");
  snprintf(cmd, sizeof cmd, "mkdir %s/label-filt && cp %s/label-filt/0.png %s/label-filt/2.png %s/label-filt/", dir,
           scene, scene, dir);
  assert_int_equal(system(cmd), 0);
  write_features(dir, 3);
  write_embeddings(dir, VLFF_LABELS_SCANNET20);
  snprintf(cmd, sizeof cmd, "%s --dataset %s --iters 0 --quiet --holdout 2 --label-tsv %s --out %s/out-sens >%s/sens.log 2>&1",
           eval, path, moved, root, root);
  if (system(cmd) != 0) {
    snprintf(cmd, sizeof cmd, "cat %s/sens.log >&2", root);
    (void)!system(cmd);
    fail_msg("vlff-eval on the .sens file failed");
  }
  snprintf(cmd, sizeof cmd, "%s/out-sens", root);
  report_frames(cmd, train, test, sizeof train);
  assert_string_equal(train, "0\n");
  assert_string_equal(test, "2\n");
}

/* Runs vlff-eval with args; its output in root/<log>.log. The exit status. */
static int run_eval(const char *args, const char *log) {
  char eval[600], cmd[3000];
  vlff_test_prog(eval, sizeof eval, "node/eval/vlff-eval");
  snprintf(cmd, sizeof cmd, "%s %s --iters 0 --quiet --holdout 2 >%s/%s.log 2>&1", eval, args, root, log);
  return system(cmd);
}

/* vlff-eval --stride N on scene, output and log named by tag: it must pass
 * and train on frames want_train, hold out want_test ("0 4\n"). */
static void eval_stride_takes(const char *scene, int stride, const char *tag, const char *want_train,
                              const char *want_test) {
  char args[1500], out[400], train[64], test[64];
  snprintf(out, sizeof out, "%s/out-%s", root, tag);
  snprintf(args, sizeof args, "--dataset %s --stride %d --out %s", scene, stride, out);
  if (run_eval(args, tag) != 0) {
    show_log(tag);
    fail_msg("vlff-eval --stride %d failed", stride);
  }
  report_frames(out, train, test, sizeof train);
  assert_string_equal(train, want_train);
  assert_string_equal(test, want_test);
}

/* vlff-eval --stride N on scene must be refused, its log holding want. */
static void eval_stride_refused(const char *scene, int stride, const char *tag, const char *want) {
  char args[1500];
  snprintf(args, sizeof args, "--dataset %s --stride %d --out %s/out-%s", scene, stride, root, tag);
  assert_int_not_equal(run_eval(args, tag), 0);
  if (!log_has(tag, want)) {
    show_log(tag);
    fail_msg("the refusal of --stride %d does not say \"%s\"", stride, want);
  }
}

/* vlff-eval on features stored for every second frame (features.hdf with
 * "frames", then features/<frame>.hdf): --stride 2 and 4 take frames they
 * hold; --stride 3 is refused before any frame is read, naming the file
 * and the first frame it lacks. */
static void test_eval_strided_features(void **state) {
  (void)state;
  char scene[400], p[700];
  scene_path(scene, sizeof scene, "scene0008_00");
  write_export(scene, 16, -1);
  write_embeddings(scene, VLFF_LABELS_SCANNET20);
  snprintf(p, sizeof p, "%s/features.hdf", scene);
  long long even[8];
  for (int k = 0; k < 8; k++) even[k] = 2 * k;
  write_feats(p, 0, 8, 2, 2, 4, 4, even, 8, 0);
  eval_stride_takes(scene, 2, "s2", "0 4 8 12\n", "2 6 10 14\n");
  eval_stride_refused(scene, 3, "s3", "scene0008_00/features.hdf: holds no map for frame 3, which --stride 3 takes");
  /* one file per frame */
  snprintf(p, sizeof p, "%s/features.hdf", scene);
  assert_int_equal(unlink(p), 0);
  snprintf(p, sizeof p, "%s/features", scene);
  assert_int_equal(mkdir(p, 0755), 0);
  for (int k = 0; k < 16; k += 4) {
    snprintf(p, sizeof p, "%s/features/%d.hdf", scene, k);
    write_feats(p, 0, 1, 2, 2, 4, 3, NULL, 0, 0);
  }
  eval_stride_takes(scene, 4, "s4", "0 8\n", "4 12\n");
  eval_stride_refused(scene, 2, "s2d", "scene0008_00/features/2.hdf: missing, which --stride 2 takes");
}

/* A scene whose training frames exceed keyframes.memory_mb: vlff-eval
 * keeps every frame --stride takes (all train fusion and the evidence, all
 * held-out ones are scored) and fits the field on as many of the training
 * frames as the budget holds, spread over the whole scene, saying so on
 * stderr and in its report (it used to thin every score's frames with a
 * larger stride). */
static void test_eval_keyframes_within_budget(void **state) {
  (void)state;
  char scene[400], train[64], test[64], p[700], eval[600], cmd[3000];
  scene_path(scene, sizeof scene, "scene0009_00");
  write_export(scene, 16, -1);
  /* 30x40x64 float16 maps and 40x30 training images: 0.15 MiB a keyframe,
   * 8 training frames 1.2 MiB */
  snprintf(p, sizeof p, "%s/features.hdf", scene);
  write_feats(p, 0, 16, 30, 40, 64, 4, NULL, 0, 0);
  write_embeddings_dim(scene, VLFF_LABELS_SCANNET20, 64);
  char cfg[600];
  snprintf(cfg, sizeof cfg, "%s/small.yaml", root);
  putf(cfg, "keyframes:\n  memory_mb: 1\n");
  vlff_test_prog(eval, sizeof eval, "node/eval/vlff-eval");
  snprintf(cmd, sizeof cmd, "%s --dataset %s -c %s --out %s/out-mem --iters 1 --threads 1 --quiet --holdout 2 "
           ">%s/mem.log 2>&1", eval, scene, cfg, root, root);
  if (system(cmd) != 0) {
    show_log("mem");
    fail_msg("vlff-eval stopped instead of choosing keyframes");
  }
  if (!log_has("mem", "the 8 training frames need 1.2 MiB as keyframes, more than keyframes.memory_mb (1): the "
                      "field fits on 6 of them spread over the whole scene (0.9 MiB); fusion and the evidence read "
                      "all 8")) {
    show_log("mem");
    fail_msg("stderr does not say how many keyframes it kept and why");
  }
  snprintf(p, sizeof p, "%s/out-mem", root);
  report_frames(p, train, test, sizeof train);
  assert_string_equal(train, "0 2 4 6 8 10 12 14\n");
  assert_string_equal(test, "1 3 5 7 9 11 13 15\n");
  char line[128];
  snprintf(cmd, sizeof cmd,
           "python3 -c 'import json,sys; s=json.load(open(sys.argv[1]))[\"source\"]; k=s[\"keyframes\"]; "
           "print(s[\"stride\"], k[\"chosen_for\"], k[\"memory_mb\"], *k[\"frames\"])' %s/out-mem/report.json",
           root);
  FILE *f = popen(cmd, "r");
  assert_non_null(f);
  assert_non_null(fgets(line, sizeof line, f));
  assert_int_equal(pclose(f), 0);
  /* the k-th of 6 is the training frame nearest the middle of its sixth */
  assert_string_equal(line, "1 keyframes.memory_mb 1 0 4 6 8 12 14\n");
  snprintf(cmd, sizeof cmd, "grep -qF 'Keyframes: the field fitted on 6 of the 8 training frames, spread over the "
                            "scene (all of them would need more than keyframes.memory_mb, 1 MiB)' %s/out-mem/report.md",
           root);
  assert_int_equal(system(cmd), 0);
}

/* A scene without its labelled mesh is refused before any frame is read,
 * naming ScanNet's file (it used to read every frame, then fail on
 * "mesh.ply: cannot open"): a broken label image, which reading the frames
 * would trip on first, is not what the error names. */
static void test_eval_names_missing_mesh(void **state) {
  (void)state;
  char dir[400], path[600], p[700], args[1500];
  sens_scene(dir, sizeof dir, path, sizeof path, "scene0012_00");
  snprintf(p, sizeof p, "%s/scene_vh_clean_2.labels.ply", dir);
  assert_int_equal(unlink(p), 0);
  snprintf(p, sizeof p, "%s/label-filt", dir);
  assert_int_equal(mkdir(p, 0755), 0);
  for (int i = 0; i < 3; i += 2) {
    snprintf(p, sizeof p, "%s/label-filt/%d.png", dir, i);
    putf(p, "not a png");
  }
  write_features(dir, 3);
  write_embeddings(dir, VLFF_LABELS_SCANNET20);
  snprintf(args, sizeof args, "--dataset %s --out %s/out-nomesh", path, root);
  assert_int_not_equal(run_eval(args, "nomesh"), 0);
  if (!log_has("nomesh", "scene0012_00/scene0012_00_vh_clean_2.labels.ply: missing") || log_has("nomesh", "mesh.ply:") ||
      log_has("nomesh", "label-filt/0.png")) {
    show_log("nomesh");
    fail_msg("the refusal does not name ScanNet's labelled mesh first");
  }
}

#define EVAL_TEST                                                                                             \
  , cmocka_unit_test(test_eval_reads_scannet), cmocka_unit_test(test_eval_strided_features),                  \
      cmocka_unit_test(test_eval_keyframes_within_budget), cmocka_unit_test(test_eval_names_missing_mesh)
#else
#define EVAL_TEST
#endif

/* A program a test started and the segments it made: stopped and removed by
 * teardown when the test failed before it got to that. */
static pid_t child;
static char replay_shm[3][64];

#ifdef VLFF_REPLAY_BUILT
/* The segments the last replay test named, removed: by the next replay test
 * before it names its own (teardown runs once, after all of them, and saw
 * only the last test's: every run left the first one's in /dev/shm). */
static void replay_shm_unlink(void) {
  for (int k = 0; k < 3; k++)
    if (replay_shm[k][0]) vlff_shm_unlink(replay_shm[k]), replay_shm[k][0] = 0;
}
/* The ring segments of the replay test named by tag, the last test's gone. */
static void replay_shm_name(const char *tag) {
  const char *what[3] = {"r", "p", "f"};
  replay_shm_unlink();
  for (int k = 0; k < 3; k++) snprintf(replay_shm[k], sizeof replay_shm[k], "/vlff-%s-%d-%s", tag, (int)getpid(), what[k]);
}
/* vlff-replay plays the raw .sens into the rings a live node reads: each
 * usable frame (the lost one passed over) arrives as the dataset reader
 * gives it, colour and depth at the colour camera's size, with the reader's
 * intrinsics, and its pose waits in the pose ring at the frame's host time. */
static void test_replay_sens(void **state) {
  (void)state;
  char dir[400], path[600], cfg[700], err[512];
  sens_scene(dir, sizeof dir, path, sizeof path, "scene0005_00");
  replay_shm_name("tscn");
  snprintf(cfg, sizeof cfg, "%s/replay.yaml", root);
  putf(cfg, "shm:\n  ring: %s\n  pose_ring: %s\n  feature_ring: %s\n  ring_slots: 4\n", replay_shm[0], replay_shm[1], replay_shm[2]);
  struct vlff_dataset ds;
  if (vlff_dataset_open(&ds, path, VLFF_DS_AUTO, err, sizeof err) < 0) fail_msg("%s", err);
  /* through sh, so that a cross-built tree's emulator goes before the program */
  char prog[700], cmd[2400];
  vlff_test_prog(prog, sizeof prog, "node/dataset/vlff-replay");
  snprintf(cmd, sizeof cmd, "exec %s -c %s --layout sens --no-features --backpressure --quiet %s", prog, cfg, path);
  char *argv[] = {"/bin/sh", "-c", cmd, NULL};
  assert_int_equal(posix_spawn(&child, "/bin/sh", NULL, NULL, argv, environ), 0);
  struct vlff_ring *fr = NULL, *pr = NULL;
  for (int k = 0; k < 500 && !(fr && pr); k++) {
    if (!fr) fr = vlff_ring_attach(replay_shm[0], VLFF_RECORD_FRAME);
    if (!pr) pr = vlff_ring_attach(replay_shm[1], VLFF_RECORD_POSE);
    if (!(fr && pr)) usleep(20000);
  }
  assert_non_null(fr);
  assert_non_null(pr);
  const int W = ds.width, H = ds.height;
  uint8_t *rgb = malloc((size_t)W * H * 3), *buf = malloc(vlff_ring_slot_size(fr));
  float *depth = malloc((size_t)W * H * sizeof *depth);
  long with_depth = 0;
  for (int i = 0; i < ds.n; i++) {
    struct vlff_ring_view v;
    ssize_t len = vlff_ring_read_copy(fr, buf, vlff_ring_slot_size(fr), &v, 10ull * 1000 * 1000 * 1000);
    if (len < 0) fail_msg("frame %d: %s", i, vlff_shm_last_message());
    assert_int_equal(vlff_frame_validate(buf, (size_t)len), 0);
    const struct vlff_frame_hdr *h = (const void *)buf;
    assert_int_equal(h->frame_id, (uint64_t)i);
    assert_int_equal((int)h->plane[VLFF_PLANE_COLOR].width, W);
    assert_int_equal((int)h->plane[VLFF_PLANE_DEPTH].width, W);
    assert_true(fabs(h->fx - ds.fx) < 1e-9 && fabs(h->cx - ds.cx) < 1e-9 && fabs(h->cy - ds.cy) < 1e-9);
    if (vlff_dataset_read_frame(&ds, i, rgb, depth, NULL, err, sizeof err) < 0) fail_msg("%s", err);
    const uint8_t *c = vlff_frame_plane(buf, VLFF_PLANE_COLOR), *d = vlff_frame_plane(buf, VLFF_PLANE_DEPTH);
    for (int y = 0; y < H; y++) {
      assert_memory_equal(c + (size_t)y * h->plane[VLFF_PLANE_COLOR].stride, rgb + (size_t)y * W * 3, (size_t)W * 3);
      const uint16_t *mm = (const void *)(d + (size_t)y * h->plane[VLFF_PLANE_DEPTH].stride);
      for (int x = 0; x < W; x++) {
        float m = depth[(size_t)y * W + x];
        if (!(isfinite(m) && m > 0)) {
          assert_int_equal(mm[x], 0);
          continue;
        }
        if (fabsf(mm[x] - m * 1000.0f) > 0.5f) fail_msg("frame %d (%d,%d): %u mm, the reader says %g m", i, x, y, mm[x], m);
        with_depth++;
      }
    }
    struct vlff_pose_rec pose;
    assert_int_equal(vlff_pose_lookup(pr, h->t_host_ns, 0, &pose), 0);
    for (int e = 0; e < 16; e++) assert_true(fabs(pose.pose[e] - ds.c2w[16 * i + e]) < 1e-9);
  }
  assert_true(fabs(ds.c2w[16 + 3] - 0.2) < 1e-6); /* the second usable frame is the .sens's third */
  assert_true(with_depth > (long)W * H / 4);       /* the plate registered into the colour camera */
  int st;
  assert_int_equal(waitpid(child, &st, 0), child);
  child = 0;
  assert_true(WIFEXITED(st) && WEXITSTATUS(st) == 0);
  assert_int_equal(vlff_ring_lost(fr), 0);
  free(rgb), free(buf), free(depth);
  vlff_ring_close(fr);
  vlff_ring_close(pr);
  vlff_dataset_close(&ds);
}

#ifdef VLFF_HAVE_HDF5
/* vlff-replay on features stored for some frames: the frames they hold are
 * played with their features, the others passed over and counted, and the
 * replay succeeds (each used to be an unreadable frame, and the exit 1). */
static void test_replay_some_features(void **state) {
  (void)state;
  char dir[400], path[600], cfg[700], p[700];
  sens_scene(dir, sizeof dir, path, sizeof path, "scene0013_00");
  snprintf(p, sizeof p, "%s/features.hdf", dir);
  const long long first[1] = {0};
  write_feats(p, 0, 1, 2, 2, 4, 4, first, 1, 0);
  replay_shm_name("tscf");
  snprintf(cfg, sizeof cfg, "%s/replay-f.yaml", root);
  putf(cfg, "shm:\n  ring: %s\n  pose_ring: %s\n  feature_ring: %s\n  ring_slots: 4\n", replay_shm[0], replay_shm[1],
       replay_shm[2]);
  char prog[700], cmd[2400];
  vlff_test_prog(prog, sizeof prog, "node/dataset/vlff-replay");
  snprintf(cmd, sizeof cmd, "%s -c %s --fps 1000 %s >%s/replay-f.log 2>&1", prog, cfg, path, root);
  if (system(cmd) != 0) {
    show_log("replay-f");
    fail_msg("vlff-replay on features of some frames failed");
  }
  if (!log_has("replay-f", "the features hold 1 of the 2 frames: the others are passed over") ||
      !log_has("replay-f", "1 frames published, 0 unreadable skipped, 1 without features passed over")) {
    show_log("replay-f");
    fail_msg("the replay does not say which frames it passed over");
  }
}
#define REPLAY_FEATURES_TEST , cmocka_unit_test(test_replay_some_features)
#else
#define REPLAY_FEATURES_TEST
#endif
#define REPLAY_TEST , cmocka_unit_test(test_replay_sens) REPLAY_FEATURES_TEST
#else
#define REPLAY_TEST
#endif

static int setup(void **state) {
  (void)state;
  snprintf(root, sizeof root, "/tmp/vlff-test-scannet-%ld-XXXXXX", (long)getpid());
  return mkdtemp(root) ? 0 : -1;
}

static int teardown(void **state) {
  (void)state;
  if (child > 0) { /* a replay waiting for a reader that failed would wait for ever */
    kill(child, SIGKILL);
    waitpid(child, NULL, 0);
    child = 0;
  }
#ifdef VLFF_REPLAY_BUILT
  replay_shm_unlink();
#endif
  nftw(root, rm_one, 16, FTW_DEPTH | FTW_PHYS);
  return 0;
}

VLFF_UNIT_MAIN(setup, teardown,
    cmocka_unit_test(test_export_layout), cmocka_unit_test(test_sens), cmocka_unit_test(test_sens_long_path),
    cmocka_unit_test(test_lost_tracking),
    cmocka_unit_test(test_required_files) FEATURES_TEST EVAL_TEST REPLAY_TEST)
