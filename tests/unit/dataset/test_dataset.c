/* Scene datasets: exact write -> read round trips, malformed inputs that
 * must fail naming the file, the ScanNet export layout, and the formats. */
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
#include <sys/stat.h>
#include <unistd.h>

#include <cmocka.h>

#ifdef VLFF_HAVE_HDF5
#include <hdf5.h>
#endif

#include "config.h"
#include "dataset.h"
#include "files.h"
#include "embeddings.h"
#include "sim.h"
#include "unit.h"

#define NF 4
/* Feature maps are HDF5 files: a build without HDF5 writes and reads
 * datasets without them (and must refuse to write them, saying why). */
#ifdef VLFF_HAVE_HDF5
#define FEATURES 1
#else
#define FEATURES 0
#endif

static int rm_one(const char *p, const struct stat *st, int flag, struct FTW *ftw) {
  (void)st, (void)flag, (void)ftw;
  return remove(p);
}

static void rm_rf(const char *dir) { nftw(dir, rm_one, 16, FTW_DEPTH | FTW_PHYS); }

struct fixture {
  char dir[256];
  struct vlff_sim *sim;
  struct vlff_sim_frame *f[NF];
  struct vlff_sim_points pts;
  float emb[VLFF_SIM_CLASSES * 16];
};

static void write_file(const char *dir, const char *name, const char *text) {
  char p[2048];
  snprintf(p, sizeof p, "%s/%s", dir, name);
  FILE *f = fopen(p, "w");
  assert_non_null(f);
  fputs(text, f);
  fclose(f);
}

static int setup(void **state) {
  struct fixture *x = calloc(1, sizeof *x);
  snprintf(x->dir, sizeof x->dir, "/tmp/vlff-test-dataset-%ld-XXXXXX", (long)getpid());
  if (!mkdtemp(x->dir)) return -1;
  struct vlff_config c;
  vlff_config_defaults(&c);
  c.sim.width = 64, c.sim.height = 48, c.field.feature_dim = 16, c.sim.seed = 11;
  char err[512];
  x->sim = vlff_sim_create(&c.sim, &c.field, err, sizeof err);
  if (!x->sim) return -1;
  for (int i = 0; i < NF; i++) {
    x->f[i] = vlff_sim_frame_new(x->sim);
    if (vlff_sim_render(x->sim, i * 3, VLFF_SIM_ALL, x->f[i], err, sizeof err) < 0) return -1;
  }
  if (vlff_sim_points(x->sim, 10, 2, 0.1, &x->pts, err, sizeof err) < 0) return -1;
  for (int k = 0; k < VLFF_SIM_CLASSES; k++) vlff_sim_text_embedding(x->sim, vlff_sim_class_name(k), x->emb + 16 * k);
  *state = x;
  return 0;
}

static int teardown(void **state) {
  struct fixture *x = *state;
  rm_rf(x->dir);
  for (int i = 0; i < NF; i++) vlff_sim_frame_free(x->f[i]);
  vlff_sim_points_free(&x->pts);
  vlff_sim_destroy(x->sim);
  free(x);
  return 0;
}

/* Write the fixture as a dataset under x->dir/<name>. */
static void write_dataset(struct fixture *x, const char *name, char *path) {
  snprintf(path, 400, "%s/%s", x->dir, name);
  char err[512] = "";
  const struct vlff_sim_frame *f0 = x->f[0];
  double lo[3], hi[3];
  vlff_sim_bounds(x->sim, lo, hi);
  if (!FEATURES) {
    assert_null(vlff_dataset_writer_open(path, NF, f0->width, f0->height, f0->fx, f0->fy, f0->cx, f0->cy, lo, hi,
                                         "sim", f0->feat_width, f0->feat_height, f0->feature_dim, err, sizeof err));
    if (!strstr(err, "HDF5")) fail_msg("error '%s' does not name HDF5", err);
  }
  struct vlff_dataset_writer *w = vlff_dataset_writer_open(path, NF, f0->width, f0->height, f0->fx, f0->fy, f0->cx,
                                                           f0->cy, lo, hi, "sim", f0->feat_width, f0->feat_height,
                                                           FEATURES ? f0->feature_dim : 0, err, sizeof err);
  if (!w) fail_msg("%s", err);
  for (int i = 0; i < NF; i++)
    if (vlff_dataset_writer_add(w, i, x->f[i]->rgb, x->f[i]->depth_mm, x->f[i]->label, x->f[i]->c2w,
                                FEATURES ? x->f[i]->features : NULL, err, sizeof err) < 0)
      fail_msg("%s", err);
  if (vlff_dataset_writer_close(w, err, sizeof err) < 0) fail_msg("%s", err);
  /* over a scene already there: its frames beyond the new one's stayed */
  assert_null(vlff_dataset_writer_open(path, NF, f0->width, f0->height, f0->fx, f0->fy, f0->cx, f0->cy, lo, hi, "sim",
                                       f0->feat_width, f0->feat_height, FEATURES ? f0->feature_dim : 0, err,
                                       sizeof err));
  if (!strstr(err, "exists and is not empty")) fail_msg("%s", err);
  char p[512];
  snprintf(p, sizeof p, "%s/points.ply", path);
  if (vlff_ply_write(p, x->pts.xyz, NULL, x->pts.label, x->pts.n, err, sizeof err) < 0) fail_msg("%s", err);
  const char *names[VLFF_SIM_CLASSES];
  for (int k = 0; k < VLFF_SIM_CLASSES; k++) names[k] = vlff_sim_class_name(k);
  snprintf(p, sizeof p, "%s/prompt_embeddings.txt", path);
  if (vlff_embeddings_save(p, 16, VLFF_SIM_CLASSES, names, x->emb, err, sizeof err) < 0) fail_msg("%s", err);
}

static void test_round_trip_exact(void **state) {
  struct fixture *x = *state;
  char path[400], err[512] = "";
  write_dataset(x, "rt", path);
  struct vlff_dataset ds;
  if (vlff_dataset_open(&ds, path, VLFF_DS_AUTO, err, sizeof err) < 0) fail_msg("%s", err);
  const struct vlff_sim_frame *f0 = x->f[0];
  assert_int_equal(ds.layout, VLFF_DS_REFERENCE);
  assert_int_equal(ds.n, NF);
  assert_int_equal(ds.width, f0->width);
  assert_int_equal(ds.height, f0->height);
  assert_true(ds.fx == f0->fx && ds.fy == f0->fy && ds.cx == f0->cx && ds.cy == f0->cy);
  assert_true(ds.has_bbox && ds.has_labels);
  assert_int_equal(ds.has_features, FEATURES);
  if (FEATURES) {
    assert_int_equal(ds.feature_dim, 16);
    assert_int_equal(ds.feat_width, f0->feat_width);
  }
  size_t n = (size_t)f0->width * f0->height, nf = (size_t)f0->feat_width * f0->feat_height * 16;
  uint8_t *rgb = malloc(n * 3), *lab = malloc(n);
  float *dep = malloc(n * sizeof(float));
  uint16_t *feat = malloc(nf * 2);
  for (int i = 0; i < NF; i++) {
    if (vlff_dataset_read_frame(&ds, i, rgb, dep, lab, err, sizeof err) < 0) fail_msg("%s", err);
    assert_memory_equal(rgb, x->f[i]->rgb, n * 3);
    assert_memory_equal(lab, x->f[i]->label, n);
    for (size_t k = 0; k < n; k++) assert_true(dep[k] == x->f[i]->depth_mm[k] * 0.001f);
    for (int k = 0; k < 16; k++) assert_true(fabs(ds.c2w[16 * i + k] - x->f[i]->c2w[k]) < 1e-12);
    if (!FEATURES) continue;
    if (vlff_dataset_read_features(&ds, i, feat, err, sizeof err) < 0) fail_msg("%s", err);
    assert_memory_equal(feat, x->f[i]->features, nf * 2);
  }
  char p[512];
  struct vlff_points pts;
  snprintf(p, sizeof p, "%s/points.ply", path);
  if (vlff_ply_read(p, &pts, err, sizeof err) < 0) fail_msg("%s", err);
  assert_int_equal(pts.n, x->pts.n);
  assert_memory_equal(pts.xyz, x->pts.xyz, pts.n * 12);
  assert_memory_equal(pts.label, x->pts.label, pts.n);
  vlff_points_free(&pts);
  /* The scene's embeddings file is the node's prompts.embeddings format:
   * ground-truth id k is record k, vectors bit-exact. */
  snprintf(p, sizeof p, "%s/prompt_embeddings.txt", path);
  struct vlff_embeddings *e = vlff_embeddings_load(p, 16, err, sizeof err);
  if (!e) fail_msg("%s", err);
  assert_int_equal(vlff_embeddings_dim(e), 16);
  assert_int_equal(vlff_embeddings_count(e), VLFF_SIM_CLASSES);
  for (int k = 0; k < VLFF_SIM_CLASSES; k++) {
    assert_string_equal(vlff_embeddings_prompt(e, k), vlff_sim_class_name(k));
    assert_memory_equal(vlff_embeddings_vector(e, k), x->emb + (size_t)k * 16, 16 * sizeof(float));
  }
  assert_string_equal(vlff_embeddings_prompt(e, 15), "shower curtain");
  assert_non_null(vlff_embeddings_lookup(e, "desk"));
  assert_null(vlff_embeddings_lookup(e, "mug"));
  vlff_embeddings_free(e);
  assert_null(vlff_embeddings_load(p, 512, err, sizeof err)); /* another D is refused */
  /* the pose files hold world-to-camera */
  snprintf(p, sizeof p, "%s/pose/00001.txt", path);
  uint8_t *buf;
  size_t len;
  assert_int_equal(vlff_read_file(p, 4096, &buf, &len, err, sizeof err), 0);
  double m[16], inv[16];
  assert_int_equal(vlff_parse_matrix((char *)buf, len, p, m, err, sizeof err), 0);
  free(buf);
  vlff_pose_invert(x->f[1]->c2w, inv);
  for (int k = 0; k < 16; k++) assert_true(fabs(m[k] - inv[k]) < 1e-12);
  free(rgb), free(lab), free(dep), free(feat);
  vlff_dataset_close(&ds);
}

static void expect_open_error(const char *path, const char *what1, const char *what2) {
  struct vlff_dataset ds;
  char err[1024] = "";
  assert_int_equal(vlff_dataset_open(&ds, path, VLFF_DS_AUTO, err, sizeof err), -1);
  print_message("  error: %s\n", err);
  if (!strstr(err, what1) || (what2 && !strstr(err, what2))) fail_msg("error '%s' lacks '%s'/'%s'", err, what1, what2 ? what2 : "");
}

/* An edit of one file of a dataset: `text` written as `file`, after which
 * opening the dataset fails naming the file and saying `what`, or with
 * `what` NULL, the file is good again. */
struct edit {
  const char *file, *text, *what;
};
#define GOOD_POSE "1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n"
#define GOOD_INTRINSICS "50 0 32 0\n0 50 24 0\n0 0 1 0\n0 0 0 1\n"

static void expect_edits(const char *path, const struct edit *e, size_t n) {
  for (size_t i = 0; i < n; i++) {
    write_file(path, e[i].file, e[i].text);
    if (e[i].what) expect_open_error(path, e[i].file, e[i].what);
  }
}

static void test_malformed(void **state) {
  struct fixture *x = *state;
  char path[400], p[512];
  write_dataset(x, "bad1", path);
  static const struct edit edits[] = {
      {"pose/00002.txt", "1 0 0 0\n0 1 0.5 0\n0 0 1 0\n0 0 0 1\n", "orthonormal"},
      {"pose/00002.txt", "1 0 0 nan\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "not finite"},
      {"pose/00002.txt", "1 0 0 0\n0 1 0 0\n0 0 1 0\n", "9"},
      {"pose/00002.txt", "-1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "reflection"},
      {"pose/00002.txt", GOOD_POSE, NULL},
      {"intrinsics.txt", "-50 0 32 0\n0 50 24 0\n0 0 1 0\n0 0 0 1\n", "positive"},
      {"intrinsics.txt", "50 0 320 0\n0 50 24 0\n0 0 1 0\n0 0 0 1\n", "outside"},
      {"intrinsics.txt", GOOD_INTRINSICS, NULL},
      {"bbox.txt", "1 1 1 0 2 2\n", "min"},
      {"bbox.txt", "0 0 0 2 2 2\n", NULL},
  };
  expect_edits(path, edits, sizeof edits / sizeof *edits);
  snprintf(p, sizeof p, "%s/depth/00003.png", path);
  assert_int_equal(remove(p), 0);
  expect_open_error(path, "depth/00003.png", "missing");
  /* an image missing in the middle: its depth map is the file without an image
   * (not the next image's depth map, which is there) */
  write_dataset(x, "bad4", path);
  snprintf(p, sizeof p, "%s/rgb/00001.png", path);
  assert_int_equal(remove(p), 0);
  expect_open_error(path, "depth/00001.png", "no matching image");
  /* a truncated image is reported when its frame is read */
  write_dataset(x, "bad2", path);
  snprintf(p, sizeof p, "%s/depth/00001.png", path);
  assert_int_equal(truncate(p, 60), 0);
  struct vlff_dataset ds;
  char err[1024] = "";
  assert_int_equal(vlff_dataset_open(&ds, path, VLFF_DS_AUTO, err, sizeof err), 0);
  float *dep = malloc(64 * 48 * sizeof(float));
  assert_int_equal(vlff_dataset_read_frame(&ds, 1, NULL, dep, NULL, err, sizeof err), -1);
  assert_non_null(strstr(err, "depth/00001.png"));
  /* an RGB image in place of a depth map */
  snprintf(p, sizeof p, "%s/depth/00002.png", path);
  assert_int_equal(vlff_png_write(p, x->f[0]->rgb, 64, 48, 3, 0, err, sizeof err), 0);
  assert_int_equal(vlff_dataset_read_frame(&ds, 2, NULL, dep, NULL, err, sizeof err), -1);
  assert_non_null(strstr(err, "16-bit"));
  free(dep);
  vlff_dataset_close(&ds);
  expect_open_error("/nonexistent-vlff-dir", "nonexistent-vlff-dir", NULL);
  if (!FEATURES) return;
  /* features with the wrong frame count */
  write_dataset(x, "bad3", path);
  snprintf(p, sizeof p, "%s/rgb/00003.png", path);
  assert_int_equal(remove(p), 0);
  snprintf(p, sizeof p, "%s/depth/00003.png", path);
  assert_int_equal(remove(p), 0);
  snprintf(p, sizeof p, "%s/pose/00003.txt", path);
  assert_int_equal(remove(p), 0);
  snprintf(p, sizeof p, "%s/gt_semantic/00003.png", path);
  assert_int_equal(remove(p), 0);
  expect_open_error(path, "features.hdf", "N=3");
}

/* Bytes of the dataset reach the error escaped (vlff/escape.h): a binary
 * intrinsics.txt (OSC title, CSI clear, invalid UTF-8) and an image whose
 * file name holds ESC and a newline must not reach a terminal raw. */
static void assert_no_raw_control(const char *err) {
  for (const unsigned char *c = (const unsigned char *)err; *c; c++)
    if (*c < 0x20 || *c == 0x7f) fail_msg("raw byte 0x%02x in error '%s'", *c, err);
}

static void test_outside_bytes_escaped(void **state) {
  struct fixture *x = *state;
  char path[400], p[512];
  write_dataset(x, "esc", path);
  struct vlff_dataset ds;
  char err[1024] = "";
  snprintf(p, sizeof p, "%s/intrinsics.txt", path);
  static const char binary[] = "\x1b]0;pwned\x07\x1b[2J\xff\xfe\x01 0 32 0\n";
  FILE *f = fopen(p, "wb");
  assert_non_null(f);
  assert_int_equal(fwrite(binary, 1, sizeof binary - 1, f), sizeof binary - 1);
  fclose(f);
  assert_int_equal(vlff_dataset_open(&ds, path, VLFF_DS_AUTO, err, sizeof err), -1);
  print_message("  error: %s\n", err);
  assert_no_raw_control(err);
  if (!strstr(err, "intrinsics.txt:1: '\\x1b]0;pwned\\x07\\x1b[2J\\xff\\xfe\\x01' is not a number"))
    fail_msg("error '%s' does not quote the token escaped", err);
  write_file(path, "intrinsics.txt", GOOD_INTRINSICS);
  /* an image named "00009<ESC>[2J<LF>x.png" without its depth and pose */
  char from[512], to[512];
  snprintf(from, sizeof from, "%s/rgb/00000.png", path);
  snprintf(to, sizeof to, "%s/rgb/00009\x1b[2J\nx.png", path);
  FILE *a = fopen(from, "rb"), *b = fopen(to, "wb");
  assert_non_null(a);
  assert_non_null(b);
  char buf[4096];
  size_t n;
  while ((n = fread(buf, 1, sizeof buf, a))) assert_int_equal(fwrite(buf, 1, n, b), n);
  fclose(a), fclose(b);
  assert_int_equal(vlff_dataset_open(&ds, path, VLFF_DS_AUTO, err, sizeof err), -1);
  print_message("  error: %s\n", err);
  assert_no_raw_control(err);
  if (!strstr(err, "00009\\x1b[2J\\x0ax"))
    fail_msg("error '%s' does not name the file escaped", err);
  assert_int_equal(remove(to), 0);
  assert_int_equal(vlff_dataset_open(&ds, path, VLFF_DS_AUTO, err, sizeof err), 0);
  vlff_dataset_close(&ds);
}

#ifdef VLFF_HAVE_HDF5
/* A features.hdf whose one dataset claims shape dims but stores nothing
 * (its chunks never written): a small file. */
static void write_claiming_hdf(const char *path, const hsize_t dims[4]) {
  H5Eset_auto2(H5E_DEFAULT, NULL, NULL);
  hid_t f = H5Fcreate(path, H5F_ACC_TRUNC, H5P_DEFAULT, H5P_DEFAULT);
  assert_true(f >= 0);
  hid_t g = H5Gcreate2(f, "features", H5P_DEFAULT, H5P_DEFAULT, H5P_DEFAULT);
  hsize_t chunk[4] = {1, 16, 16, 16};
  hid_t sp = H5Screate_simple(4, dims, NULL), pl = H5Pcreate(H5P_DATASET_CREATE);
  H5Pset_chunk(pl, 4, chunk);
  hid_t t = H5Tcopy(H5T_IEEE_F32LE);
  H5Tset_fields(t, 15, 10, 5, 0, 10);
  H5Tset_size(t, 2);
  H5Tset_ebias(t, 15);
  hid_t d = H5Dcreate2(g, "sim", t, sp, H5P_DEFAULT, pl, H5P_DEFAULT);
  assert_true(d >= 0);
  H5Dclose(d), H5Tclose(t), H5Pclose(pl), H5Sclose(sp), H5Gclose(g), H5Fclose(f);
}
#endif

/* Physically absurd values (issue 29 S5) and non-regular files: refused at
 * open, naming the file and the bound. */
static void test_physical_bounds(void **state) {
  struct fixture *x = *state;
  char path[400], p[512];
  write_dataset(x, "phys", path);
  /* Reference layout poses are world-to-camera: a camera at 1e300. */
  write_file(path, "pose/00002.txt", "1 0 0 1e300\n0 1 0 0\n0 0 1 0\n0 0 0 1\n");
  expect_open_error(path, "pose/00002.txt", "camera x = -1e+300 m outside");
  /* Without bbox.txt, only the absolute bound applies. */
  write_file(path, "pose/00002.txt", "1 0 0 0\n0 1 0 0\n0 0 1 2e4\n0 0 0 1\n");
  snprintf(p, sizeof p, "%s/bbox.txt", path);
  assert_int_equal(remove(p), 0);
  expect_open_error(path, "pose/00002.txt", "no scene box");
  static const struct edit edits[] = {
      {"pose/00002.txt", GOOD_POSE, NULL},
      {"intrinsics.txt", "1e-30 0 32 0\n0 1e-30 24 0\n0 0 1 0\n0 0 0 1\n", "fx 1e-30 outside"},
      {"intrinsics.txt", "1e30 0 32 0\n0 1e30 24 0\n0 0 1 0\n0 0 0 1\n",
       "not a physical camera for the 64x48 images: fx 1e+30 outside"},
      {"intrinsics.txt", "50 0 32 0\n0 5 24 0\n0 0 1 0\n0 0 0 1\n", "pixel aspect"},
      /* the field's cameras have no skew: one was dropped, every ray off by it */
      {"intrinsics.txt", "50 1e6 32 0\n0 50 24 0\n0 0 1 0\n0 0 0 1\n",
       "intrinsics.txt: skew 1e+06 is more than 0.1 % of fx=50; the camera model has none"},
      {"intrinsics.txt", "50 0.04 32 0\n0 50 24 0\n0 0 1 0\n0 0 0 1\n", NULL},
      {"intrinsics.txt", GOOD_INTRINSICS, NULL},
  };
  expect_edits(path, edits, sizeof edits / sizeof *edits);
  struct vlff_dataset ds;
  char err[1024] = "";
  assert_int_equal(vlff_dataset_open(&ds, path, VLFF_DS_AUTO, err, sizeof err), 0);
  vlff_dataset_close(&ds);
  /* A FIFO in place of an optional file: refused, not waited on. */
  snprintf(p, sizeof p, "%s/bbox.txt", path);
  assert_int_equal(mkfifo(p, 0600), 0);
  expect_open_error(path, "bbox.txt", "is a FIFO, expected a regular file");
  assert_int_equal(remove(p), 0);
  if (!FEATURES) return;
#ifdef VLFF_HAVE_HDF5
  snprintf(p, sizeof p, "%s/features.hdf", path);
  assert_int_equal(remove(p), 0);
  assert_int_equal(mkfifo(p, 0600), 0);
  expect_open_error(path, "features.hdf", "is a FIFO");
  assert_int_equal(remove(p), 0);
  /* A small file claiming 8 GiB per frame: refused before any buffer. */
  hsize_t huge[4] = {NF, 8192, 8192, 64};
  write_claiming_hdf(p, huge);
  struct stat st;
  assert_int_equal(stat(p, &st), 0);
  assert_true(st.st_size < 65536);
  expect_open_error(path, "features.hdf", "claims 8589934592 bytes per frame");
  /* Within the per-frame cap, but the file holds none of the data. */
  hsize_t empty[4] = {NF, 64, 64, 16};
  write_claiming_hdf(p, empty);
  expect_open_error(path, "features.hdf", "(524288 bytes) but the file stores 0 bytes");
#endif
}

static void test_scannet_layout(void **state) {
  struct fixture *x = *state;
  char path[400], p[512], err[512];
  snprintf(path, sizeof path, "%s/scannet", x->dir);
  const char *subs[] = {"", "/color", "/depth", "/pose", "/intrinsic"};
  for (int i = 0; i < 5; i++) {
    snprintf(p, sizeof p, "%s%s", path, subs[i]);
    assert_int_equal(mkdir(p, 0755), 0);
  }
  const struct vlff_sim_frame *f0 = x->f[0];
  for (int i = 0; i < NF; i++) {
    snprintf(p, sizeof p, "%s/color/%d.png", path, i);
    assert_int_equal(vlff_png_write(p, x->f[i]->rgb, 64, 48, 3, 0, err, sizeof err), 0);
    /* depth at half resolution, like ScanNet's 640x480 against 1296x968 */
    uint16_t half[32 * 24];
    for (int v = 0; v < 24; v++)
      for (int u = 0; u < 32; u++) half[v * 32 + u] = x->f[i]->depth_mm[(2 * v) * 64 + 2 * u];
    snprintf(p, sizeof p, "%s/depth/%d.png", path, i);
    assert_int_equal(vlff_png_write(p, half, 32, 24, 1, 1, err, sizeof err), 0);
    char txt[1024];
    const double *m = x->f[i]->c2w;
    if (i == 2)
      snprintf(txt, sizeof txt, "-inf -inf -inf -inf\n-inf -inf -inf -inf\n-inf -inf -inf -inf\n-inf -inf -inf -inf\n");
    else
      snprintf(txt, sizeof txt, "%.17g %.17g %.17g %.17g\n%.17g %.17g %.17g %.17g\n%.17g %.17g %.17g %.17g\n0 0 0 1\n", m[0],
               m[1], m[2], m[3], m[4], m[5], m[6], m[7], m[8], m[9], m[10], m[11]);
    snprintf(p, sizeof p, "pose/%d.txt", i);
    write_file(path, p, txt);
  }
  char k[256];
  snprintf(k, sizeof k, "%.17g 0 %.17g 0\n0 %.17g %.17g 0\n0 0 1 0\n0 0 0 1\n", f0->fx, f0->cx, f0->fy, f0->cy);
  write_file(path, "intrinsic/intrinsic_color.txt", k);
  struct vlff_dataset ds;
  if (vlff_dataset_open(&ds, path, VLFF_DS_AUTO, err, sizeof err) < 0) fail_msg("%s", err);
  assert_int_equal(ds.layout, VLFF_DS_SCANNET);
  assert_int_equal(ds.n, NF - 1);
  assert_int_equal(ds.skipped, 1);
  assert_string_equal(ds.stem[2], "3");
  for (int q = 0; q < 16; q++) assert_true(ds.c2w[16 * 2 + q] == x->f[3]->c2w[q]);
  float dep[64 * 48];
  assert_int_equal(vlff_dataset_read_frame(&ds, 0, NULL, dep, NULL, err, sizeof err), 0);
  assert_true(dep[10 * 64 + 20] == x->f[0]->depth_mm[10 * 64 + 20] * 0.001f);
  vlff_dataset_close(&ds);
  /* Two stems of one frame number (3 and 03) were two frames, the pose
   * jumping between them; a 20-digit stem was listed but no number. */
  char a[600], b[600];
  snprintf(a, sizeof a, "%s/color/3.png", path);
  snprintf(b, sizeof b, "%s/color/03.png", path);
  assert_int_equal(link(a, b), 0);
  assert_int_equal(vlff_dataset_open(&ds, path, VLFF_DS_AUTO, err, sizeof err), -1);
  if (!strstr(err, "color: '03.png' and '3.png' are both frame 3")) fail_msg("%s", err);
  snprintf(a, sizeof a, "%s/color/99999999999999999999.png", path);
  assert_int_equal(rename(b, a), 0);
  assert_int_equal(vlff_dataset_open(&ds, path, VLFF_DS_AUTO, err, sizeof err), -1);
  if (!strstr(err, "'99999999999999999999.png': a frame number of more than 18 digits")) fail_msg("%s", err);
  assert_int_equal(unlink(a), 0);
}

static void test_ply_formats(void **state) {
  (void)state;
  struct vlff_points p;
  char err[512];
  const char ascii[] = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
                       "property ushort label\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n"
                       "0 1 2 3\n4 5 6 300\n";
  assert_int_equal(vlff_ply_parse((const uint8_t *)ascii, strlen(ascii), "a.ply", &p, err, sizeof err), 0);
  assert_int_equal(p.n, 2);
  assert_true(p.xyz[5] == 6.0f && p.label[0] == 3 && p.label[1] == 255);
  vlff_points_free(&p);
  const char nolabel[] = "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\n";
  assert_int_equal(vlff_ply_parse((const uint8_t *)nolabel, strlen(nolabel), "b.ply", &p, err, sizeof err), -1);
  assert_non_null(strstr(err, "label"));
  const char trunc[] = "ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\nproperty float y\n"
                       "property float z\nproperty uchar label\nend_header\n0123456789abc";
  assert_int_equal(vlff_ply_parse((const uint8_t *)trunc, strlen(trunc), "c.ply", &p, err, sizeof err), -1);
  assert_non_null(strstr(err, "truncated"));
  /* What the header does not declare, and values its types cannot hold,
   * are refused: a count of 10 over a file of 4746 vertices scored 10
   * points; a count of 0 scored nothing, as 0.0; a uchar label of 300 or -5
   * was taken as unlabelled. */
  static const struct {
    const char *ply, *says;
  } bad[] = {
      {"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
       "property float z\nproperty uchar label\nend_header\n0123456789abcdefghijklmnopqrstuvwxyz",
       "d.ply: 23 bytes after the 1 vertices the header declares"},
      {"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
       "property uchar label\nend_header\n0 0 0 1\n1 1 1 2\n",
       "d.ply: data after the 1 vertices the header declares"},
      {"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
       "property uchar label\nend_header\n0 0 0 300\n",
       "d.ply: vertex 0 property 3: '300' is not a uchar (0..255)"},
      {"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
       "property uchar label\nend_header\n0 0 0 -5\n",
       "is not a uchar"},
      {"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
       "property int label\nend_header\n0 0 0 2.5\n",
       "'2.5' is not a int"},
      {"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\n"
       "property uchar label\nend_header\n",
       "d.ply: the vertex element holds no vertices"},
  };
  for (size_t k = 0; k < sizeof bad / sizeof *bad; k++) {
    assert_int_equal(vlff_ply_parse((const uint8_t *)bad[k].ply, strlen(bad[k].ply), "d.ply", &p, err, sizeof err), -1);
    if (!strstr(err, bad[k].says)) fail_msg("case %zu: %s", k, err);
  }
  /* an element after the vertices (ScanNet's faces) owns the bytes after them */
  const char faces[] = "ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                       "property float z\nproperty uchar label\nelement face 1\nproperty list uchar int vertex_indices\n"
                       "end_header\n0123456789abc\x03\0\0\0\0\0\0\0\0\0\0\0\0";
  assert_int_equal(vlff_ply_parse((const uint8_t *)faces, sizeof faces - 1, "e.ply", &p, err, sizeof err), 0);
  assert_int_equal(p.n, 1);
  vlff_points_free(&p);
}

VLFF_UNIT_MAIN(setup, teardown,
    cmocka_unit_test(test_round_trip_exact), cmocka_unit_test(test_malformed),
    cmocka_unit_test(test_scannet_layout), cmocka_unit_test(test_physical_bounds),
    cmocka_unit_test(test_ply_formats), cmocka_unit_test(test_outside_bytes_escaped))
