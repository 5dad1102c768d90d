/*
 * vlff_dataset: RGB-D scene directories on disk, read and written.
 *
 * Layouts
 *  Reference layout (the paper's implementation; read and written):
 *    rgb/<stem>.png|.jpg       RGB8 (we write PNG: lossless round trips)
 *    depth/<stem>.png          uint16 millimetres, 0 = invalid
 *    pose/<stem>.txt           4x4 WORLD-TO-CAMERA (T_cw), OpenCV camera axes
 *                              (x right, y down, z forward); inverted on read
 *    intrinsics.txt            4x4 (or 3x3) camera matrix at the rgb size
 *    bbox.txt                  6 numbers: scene min xyz, max xyz (metres)
 *    features.hdf              HDF5 dataset features/<name>, [N,H,W,C] float16;
 *                              with a 1-D integer dataset "frames" [N] at the
 *                              file's root, row r holds frame frames[r]
 *                              (strictly increasing frame numbers)
 *    features/<stem>.hdf       instead of features.hdf: one file per frame,
 *                              features/<name> [1,H,W,C] or [H,W,C]; frames
 *                              without a file have no features
 *    gt_semantic/<stem>.png    8- or 16-bit class ids 0..K-1; >= K (255) = unlabelled
 *    points.ply (or mesh.ply)  labelled point set: vertex x,y,z + "label"
 *    timestamps.txt            optional: "STEM SECONDS" per frame (vlff_dataset_stamps)
 *    prompt_embeddings.txt     prompt -> vector, in the vlff-embeddings format
 *                              (node/vlm/embeddings.h: read with
 *                              vlff_embeddings_load, written with
 *                              vlff_embeddings_save); ground-truth id k is
 *                              record k
 *  ScanNet export layout (read only), as ScanNet's SensReader writes it:
 *  color/<i>.jpg, depth/<i>.png (uint16 mm), pose/<i>.txt CAMERA-TO-WORLD,
 *  intrinsic/intrinsic_color.txt and, when present, intrinsic_depth.txt,
 *  extrinsic_color.txt, extrinsic_depth.txt (sensor-to-rig, identity when
 *  absent); label-filt/<i>.png holds ScanNet label ids (16-bit), mapped
 *  through scannetv2-labels.combined.tsv (options.label_tsv, else looked for
 *  in the scene directory and its two parents) to the 20 benchmark classes
 *  or to NYU40 (options.label_set); a gt_semantic/ directory, when present
 *  instead, holds class ids directly.
 *  ScanNet .sens (read only): the raw stream file (a path to it, or a
 *  directory holding one *.sens and no color/): JPEG/PNG/raw colour,
 *  zlib/raw depth with its depth shift, poses, both cameras' intrinsics
 *  and extrinsics. Frame i's stem is "i"; label-filt/, the TSV,
 *  features.hdf and the labelled mesh are looked for beside the file.
 *  Intrinsics are returned in the field's convention, pixel (u,v) centred
 *  at (u+0.5, v+0.5): ScanNet's (OpenCV's, centred at (u,v)) are shifted by
 *  half a pixel on read; the reference layout's are taken as written.
 *  In both ScanNet layouts, when a depth intrinsic is given, frames are
 *  returned in the colour camera's geometry at the depth camera's size
 *  (width, height, fx..cy describe that camera): colour box-filtered down,
 *  labels sampled nearest, depth registered (back-projected with the depth
 *  intrinsics, moved by the extrinsic, projected, nearest surface wins,
 *  unreached pixels 0 = invalid). The 3D ground truth is
 *  <scene>_vh_clean_2.labels.ply (vertex 'label' = NYU40 id) mapped to the
 *  same classes (vlff_dataset_read_points).
 *  Frames whose pose is non-finite (ScanNet marks lost tracking with -inf)
 *  are skipped and counted, as ScanNet's own tools do; the others keep their
 *  stems (ScanNet frame numbers). A frame's number is its stem when every
 *  stem is an integer, else its position among the listed frames.
 *  features.hdf holds a map per usable frame, or one per listed frame (lost
 *  ones included, their rows passed over), or, with "frames", the frames it
 *  names (rows naming a lost frame passed over; a number beyond the scene's
 *  last frame, or out of order, refused naming the file and the row).
 *  Frames are matched by file stem; stems sort numerically when all are
 *  integers, otherwise by name. Without a depth intrinsic, depth of a
 *  different size than rgb must share its aspect and is resampled (nearest)
 *  to the rgb size, so one set of intrinsics serves both.
 *
 * Contract
 *  - Functions returning int give 0 on success, -1 on error with one line in
 *    err naming the offending file (and line or frame) and what was wrong.
 *  - Every value read is validated: sizes against each other, counts, finite
 *    numbers, orthonormal right-handed rotations (|R^T R - I| < 1e-3,
 *    det > 0), a [0 0 0 1] last row, positive focal lengths, principal points
 *    inside the image, bbox min < max; intrinsics and camera positions
 *    within physical bounds (bounds.h: field of view, pixel aspect, the
 *    camera no further outside bbox.txt than the box is big, or within an
 *    absolute bound without one); features.hdf's shape at most
 *    VLFF_DS_MAX_FEATURE_FRAME_BYTES per frame and backed by the data the
 *    file really stores, checked before anything is allocated for it.
 *  - Only regular files are read (files.h): a FIFO or device at a dataset
 *    file's name is refused, never waited on.
 *  - Files are written atomically: temp file, fsync, rename.
 *  - A vlff_dataset is used by one thread at a time; the caller owns every
 *    buffer it passes. The parse functions take memory buffers (the fuzz
 *    targets call them directly).
 */
#ifndef VLFF_DATASET_H
#define VLFF_DATASET_H

#include <stddef.h>
#include <stdint.h>

#define VLFF_DS_NAME 64
/* The longest path of a scene (its directory or .sens file) and of a label
 * table the reader takes, in bytes. A longer one is refused at open, naming
 * it, so that no path formed from it (dir/label-filt/<stem>.png) is cut
 * short and no file is read in place of another. */
#define VLFF_DS_PATH_MAX 4000
/* One frame's features may claim at most this much memory. */
#define VLFF_DS_MAX_FEATURE_FRAME_BYTES (256ull << 20)

enum vlff_dataset_layout { VLFF_DS_AUTO, VLFF_DS_REFERENCE, VLFF_DS_SCANNET, VLFF_DS_SENS };
/* ScanNet label sets: the 20 benchmark classes (NYU40 ids 1 2 3 4 5 6 7 8 9
 * 10 11 12 14 16 24 28 33 34 36 39, in that order) or all 40 NYU40 classes
 * (class k = NYU40 id k + 1). */
enum vlff_label_set { VLFF_LABELS_SCANNET20, VLFF_LABELS_NYU40 };

/* What a caller cannot do without (options.require): open checks that it
 * is there and opens before any frame is listed or read, and names the
 * missing file by the name the layout gives it (ScanNet's
 * <scene>_vh_clean_2.labels.ply, label-filt/, features.hdf). */
enum {
  VLFF_DS_REQUIRE_POINTS = 1,   /* the labelled 3D ground truth */
  VLFF_DS_REQUIRE_LABELS = 2,   /* gt_semantic/ or label-filt/ (and the TSV) */
  VLFF_DS_REQUIRE_FEATURES = 4, /* features.hdf or features/ */
};

struct vlff_dataset_options {
  int layout;             /* enum vlff_dataset_layout */
  int label_set;          /* enum vlff_label_set (ScanNet) */
  const char *label_tsv;  /* scannetv2-labels.combined.tsv; NULL = look for it */
  int require;            /* VLFF_DS_REQUIRE_* */
};
struct vlff_sens;
struct vlff_points;

struct vlff_dataset {
  char dir[VLFF_DS_PATH_MAX + 1];
  int layout;                  /* enum vlff_dataset_layout actually found */
  int n;                       /* usable frames */
  int skipped;                 /* ScanNet frames dropped for invalid poses */
  int n_listed;                /* frames the scene lists: n + skipped */
  int *listed;                 /* [n] frame i's position among those listed */
  long *number;                /* [n] frame i's number (see the layouts) */
  long last_number;            /* the last listed frame's number, lost or not */
  int width, height;           /* rgb size (depth and labels are returned at it) */
  double fx, fy, cx, cy;
  int has_bbox;
  double bbox_lo[3], bbox_hi[3];
  double *c2w;                 /* [n][16] camera-to-world */
  char (*stem)[VLFF_DS_NAME];  /* [n] */
  int has_labels;              /* gt_semantic/ present for every frame */
  int has_features;
  int feat_files;              /* features/<stem>.hdf, one per frame (else features.hdf) */
  int *feat_row;               /* [n] frame i's row in features.hdf (0: its own file); -1 none */
  int feat_frames;             /* frames with features */
  char feat_name[VLFF_DS_NAME];
  int feat_height, feat_width, feature_dim;
  char rgb_ext[8];
  /* ScanNet with a depth camera of its own (see the layouts) */
  int registered;
  int color_width, color_height, depth_width, depth_height; /* as stored */
  double dfx, dfy, dcx, dcy;   /* depth camera */
  double d2c[16];              /* depth camera to colour camera */
  int label_set;               /* enum vlff_label_set */
  uint8_t *label_map;          /* ScanNet label id -> class (255 none); NULL: ids are classes */
  char label_dir[16];          /* "gt_semantic" or "label-filt" */
  struct vlff_sens *sens;      /* the open .sens file (layout VLFF_DS_SENS) */
};

/* Open a scene directory: list and validate every frame's pose, the
 * intrinsics, bbox and the features' shape; images are read per frame.
 * dir and options.label_tsv longer than VLFF_DS_PATH_MAX are refused. */
int vlff_dataset_open(struct vlff_dataset *ds, const char *dir, int layout, char *err, size_t errlen);
/* The same with every option (opts NULL = defaults: auto layout, 20 classes). */
int vlff_dataset_open_opts(struct vlff_dataset *ds, const char *dir, const struct vlff_dataset_options *opts,
                           char *err, size_t errlen);
/* The labelled 3D ground truth's path: points.ply or mesh.ply (reference),
 * or the one *_vh_clean_2.labels.ply in the scene directory or its parent
 * (ScanNet; points.ply or mesh.ply beside the scene stand in for it). -1
 * with err naming the file as the layout calls it when none is there or it
 * cannot be opened. */
int vlff_dataset_points_path(const struct vlff_dataset *ds, char *path, size_t cap, char *err, size_t errlen);
/* The labelled 3D ground truth: points.ply or mesh.ply (reference), or
 * *_vh_clean_2.labels.ply mapped to the label set (ScanNet). */
int vlff_dataset_read_points(const struct vlff_dataset *ds, struct vlff_points *p, char *err, size_t errlen);
/* Classes of a label set, and class k's name (NULL when out of range). */
int vlff_label_set_classes(int set);
const char *vlff_label_set_name(int set, int k);
void vlff_dataset_close(struct vlff_dataset *ds);

/* Frame i's images: rgb [h][w][3], depth metres [h][w], label [h][w] (255 =
 * unlabelled; only when has_labels). Any output may be NULL. */
int vlff_dataset_read_frame(const struct vlff_dataset *ds, int i, uint8_t *rgb, float *depth,
                            uint8_t *label, char *err, size_t errlen);
/* Frame i's features, float16 [feat_height][feat_width][feature_dim]; -1
 * naming the file and the frame when the features hold none for it
 * (feat_row[i] < 0). */
int vlff_dataset_read_features(const struct vlff_dataset *ds, int i, uint16_t *out, char *err,
                               size_t errlen);

/* The recording's frame times: t[i] = frame i's stamp minus frame 0's, in
 * seconds, for every usable frame (t has ds->n entries). From
 * timestamps.txt in the scene directory (any layout; one "STEM SECONDS" line
 * per frame, '#' comments; every usable frame's stem listed) or, for .sens,
 * the colour stamps in the file (all zero = none). Stamps must be finite and
 * non-decreasing in frame order, at most 60 s apart. Returns 1 with t
 * filled, 0 when the scene has no stamps, -1 with err naming the file and
 * frame. */
int vlff_dataset_stamps(const struct vlff_dataset *ds, double *t, char *err, size_t errlen);
/* Writes DIR/timestamps.txt for frames written by the writer (stems %05d):
 * frame i at t[i] seconds. Atomic. */
int vlff_dataset_write_stamps(const char *dir, int n, const double *t, char *err, size_t errlen);

/* Writer for the reference layout. nframes and the feature shape are fixed
 * at open (feature_dim 0 = no features.hdf). */
struct vlff_dataset_writer;
struct vlff_dataset_writer *vlff_dataset_writer_open(const char *dir, int nframes, int width,
                                                     int height, double fx, double fy, double cx,
                                                     double cy, const double bbox_lo[3],
                                                     const double bbox_hi[3], const char *feat_name,
                                                     int feat_width, int feat_height, int feature_dim,
                                                     char *err, size_t errlen);
/* Frame i (0..nframes-1): rgb required; depth_mm, label, features may be NULL. */
int vlff_dataset_writer_add(struct vlff_dataset_writer *w, int i, const uint8_t *rgb,
                            const uint16_t *depth_mm, const uint8_t *label, const double c2w[16],
                            const uint16_t *features, char *err, size_t errlen);
/* Finish (features.hdf is renamed into place only here) and free. Fails if
 * a frame was never added. */
int vlff_dataset_writer_close(struct vlff_dataset_writer *w, char *err, size_t errlen);
void vlff_dataset_writer_abort(struct vlff_dataset_writer *w);

/* ---- formats ------------------------------------------------------------ */

/* Decoded image: channels 1 or 3, bit depth 8 or 16 (16: host-order uint16). */
struct vlff_image {
  int width, height, channels, depth16;
  void *data;
};
void vlff_image_free(struct vlff_image *im);
/* PNG (and JPEG when built with OpenCV), from memory or a file. Images
 * larger than 16384 x 16384 are refused. */
int vlff_image_decode(const uint8_t *buf, size_t len, const char *name, struct vlff_image *im,
                      char *err, size_t errlen);
int vlff_image_read(const char *path, struct vlff_image *im, char *err, size_t errlen);
/* PNG writer: channels 1 or 3, 8 or 16 bit (16 = host-order uint16 input). */
int vlff_png_write(const char *path, const void *data, int width, int height, int channels,
                   int depth16, char *err, size_t errlen);

/* A 4x4 (16 numbers) or 3x3 (9 numbers, expanded) matrix from text. */
int vlff_parse_matrix(const char *buf, size_t len, const char *name, double m[16], char *err,
                      size_t errlen);
/* Validate a rigid transform (see the contract). */
int vlff_check_pose(const double m[16], const char *name, char *err, size_t errlen);
/* Invert a rigid transform. */
void vlff_pose_invert(const double m[16], double out[16]);
int vlff_parse_bbox(const char *buf, size_t len, const char *name, double lo[3], double hi[3],
                    char *err, size_t errlen);

/* Labelled point set. */
struct vlff_points {
  size_t n;
  float *xyz;     /* [n][3] */
  uint8_t *label; /* [n]; 255 = unlabelled (values > 255 map to 255) */
};
void vlff_points_free(struct vlff_points *p);
int vlff_ply_parse(const uint8_t *buf, size_t len, const char *name, struct vlff_points *p,
                   char *err, size_t errlen);
int vlff_ply_read(const char *path, struct vlff_points *p, char *err, size_t errlen);
/* Binary little-endian PLY: float x,y,z; uchar red,green,blue (optional
 * colours, may be NULL); uchar label. */
int vlff_ply_write(const char *path, const float *xyz, const uint8_t *rgb, const uint8_t *label,
                   size_t n, char *err, size_t errlen);

/* Whole-file reads and atomic writes: node/common/files.h. */

#endif
