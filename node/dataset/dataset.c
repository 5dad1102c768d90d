/*
 * Scene directories: listing and validating the reference and ScanNet
 * layouts, reading frames and features, and writing the reference layout.
 * See dataset.h for the layouts and the conventions they use.
 */
#include "dataset.h"

#include <dirent.h>
#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#ifdef VLFF_HAVE_HDF5
#include <hdf5.h>
#endif

#include "bounds.h"
#include "dataset_internal.h"
#include "vlff/escape.h"
#include "files.h"
#include "mem.h"

#define seterr vlff_errf
#define PATHMAX 4352

static int is_dir(const char *p) {
  struct stat st;
  return stat(p, &st) == 0 && S_ISDIR(st.st_mode);
}

static int is_file(const char *p) {
  struct stat st;
  return stat(p, &st) == 0 && S_ISREG(st.st_mode);
}

/* a/b into out[PATHMAX]: a is at most VLFF_DS_PATH_MAX bytes (open refuses
 * longer), b a name of the layout with a stem of under VLFF_DS_NAME, so it
 * always fits; the clamp only keeps a broken caller inside out. */
_Static_assert(VLFF_DS_PATH_MAX + 1 + VLFF_DS_NAME + 64 < PATHMAX, "dataset paths fit PATHMAX");
static void join(char *out, const char *a, const char *b) {
  size_t la = strnlen(a, PATHMAX - 2), lb = strnlen(b, PATHMAX - 2 - la);
  memcpy(out, a, la);
  out[la] = '/';
  memcpy(out + la + 1, b, lb);
  out[la + 1 + lb] = 0;
}

/* An optional file dir/name, its path left in p[PATHMAX]: 1 when present
 * (and regular), 0 when absent, -1 with err when something else sits at its
 * name (a FIFO would block a reader, a directory is a mistake worth naming). */
static int optional_file(char *p, const char *dir, const char *name, char *err, size_t errlen) {
  struct stat st;
  join(p, dir, name);
  if (stat(p, &st) < 0) return 0;
  return vlff_check_regular(p, err, errlen) < 0 ? -1 : 1;
}

/* ---- listing ------------------------------------------------------------ */

struct stems {
  char (*s)[VLFF_DS_NAME];
  int n, cap;
  char ext[8];
};

static int all_digits(const char *s) {
  if (!*s) return 0;
  for (; *s; s++)
    if (*s < '0' || *s > '9') return 0;
  return 1;
}

static int numeric_sort;
static int stem_cmp(const void *a, const void *b) {
  const char *x = a, *y = b;
  if (numeric_sort) {
    long long u = atoll(x), v = atoll(y);
    if (u != v) return u < v ? -1 : 1;
  }
  return strcmp(x, y);
}

/* Stems of the files in dir with one of the extensions (".png,.jpg"). */
static int list_stems(const char *dir, const char *exts, struct stems *st, char *err, size_t errlen) {
  memset(st, 0, sizeof *st);
  DIR *d = opendir(dir);
  if (!d) {
    seterr(err, errlen, "%s: cannot open directory: %s", VLFF_Q(dir), strerror(errno));
    return -1;
  }
  struct dirent *e;
  while ((e = readdir(d))) {
    const char *dot = strrchr(e->d_name, '.');
    if (!dot || dot == e->d_name) continue;
    char ext[8];
    size_t el = strlen(dot);
    if (el >= sizeof ext) continue;
    memcpy(ext, dot, el + 1);
    char want[64];
    snprintf(want, sizeof want, ",%s,", exts);
    char probe[16];
    snprintf(probe, sizeof probe, ",%s,", ext);
    if (!strstr(want, probe)) continue;
    size_t sl = (size_t)(dot - e->d_name);
    if (sl >= VLFF_DS_NAME) {
      closedir(d);
      seterr(err, errlen, "%s/%s: file name too long", VLFF_Q(dir), VLFF_Q(e->d_name));
      free(st->s);
      return -1;
    }
    if (st->ext[0] && strcmp(st->ext, ext)) {
      closedir(d);
      seterr(err, errlen, "%s: mixes %s and %s files", VLFF_Q(dir), st->ext, ext);
      free(st->s);
      return -1;
    }
    snprintf(st->ext, sizeof st->ext, "%s", ext);
    if (st->n == st->cap) {
      int nc = st->cap ? 2 * st->cap : 256;
      void *p = realloc(st->s, (size_t)nc * sizeof *st->s);
      if (!p) {
        closedir(d);
        free(st->s);
        seterr(err, errlen, "%s: out of memory", VLFF_Q(dir));
        return -1;
      }
      st->s = p, st->cap = nc;
    }
    memcpy(st->s[st->n], e->d_name, sl);
    st->s[st->n][sl] = 0;
    st->n++;
  }
  closedir(d);
  numeric_sort = 1;
  for (int i = 0; i < st->n; i++)
    if (!all_digits(st->s[i])) numeric_sort = 0;
  /* A frame's number is its stem when every stem is an integer: one past
   * 18 digits does not fit the number (it was listed, and --stride took
   * it as another), and two stems of one number (3 and 03) would be one
   * frame twice, its pose jumping between them. */
  for (int i = 0; numeric_sort && i < st->n; i++)
    if (strlen(st->s[i]) > 18) {
      seterr(err, errlen, "%s: '%s%s': a frame number of more than 18 digits", VLFF_Q(dir), VLFF_Q(st->s[i]), st->ext);
      free(st->s);
      return -1;
    }
  if (st->n) qsort(st->s, (size_t)st->n, sizeof *st->s, stem_cmp);
  for (int i = 1; numeric_sort && i < st->n; i++)
    if (atoll(st->s[i]) == atoll(st->s[i - 1])) {
      seterr(err, errlen, "%s: '%s%s' and '%s%s' are both frame %lld", VLFF_Q(dir), VLFF_Q(st->s[i - 1]), st->ext,
             VLFF_Q(st->s[i]), st->ext, atoll(st->s[i]));
      free(st->s);
      return -1;
    }
  return 0;
}

static int read_text(const char *path, char **buf, size_t *len, char *err, size_t errlen) {
  uint8_t *b;
  if (vlff_read_file(path, 1 << 20, &b, len, err, errlen) < 0) return -1;
  *buf = (char *)b;
  return 0;
}

/* ---- HDF5 --------------------------------------------------------------- */

#ifdef VLFF_HAVE_HDF5
/* IEEE binary16 as HDF5 describes it (the layout numpy/h5py write). */
static hid_t h5_half(void) {
  hid_t t = H5Tcopy(H5T_IEEE_F32LE);
  H5Tset_fields(t, 15, 10, 5, 0, 10);
  H5Tset_size(t, 2);
  H5Tset_ebias(t, 15);
  return t;
}

struct h5find {
  char name[VLFF_DS_NAME], other[VLFF_DS_NAME]; /* the first dataset, and a second */
  int found;
};

/* The group's datasets in name order: the first's name, and how many
 * (a second's name kept for messages). */
static herr_t h5_first_dataset(hid_t g, const char *name, const H5L_info_t *info, void *op) {
  (void)info;
  struct h5find *f = op;
  H5O_info_t oi;
  if (H5Oget_info_by_name(g, name, &oi, H5P_DEFAULT) < 0) return 0;
  if (oi.type != H5O_TYPE_DATASET || strlen(name) >= VLFF_DS_NAME) return 0;
  snprintf(f->found ? f->other : f->name, sizeof f->name, "%s", name);
  f->found++;
  return 0;
}

/* An open feature file's dataset features/<name> as [rows][h][w][c]. */
struct h5feat {
  hid_t f, d;
  hsize_t dims[4];
  char name[VLFF_DS_NAME];
};

static void h5feat_close(struct h5feat *h) {
  if (h->d >= 0) H5Dclose(h->d);
  if (h->f >= 0) H5Fclose(h->f);
  h->d = h->f = -1;
}

/* Open path's first dataset in group "features": [N,H,W,C] floating point
 * (or, for one frame's own file, [1,H,W,C] or [H,W,C]), with sane sizes, a
 * frame no larger than VLFF_DS_MAX_FEATURE_FRAME_BYTES, and the data the
 * file really stores accounting for the shape: a header may claim any
 * shape, and the reader allocates a frame of it (deflate cannot shrink
 * data below about 1/1032 of its size; unfiltered data is stored whole). */
static int h5feat_open(struct h5feat *h, const char *path, int one_frame, char *err, size_t errlen) {
  h->f = h->d = -1;
  struct stat fst;
  if (vlff_check_regular(path, err, errlen) < 0) return -1;
  if (stat(path, &fst) < 0) {
    seterr(err, errlen, "%s: cannot stat: %s", VLFF_Q(path), strerror(errno));
    return -1;
  }
  H5Eset_auto2(H5E_DEFAULT, NULL, NULL);
  h->f = H5Fopen(path, H5F_ACC_RDONLY, H5P_DEFAULT);
  if (h->f < 0) {
    seterr(err, errlen, "%s: not a readable HDF5 file", VLFF_Q(path));
    return -1;
  }
  hid_t g = -1, sp = -1, ty = -1;
  g = H5Gopen2(h->f, "features", H5P_DEFAULT);
  if (g < 0) {
    seterr(err, errlen, "%s: no group 'features'", VLFF_Q(path));
    goto fail;
  }
  struct h5find fd = {.found = 0};
  H5Literate(g, H5_INDEX_NAME, H5_ITER_INC, NULL, h5_first_dataset, &fd);
  if (!fd.found) {
    seterr(err, errlen, "%s: group 'features' holds no dataset", VLFF_Q(path));
    goto fail;
  }
  /* A frame's own file holds its one map: with two, which is the frame's
   * is a guess (the first by name was taken, silently). A scene's
   * features.hdf keeps its first, as the reference's readers do. */
  if (one_frame && fd.found > 1) {
    seterr(err, errlen, "%s: group 'features' holds %d datasets ('%s', '%s'...), a frame's file one map",
           VLFF_Q(path), fd.found, VLFF_Q(fd.name), VLFF_Q(fd.other));
    goto fail;
  }
  snprintf(h->name, sizeof h->name, "%s", fd.name);
  h->d = H5Dopen2(g, fd.name, H5P_DEFAULT);
  sp = h->d >= 0 ? H5Dget_space(h->d) : -1;
  ty = h->d >= 0 ? H5Dget_type(h->d) : -1;
  if (h->d < 0 || sp < 0 || ty < 0) {
    seterr(err, errlen, "%s: features/%s cannot be opened", VLFF_Q(path), VLFF_Q(fd.name));
    goto fail;
  }
  int rank = H5Sget_simple_extent_ndims(sp);
  hsize_t dims[4] = {1, 0, 0, 0};
  if (rank == 4 || (one_frame && rank == 3)) {
    if (H5Sget_simple_extent_dims(sp, dims + 4 - rank, NULL) != rank) rank = -1;
  }
  if (rank != 4 && !(one_frame && rank == 3)) {
    seterr(err, errlen, "%s: features/%s must be %s", VLFF_Q(path), VLFF_Q(fd.name),
           one_frame ? "[1,H,W,C] or [H,W,C] (one frame)" : "4-D [N,H,W,C]");
    goto fail;
  }
  if (H5Tget_class(ty) != H5T_FLOAT) {
    seterr(err, errlen, "%s: features/%s is not floating point", VLFF_Q(path), VLFF_Q(fd.name));
    goto fail;
  }
  if ((one_frame && dims[0] != 1) || dims[1] < 1 || dims[2] < 1 || dims[3] < 1 || dims[1] > 8192 ||
      dims[2] > 8192 || dims[3] > 8192) {
    seterr(err, errlen, "%s: features/%s has shape [%llu,%llu,%llu,%llu]; expected %s and H, W, C in 1..8192",
           VLFF_Q(path), VLFF_Q(fd.name), (unsigned long long)dims[0], (unsigned long long)dims[1],
           (unsigned long long)dims[2], (unsigned long long)dims[3], one_frame ? "one frame" : "[N,H,W,C]");
    goto fail;
  }
  unsigned long long frame_bytes = (unsigned long long)dims[1] * dims[2] * dims[3] * sizeof(uint16_t);
  if (frame_bytes > VLFF_DS_MAX_FEATURE_FRAME_BYTES) {
    seterr(err, errlen, "%s: features/%s claims %llu bytes per frame ([%llu,%llu,%llu] float16), more than the %llu allowed",
           VLFF_Q(path), VLFF_Q(fd.name), frame_bytes, (unsigned long long)dims[1], (unsigned long long)dims[2],
           (unsigned long long)dims[3], (unsigned long long)VLFF_DS_MAX_FEATURE_FRAME_BYTES);
    goto fail;
  }
  {
    unsigned long long raw = frame_bytes * dims[0], stored = (unsigned long long)H5Dget_storage_size(h->d);
    hid_t pl = H5Dget_create_plist(h->d);
    int nfilters = pl >= 0 ? H5Pget_nfilters(pl) : -1;
    if (pl >= 0) H5Pclose(pl);
    unsigned long long need = nfilters == 0 ? raw : raw / 1032;
    if (nfilters < 0 || stored < need || (unsigned long long)fst.st_size < need) {
      seterr(err, errlen, "%s: features/%s claims shape [%llu,%llu,%llu,%llu] (%llu bytes) but the file stores %llu bytes of it",
             VLFF_Q(path), VLFF_Q(fd.name), (unsigned long long)dims[0], (unsigned long long)dims[1],
             (unsigned long long)dims[2], (unsigned long long)dims[3], raw, stored);
      goto fail;
    }
  }
  memcpy(h->dims, dims, sizeof dims);
  H5Tclose(ty), H5Sclose(sp), H5Gclose(g);
  return 0;
fail:
  if (ty >= 0) H5Tclose(ty);
  if (sp >= 0) H5Sclose(sp);
  if (g >= 0) H5Gclose(g);
  h5feat_close(h);
  return -1;
}

/* features.hdf's "frames": the frame number of each of its rows, strictly
 * increasing and within the scene's; each usable frame gets the row that
 * names it (rows naming a lost frame, or one the scene does not list, are
 * passed over). */
static int features_frame_numbers(struct vlff_dataset *ds, const struct h5feat *h, const char *path, char *err,
                                  size_t errlen) {
  int rc = -1;
  long long *num = NULL;
  hid_t d = H5Dopen2(h->f, "frames", H5P_DEFAULT);
  hid_t sp = d >= 0 ? H5Dget_space(d) : -1, ty = d >= 0 ? H5Dget_type(d) : -1;
  hsize_t n = 0;
  if (d < 0 || sp < 0 || ty < 0 || H5Tget_class(ty) != H5T_INTEGER || H5Sget_simple_extent_ndims(sp) != 1 ||
      H5Sget_simple_extent_dims(sp, &n, NULL) != 1) {
    seterr(err, errlen, "%s: 'frames' must be a 1-D integer dataset (row r's frame number)", VLFF_Q(path));
    goto out;
  }
  if (n != h->dims[0]) {
    seterr(err, errlen, "%s: 'frames' names %llu frames but features/%s holds %llu", VLFF_Q(path),
           (unsigned long long)n, VLFF_Q(h->name), (unsigned long long)h->dims[0]);
    goto out;
  }
  if (n > (hsize_t)ds->last_number + 1) { /* strictly increasing within 0..last cannot hold more */
    seterr(err, errlen, "%s: 'frames' names %llu frames; the scene's run 0..%ld", VLFF_Q(path),
           (unsigned long long)n, ds->last_number);
    goto out;
  }
  num = malloc((size_t)n * sizeof *num + 1);
  if (!num || H5Dread(d, H5T_NATIVE_LLONG, H5S_ALL, H5S_ALL, H5P_DEFAULT, num) < 0) {
    seterr(err, errlen, "%s: 'frames' cannot be read", VLFF_Q(path));
    goto out;
  }
  for (hsize_t r = 0; r < n; r++) {
    if (num[r] < 0 || num[r] > ds->last_number) {
      seterr(err, errlen, "%s: frames[%llu] = %lld: the scene's frames run 0..%ld", VLFF_Q(path),
             (unsigned long long)r, num[r], ds->last_number);
      goto out;
    }
    if (r > 0 && num[r] <= num[r - 1]) {
      seterr(err, errlen, "%s: frames[%llu] = %lld after frame %lld: frame numbers must increase", VLFF_Q(path),
             (unsigned long long)r, num[r], num[r - 1]);
      goto out;
    }
  }
  hsize_t r = 0;
  for (int i = 0; i < ds->n; i++) {
    while (r < n && num[r] < ds->number[i]) r++;
    ds->feat_row[i] = r < n && num[r] == ds->number[i] ? (int)r : -1;
    ds->feat_frames += ds->feat_row[i] >= 0;
  }
  if (ds->feat_frames == 0) {
    seterr(err, errlen, "%s: 'frames' names no usable frame of the scene", VLFF_Q(path));
    goto out;
  }
  rc = 0;
out:
  free(num);
  if (ty >= 0) H5Tclose(ty);
  if (sp >= 0) H5Sclose(sp);
  if (d >= 0) H5Dclose(d);
  return rc;
}

/* features.hdf: a map per usable frame, one per frame the scene lists (a
 * feature extractor run over every exported image includes ScanNet's
 * lost-tracking frames, whose rows are then passed over), or the frames its
 * "frames" dataset names. */
static int features_probe(struct vlff_dataset *ds, const char *path, char *err, size_t errlen) {
  struct h5feat h;
  if (h5feat_open(&h, path, 0, err, errlen) < 0) return -1;
  int rc = -1;
  if (H5Lexists(h.f, "frames", H5P_DEFAULT) > 0) {
    if (features_frame_numbers(ds, &h, path, err, errlen) < 0) goto out;
  } else {
    int per_listed = ds->skipped > 0 && h.dims[0] == (hsize_t)ds->n_listed;
    if (h.dims[0] != (hsize_t)ds->n && !per_listed) {
      char also[96] = "";
      if (ds->skipped > 0)
        snprintf(also, sizeof also, " (or %d, every frame listed, %d of them skipped for lost tracking)",
                 ds->n_listed, ds->skipped);
      seterr(err, errlen, "%s: features/%s holds %llu frames; expected N=%d frames%s, or a 'frames' dataset "
                          "naming the frames it holds",
             VLFF_Q(path), VLFF_Q(h.name), (unsigned long long)h.dims[0], ds->n, also);
      goto out;
    }
    for (int i = 0; i < ds->n; i++) ds->feat_row[i] = per_listed ? ds->listed[i] : i;
    ds->feat_frames = ds->n;
  }
  snprintf(ds->feat_name, sizeof ds->feat_name, "%s", h.name);
  ds->feat_height = (int)h.dims[1], ds->feat_width = (int)h.dims[2], ds->feature_dim = (int)h.dims[3];
  ds->has_features = 1;
  rc = 0;
out:
  h5feat_close(&h);
  return rc;
}

/* features/<stem>.hdf, one file per frame: every file must name a frame of
 * the scene (a lost one is passed over); the first sets the shape, which
 * every other file must have when it is read. */
static int features_dir_probe(struct vlff_dataset *ds, const char *dir, char *err, size_t errlen) {
  struct stems st;
  if (list_stems(dir, ".hdf", &st, err, errlen) < 0) return -1;
  int rc = -1, first = -1, j = 0;
  if (st.n == 0) {
    seterr(err, errlen, "%s: no .hdf files (one per frame, named by its stem)", VLFF_Q(dir));
    goto out;
  }
  for (int k = 0; k < st.n; k++) {
    int hit = -1;
    for (int m = 0; m < ds->n && hit < 0; m++, j = (j + 1) % ds->n) /* both in the scene's order: j follows */
      if (!strcmp(ds->stem[j], st.s[k])) hit = j;
    if (hit < 0) {
      char *end;
      errno = 0;
      long v = strtol(st.s[k], &end, 10);
      if (ds->skipped > 0 && all_digits(st.s[k]) && !errno && v <= ds->last_number) continue; /* a lost frame */
      seterr(err, errlen, "%s/%s.hdf: the scene has no frame %s (a frame's file is named by its stem, as its "
                          "colour image is)", VLFF_Q(dir), VLFF_Q(st.s[k]), VLFF_Q(st.s[k]));
      goto out;
    }
    ds->feat_row[hit] = 0;
    if (first < 0 || hit < first) first = hit;
  }
  if (first < 0) {
    seterr(err, errlen, "%s: no file names a usable frame of the scene", VLFF_Q(dir));
    goto out;
  }
  char p[PATHMAX], name[VLFF_DS_NAME + 8];
  snprintf(name, sizeof name, "%s.hdf", ds->stem[first]);
  join(p, dir, name);
  struct h5feat h;
  if (h5feat_open(&h, p, 1, err, errlen) < 0) goto out;
  snprintf(ds->feat_name, sizeof ds->feat_name, "%s", h.name);
  ds->feat_height = (int)h.dims[1], ds->feat_width = (int)h.dims[2], ds->feature_dim = (int)h.dims[3];
  h5feat_close(&h);
  for (int i = 0; i < ds->n; i++) ds->feat_frames += ds->feat_row[i] >= 0;
  ds->feat_files = 1;
  ds->has_features = 1;
  rc = 0;
out:
  free(st.s);
  return rc;
}
#endif

/* ---- open --------------------------------------------------------------- */

void vlff_dataset_close(struct vlff_dataset *ds) {
  if (!ds) return;
  VLFF_FREE_ALL(ds->c2w, ds->stem, ds->listed, ds->label_map, ds->number, ds->feat_row);
  vlff_sens_close(ds->sens);
  memset(ds, 0, sizeof *ds);
}

static int check_intrinsics(struct vlff_dataset *ds, const double K[16], const char *path, char *err,
                            size_t errlen) {
  ds->fx = K[0], ds->fy = K[5], ds->cx = K[2], ds->cy = K[6];
  if (!(ds->fx > 0) || !(ds->fy > 0)) {
    seterr(err, errlen, "%s: focal lengths fx=%g fy=%g must be positive", VLFF_Q(path), ds->fx, ds->fy);
    return -1;
  }
  if (!(ds->cx > 0 && ds->cx < ds->width) || !(ds->cy > 0 && ds->cy < ds->height)) {
    seterr(err, errlen, "%s: principal point (%g, %g) lies outside the %dx%d image", VLFF_Q(path), ds->cx, ds->cy,
           ds->width, ds->height);
    return -1;
  }
  if (fabs(K[8]) > 1e-9 || fabs(K[9]) > 1e-9 || fabs(K[10] - 1) > 1e-9 || fabs(K[4]) > 1e-9) {
    seterr(err, errlen, "%s: not a camera matrix (expected [fx s cx; 0 fy cy; 0 0 1])", VLFF_Q(path));
    return -1;
  }
  char why[200];
  if (vlff_skew_plausible(ds->fx, K[1], why, sizeof why)) {
    seterr(err, errlen, "%s: %s", VLFF_Q(path), why);
    return -1;
  }
  if (vlff_intrinsics_plausible(ds->width, ds->height, ds->fx, ds->fy, ds->cx, ds->cy, why, sizeof why)) {
    seterr(err, errlen, "%s: not a physical camera for the %dx%d images: %s", VLFF_Q(path), ds->width, ds->height, why);
    return -1;
  }
  return 0;
}

/* Refuse a path longer than VLFF_DS_PATH_MAX, its length and its start
 * named (the whole would not fit the message). */
static int path_too_long(const char *what, const char *path, char *err, size_t errlen) {
  size_t l = strlen(path);
  if (l <= VLFF_DS_PATH_MAX) return 0;
  seterr(err, errlen, "%s path of %zu bytes is longer than the %d a dataset path may have: '%s...'", what, l,
         VLFF_DS_PATH_MAX, VLFF_QMAX(path, 120));
  return -1;
}

int vlff_dataset_open(struct vlff_dataset *ds, const char *dir, int layout, char *err, size_t errlen) {
  struct vlff_dataset_options o = {.layout = layout, .label_set = VLFF_LABELS_SCANNET20};
  return vlff_dataset_open_opts(ds, dir, &o, err, errlen);
}

/* The .sens file a path names: the path itself, or the one *.sens in a
 * directory; 0 when there is none. */
static int find_sens(const char *dir, char *out, char *err, size_t errlen) {
  size_t l = strlen(dir);
  if (is_file(dir) && l > 5 && !strcmp(dir + l - 5, ".sens")) {
    snprintf(out, PATHMAX, "%s", dir);
    return 1;
  }
  struct stems st;
  if (!is_dir(dir) || list_stems(dir, ".sens", &st, err, errlen) < 0) return 0;
  int n = st.n;
  if (n == 1) {
    char name[VLFF_DS_NAME + 8];
    snprintf(name, sizeof name, "%s.sens", st.s[0]);
    join(out, dir, name);
  }
  free(st.s);
  if (n > 1) {
    seterr(err, errlen, "%s: %d .sens files; name the one to read", VLFF_Q(dir), n);
    return -1;
  }
  return n;
}

/* ScanNet export with a depth camera of its own: intrinsic_depth.txt. */
static int scannet_export_cameras(struct vlff_dataset *ds, const char *dir, char *err, size_t errlen) {
  char p[PATHMAX];
  /* absent: the depth is the colour camera's; a FIFO or a directory there
   * is refused, not taken for absent (optional_file) */
  int have = optional_file(p, dir, "intrinsic/intrinsic_depth.txt", err, errlen);
  if (have <= 0) return have;
  const char *names[4] = {"intrinsic/intrinsic_color.txt", "intrinsic/intrinsic_depth.txt",
                          "intrinsic/extrinsic_color.txt", "intrinsic/extrinsic_depth.txt"};
  double m[4][16];
  for (int k = 0; k < 4; k++) {
    join(p, dir, names[k]);
    if (k >= 2 && (have = optional_file(p, dir, names[k], err, errlen)) <= 0) {
      if (have < 0) return -1;
      for (int e = 0; e < 16; e++) m[k][e] = e % 5 == 0; /* extrinsics absent: the cameras coincide */
      continue;
    }
    char *buf;
    size_t len;
    if (read_text(p, &buf, &len, err, errlen) < 0) return -1;
    int rc = vlff_parse_matrix(buf, len, p, m[k], err, errlen);
    free(buf);
    if (rc < 0) return -1;
  }
  char name[VLFF_DS_NAME + 16];
  snprintf(name, sizeof name, "depth/%s.png", ds->stem[0]);
  join(p, dir, name);
  struct vlff_image im;
  if (vlff_image_read(p, &im, err, errlen) < 0) return -1;
  int dw = im.width, dh = im.height;
  vlff_image_free(&im);
  join(p, dir, "intrinsic");
  return vlff_scannet_geometry(ds, m[0], ds->width, ds->height, m[1], dw, dh, m[2], m[3], p, err, errlen);
}

/* Ground-truth label images: gt_semantic/ (class ids), or ScanNet's
 * label-filt/ (label ids, mapped through the TSV, which is found and read
 * here, before any frame is listed). */
static int label_table(struct vlff_dataset *ds, const char *dir, const struct vlff_dataset_options *o, char *err,
                       size_t errlen) {
  char p[PATHMAX], q[PATHMAX];
  snprintf(ds->label_dir, sizeof ds->label_dir, "gt_semantic");
  join(p, dir, "gt_semantic");
  if (is_dir(p)) return 0;
  join(p, dir, "label-filt");
  if (ds->layout == VLFF_DS_REFERENCE || !is_dir(p)) return 0;
  snprintf(ds->label_dir, sizeof ds->label_dir, "label-filt");
  char tsv[PATHMAX] = "";
  if (o->label_tsv) snprintf(tsv, sizeof tsv, "%s", o->label_tsv);
  const char *up[3] = {"scannetv2-labels.combined.tsv", "../scannetv2-labels.combined.tsv",
                       "../../scannetv2-labels.combined.tsv"};
  for (int k = 0; k < 3 && !tsv[0]; k++) {
    int r = optional_file(q, dir, up[k], err, errlen); /* a FIFO or directory there is named, not passed over */
    if (r < 0) return -1;
    if (r > 0) snprintf(tsv, sizeof tsv, "%s", q);
  }
  if (!tsv[0]) {
    seterr(err, errlen, "%s: label-filt/ holds ScanNet label ids, but scannetv2-labels.combined.tsv is neither "
                        "given nor in the scene directory or its two parents", VLFF_Q(dir));
    return -1;
  }
  return vlff_scannet_labels_load(ds, tsv, o->label_set, err, errlen);
}

/* The label directory, when label_table found one, must label every frame. */
static int open_labels(struct vlff_dataset *ds, const char *dir, char *err, size_t errlen) {
  char p[PATHMAX], q[PATHMAX];
  join(p, dir, ds->label_dir);
  if (!is_dir(p) || (ds->layout == VLFF_DS_REFERENCE && strcmp(ds->label_dir, "gt_semantic"))) return 0;
  for (int i = 0; i < ds->n; i++) {
    char name[VLFF_DS_NAME + 24];
    snprintf(name, sizeof name, "%s/%s.png", ds->label_dir, ds->stem[i]);
    join(q, dir, name);
    if (!is_file(q)) {
      seterr(err, errlen, "%s: missing (%s/ must label every frame)", VLFF_Q(q), ds->label_dir);
      return -1;
    }
  }
  ds->has_labels = 1;
  return 0;
}

/* The layout a scene path is read as: the one asked for, or (auto) a .sens
 * file where neither rgb/ nor color/ is found, else rgb/ (reference) or
 * color/ (ScanNet export). Fills sens with the .sens file's path for that
 * layout; -1 with err set when none fits. */
static int choose_layout(const char *dir, int layout, char sens[PATHMAX], char *err, size_t errlen) {
  char p[PATHMAX], q[PATHMAX];
  join(p, dir, "rgb");
  join(q, dir, "color");
  if (layout == VLFF_DS_SENS || (layout == VLFF_DS_AUTO && !is_dir(p) && !is_dir(q))) {
    int found = find_sens(dir, sens, err, errlen);
    if (found < 0) return -1;
    if (found) layout = VLFF_DS_SENS;
    else if (layout == VLFF_DS_SENS) {
      seterr(err, errlen, "%s: no .sens file", VLFF_Q(dir));
      return -1;
    }
  }
  if (layout == VLFF_DS_AUTO) {
    if (is_dir(p)) layout = VLFF_DS_REFERENCE;
    else if (is_dir(q)) layout = VLFF_DS_SCANNET;
    else {
      seterr(err, errlen, "%s: neither rgb/ (reference layout), color/ (ScanNet export) nor a .sens file found",
             VLFF_Q(dir));
      return -1;
    }
  }
  return layout;
}

/* The image directory's stems (rgb/ or color/), each with its depth image
 * and pose: depth/ and pose/ must hold exactly one file per image. On
 * success rgb holds the stems (the caller frees rgb->s); on failure nothing
 * is held. */
static int list_frames(struct vlff_dataset *ds, const char *dir, struct stems *rgb, char *err, size_t errlen) {
  char p[PATHMAX];
  join(p, dir, ds->layout == VLFF_DS_REFERENCE ? "rgb" : "color");
  if (list_stems(p, ".png,.jpg,.jpeg", rgb, err, errlen) < 0) return -1;
  if (rgb->n == 0) {
    seterr(err, errlen, "%s: no .png or .jpg images", VLFF_Q(p));
    free(rgb->s);
    return -1;
  }
  snprintf(ds->rgb_ext, sizeof ds->rgb_ext, "%s", rgb->ext);
  const char *sub[2] = {"depth", "pose"};
  const char *ext[2] = {".png", ".txt"};
  for (int k = 0; k < 2; k++) {
    struct stems o;
    join(p, dir, sub[k]);
    if (list_stems(p, ext[k], &o, err, errlen) < 0) {
      free(rgb->s);
      return -1;
    }
    int bad = -1;
    for (int i = 0; i < rgb->n && bad < 0; i++)
      if (i >= o.n || strcmp(rgb->s[i], o.s[i])) bad = i;
    if (bad < 0 && o.n != rgb->n) bad = rgb->n;
    if (bad >= 0) {
      /* both lists in stem order: at the first difference the earlier stem
       * is the one the other directory lacks */
      if (bad < rgb->n && (bad >= o.n || stem_cmp(rgb->s[bad], o.s[bad]) < 0))
        seterr(err, errlen, "%s/%s%s: missing (there is an image %s%s)", VLFF_Q(p), VLFF_Q(rgb->s[bad]), ext[k],
               VLFF_Q(rgb->s[bad]), rgb->ext);
      else
        seterr(err, errlen, "%s/%s%s: no matching image", VLFF_Q(p), VLFF_Q(o.s[bad]), ext[k]);
      free(o.s), free(rgb->s);
      return -1;
    }
    free(o.s);
  }
  return 0;
}

/* Every listed frame's pose (camera-to-world; the reference layout stores
 * world-to-camera) into ds->c2w, its stem into ds->stem. A ScanNet pose of
 * inf or nan (tracking lost) skips its frame; any other bad pose fails. */
static int read_poses(struct vlff_dataset *ds, const char *dir, const struct stems *rgb, char *err,
                      size_t errlen) {
  const int ref = ds->layout == VLFF_DS_REFERENCE;
  char p[PATHMAX];
  ds->stem = calloc((size_t)rgb->n, sizeof *ds->stem);
  ds->c2w = calloc((size_t)rgb->n, 16 * sizeof(double));
  ds->listed = calloc((size_t)rgb->n, sizeof *ds->listed);
  ds->n_listed = rgb->n;
  {
    char *end;
    const char *last = rgb->s[rgb->n - 1];
    errno = 0;
    long v = strtol(last, &end, 10);
    ds->last_number = all_digits(last) && !errno ? v : rgb->n - 1; /* frame_numbers settles it */
  }
  if (!ds->stem || !ds->c2w || !ds->listed) {
    seterr(err, errlen, "%s: out of memory", VLFF_Q(dir));
    return -1;
  }
  for (int i = 0; i < rgb->n; i++) {
    char name[VLFF_DS_NAME + 8];
    snprintf(name, sizeof name, "pose/%s.txt", rgb->s[i]);
    join(p, dir, name);
    char *buf;
    size_t len;
    if (read_text(p, &buf, &len, err, errlen) < 0) return -1;
    double m[16];
    int rc = vlff_parse_matrix(buf, len, p, m, err, errlen);
    int nonfinite = 0;
    for (const char *const *w = (const char *const[]){"inf", "Inf", "INF", "nan", "NaN", "NAN", NULL}; rc < 0 && *w; w++)
      nonfinite |= strstr(buf, *w) != NULL;
    free(buf);
    if (rc < 0 && !ref && nonfinite) {
      ds->skipped++; /* ScanNet: lost tracking */
      continue;
    }
    if (rc < 0 || vlff_check_pose(m, p, err, errlen) < 0) return -1;
    double *out = ds->c2w + (size_t)ds->n * 16;
    if (ref) vlff_pose_invert(m, out); /* stored world-to-camera */
    else memcpy(out, m, sizeof m);
    snprintf(ds->stem[ds->n], VLFF_DS_NAME, "%s", rgb->s[i]);
    ds->listed[ds->n++] = i;
  }
  if (ds->n == 0) {
    seterr(err, errlen, "%s: every frame's pose is invalid", VLFF_Q(dir));
    return -1;
  }
  return 0;
}

/* The image size (the first frame's, which must be 8-bit RGB), the colour
 * camera's intrinsics and, for a ScanNet export, its depth camera. */
static int read_cameras(struct vlff_dataset *ds, const char *dir, char *err, size_t errlen) {
  const int ref = ds->layout == VLFF_DS_REFERENCE;
  char p[PATHMAX];
  {
    char name[VLFF_DS_NAME + 16];
    snprintf(name, sizeof name, "%s/%s%s", ref ? "rgb" : "color", ds->stem[0], ds->rgb_ext);
    join(p, dir, name);
    struct vlff_image im;
    if (vlff_image_read(p, &im, err, errlen) < 0) return -1;
    ds->width = im.width, ds->height = im.height;
    int ok = im.channels == 3 && !im.depth16;
    vlff_image_free(&im);
    if (!ok) {
      seterr(err, errlen, "%s: expected an 8-bit RGB image", VLFF_Q(p));
      return -1;
    }
  }
  {
    join(p, dir, ref ? "intrinsics.txt" : "intrinsic/intrinsic_color.txt");
    char *buf;
    size_t len;
    double K[16];
    if (read_text(p, &buf, &len, err, errlen) < 0) return -1;
    int rc = vlff_parse_matrix(buf, len, p, K, err, errlen);
    free(buf);
    if (rc < 0 || check_intrinsics(ds, K, p, err, errlen) < 0) return -1;
  }
  ds->color_width = ds->width, ds->color_height = ds->height;
  if (!ref && scannet_export_cameras(ds, dir, err, errlen) < 0) return -1;
  if (!ref && !ds->registered) ds->cx += 0.5, ds->cy += 0.5; /* OpenCV's pixel centres to the field's */
  return 0;
}

/* bbox.txt, when there is one. */
static int read_bbox(struct vlff_dataset *ds, const char *dir, char *err, size_t errlen) {
  char p[PATHMAX];
  int have = optional_file(p, dir, "bbox.txt", err, errlen);
  if (have <= 0) return have;
  char *buf;
  size_t len;
  if (read_text(p, &buf, &len, err, errlen) < 0) return -1;
  int rc = vlff_parse_bbox(buf, len, p, ds->bbox_lo, ds->bbox_hi, err, errlen);
  free(buf);
  if (rc < 0) return -1;
  ds->has_bbox = 1;
  return 0;
}

/* Camera positions against the scene box (or an absolute bound without
 * one): a translation of 1e300 would wreck every result silently. The error
 * names the pose's file, or the .sens file and the frame. */
static int check_positions(const struct vlff_dataset *ds, const char *dir, const char *sens, char *err,
                           size_t errlen) {
  for (int i = 0; i < ds->n; i++) {
    char why[200];
    if (vlff_pose_plausible(ds->c2w + (size_t)i * 16, ds->has_bbox ? ds->bbox_lo : NULL,
                            ds->has_bbox ? ds->bbox_hi : NULL, why, sizeof why)) {
      if (ds->layout == VLFF_DS_SENS) {
        seterr(err, errlen, "%s: frame %s: %s", VLFF_Q(sens), VLFF_Q(ds->stem[i]), why);
      } else {
        char name[VLFF_DS_NAME + 8], p[PATHMAX];
        snprintf(name, sizeof name, "pose/%s.txt", ds->stem[i]);
        join(p, dir, name);
        seterr(err, errlen, "%s: %s", VLFF_Q(p), why);
      }
      return -1;
    }
  }
  return 0;
}

/* The frames' numbers: their stems when all are integers, else their
 * positions among the listed frames (lost ones included). */
static int frame_numbers(struct vlff_dataset *ds, char *err, size_t errlen) {
  ds->number = calloc((size_t)ds->n, sizeof *ds->number);
  ds->feat_row = malloc((size_t)ds->n * sizeof *ds->feat_row);
  if (!ds->number || !ds->feat_row) {
    seterr(err, errlen, "%s: out of memory", VLFF_Q(ds->dir));
    return -1;
  }
  int stems = 1;
  for (int i = 0; i < ds->n && stems; i++) {
    char *end;
    errno = 0;
    long v = strtol(ds->stem[i], &end, 10);
    stems = all_digits(ds->stem[i]) && !errno && v <= ds->last_number;
    ds->number[i] = v;
  }
  if (!stems) {
    for (int i = 0; i < ds->n; i++) ds->number[i] = ds->listed[i];
    ds->last_number = ds->n_listed - 1;
  }
  for (int i = 0; i < ds->n; i++) ds->feat_row[i] = -1;
  return 0;
}

/* The features, when there are any: features.hdf or a features/ directory
 * of one file per frame (without HDF5 they are simply not offered:
 * has_features stays 0). */
static int open_features(struct vlff_dataset *ds, const char *dir, char *err, size_t errlen) {
  char p[PATHMAX], q[PATHMAX];
  int have = optional_file(p, dir, "features.hdf", err, errlen);
  if (have < 0) return -1;
  join(q, dir, "features");
  if (have && is_dir(q)) {
    seterr(err, errlen, "%s: both features.hdf and features/ (one file per frame): keep one", VLFF_Q(dir));
    return -1;
  }
#ifdef VLFF_HAVE_HDF5
  if (have) return features_probe(ds, p, err, errlen);
  if (is_dir(q)) return features_dir_probe(ds, q, err, errlen);
#endif
  return 0;
}

/* What the caller requires (options.require), before any frame is listed:
 * a scene missing one of them would otherwise be read in full first. */
static int check_required(struct vlff_dataset *ds, const char *sens, int require, char *err, size_t errlen) {
  char p[PATHMAX], q[PATHMAX];
  const int ref = ds->layout == VLFF_DS_REFERENCE;
  if ((require & VLFF_DS_REQUIRE_POINTS) &&
      vlff_scannet_points_path(ds->dir, ds->layout, sens, p, sizeof p, err, errlen) < 0)
    return -1;
  if (require & VLFF_DS_REQUIRE_LABELS) {
    join(p, ds->dir, "gt_semantic");
    join(q, ds->dir, "label-filt");
    if (!is_dir(p) && (ref || !is_dir(q))) {
      if (ref) seterr(err, errlen, "%s: missing (the 2D ground truth, one label image per frame)", VLFF_Q(p));
      else
        seterr(err, errlen, "%s: missing: ScanNet's 2D labels (the scene's <scene>_2d-label-filt.zip, unzipped "
                            "there; or gt_semantic/ with class ids)", VLFF_Q(q));
      return -1;
    }
  }
  if (require & VLFF_DS_REQUIRE_FEATURES) {
    join(p, ds->dir, "features.hdf");
    join(q, ds->dir, "features");
    if (access(p, F_OK) != 0 && !is_dir(q)) {
      seterr(err, errlen, "%s: missing (nor a features/ directory of one <frame>.hdf per frame): the scene's feature maps",
             VLFF_Q(p));
      return -1;
    }
#ifndef VLFF_HAVE_HDF5
    seterr(err, errlen, "%s: this build has no HDF5 support to read the features", VLFF_Q(ds->dir));
    return -1;
#endif
  }
  return 0;
}

int vlff_dataset_open_opts(struct vlff_dataset *ds, const char *dir, const struct vlff_dataset_options *opts,
                           char *err, size_t errlen) {
  static const struct vlff_dataset_options defaults = {.layout = VLFF_DS_AUTO, .label_set = VLFF_LABELS_SCANNET20};
  if (!opts) opts = &defaults;
  memset(ds, 0, sizeof *ds);
  if (path_too_long("dataset", dir, err, errlen) ||
      (opts->label_tsv && path_too_long("label table", opts->label_tsv, err, errlen)))
    return -1;
  if (opts->label_set != VLFF_LABELS_SCANNET20 && opts->label_set != VLFF_LABELS_NYU40) {
    seterr(err, errlen, "%s: unknown label set %d", VLFF_Q(dir), opts->label_set);
    return -1;
  }
  snprintf(ds->dir, sizeof ds->dir, "%s", dir);
  char sens[PATHMAX] = "";
  int layout = choose_layout(dir, opts->layout, sens, err, errlen);
  if (layout < 0) return -1;
  ds->layout = layout;
  /* the scene directory (labels, features, mesh) of a .sens is the file's */
  char *slash = strrchr(sens, '/');
  if (layout == VLFF_DS_SENS && is_file(dir))
    snprintf(ds->dir, sizeof ds->dir, "%.*s", slash ? (int)(slash - sens) : 1, slash ? sens : ".");
  if (check_required(ds, sens, opts->require, err, errlen) < 0 || label_table(ds, ds->dir, opts, err, errlen) < 0)
    goto fail;
  if (layout == VLFF_DS_SENS) {
    if (vlff_sens_open(ds, sens, err, errlen) < 0) goto fail;
  } else { /* a reference or ScanNet-export directory */
    struct stems rgb;
    if (list_frames(ds, dir, &rgb, err, errlen) < 0) goto fail;
    int rc = read_poses(ds, dir, &rgb, err, errlen);
    free(rgb.s);
    if (rc < 0 || read_cameras(ds, dir, err, errlen) < 0) goto fail;
  }
  dir = ds->dir;
  if (frame_numbers(ds, err, errlen) < 0 || read_bbox(ds, dir, err, errlen) < 0 ||
      check_positions(ds, dir, sens, err, errlen) < 0 || open_labels(ds, dir, err, errlen) < 0 ||
      open_features(ds, dir, err, errlen) < 0)
    goto fail;
  return 0;
fail:
  vlff_dataset_close(ds);
  return -1;
}

/* ---- frames ------------------------------------------------------------- */

/* Frame i's label image resampled to the output size and mapped (ScanNet). */
static int read_label(const struct vlff_dataset *ds, int i, uint8_t *label, char *err, size_t errlen) {
  char name[VLFF_DS_NAME + 24], p[PATHMAX];
  snprintf(name, sizeof name, "%s/%s.png", ds->label_dir, ds->stem[i]);
  join(p, ds->dir, name);
  struct vlff_image im;
  if (vlff_image_read(p, &im, err, errlen) < 0) return -1;
  int rc = vlff_scannet_map_labels(ds, &im, p, label, err, errlen);
  vlff_image_free(&im);
  return rc;
}

/* ScanNet with its own depth camera: colour, depth and labels brought into
 * the output camera (see dataset.h). */
static int read_registered(const struct vlff_dataset *ds, int i, uint8_t *rgb, float *depth, uint8_t *label,
                           char *err, size_t errlen) {
  uint8_t *crgb = NULL;
  uint16_t *dmm = NULL;
  double scale = 0.001;
  char name[VLFF_DS_NAME + 24], p[PATHMAX];
  struct vlff_image im = {0}, dim = {0};
  int rc = -1;
  if (ds->sens) {
    if (vlff_sens_read(ds, i, rgb ? &crgb : NULL, depth ? &dmm : NULL, err, errlen) < 0) return -1;
    scale = vlff_sens_depth_scale(ds);
  } else {
    if (rgb) {
      snprintf(name, sizeof name, "color/%s%s", ds->stem[i], ds->rgb_ext);
      join(p, ds->dir, name);
      if (vlff_image_read(p, &im, err, errlen) < 0) goto out;
      if (im.width != ds->color_width || im.height != ds->color_height || im.channels != 3 || im.depth16) {
        seterr(err, errlen, "%s: %dx%d %d-channel; expected %dx%d RGB8 like the first frame", VLFF_Q(p), im.width,
               im.height, im.channels, ds->color_width, ds->color_height);
        goto out;
      }
      crgb = im.data;
    }
    if (depth) {
      snprintf(name, sizeof name, "depth/%s.png", ds->stem[i]);
      join(p, ds->dir, name);
      if (vlff_image_read(p, &dim, err, errlen) < 0) goto out;
      if (dim.width != ds->depth_width || dim.height != ds->depth_height || dim.channels != 1 || !dim.depth16) {
        seterr(err, errlen, "%s: expected a %dx%d 16-bit single-channel PNG (millimetres)", VLFF_Q(p), ds->depth_width,
               ds->depth_height);
        goto out;
      }
      dmm = dim.data;
    }
  }
  if (rgb) vlff_scannet_resample_rgb(ds, crgb, rgb);
  if (depth) vlff_scannet_register_depth(ds, dmm, scale, depth);
  if (label && !ds->has_labels) {
    seterr(err, errlen, "%s: no gt_semantic/ or label-filt/ labels", VLFF_Q(ds->dir));
    goto out;
  }
  rc = label ? read_label(ds, i, label, err, errlen) : 0;
out:
  if (ds->sens) free(crgb), free(dmm);
  vlff_image_free(&im);
  vlff_image_free(&dim);
  return rc;
}

int vlff_dataset_read_frame(const struct vlff_dataset *ds, int i, uint8_t *rgb, float *depth,
                            uint8_t *label, char *err, size_t errlen) {
  if (i < 0 || i >= ds->n) {
    seterr(err, errlen, "%s: frame %d out of range 0..%d", VLFF_Q(ds->dir), i, ds->n - 1);
    return -1;
  }
  if (ds->registered) return read_registered(ds, i, rgb, depth, label, err, errlen);
  const int ref = ds->layout == VLFF_DS_REFERENCE;
  const int W = ds->width, H = ds->height;
  char name[VLFF_DS_NAME + 24], p[PATHMAX];
  struct vlff_image im;
  if (rgb) {
    snprintf(name, sizeof name, "%s/%s%s", ref ? "rgb" : "color", ds->stem[i], ds->rgb_ext);
    join(p, ds->dir, name);
    if (vlff_image_read(p, &im, err, errlen) < 0) return -1;
    if (im.width != W || im.height != H || im.channels != 3 || im.depth16) {
      seterr(err, errlen, "%s: %dx%d %d-channel %d-bit; expected %dx%d RGB8 like the first frame", VLFF_Q(p),
             im.width, im.height, im.channels, im.depth16 ? 16 : 8, W, H);
      vlff_image_free(&im);
      return -1;
    }
    memcpy(rgb, im.data, (size_t)W * H * 3);
    vlff_image_free(&im);
  }
  if (depth) {
    snprintf(name, sizeof name, "depth/%s.png", ds->stem[i]);
    join(p, ds->dir, name);
    if (vlff_image_read(p, &im, err, errlen) < 0) return -1;
    if (im.channels != 1 || !im.depth16) {
      seterr(err, errlen, "%s: depth must be a 16-bit single-channel PNG (millimetres)", VLFF_Q(p));
      vlff_image_free(&im);
      return -1;
    }
    if ((long long)im.width * H != (long long)im.height * W) {
      /* a different aspect ratio cannot share the colour intrinsics */
      seterr(err, errlen, "%s: %dx%d does not have the colour images' %dx%d aspect", VLFF_Q(p), im.width,
             im.height, W, H);
      vlff_image_free(&im);
      return -1;
    }
    const uint16_t *d = im.data;
    for (int v = 0; v < H; v++)
      for (int u = 0; u < W; u++) {
        int su = (int)((u + 0.5) * im.width / W), sv = (int)((v + 0.5) * im.height / H);
        depth[(size_t)v * W + u] = d[(size_t)sv * im.width + su] * 0.001f;
      }
    vlff_image_free(&im);
  }
  if (label) {
    if (!ds->has_labels) {
      seterr(err, errlen, "%s: no gt_semantic/ labels", VLFF_Q(ds->dir));
      return -1;
    }
    if (ds->label_map) return read_label(ds, i, label, err, errlen);
    snprintf(name, sizeof name, "gt_semantic/%s.png", ds->stem[i]);
    join(p, ds->dir, name);
    if (vlff_image_read(p, &im, err, errlen) < 0) return -1;
    if (im.channels != 1 || im.width != W || im.height != H) {
      seterr(err, errlen, "%s: labels must be single-channel %dx%d, got %dx%d with %d channels", VLFF_Q(p), W, H,
             im.width, im.height, im.channels);
      vlff_image_free(&im);
      return -1;
    }
    for (size_t k = 0; k < (size_t)W * H; k++) {
      unsigned v = im.depth16 ? ((uint16_t *)im.data)[k] : ((uint8_t *)im.data)[k];
      label[k] = v < 255 ? (uint8_t)v : 255;
    }
    vlff_image_free(&im);
  }
  return 0;
}

int vlff_dataset_read_features(const struct vlff_dataset *ds, int i, uint16_t *out, char *err,
                               size_t errlen) {
  if (!ds->has_features) {
    seterr(err, errlen, "%s: no features.hdf", VLFF_Q(ds->dir));
    return -1;
  }
  if (i < 0 || i >= ds->n) {
    seterr(err, errlen, "%s: frame %d out of range", VLFF_Q(ds->dir), i);
    return -1;
  }
#ifdef VLFF_HAVE_HDF5
  char p[PATHMAX], name[VLFF_DS_NAME + 16];
  if (ds->feat_files) snprintf(name, sizeof name, "features/%s.hdf", ds->stem[i]);
  else snprintf(name, sizeof name, "features.hdf");
  join(p, ds->dir, name);
  if (ds->feat_row[i] < 0) {
    seterr(err, errlen, "%s: holds no features for frame %s (%s for %d of the scene's %d frames)", VLFF_Q(p),
           VLFF_Q(ds->stem[i]), ds->feat_files ? "features/ has files" : "it has maps", ds->feat_frames, ds->n);
    return -1;
  }
  struct h5feat h;
  if (h5feat_open(&h, p, ds->feat_files, err, errlen) < 0) return -1;
  if (ds->feat_files && strcmp(h.name, ds->feat_name)) {
    seterr(err, errlen, "%s: holds features/%s; the scene's other frame files hold features/%s", VLFF_Q(p),
           VLFF_Q(h.name), VLFF_Q(ds->feat_name));
    h5feat_close(&h);
    return -1;
  }
  if (h.dims[1] != (hsize_t)ds->feat_height || h.dims[2] != (hsize_t)ds->feat_width ||
      h.dims[3] != (hsize_t)ds->feature_dim) {
    seterr(err, errlen, "%s: features/%s is %llux%llux%llu; the scene's are %dx%dx%d", VLFF_Q(p), VLFF_Q(h.name),
           (unsigned long long)h.dims[1], (unsigned long long)h.dims[2], (unsigned long long)h.dims[3],
           ds->feat_height, ds->feat_width, ds->feature_dim);
    h5feat_close(&h);
    return -1;
  }
  hid_t fs = H5Dget_space(h.d);
  hid_t ht = h5_half();
  hsize_t cnt[4] = {1, (hsize_t)ds->feat_height, (hsize_t)ds->feat_width, (hsize_t)ds->feature_dim};
  hsize_t start[4] = {(hsize_t)ds->feat_row[i], 0, 0, 0};
  int rank = fs >= 0 ? H5Sget_simple_extent_ndims(fs) : -1;
  /* a one-frame file may be [H,W,C]: select in its own rank */
  hid_t ms = H5Screate_simple(rank == 3 ? 3 : 4, rank == 3 ? cnt + 1 : cnt, NULL);
  int rc = -1;
  if (fs >= 0 && (rank == 3 || rank == 4) &&
      H5Sselect_hyperslab(fs, H5S_SELECT_SET, rank == 3 ? start + 1 : start, NULL, rank == 3 ? cnt + 1 : cnt,
                          NULL) >= 0 &&
      H5Dread(h.d, ht, ms, fs, H5P_DEFAULT, out) >= 0)
    rc = 0;
  else
    seterr(err, errlen, "%s: reading features/%s for frame %s failed (compressed with a filter this libhdf5 lacks, "
                        "e.g. lzf?)",
           VLFF_Q(p), VLFF_Q(h.name), VLFF_Q(ds->stem[i]));
  H5Sclose(ms);
  H5Tclose(ht);
  if (fs >= 0) H5Sclose(fs);
  h5feat_close(&h);
  if (rc == 0) {
    /* non-finite features, or values beyond any model's (bounds.h), would
     * poison training and evaluation, and the node refuses them */
    size_t n = (size_t)ds->feat_height * ds->feat_width * ds->feature_dim;
    for (size_t k = 0; k < n; k++)
      if ((out[k] & 0x7FFFu) > VLFF_FEATURE_MAX_ABS_F16) {
        seterr(err, errlen, "%s: features/%s frame %s has a %s value at element %zu (beyond +-%g)", VLFF_Q(p),
               VLFF_Q(ds->feat_name), VLFF_Q(ds->stem[i]), (out[k] & 0x7c00u) == 0x7c00u ? "non-finite" : "huge",
               k, VLFF_FEATURE_MAX_ABS);
        return -1;
      }
  }
  return rc;
#else
  seterr(err, errlen, "%s: this build has no HDF5 support", VLFF_Q(ds->dir));
  return -1;
#endif
}

/* ---- writer ------------------------------------------------------------- */

struct vlff_dataset_writer {
  char dir[PATHMAX];
  int n, width, height, fw, fh, dim;
  unsigned char *added;
#ifdef VLFF_HAVE_HDF5
  hid_t file, dset, half;
  char h5tmp[PATHMAX];
#endif
};

static int mkdir_p1(const char *p, char *err, size_t errlen) {
  if (mkdir(p, 0755) < 0 && errno != EEXIST) {
    seterr(err, errlen, "%s: cannot create directory: %s", VLFF_Q(p), strerror(errno));
    return -1;
  }
  if (!is_dir(p)) {
    seterr(err, errlen, "%s: exists and is not a directory", VLFF_Q(p));
    return -1;
  }
  return 0;
}

static int write_text_matrix(const char *path, const double m[16], char *err, size_t errlen) {
  char b[1024];
  size_t n = 0;
  for (int r = 0; r < 4; r++)
    n += (size_t)snprintf(b + n, sizeof b - n, "%.17g %.17g %.17g %.17g\n", m[4 * r], m[4 * r + 1],
                          m[4 * r + 2], m[4 * r + 3]);
  return vlff_write_file_atomic(path, b, n, err, errlen);
}

void vlff_dataset_writer_abort(struct vlff_dataset_writer *w) {
  if (!w) return;
#ifdef VLFF_HAVE_HDF5
  if (w->dset >= 0) H5Dclose(w->dset);
  if (w->half >= 0) H5Tclose(w->half);
  if (w->file >= 0) {
    H5Fclose(w->file);
    unlink(w->h5tmp);
  }
#endif
  free(w->added);
  free(w);
}

struct vlff_dataset_writer *vlff_dataset_writer_open(const char *dir, int nframes, int width,
                                                     int height, double fx, double fy, double cx,
                                                     double cy, const double bbox_lo[3],
                                                     const double bbox_hi[3], const char *feat_name,
                                                     int feat_width, int feat_height, int feature_dim,
                                                     char *err, size_t errlen) {
  if (nframes < 1 || width < 1 || height < 1 || !(fx > 0) || !(fy > 0) || feature_dim < 0 ||
      (feature_dim > 0 && (feat_width < 1 || feat_height < 1 || !feat_name || !feat_name[0] ||
                        strlen(feat_name) >= VLFF_DS_NAME || strchr(feat_name, '/')))) {
    seterr(err, errlen, "%s: invalid dataset shape", VLFF_Q(dir));
    return NULL;
  }
  if (path_too_long("dataset", dir, err, errlen)) return NULL;
  struct vlff_dataset_writer *w = calloc(1, sizeof *w);
  if (!w) return NULL;
#ifdef VLFF_HAVE_HDF5
  w->file = w->dset = w->half = -1;
#endif
  snprintf(w->dir, sizeof w->dir, "%s", dir);
  w->n = nframes, w->width = width, w->height = height;
  w->fw = feat_width, w->fh = feat_height, w->dim = feature_dim;
  w->added = calloc((size_t)nframes, 1);
  char p[PATHMAX];
#ifndef VLFF_HAVE_HDF5
  if (feature_dim > 0) { /* said before anything is made */
    seterr(err, errlen, "%s: features need HDF5, which this build was configured without", VLFF_Q(dir));
    goto fail;
  }
#endif
  /* Into a new or empty directory only: over an older, larger scene its
   * frames beyond this one's stayed and were read with them. */
  DIR *old = opendir(dir);
  if (old) {
    struct dirent *e;
    int any = 0;
    while (!any && (e = readdir(old))) any = strcmp(e->d_name, ".") && strcmp(e->d_name, "..");
    closedir(old);
    if (any) {
      seterr(err, errlen, "%s: exists and is not empty: a scene is written into a new or empty directory", VLFF_Q(dir));
      goto fail;
    }
  }
  if (!w->added || mkdir_p1(dir, err, errlen) < 0) goto fail;
  const char *subs[] = {"rgb", "depth", "pose", "gt_semantic"};
  for (int i = 0; i < 4; i++) {
    join(p, dir, subs[i]);
    if (mkdir_p1(p, err, errlen) < 0) goto fail;
  }
  double K[16] = {fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0, 0, 0, 0, 1};
  join(p, dir, "intrinsics.txt");
  if (write_text_matrix(p, K, err, errlen) < 0) goto fail;
  if (bbox_lo && bbox_hi) {
    char b[512];
    int n = snprintf(b, sizeof b, "%.9g %.9g %.9g %.9g %.9g %.9g\n", bbox_lo[0], bbox_lo[1], bbox_lo[2],
                     bbox_hi[0], bbox_hi[1], bbox_hi[2]);
    join(p, dir, "bbox.txt");
    if (vlff_write_file_atomic(p, b, (size_t)n, err, errlen) < 0) goto fail;
  }
  if (feature_dim > 0) {
#ifdef VLFF_HAVE_HDF5
    H5Eset_auto2(H5E_DEFAULT, NULL, NULL);
    snprintf(w->h5tmp, sizeof w->h5tmp, "%s/features.hdf.tmp.%ld", dir, (long)getpid());
    w->file = H5Fcreate(w->h5tmp, H5F_ACC_TRUNC, H5P_DEFAULT, H5P_DEFAULT);
    if (w->file < 0) {
      seterr(err, errlen, "%s: cannot create HDF5 file", VLFF_Q(w->h5tmp));
      goto fail;
    }
    hid_t g = H5Gcreate2(w->file, "features", H5P_DEFAULT, H5P_DEFAULT, H5P_DEFAULT);
    hsize_t dims[4] = {(hsize_t)nframes, (hsize_t)feat_height, (hsize_t)feat_width, (hsize_t)feature_dim};
    hsize_t chunk[4] = {1, (hsize_t)feat_height, (hsize_t)feat_width, (hsize_t)feature_dim};
    hid_t sp = H5Screate_simple(4, dims, NULL);
    hid_t pl = H5Pcreate(H5P_DATASET_CREATE);
    H5Pset_chunk(pl, 4, chunk);
    w->half = h5_half();
    w->dset = g >= 0 ? H5Dcreate2(g, feat_name, w->half, sp, H5P_DEFAULT, pl, H5P_DEFAULT) : -1;
    H5Pclose(pl);
    H5Sclose(sp);
    if (g >= 0) H5Gclose(g);
    if (w->dset < 0) {
      seterr(err, errlen, "%s: cannot create dataset features/%s", VLFF_Q(w->h5tmp), VLFF_Q(feat_name));
      goto fail;
    }
#else
    seterr(err, errlen, "%s: features need HDF5, which this build was configured without", VLFF_Q(dir));
    goto fail;
#endif
  }
  return w;
fail:
  vlff_dataset_writer_abort(w);
  return NULL;
}

int vlff_dataset_writer_add(struct vlff_dataset_writer *w, int i, const uint8_t *rgb,
                            const uint16_t *depth_mm, const uint8_t *label, const double c2w[16],
                            const uint16_t *features, char *err, size_t errlen) {
  if (i < 0 || i >= w->n || !rgb) {
    seterr(err, errlen, "%s: frame %d out of range 0..%d or without rgb", VLFF_Q(w->dir), i, w->n - 1);
    return -1;
  }
  char name[64], p[PATHMAX];
  if (vlff_check_pose(c2w, "pose to write", err, errlen) < 0) return -1;
  snprintf(name, sizeof name, "rgb/%05d.png", i);
  join(p, w->dir, name);
  if (vlff_png_write(p, rgb, w->width, w->height, 3, 0, err, errlen) < 0) return -1;
  if (depth_mm) {
    snprintf(name, sizeof name, "depth/%05d.png", i);
    join(p, w->dir, name);
    if (vlff_png_write(p, depth_mm, w->width, w->height, 1, 1, err, errlen) < 0) return -1;
  }
  if (label) {
    snprintf(name, sizeof name, "gt_semantic/%05d.png", i);
    join(p, w->dir, name);
    if (vlff_png_write(p, label, w->width, w->height, 1, 0, err, errlen) < 0) return -1;
  }
  double tcw[16];
  vlff_pose_invert(c2w, tcw);
  snprintf(name, sizeof name, "pose/%05d.txt", i);
  join(p, w->dir, name);
  if (write_text_matrix(p, tcw, err, errlen) < 0) return -1;
  if (w->dim > 0) {
    if (!features) {
      seterr(err, errlen, "%s: frame %d needs features", VLFF_Q(w->dir), i);
      return -1;
    }
#ifdef VLFF_HAVE_HDF5
    hsize_t start[4] = {(hsize_t)i, 0, 0, 0};
    hsize_t cnt[4] = {1, (hsize_t)w->fh, (hsize_t)w->fw, (hsize_t)w->dim};
    hid_t fs = H5Dget_space(w->dset);
    hid_t ms = H5Screate_simple(4, cnt, NULL);
    int ok = H5Sselect_hyperslab(fs, H5S_SELECT_SET, start, NULL, cnt, NULL) >= 0 &&
             H5Dwrite(w->dset, w->half, ms, fs, H5P_DEFAULT, features) >= 0;
    H5Sclose(ms);
    H5Sclose(fs);
    if (!ok) {
      seterr(err, errlen, "%s: writing features of frame %d failed", VLFF_Q(w->h5tmp), i);
      return -1;
    }
#endif
  }
  w->added[i] = 1;
  return 0;
}

int vlff_dataset_writer_close(struct vlff_dataset_writer *w, char *err, size_t errlen) {
  for (int i = 0; i < w->n; i++)
    if (!w->added[i]) {
      seterr(err, errlen, "%s: frame %d was never written", VLFF_Q(w->dir), i);
      vlff_dataset_writer_abort(w);
      return -1;
    }
#ifdef VLFF_HAVE_HDF5
  if (w->file >= 0) {
    H5Dclose(w->dset);
    H5Tclose(w->half);
    w->dset = w->half = -1;
    herr_t rc = H5Fclose(w->file);
    w->file = -1;
    char p[PATHMAX];
    join(p, w->dir, "features.hdf");
    int fd = rc >= 0 ? open(w->h5tmp, O_RDONLY | O_CLOEXEC) : -1;
    int ok = fd >= 0 && fsync(fd) == 0;
    if (fd >= 0) close(fd);
    if (!ok || rename(w->h5tmp, p) < 0) {
      seterr(err, errlen, "%s: finishing features.hdf failed: %s", VLFF_Q(w->h5tmp), strerror(errno));
      unlink(w->h5tmp);
      vlff_dataset_writer_abort(w);
      return -1;
    }
  }
#endif
  free(w->added);
  free(w);
  return 0;
}
