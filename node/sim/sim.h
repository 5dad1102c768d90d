/*
 * vlff_sim: procedural indoor RGB-D scenes with ground truth and LSeg-like
 * simulated vision-language features.
 *
 * A seed picks a room, a flat or a building of flats off a corridor
 * (sim.layout; walls, floor, ceiling) furnished with the 20 ScanNet
 * benchmark classes, built from axis-aligned boxes and vertical cylinders
 * with procedural textures. Frames are ray-cast analytically: RGB with
 * Lambertian shading (view-independent, so the field's photometric loss sees
 * consistent colours), depth with range-dependent noise, holes and a range
 * limit like a stereo camera, per-pixel class ids, and dense features at a
 * quarter of the image resolution whose errors mimic LSeg's: blurred
 * boundaries, per-pixel noise, per-frame confusion patches and
 * view-dependent confusions between similar classes.
 *
 * Conventions (the same as node/field/field.h)
 *  - World frame in metres, z up. The room is centred in field.scene_min/max
 *    (shrunk by 0.1 m), floor and ceiling within the box; the flat and the
 *    building (sim.layout) fill the box less 0.1 m each side.
 *  - Cameras follow OpenCV: x right, y down, z forward; poses are
 *    camera-to-world, 4x4 row-major double; pixel (u,v)'s centre is at
 *    (u+0.5, v+0.5).
 *  - Depth is metres along the camera z axis; 0 = invalid.
 *  - Class ids 0..19 follow the default prompt set (wall, floor, ..., other
 *    furniture); VLFF_SIM_UNLABELLED (255) marks the ceiling and misses.
 *  - Features are IEEE float16 bits, HWC, D = field.feature_dim, not
 *    normalised (like LSeg's raw output).
 *  - A changing world (sim.changes, docs/sim.md): at each change's time_s
 *    an object (a class name, or class#n for the n-th of that class as
 *    built) moves (its footprint's centre to `to`, x y), is removed, or is
 *    added (absent before; at `to`, or where it was built). A frame renders
 *    the scene at its own time (index / sim.rate_hz): RGB, depth, labels and
 *    features alike, so ground truth moves with the object.
 *
 * Contract
 *  - Functions returning int give 0 on success, -1 on error with a message
 *    in err (when not NULL).
 *  - Everything is a pure function of (config, frame index): two sims made
 *    from the same config give bit-identical frames.
 *  - A vlff_sim is immutable after create: any number of threads may render
 *    different frames concurrently, each into its own vlff_sim_frame.
 *  - The caller owns frames (vlff_sim_frame_new/free) and point sets.
 */
#ifndef VLFF_SIM_H
#define VLFF_SIM_H

#include <stddef.h>
#include <stdint.h>

#include "config.h"

#define VLFF_SIM_CLASSES 20
#define VLFF_SIM_UNLABELLED 255

struct vlff_sim;

/* One rendered frame; buffers are allocated by vlff_sim_frame_new for the
 * sim's sizes and reused across renders. */
struct vlff_sim_frame {
  long long index;
  double time_s;              /* index / sim.rate_hz */
  int width, height;
  double fx, fy, cx, cy;
  double c2w[16];             /* the pose reported (corrupted on bad-pose frames) */
  double c2w_true[16];        /* the pose actually rendered */
  int bad_pose;               /* 1 when c2w != c2w_true (sim.bad_pose_frac) */
  uint8_t *rgb;               /* [h][w][3] */
  float *depth;               /* [h][w] measured metres: noise, holes, range limit; 0 = invalid */
  float *depth_gt;            /* [h][w] exact metres to the first surface */
  uint16_t *depth_mm;         /* [h][w] measured depth in millimetres (0 = invalid) */
  uint8_t *label;             /* [h][w] class id, 255 = unlabelled */
  int feat_width, feat_height, feature_dim;
  uint16_t *features;         /* float16 [fh][fw][D] */
};

/* Render flags (0 renders the labels, exact depth and pose alone). */
enum { VLFF_SIM_RGBD = 1, VLFF_SIM_FEATURES = 2, VLFF_SIM_ALL = 3 };

/* Create from the sim section, in the field section's scene box
 * (scene_min/max) with its feature dimension (feature_dim). */
struct vlff_sim *vlff_sim_create(const struct vlff_cfg_sim *sim, const struct vlff_cfg_field *field, char *err,
                                 size_t errlen);
void vlff_sim_destroy(struct vlff_sim *s);

struct vlff_sim_frame *vlff_sim_frame_new(const struct vlff_sim *s);
void vlff_sim_frame_free(struct vlff_sim_frame *f);

/* Render frame `index` (>= 0; the trajectory continues past sim.frames).
 * Thread-safe for distinct frames. */
int vlff_sim_render(const struct vlff_sim *s, long long index, unsigned what,
                    struct vlff_sim_frame *f, char *err, size_t errlen);

/* The scene frame a stream's frame id (>= 0) shows: the id modulo
 * sim.frames (the walk repeats); with sim.range_count, sim.range_first plus
 * the id modulo sim.range_count (a part of the walk, repeated); or the id
 * itself with sim.changes, so that
 * the scene's time runs on and each change happens once. vlff-sim's stream
 * and the node's sim source agree through it. */
long long vlff_sim_stream_frame(const struct vlff_sim *s, long long id);

/* The box (world AABB) of the object `name` (as sim.changes names it) at
 * sim time time_s: 1 when it is present then, 0 when absent (removed, or
 * not added yet; the box is where it was last), -1 with err for a name the
 * scene does not have. */
int vlff_sim_object_box(const struct vlff_sim *s, const char *name, double time_s, double lo[3], double hi[3],
                        char *err, size_t errlen);

/* The camera of frame `index` without rendering it. */
void vlff_sim_pose(const struct vlff_sim *s, long long index, double c2w[16]);
void vlff_sim_intrinsics(const struct vlff_sim *s, double *fx, double *fy, double *cx, double *cy);
void vlff_sim_size(const struct vlff_sim *s, int *width, int *height, int *feat_width,
                   int *feat_height, int *feature_dim);
/* Room bounds (inside of the walls) and the scene box of all geometry. */
void vlff_sim_bounds(const struct vlff_sim *s, double lo[3], double hi[3]);
/* The flat and building layouts' rooms (inside faces of their walls, xy)
 * and the flat each belongs to (0.., -1 for the building's corridor). Fills
 * at most max and returns how many there are (0 for the room layout). */
struct vlff_sim_room {
  double lo[2], hi[2];
  int flat;
};
int vlff_sim_rooms(const struct vlff_sim *s, struct vlff_sim_room *out, int max);
/* Number of flats (1 for the flat layout, sim.flats for the building, 0
 * for the room), and the one whose inside holds xy, or -1 (the corridor,
 * a wall, outside). */
int vlff_sim_flat_count(const struct vlff_sim *s);
int vlff_sim_flat_at(const struct vlff_sim *s, double x, double y);
/* Length in metres of the walk the flat and building layouts loop once per
 * sim.frames frames (0 for the room layout). */
double vlff_sim_walk_length(const struct vlff_sim *s);
/* Number of primitives of each class present (counts[VLFF_SIM_CLASSES]). */
void vlff_sim_class_counts(const struct vlff_sim *s, int counts[VLFF_SIM_CLASSES]);

/* Exact ray cast from world point o along direction d (need not be unit):
 * returns the hit parameter t (point = o + t d) or -1 when nothing is hit,
 * and the hit's class id and unit normal facing the ray (either may be NULL).
 * In the scene at sim time 0; _at: at time_s (sim.changes). */
double vlff_sim_raycast(const struct vlff_sim *s, const double o[3], const double d[3],
                        int *label, double normal[3]);
double vlff_sim_raycast_at(const struct vlff_sim *s, double time_s, const double o[3], const double d[3], int *label,
                           double normal[3]);

/* The class name of id c (0..19), or NULL. */
const char *vlff_sim_class_name(int c);
/* Class id of a prompt text (case-insensitive exact name), or -1. */
int vlff_sim_class_of(const char *name);

/* The simulated text encoder: the unit-norm embedding of `text` (D floats).
 * A class name gets a vector close to, but not equal to, its feature
 * prototype; any other text gets a deterministic vector from a hash of the
 * text, with only the generic similarity every embedding shares. */
void vlff_sim_text_embedding(const struct vlff_sim *s, const char *text, float *out);
/* The unit-norm feature prototype of class c (D floats); c may be
 * VLFF_SIM_CLASSES for the unlabelled ceiling's. */
void vlff_sim_prototype(const struct vlff_sim *s, int c, float *out);

/* A ground-truth labelled point set for 3D evaluation: surface points seen
 * from frames 0, step, 2 step, ... < nframes (exact depth) through every
 * second pixel, one per cubic voxel of `voxel` metres, in the scene as it
 * stands at frame nframes - 1 (sim.changes). xyz [n][3], label [n] (255 =
 * unlabelled); rays: how many rays were cast. */
struct vlff_sim_points {
  size_t n;
  float *xyz;
  uint8_t *label;
  uint64_t rays;
};
int vlff_sim_points(const struct vlff_sim *s, int nframes, int step, double voxel,
                    struct vlff_sim_points *out, char *err, size_t errlen);
/* The same casting at most max_rays rays: a view of more than a sixteenth
 * of them takes every 4th, 8th ... pixel, and more views than the rest
 * hold every 2 step-th, 4 step-th ... frame. The node's live score uses
 * VLFF_SIM_POINTS_RAYS: sim.frames 1000000 cast 4 billion rays at its
 * start, hours deaf to SIGTERM (the default run casts 1.2 million). */
#define VLFF_SIM_POINTS_RAYS (1u << 24)
int vlff_sim_points_budget(const struct vlff_sim *s, int nframes, int step, double voxel, uint64_t max_rays,
                           struct vlff_sim_points *out, char *err, size_t errlen);
void vlff_sim_points_free(struct vlff_sim_points *p);

#endif
