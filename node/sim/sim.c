/*
 * Procedural rooms, analytic ray casting and LSeg-like features.
 *
 * The scene is a list of primitives (axis-aligned boxes, vertical
 * cylinders) under a small BVH; walls, floor and ceiling are thin boxes just
 * outside the room so every ray from inside hits something. Every random
 * choice comes from a counter-based hash of (seed, purpose, index), so any
 * frame can be rendered alone, in any order, on any thread, and is
 * bit-identical every time.
 *
 * The feature model is built to make multi-view fusion matter: errors that
 * are independent per frame (noise, confusion patches) or per viewing
 * direction (view-dependent confusions) average out over views; errors
 * shared by every view (boundary blur, the prototypes' own similarity) do
 * not.
 */
#include "sim.h"

#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <strings.h>

#include "field.h" /* float16 conversions */
#include "hash.h"
#include "hot.h"
#include "log.h"
#include "mem.h"
#include "rng.h"
#include "vlff/escape.h"

static const char *const class_names[VLFF_SIM_CLASSES] = {
    "wall",    "floor",       "cabinet", "bed",          "chair",          "sofa",   "table",
    "door",    "window",      "bookshelf", "picture",    "counter",        "desk",   "curtain",
    "refrigerator", "shower curtain", "toilet", "sink",  "bathtub",        "other furniture"};

enum { C_WALL, C_FLOOR, C_CABINET, C_BED, C_CHAIR, C_SOFA, C_TABLE, C_DOOR, C_WINDOW,
       C_BOOKSHELF, C_PICTURE, C_COUNTER, C_DESK, C_CURTAIN, C_FRIDGE, C_SHOWER, C_TOILET,
       C_SINK, C_BATHTUB, C_OTHER };

/* Prototype index for the unlabelled ceiling. */
#define P_CEIL VLFF_SIM_CLASSES
#define NPROTO (VLFF_SIM_CLASSES + 1)

/* The feature space is the same for every scene (like a fixed LSeg model),
 * so prompt embeddings written for one scene are valid for all. */
#define FEATURE_SPACE_SEED 0x5eed5eedu

enum { PRIM_BOX, PRIM_CYL };

/* The building's bounds: sim.flats <= 8 flats of 3 rooms and a corridor;
 * each flat's tour takes under 48 waypoints. */
#define MAX_FLATS 8
#define MAX_ROOMS (3 * MAX_FLATS + 1)
#define MAX_WAY (48 * MAX_FLATS + 8)

struct prim {
  int kind;
  int label;               /* class id or 255 */
  double lo[3], hi[3];     /* AABB (a cylinder's too) */
  double cx, cy, r;        /* cylinder axis (vertical) and radius */
  float albedo[3];
  int pattern;             /* 0 noise, 1 stripes, 2 checker, 3 grain */
  double tex_scale;
  uint32_t tex_seed;
  int obj;                 /* the object it belongs to (its feature bias) */
};

struct bvh_node {
  double lo[3], hi[3];
  int left, right;         /* children, or -1 for a leaf */
  int first, count;        /* leaf: prims[order[first..first+count)] */
};

/* The scene at a time (sim.changes): the primitives as built, moved where
 * the changes up to then put their objects (same indices), and a BVH over
 * those present. */
struct sim_world {
  double from_s;           /* in force from this sim time on */
  struct prim *prims;      /* [nprims] */
  struct bvh_node *nodes;
  int *order, count, nnodes; /* the present primitives (count of them) under nodes */
};

struct vlff_sim {
  struct vlff_cfg_sim cfg;
  uint32_t seed;
  int width, height, fw, fh, dim;
  double fx, fy, cx, cy;
  double room_lo[3], room_hi[3];
  double bbox_lo[3], bbox_hi[3];
  struct prim *prims;
  int nprims, cap;
  struct sim_world *worlds; /* [nworlds]: as built (before any change), then after each change */
  int nworlds;
  float *proto;            /* [NPROTO][D] unit */
  float *text;             /* [VLFF_SIM_CLASSES][D] unit */
  float *generic;          /* [D] the component every embedding shares */
  int partner[NPROTO];     /* the class each is most often confused with */
  float view_strength[NPROTO], view_phase[NPROTO];
  int class_counts[VLFF_SIM_CLASSES];
  /* Objects: every primitive carries the id current when it was added. */
  int cur_obj, nobj;
  float *obj_vec;          /* [nobj][D] view-consistent additive bias */
  float *obj_mix;          /* [nobj] weight moved toward obj_to */
  int *obj_to;             /* [nobj] the class an object's features lean to */
  /* Flat and building layouts: rooms (inside faces of their walls), the
   * flat each belongs to (-1: the building's corridor) and doorways. */
  int nrooms;
  double rooms[MAX_ROOMS][4];      /* x0 y0 x1 y1 */
  int room_flat[MAX_ROOMS];
  int nflats;
  double flats[MAX_FLATS][4];      /* each flat's inside, x0 y0 x1 y1 */
  int ndoors;
  double doors[MAX_ROOMS][2];      /* doorway centres in xy */
  int nway;
  double way[MAX_WAY][2];          /* closed walk through the rooms, xy */
  double way_len[MAX_WAY + 1];     /* cumulative length at each waypoint */
};

/* ---- deterministic randomness ------------------------------------------ */

static uint64_t hash3(uint64_t a, uint64_t b, uint64_t c) {
  return vlff_mix64(a ^ vlff_mix64(b ^ vlff_mix64(c)));
}

struct rng {
  uint64_t s;
};

static struct rng rng_make(uint64_t a, uint64_t b, uint64_t c) {
  struct rng r = {hash3(a, b, c)};
  return r;
}

static uint64_t rng_u64(struct rng *r) { return vlff_rng_next(&r->s); }

static double rng_uniform(struct rng *r) { return vlff_rng_double(&r->s); }

static double rng_range(struct rng *r, double lo, double hi) { return lo + (hi - lo) * rng_uniform(r); }

static double rng_normal(struct rng *r) {
  double u1 = rng_uniform(r), u2 = rng_uniform(r);
  if (u1 < 1e-300) u1 = 1e-300;
  return sqrt(-2.0 * log(u1)) * cos(2.0 * M_PI * u2);
}

/* ---- small vector helpers ---------------------------------------------- */

static void normalize_f(float *v, int n) {
  double s = 0;
  for (int i = 0; i < n; i++) s += (double)v[i] * v[i];
  s = s > 0 ? 1.0 / sqrt(s) : 0;
  for (int i = 0; i < n; i++) v[i] = (float)(v[i] * s);
}

static void random_unit(struct rng *r, float *v, int n) {
  for (int i = 0; i < n; i++) v[i] = (float)rng_normal(r);
  normalize_f(v, n);
}

static void cross3(const double a[3], const double b[3], double o[3]) {
  o[0] = a[1] * b[2] - a[2] * b[1];
  o[1] = a[2] * b[0] - a[0] * b[2];
  o[2] = a[0] * b[1] - a[1] * b[0];
}

static void norm3(double v[3]) {
  double n = sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
  if (n > 0) v[0] /= n, v[1] /= n, v[2] /= n;
}

/* ---- scene construction ------------------------------------------------ */

static struct prim *add_prim(struct vlff_sim *s, int kind, int label) {
  if (s->nprims == s->cap) {
    int cap = s->cap ? 2 * s->cap : 64;
    struct prim *p = realloc(s->prims, (size_t)cap * sizeof *p);
    if (!p) return NULL;
    s->prims = p;
    s->cap = cap;
  }
  struct prim *p = &s->prims[s->nprims++];
  memset(p, 0, sizeof *p);
  p->kind = kind;
  p->label = label;
  p->obj = s->cur_obj;
  return p;
}

/* Per-class base colours: plausible, and distinct enough that colour alone
 * hints at the class the way it does in real rooms. */
static const float class_rgb[VLFF_SIM_CLASSES][3] = {
    {0.82f, 0.80f, 0.74f}, {0.55f, 0.40f, 0.28f}, {0.62f, 0.48f, 0.34f}, {0.70f, 0.72f, 0.85f},
    {0.35f, 0.22f, 0.15f}, {0.45f, 0.30f, 0.50f}, {0.60f, 0.42f, 0.25f}, {0.88f, 0.86f, 0.80f},
    {0.70f, 0.85f, 0.95f}, {0.40f, 0.28f, 0.18f}, {0.85f, 0.55f, 0.30f}, {0.75f, 0.75f, 0.72f},
    {0.50f, 0.36f, 0.22f}, {0.75f, 0.30f, 0.30f}, {0.92f, 0.92f, 0.94f}, {0.55f, 0.75f, 0.80f},
    {0.96f, 0.96f, 0.96f}, {0.90f, 0.90f, 0.92f}, {0.93f, 0.93f, 0.90f}, {0.45f, 0.50f, 0.35f}};

static void style(struct vlff_sim *s, struct prim *p, struct rng *r) {
  const float *base = p->label < VLFF_SIM_CLASSES ? class_rgb[p->label] : (const float[3]){0.9f, 0.9f, 0.88f};
  for (int i = 0; i < 3; i++) {
    double v = base[i] * rng_range(r, 0.8, 1.15);
    p->albedo[i] = (float)(v < 0.02 ? 0.02 : v > 0.98 ? 0.98 : v);
  }
  p->pattern = (int)(rng_u64(r) % 4);
  p->tex_scale = rng_range(r, 3.0, 12.0);
  p->tex_seed = (uint32_t)rng_u64(r);
  (void)s;
}

static struct prim *box(struct vlff_sim *s, struct rng *r, int label, double x0, double y0,
                        double z0, double x1, double y1, double z1) {
  struct prim *p = add_prim(s, PRIM_BOX, label);
  if (!p) return NULL;
  p->lo[0] = fmin(x0, x1), p->hi[0] = fmax(x0, x1);
  p->lo[1] = fmin(y0, y1), p->hi[1] = fmax(y0, y1);
  p->lo[2] = fmin(z0, z1), p->hi[2] = fmax(z0, z1);
  style(s, p, r);
  return p;
}

static struct prim *cyl(struct vlff_sim *s, struct rng *r, int label, double cx, double cy,
                        double rad, double z0, double z1) {
  struct prim *p = add_prim(s, PRIM_CYL, label);
  if (!p) return NULL;
  p->cx = cx, p->cy = cy, p->r = rad;
  p->lo[0] = cx - rad, p->hi[0] = cx + rad;
  p->lo[1] = cy - rad, p->hi[1] = cy + rad;
  p->lo[2] = z0, p->hi[2] = z1;
  style(s, p, r);
  return p;
}

/* A footprint on the floor, in world xy, and the wall it stands against
 * (0: y=min, 1: y=max, 2: x=min, 3: x=max, -1: free-standing). */
struct spot {
  double x0, y0, x1, y1;
  int wall;
};

struct top {
  double x0, y0, x1, y1, z;
};

struct layout {
  const double *lo, *hi;      /* the room being furnished (inside faces) */
  struct spot used[64];
  int nused;
  struct spot wall_used[32];  /* wall-mounted items, as spans on the walls */
  int nwall;
  struct top tops[16];
  int ntops;
};

static int overlaps(const struct spot *a, const struct spot *b, double gap) {
  return a->x0 < b->x1 + gap && b->x0 < a->x1 + gap && a->y0 < b->y1 + gap && b->y0 < a->y1 + gap;
}

/* Place a w (along the wall) x d (away from it) footprint against a random
 * wall, or free-standing when wall < 0 is asked for (wall = -1). Returns 0
 * when no free place was found in a bounded number of tries. */
static int place(struct vlff_sim *s, struct layout *L, struct rng *r, double w, double d,
                 int against_wall, double gap, struct spot *out) {
  const double *lo = L->lo, *hi = L->hi;
  for (int tries = 0; tries < 300; tries++) {
    struct spot sp;
    /* crowded rooms: shrink the item a little after every 100 failures */
    if (tries && tries % 100 == 0) w *= 0.85, d *= 0.85;
    if (against_wall) {
      int wall = (int)(rng_u64(r) % 4);
      double len = wall < 2 ? hi[0] - lo[0] : hi[1] - lo[1];
      if (w > len - 0.2) continue;
      double a = rng_range(r, (wall < 2 ? lo[0] : lo[1]) + 0.05,
                           (wall < 2 ? hi[0] : hi[1]) - 0.05 - w);
      switch (wall) {
      case 0: sp = (struct spot){a, lo[1], a + w, lo[1] + d, 0}; break;
      case 1: sp = (struct spot){a, hi[1] - d, a + w, hi[1], 1}; break;
      case 2: sp = (struct spot){lo[0], a, lo[0] + d, a + w, 2}; break;
      default: sp = (struct spot){hi[0] - d, a, hi[0], a + w, 3}; break;
      }
    } else {
      double ww = rng_uniform(r) < 0.5 ? w : d, dd = ww == w ? d : w;
      double cxm = 0.5 * (lo[0] + hi[0]), cym = 0.5 * (lo[1] + hi[1]);
      double hx = 0.5 * (hi[0] - lo[0]) - 0.5 - ww / 2, hy = 0.5 * (hi[1] - lo[1]) - 0.5 - dd / 2;
      if (hx <= 0 || hy <= 0) continue;
      double x = rng_range(r, cxm - hx, cxm + hx), y = rng_range(r, cym - hy, cym + hy);
      sp = (struct spot){x - ww / 2, y - dd / 2, x + ww / 2, y + dd / 2, -1};
    }
    int ok = 1;
    for (int i = 0; i < L->nused && ok; i++)
      if (overlaps(&sp, &L->used[i], gap)) ok = 0;
    if (!ok) continue;
    if (L->nused < (int)(sizeof L->used / sizeof L->used[0])) L->used[L->nused++] = sp;
    *out = sp;
    s->cur_obj++; /* every placed item is a new object */
    return 1;
  }
  return 0;
}

/* A span on a wall for flat wall-mounted items (windows, pictures): they
 * only need the wall free at their height, tracked separately. */
static int place_on_wall(struct vlff_sim *s, struct layout *L, struct rng *r, double w,
                         struct spot *out) {
  for (int tries = 0; tries < 200; tries++) {
    struct spot sp;
    if (!place(s, &(struct layout){.lo = L->lo, .hi = L->hi, .nused = 0}, r, w, 0.02, 1, 0, &sp)) return 0;
    int ok = 1;
    for (int i = 0; i < L->nwall && ok; i++)
      if (overlaps(&sp, &L->wall_used[i], 0.15)) ok = 0;
    if (!ok) continue;
    if (L->nwall < (int)(sizeof L->wall_used / sizeof L->wall_used[0])) L->wall_used[L->nwall++] = sp;
    *out = sp;
    return 1;
  }
  return 0;
}

/* Shrink a spot to its part within `depth` of the wall and offset `off`
 * from it (for items mounted on or standing off a wall). */
static struct spot wall_slab(const struct spot *sp, double off, double depth) {
  struct spot o = *sp;
  switch (sp->wall) {
  case 0: o.y0 = sp->y0 + off, o.y1 = sp->y0 + off + depth; break;
  case 1: o.y1 = sp->y1 - off, o.y0 = sp->y1 - off - depth; break;
  case 2: o.x0 = sp->x0 + off, o.x1 = sp->x0 + off + depth; break;
  case 3: o.x1 = sp->x1 - off, o.x0 = sp->x1 - off - depth; break;
  default: break;
  }
  return o;
}

static void legs(struct vlff_sim *s, struct rng *r, int label, const struct spot *sp, double z0,
                 double z1, double t) {
  double xs[2] = {sp->x0, sp->x1 - t}, ys[2] = {sp->y0, sp->y1 - t};
  for (int i = 0; i < 2; i++)
    for (int j = 0; j < 2; j++) box(s, r, label, xs[i], ys[j], z0, xs[i] + t, ys[j] + t, z1);
}

/* Shell: walls, floor, ceiling as thin boxes outside lo..hi, each its own
 * object. */
static void shell(struct vlff_sim *s, struct rng *r, const double *lo, const double *hi) {
  const double t = 0.1, fz = lo[2];
  int first = s->nprims;
  s->cur_obj++;
  box(s, r, C_WALL, lo[0] - t, lo[1] - t, fz - t, hi[0] + t, lo[1], hi[2] + t);
  s->cur_obj++;
  box(s, r, C_WALL, lo[0] - t, hi[1], fz - t, hi[0] + t, hi[1] + t, hi[2] + t);
  s->cur_obj++;
  box(s, r, C_WALL, lo[0] - t, lo[1], fz - t, lo[0], hi[1], hi[2] + t);
  s->cur_obj++;
  box(s, r, C_WALL, hi[0], lo[1], fz - t, hi[0] + t, hi[1], hi[2] + t);
  s->cur_obj++;
  box(s, r, C_FLOOR, lo[0], lo[1], fz - t, hi[0], hi[1], fz);
  s->cur_obj++;
  box(s, r, VLFF_SIM_UNLABELLED, lo[0], lo[1], hi[2], hi[0], hi[1], hi[2] + t);
  for (int i = first; i < first + 6 && i < s->nprims; i++)
    s->prims[i].pattern = i < first + 4 ? 0 : s->prims[i].pattern;
}

/* What furnish() puts in a room. F_ROOM is today's single room; the rest
 * furnish the flat's rooms (small, thin and hand-sized things). */
enum {
  F_DOOR = 1 << 0, F_DESK = 1 << 1, F_DINING = 1 << 2, F_BED = 1 << 3, F_SOFA = 1 << 4, F_BATH = 1 << 5,
  F_COUNTER = 1 << 6, F_FRIDGE = 1 << 7, F_SHELF = 1 << 8, F_CABINET = 1 << 9, F_TOILET = 1 << 10,
  F_OTHER = 1 << 11, F_WINDOW = 1 << 12, F_PICTURES = 1 << 13, F_ROOM = (1 << 14) - 1,
  F_LAMPS = 1 << 14, F_SMALL = 1 << 15, F_VANITY = 1 << 16, F_MORE_CHAIRS = 1 << 17
};

/* A horizontal top small objects can stand on. */
static void add_top(struct layout *L, double x0, double y0, double x1, double y1, double z) {
  if (L->ntops < (int)(sizeof L->tops / sizeof L->tops[0]))
    L->tops[L->ntops++] = (struct top){fmin(x0, x1), fmin(y0, y1), fmax(x0, x1), fmax(y0, y1), z};
}

/* A chair with four legs, its back on the side back_dir names (0: +x,
 * 1: -x, 2: +y, 3: -y). */
static void chair(struct vlff_sim *s, struct rng *r, double cx, double cy, double half, double fz,
                  int back_dir) {
  s->cur_obj++;
  struct spot c = {cx - half, cy - half, cx + half, cy + half, -1};
  double zs = fz + 0.43;
  box(s, r, C_CHAIR, c.x0, c.y0, zs, c.x1, c.y1, zs + 0.05);
  legs(s, r, C_CHAIR, &c, fz, zs, 0.04);
  struct spot b = c;
  switch (back_dir) {
  case 0: b.x0 = b.x1 - 0.05; break;
  case 1: b.x1 = b.x0 + 0.05; break;
  case 2: b.y0 = b.y1 - 0.05; break;
  default: b.y1 = b.y0 + 0.05; break;
  }
  box(s, r, C_CHAIR, b.x0, b.y0, zs + 0.05, b.x1, b.y1, zs + 0.47);
}

/* The door (with a clearance zone kept) and a desk with its chair, against
 * walls: bigger items first, so that they find room. */
static void furnish_door_desk(struct vlff_sim *s, struct rng *r, struct layout *L, unsigned what, double fz) {
  struct spot sp;
  /* Bigger items first so they find room; door keeps a clearance zone. */
  if ((what & F_DOOR) && place(s, L, r, rng_range(r, 0.8, 1.0), 0.7, 1, 0.1, &sp)) {
    struct spot d = wall_slab(&sp, -0.005, 0.045);
    box(s, r, C_DOOR, d.x0, d.y0, fz, d.x1, d.y1, fz + rng_range(r, 1.95, 2.1));
    if (L->nwall < 32) L->wall_used[L->nwall++] = sp;
  }
  if ((what & F_DESK) && place(s, L, r, rng_range(r, 1.1, 1.4), 0.65, 1, 0.5, &sp)) {
    double zt = fz + 0.74;
    box(s, r, C_DESK, sp.x0, sp.y0, zt - 0.04, sp.x1, sp.y1, zt);
    add_top(L, sp.x0, sp.y0, sp.x1, sp.y1, zt);
    legs(s, r, C_DESK, &sp, fz, zt - 0.04, 0.05);
    /* a chair in front of the desk */
    double cx = 0.5 * (sp.x0 + sp.x1), cy = 0.5 * (sp.y0 + sp.y1);
    double dx = sp.wall == 2 ? 0.65 : sp.wall == 3 ? -0.65 : 0;
    double dy = sp.wall == 0 ? 0.65 : sp.wall == 1 ? -0.65 : 0;
    struct spot c = {cx + dx - 0.22, cy + dy - 0.22, cx + dx + 0.22, cy + dy + 0.22, -1};
    s->cur_obj++;
    box(s, r, C_CHAIR, c.x0, c.y0, fz + 0.42, c.x1, c.y1, fz + 0.47);
    legs(s, r, C_CHAIR, &c, fz, fz + 0.42, 0.04);
    struct spot back = c;
    if (dx > 0) back.x0 = back.x1 - 0.05;
    else if (dx < 0) back.x1 = back.x0 + 0.05;
    else if (dy > 0) back.y0 = back.y1 - 0.05;
    else back.y1 = back.y0 + 0.05;
    box(s, r, C_CHAIR, back.x0, back.y0, fz + 0.47, back.x1, back.y1, fz + 0.9);
    if (L->nused < 64) L->used[L->nused++] = c;
  }
}

/* A free-standing dining table with chairs. */
static void furnish_dining(struct vlff_sim *s, struct rng *r, struct layout *L, unsigned what, double fz) {
  struct spot sp;
  if ((what & F_DINING) && place(s, L, r, rng_range(r, 1.0, 1.4), rng_range(r, 0.7, 0.9), 0, 0.7, &sp)) {
    double zt = fz + 0.75;
    box(s, r, C_TABLE, sp.x0, sp.y0, zt - 0.05, sp.x1, sp.y1, zt);
    add_top(L, sp.x0, sp.y0, sp.x1, sp.y1, zt);
    legs(s, r, C_TABLE, &sp, fz, zt - 0.05, 0.06);
    int along_x = sp.x1 - sp.x0 > sp.y1 - sp.y0;
    for (int side = 0; side < 2; side++) {
      double cx = 0.5 * (sp.x0 + sp.x1), cy = 0.5 * (sp.y0 + sp.y1);
      double o = side ? 1 : -1;
      if (along_x) cy += o * (0.5 * (sp.y1 - sp.y0) + 0.3);
      else cx += o * (0.5 * (sp.x1 - sp.x0) + 0.3);
      struct spot c = {cx - 0.21, cy - 0.21, cx + 0.21, cy + 0.21, -1};
      s->cur_obj++;
      box(s, r, C_CHAIR, c.x0, c.y0, fz + 0.43, c.x1, c.y1, fz + 0.48);
      legs(s, r, C_CHAIR, &c, fz, fz + 0.43, 0.04);
      struct spot back = c;
      if (along_x) {
        if (o > 0) back.y0 = back.y1 - 0.05; else back.y1 = back.y0 + 0.05;
      } else {
        if (o > 0) back.x0 = back.x1 - 0.05; else back.x1 = back.x0 + 0.05;
      }
      box(s, r, C_CHAIR, back.x0, back.y0, fz + 0.48, back.x1, back.y1, fz + 0.92);
    }
    /* and one at each end */
    if (what & F_MORE_CHAIRS)
      for (int side = 0; side < 2; side++) {
        double cx = 0.5 * (sp.x0 + sp.x1), cy = 0.5 * (sp.y0 + sp.y1);
        double o = side ? 1 : -1;
        if (along_x) cx += o * (0.5 * (sp.x1 - sp.x0) + 0.28);
        else cy += o * (0.5 * (sp.y1 - sp.y0) + 0.28);
        chair(s, r, cx, cy, 0.2, fz, along_x ? (o > 0 ? 0 : 1) : (o > 0 ? 2 : 3));
      }
  }
}

/* The large pieces against walls: bed, sofa, bathtub, counter, fridge,
 * shelf, cabinets, toilet. */
static void furnish_large(struct vlff_sim *s, struct rng *r, struct layout *L, unsigned what, double fz) {
  struct spot sp;
  if ((what & F_BED) && place(s, L, r, rng_range(r, 1.9, 2.1), rng_range(r, 1.0, 1.4), 1, 0.2, &sp)) {
    box(s, r, C_BED, sp.x0, sp.y0, fz, sp.x1, sp.y1, fz + rng_range(r, 0.45, 0.6));
    struct spot h = sp;
    if (sp.wall < 2) h.x1 = h.x0 + 0.08;
    else h.y1 = h.y0 + 0.08;
    box(s, r, C_BED, h.x0, h.y0, fz, h.x1, h.y1, fz + rng_range(r, 0.9, 1.1));
  }
  if ((what & F_SOFA) && place(s, L, r, rng_range(r, 1.6, 2.0), rng_range(r, 0.8, 0.9), 1, 0.2, &sp)) {
    double zs = fz + 0.42, zb = fz + rng_range(r, 0.8, 0.95);
    box(s, r, C_SOFA, sp.x0, sp.y0, fz, sp.x1, sp.y1, zs);
    struct spot b = wall_slab(&sp, 0, 0.22);
    box(s, r, C_SOFA, b.x0, b.y0, zs, b.x1, b.y1, zb);
    /* arms at the two ends along the wall */
    int along_x = sp.wall < 2;
    double a = 0.18;
    if (along_x) {
      box(s, r, C_SOFA, sp.x0, sp.y0, zs, sp.x0 + a, sp.y1, zs + 0.2);
      box(s, r, C_SOFA, sp.x1 - a, sp.y0, zs, sp.x1, sp.y1, zs + 0.2);
    } else {
      box(s, r, C_SOFA, sp.x0, sp.y0, zs, sp.x1, sp.y0 + a, zs + 0.2);
      box(s, r, C_SOFA, sp.x0, sp.y1 - a, zs, sp.x1, sp.y1, zs + 0.2);
    }
  }
  if ((what & F_BATH) && place(s, L, r, rng_range(r, 1.5, 1.7), rng_range(r, 0.7, 0.8), 1, 0.1, &sp)) {
    double zt = fz + rng_range(r, 0.5, 0.6);
    box(s, r, C_BATHTUB, sp.x0, sp.y0, fz, sp.x1, sp.y1, zt);
    /* shower curtain hanging along the tub's open side */
    struct spot c = wall_slab(&sp, (sp.wall < 2 ? sp.y1 - sp.y0 : sp.x1 - sp.x0) - 0.03, 0.02);
    box(s, r, C_SHOWER, c.x0, c.y0, zt + 0.15, c.x1, c.y1, fz + 2.0);
  }
  if ((what & F_COUNTER) && place(s, L, r, rng_range(r, 1.4, 2.0), 0.6, 1, 0.1, &sp)) {
    double zc = fz + rng_range(r, 0.88, 0.95);
    box(s, r, C_COUNTER, sp.x0, sp.y0, fz, sp.x1, sp.y1, zc);
    /* a sink basin set into the counter top */
    double cx = 0.5 * (sp.x0 + sp.x1), cy = 0.5 * (sp.y0 + sp.y1);
    s->cur_obj++;
    box(s, r, C_SINK, cx - 0.25, cy - 0.2, zc, cx + 0.25, cy + 0.2, zc + 0.12);
  }
  if ((what & F_FRIDGE) && place(s, L, r, rng_range(r, 0.7, 0.8), 0.7, 1, 0.1, &sp))
    box(s, r, C_FRIDGE, sp.x0, sp.y0, fz, sp.x1, sp.y1, fz + rng_range(r, 1.7, 1.9));
  if ((what & F_SHELF) && place(s, L, r, rng_range(r, 0.8, 1.2), 0.35, 1, 0.1, &sp)) {
    double zt = fz + rng_range(r, 1.6, 2.0);
    box(s, r, C_BOOKSHELF, sp.x0, sp.y0, fz, sp.x1, sp.y1, zt);
  }
  for (int i = 0, n = (what & F_CABINET) ? 1 + (int)(rng_u64(r) % 2) : 0; i < n; i++)
    if (place(s, L, r, rng_range(r, 0.6, 1.0), 0.5, 1, 0.1, &sp)) {
      double zt = fz + rng_range(r, 0.7, 1.0);
      box(s, r, C_CABINET, sp.x0, sp.y0, fz, sp.x1, sp.y1, zt);
      add_top(L, sp.x0, sp.y0, sp.x1, sp.y1, zt);
    }
  if ((what & F_TOILET) && place(s, L, r, 0.45, 0.7, 1, 0.15, &sp)) {
    double cx = 0.5 * (sp.x0 + sp.x1), cy = 0.5 * (sp.y0 + sp.y1);
    cyl(s, r, C_TOILET, cx, cy, 0.2, fz, fz + 0.42);
    struct spot tank = wall_slab(&sp, 0, 0.2);
    box(s, r, C_TOILET, tank.x0, tank.y0, fz + 0.3, tank.x1, tank.y1, fz + 0.8);
  }
}

/* The lighter pieces: side tables, wall-mounted window and pictures, a
 * vanity, floor lamps. */
static void furnish_lighter(struct vlff_sim *s, struct rng *r, struct layout *L, unsigned what, double fz) {
  const double *lo = L->lo, *hi = L->hi;
  struct spot sp;
  for (int i = 0, n = (what & F_OTHER) ? 1 + (int)(rng_u64(r) % 2) : 0; i < n; i++) {
    if (!place(s, L, r, 0.5, 0.5, i & 1, 0.3, &sp)) continue;
    double cx = 0.5 * (sp.x0 + sp.x1), cy = 0.5 * (sp.y0 + sp.y1);
    if (rng_uniform(r) < 0.5) cyl(s, r, C_OTHER, cx, cy, 0.24, fz, fz + rng_range(r, 0.4, 0.6));
    else box(s, r, C_OTHER, sp.x0, sp.y0, fz, sp.x1, sp.y1, fz + rng_range(r, 0.4, 0.6));
  }
  /* Wall-mounted: window with a curtain beside it, pictures. */
  if ((what & F_WINDOW) && place_on_wall(s, L, r, rng_range(r, 0.9, 1.3), &sp)) {
    struct spot w = wall_slab(&sp, -0.01, 0.03);
    double z0 = fz + rng_range(r, 0.9, 1.1), z1 = fmin(z0 + rng_range(r, 1.0, 1.3), hi[2] - 0.15);
    box(s, r, C_WINDOW, w.x0, w.y0, z0, w.x1, w.y1, z1);
    struct spot c = wall_slab(&sp, 0.05, 0.04);
    double cw = 0.35;
    if (sp.wall < 2) c.x1 = c.x0, c.x0 -= cw; else c.y1 = c.y0, c.y0 -= cw;
    s->cur_obj++;
    if (c.x0 > lo[0] && c.y0 > lo[1]) box(s, r, C_CURTAIN, c.x0, c.y0, fz + 0.3, c.x1, c.y1, z1 + 0.1);
  }
  for (int i = 0, n = (what & F_PICTURES) ? 2 + (int)(rng_u64(r) % 2) : 0; i < n; i++)
    if (place_on_wall(s, L, r, rng_range(r, 0.4, 0.8), &sp)) {
      struct spot p = wall_slab(&sp, 0, 0.025);
      double z0 = fz + rng_range(r, 1.3, 1.6);
      box(s, r, C_PICTURE, p.x0, p.y0, z0, p.x1, p.y1, z0 + rng_range(r, 0.3, 0.6));
    }
  /* A bathroom vanity: a small cabinet with a basin on it. */
  if ((what & F_VANITY) && place(s, L, r, rng_range(r, 0.55, 0.75), 0.45, 1, 0.1, &sp)) {
    double zc = fz + rng_range(r, 0.8, 0.86);
    box(s, r, C_CABINET, sp.x0, sp.y0, fz, sp.x1, sp.y1, zc);
    double cx = 0.5 * (sp.x0 + sp.x1), cy = 0.5 * (sp.y0 + sp.y1);
    s->cur_obj++;
    box(s, r, C_SINK, cx - 0.2, cy - 0.16, zc, cx + 0.2, cy + 0.16, zc + 0.14);
  }
  /* Floor lamps: a thin pole on a disc under a shade, against a wall. */
  for (int i = 0, n = (what & F_LAMPS) ? 1 + (int)(rng_u64(r) % 2) : 0; i < n; i++)
    if (place(s, L, r, 0.36, 0.36, 1, 0.1, &sp)) {
      double cx = 0.5 * (sp.x0 + sp.x1), cy = 0.5 * (sp.y0 + sp.y1), h = rng_range(r, 1.4, 1.7);
      cyl(s, r, C_OTHER, cx, cy, 0.14, fz, fz + 0.03);
      cyl(s, r, C_OTHER, cx, cy, 0.015, fz + 0.03, fz + h - 0.2);
      cyl(s, r, C_OTHER, cx, cy, rng_range(r, 0.13, 0.18), fz + h - 0.22, fz + h);
    }
}

/* Hand-sized things on the tops the pieces above left: cups, books, boxes. */
static void furnish_tops(struct vlff_sim *s, struct rng *r, struct layout *L, unsigned what, double fz) {
  for (int t = 0; (what & F_SMALL) && t < L->ntops; t++) {
    const struct top *tp = &L->tops[t];
    for (int i = 0, n = 1 + (int)(rng_u64(r) % 3); i < n; i++) {
      double hw = rng_range(r, 0.03, 0.08), hd = rng_range(r, 0.03, 0.08), h = rng_range(r, 0.06, 0.25);
      if (tp->x1 - tp->x0 < 2 * hw + 0.04 || tp->y1 - tp->y0 < 2 * hd + 0.04) continue;
      double cx = rng_range(r, tp->x0 + hw + 0.02, tp->x1 - hw - 0.02);
      double cy = rng_range(r, tp->y0 + hd + 0.02, tp->y1 - hd - 0.02);
      s->cur_obj++;
      if (rng_uniform(r) < 0.4) cyl(s, r, C_OTHER, cx, cy, fmin(hw, hd), tp->z, tp->z + h);
      else box(s, r, C_OTHER, cx - hw, cy - hd, tp->z, cx + hw, cy + hd, tp->z + h);
    }
  }
}

/* Furniture for what (F_ flags) in the layout's box, drawn from *rr in a
 * fixed order (a seed gives the same room), stage by stage. */
static void furnish(struct vlff_sim *s, struct rng *rr, struct layout *L, unsigned what) {
  struct rng r = *rr;
  double fz = L->lo[2];
  furnish_door_desk(s, &r, L, what, fz);
  furnish_dining(s, &r, L, what, fz);
  furnish_large(s, &r, L, what, fz);
  furnish_lighter(s, &r, L, what, fz);
  furnish_tops(s, &r, L, what, fz);
  *rr = r;
}

static void build_room(struct vlff_sim *s, int attempt) {
  struct rng r = rng_make(s->seed, 1, (uint64_t)attempt);
  s->nprims = 0, s->cur_obj = 0;
  shell(s, &r, s->room_lo, s->room_hi);
  struct layout L = {.lo = s->room_lo, .hi = s->room_hi};
  furnish(s, &r, &L, F_ROOM);
}

/* Keep a doorway free on one side of a wall: nothing stands in front of
 * it and nothing hangs over it. wall: the room's wall the doorway is in
 * (0: y=min, 1: y=max, 2: x=min, 3: x=max); c: its centre along the wall. */
static void keep_clear(struct layout *L, int wall, double c, double half) {
  const double *lo = L->lo, *hi = L->hi, deep = 1.1;
  struct spot sp;
  switch (wall) {
  case 0: sp = (struct spot){c - half, lo[1], c + half, lo[1] + deep, 0}; break;
  case 1: sp = (struct spot){c - half, hi[1] - deep, c + half, hi[1], 1}; break;
  case 2: sp = (struct spot){lo[0], c - half, lo[0] + deep, c + half, 2}; break;
  default: sp = (struct spot){hi[0] - deep, c - half, hi[0], c + half, 3}; break;
  }
  if (L->nused < (int)(sizeof L->used / sizeof L->used[0])) L->used[L->nused++] = sp;
  if (L->nwall < (int)(sizeof L->wall_used / sizeof L->wall_used[0])) L->wall_used[L->nwall++] = sp;
}

/* One flat's plan: where its interior walls and doorways are, and the
 * first of its three rooms in s->rooms (living room, bedroom, bathroom). */
struct flat_plan {
  double ys, yb, yt, wx0, wx1;
  int entrance;      /* a doorway in its y=lo[1] wall onto the building's corridor */
  double xe;         /* that doorway's centre in x */
  int room0;
};

/* A flat inside lo..hi (the inside faces of walls that already stand): the
 * box split by interior walls into a living room (with a kitchen corner) on
 * one side and a bedroom and a bathroom on the other, each opening onto the
 * living room through a doorway with its door leaf standing open.
 * Furniture keeps the doorways clear. fp->entrance asks for a doorway onto
 * the corridor too (the building); the lone flat draws nothing for it, so
 * its seeds give the same flat as before the building existed. */
static void flat_inside(struct vlff_sim *s, struct rng *r, const double *lo, const double *hi, int flat_id,
                        struct flat_plan *fp) {
  const double tw = 0.1, dw = 0.9, dh = 2.05, fz = lo[2], hz = hi[2];
  double xs = lo[0] + (hi[0] - lo[0]) * rng_range(r, 0.5, 0.6);
  double ys = lo[1] + (hi[1] - lo[1]) * rng_range(r, 0.42, 0.58);
  double yb = rng_range(r, ys + tw / 2 + 0.7, hi[1] - 0.7);  /* bedroom doorway */
  double yt = rng_range(r, lo[1] + 0.7, ys - tw / 2 - 0.7);  /* bathroom doorway */
  double wx0 = xs - tw / 2, wx1 = xs + tw / 2;
  /* the entrance, clear of the living room's corners */
  if (fp->entrance) fp->xe = rng_range(r, lo[0] + 1.0, wx0 - 1.0);
  /* wall between the living room and the rest, with two openings */
  s->cur_obj++;
  box(s, r, C_WALL, wx0, lo[1], fz, wx1, yt - dw / 2, hz);
  s->cur_obj++;
  box(s, r, C_WALL, wx0, yt + dw / 2, fz, wx1, yb - dw / 2, hz);
  s->cur_obj++;
  box(s, r, C_WALL, wx0, yb + dw / 2, fz, wx1, hi[1], hz);
  s->cur_obj++;
  box(s, r, C_WALL, wx0, yt - dw / 2, fz + dh, wx1, yt + dw / 2, hz);
  s->cur_obj++;
  box(s, r, C_WALL, wx0, yb - dw / 2, fz + dh, wx1, yb + dw / 2, hz);
  /* wall between bedroom and bathroom */
  s->cur_obj++;
  box(s, r, C_WALL, wx1, ys - tw / 2, fz, hi[0], ys + tw / 2, hz);
  for (int i = s->nprims - 6; i < s->nprims; i++) s->prims[i].pattern = 0;
  /* door leaves standing open into the bedroom and the bathroom */
  s->cur_obj++;
  box(s, r, C_DOOR, wx1, yb + dw / 2, fz, wx1 + 0.85, yb + dw / 2 + 0.04, fz + dh - 0.02);
  s->cur_obj++;
  box(s, r, C_DOOR, wx1, yt - dw / 2 - 0.04, fz, wx1 + 0.85, yt - dw / 2, fz + dh - 0.02);
  /* and the entrance's, open into the living room against its -x jamb
   * (away from the bathroom doorway the walk heads for) */
  if (fp->entrance) {
    s->cur_obj++;
    box(s, r, C_DOOR, fp->xe - dw / 2 - 0.04, lo[1], fz, fp->xe - dw / 2, lo[1] + 0.85, fz + dh - 0.02);
  }

  double rl[3][3] = {{lo[0], lo[1], fz}, {wx1, ys + tw / 2, fz}, {wx1, lo[1], fz}};
  double rh[3][3] = {{wx0, hi[1], hz}, {hi[0], hi[1], hz}, {hi[0], ys - tw / 2, hz}};
  static const unsigned what[3] = {
      F_DOOR | F_DINING | F_MORE_CHAIRS | F_SOFA | F_COUNTER | F_FRIDGE | F_SHELF | F_CABINET | F_OTHER | F_WINDOW |
          F_PICTURES | F_LAMPS | F_SMALL,
      F_BED | F_DESK | F_CABINET | F_OTHER | F_WINDOW | F_PICTURES | F_LAMPS | F_SMALL,
      F_BATH | F_TOILET | F_VANITY | F_PICTURES | F_SMALL};
  fp->room0 = s->nrooms;
  for (int k = 0; k < 3; k++) {
    struct layout L = {.lo = rl[k], .hi = rh[k]};
    if (k == 0) keep_clear(&L, 3, yb, 0.6), keep_clear(&L, 3, yt, 0.6);
    else keep_clear(&L, 2, k == 1 ? yb : yt, 0.65);
    if (k == 0 && fp->entrance) keep_clear(&L, 0, fp->xe, 0.6);
    furnish(s, r, &L, what[k]);
    double *rm = s->rooms[s->nrooms];
    rm[0] = rl[k][0], rm[1] = rl[k][1], rm[2] = rh[k][0], rm[3] = rh[k][1];
    s->room_flat[s->nrooms++] = flat_id;
  }
  s->doors[s->ndoors][0] = xs, s->doors[s->ndoors++][1] = yb;
  s->doors[s->ndoors][0] = xs, s->doors[s->ndoors++][1] = yt;
  if (fp->entrance) s->doors[s->ndoors][0] = fp->xe, s->doors[s->ndoors++][1] = lo[1] - tw / 2;
  fp->ys = ys, fp->yb = yb, fp->yt = yt, fp->wx0 = wx0, fp->wx1 = wx1;
}

static void way_add(struct vlff_sim *s, double x, double y) {
  if (s->nway < MAX_WAY) s->way[s->nway][0] = x, s->way[s->nway][1] = y, s->nway++;
}

/* A flat's tour: a loop in the living room, through the bedroom doorway, a
 * loop there and back, the same for the bathroom. It starts (and its living
 * room loop ends) on the loop's side facing the doorways; it ends in the
 * living room in front of the bathroom doorway.
 *  - scale: the loops' half-axes as a fraction of their room's sides;
 *  - past: how far beyond the doorways the walk turns toward a loop (beyond
 *    the 0.85-m door leaves, or a turn toward a loop close to a leaf can
 *    cut through it);
 *  - living_loop 0: cross the living room through its middle instead of
 *    looping (the building's walk crosses each living room three times). */
static void flat_tour(struct vlff_sim *s, const struct flat_plan *fp, double scale, double past, int living_loop) {
  for (int room = 0; room < 3; room++) {
    const double *rm = s->rooms[fp->room0 + room];
    double cx = 0.5 * (rm[0] + rm[2]), cy = 0.5 * (rm[1] + rm[3]);
    double ax = scale * (rm[2] - rm[0]), ay = scale * (rm[3] - rm[1]);
    double yd = room == 1 ? fp->yb : fp->yt;
    /* a narrow room's loop stays past the door leaf on the doorway's side */
    if (room > 0) ax = fmin(ax, cx - fp->wx1 - past);
    if (room > 0) way_add(s, fp->wx0 - 0.8, yd), way_add(s, fp->wx1 + past, yd);
    int m = room == 0 ? 10 : 7;
    if (room == 0 && !living_loop) {
      way_add(s, cx, cy); /* across the living room through its middle */
      continue;
    }
    /* start on the side facing the doorways (+x in the living room, -x
     * in the others) and go round once */
    double a0 = room == 0 ? 0 : M_PI;
    for (int i = 0; i <= m; i++) {
      double a = a0 + 2 * M_PI * i / m;
      way_add(s, cx + ax * cos(a), cy + ay * sin(a));
    }
    if (room > 0) way_add(s, fp->wx1 + past, yd), way_add(s, fp->wx0 - 0.8, yd);
  }
}

static void way_close(struct vlff_sim *s) {
  int n = s->nway;
  s->way_len[0] = 0;
  for (int i = 0; i < n; i++) {
    const double *p = s->way[i], *q = s->way[(i + 1) % n];
    s->way_len[i + 1] = s->way_len[i] + hypot(q[0] - p[0], q[1] - p[1]);
  }
}

/* The flat: the whole box, its walk one tour closed on itself. */
static void build_flat(struct vlff_sim *s, int attempt) {
  struct rng r = rng_make(s->seed, 1, (uint64_t)attempt);
  s->nprims = 0, s->cur_obj = 0, s->nrooms = s->ndoors = s->nway = 0;
  shell(s, &r, s->room_lo, s->room_hi);
  struct flat_plan fp = {.entrance = 0};
  flat_inside(s, &r, s->room_lo, s->room_hi, 0, &fp);
  s->nflats = 1;
  memcpy(s->flats[0], (double[4]){s->room_lo[0], s->room_lo[1], s->room_hi[0], s->room_hi[1]}, sizeof s->flats[0]);
  flat_tour(s, &fp, 0.28, 0.8, 1); /* the walk every flat seed has had */
  way_close(s);
}

/* The building's corridor: along its y=lo side, the flats' entrances in
 * the wall that closes it. */
#define CORRIDOR_M 1.8

/* Walls take the plain noise texture, as the shell's do. */
static void plain(struct prim *p) {
  if (p) p->pattern = 0;
}

static int classes_from(const struct vlff_sim *s, int first) {
  int have[VLFF_SIM_CLASSES] = {0}, nc = 0;
  have[C_WALL] = have[C_FLOOR] = 1; /* the building's shell */
  for (int i = first; i < s->nprims; i++)
    if (s->prims[i].label < VLFF_SIM_CLASSES) have[s->prims[i].label] = 1;
  for (int c = 0; c < VLFF_SIM_CLASSES; c++) nc += have[c];
  return nc;
}

/* The building: sim.flats flats side by side along x, each a flat as above,
 * opening through an entrance onto a corridor along the box's y=lo side.
 * Each flat is re-drawn (its own stream per attempt) until it holds every
 * class. The walk starts in flat 0's living room, tours every flat in turn
 * (out along the corridor, in through the entrance, round the flat, out),
 * walks the corridor back to flat 0 and ends where it started. */
static void build_building(struct vlff_sim *s, int attempt) {
  (void)attempt; /* the flats draw their own attempts */
  struct rng r = rng_make(s->seed, 1, 0);
  s->nprims = 0, s->cur_obj = 0, s->nrooms = s->ndoors = s->nway = 0;
  const double *lo = s->room_lo, *hi = s->room_hi;
  const double tw = 0.1, dw = 0.9, dh = 2.05, fz = lo[2], hz = hi[2];
  const int nf = s->cfg.flats;
  shell(s, &r, lo, hi);
  const double cy1 = lo[1] + CORRIDOR_M, fy0 = cy1 + tw, yc = 0.5 * (lo[1] + cy1);
  const double wf = (hi[0] - lo[0] - (nf - 1) * tw) / nf;
  /* party walls between neighbouring flats */
  for (int k = 1; k < nf; k++) {
    double x = lo[0] + k * wf + (k - 1) * tw;
    s->cur_obj++;
    plain(box(s, &r, C_WALL, x, cy1, fz, x + tw, hi[1], hz));
  }
  double *rc = s->rooms[s->nrooms];
  rc[0] = lo[0], rc[1] = lo[1], rc[2] = hi[0], rc[3] = cy1;
  s->room_flat[s->nrooms++] = -1;
  struct flat_plan fp[MAX_FLATS];
  for (int k = 0; k < nf; k++) {
    double fl[3] = {lo[0] + k * (wf + tw), fy0, fz}, fh[3] = {fl[0] + wf, hi[1], hz};
    memcpy(s->flats[k], (double[4]){fl[0], fl[1], fh[0], fh[1]}, sizeof s->flats[k]);
    int first = s->nprims, obj = s->cur_obj, rooms = s->nrooms, doors = s->ndoors, best = 0, best_nc = -1;
    for (int a = 0; a < 17; a++) {
      s->nprims = first, s->cur_obj = obj, s->nrooms = rooms, s->ndoors = doors;
      fp[k] = (struct flat_plan){.entrance = 1};
      struct rng fr = rng_make(s->seed, 20 + (uint64_t)k, (uint64_t)(a < 16 ? a : best));
      flat_inside(s, &fr, fl, fh, k, &fp[k]);
      if (a == 16) break; /* the fullest attempt, rebuilt */
      int nc = classes_from(s, first);
      if (nc > best_nc) best_nc = nc, best = a;
      if (nc == VLFF_SIM_CLASSES) break;
    }
  }
  s->nflats = nf;
  /* the corridor's wall: solid between the entrances, a lintel over each */
  double x = lo[0];
  for (int k = 0; k <= nf; k++) {
    double x1 = k < nf ? fp[k].xe - dw / 2 : hi[0];
    s->cur_obj++;
    plain(box(s, &r, C_WALL, x, cy1, fz, x1, fy0, hz));
    if (k == nf) break;
    s->cur_obj++;
    plain(box(s, &r, C_WALL, x1, cy1, fz + dh, x1 + dw, fy0, hz));
    x = x1 + dw;
  }
  for (int k = 0; k < nf; k++) {
    double xe = fp[k].xe, in = fy0 + 0.9;
    if (k > 0) way_add(s, xe, yc), way_add(s, xe, in);
    flat_tour(s, &fp[k], 0.2, 1.0, 0);
    way_add(s, xe, in), way_add(s, xe, yc);
  }
  way_add(s, fp[0].xe, yc), way_add(s, fp[0].xe, fy0 + 0.9);
  way_close(s);
}

/* ---- BVH ---------------------------------------------------------------- */

static int bvh_build(struct sim_world *s, int first, int count) {
  int id = s->nnodes++;
  struct bvh_node *n = &s->nodes[id];
  for (int k = 0; k < 3; k++) n->lo[k] = INFINITY, n->hi[k] = -INFINITY;
  for (int i = first; i < first + count; i++) {
    const struct prim *p = &s->prims[s->order[i]];
    for (int k = 0; k < 3; k++) n->lo[k] = fmin(n->lo[k], p->lo[k]), n->hi[k] = fmax(n->hi[k], p->hi[k]);
  }
  if (count <= 2) {
    n->left = n->right = -1;
    n->first = first, n->count = count;
    return id;
  }
  int axis = 0;
  for (int k = 1; k < 3; k++)
    if (n->hi[k] - n->lo[k] > n->hi[axis] - n->lo[axis]) axis = k;
  /* median split by centroid (insertion sort: a hundred items) */
  for (int i = first + 1; i < first + count; i++) {
    int v = s->order[i], j = i - 1;
    double c = s->prims[v].lo[axis] + s->prims[v].hi[axis];
    while (j >= first && s->prims[s->order[j]].lo[axis] + s->prims[s->order[j]].hi[axis] > c) {
      s->order[j + 1] = s->order[j];
      j--;
    }
    s->order[j + 1] = v;
  }
  int half = count / 2;
  int l = bvh_build(s, first, half);
  int r = bvh_build(s, first + half, count - half);
  n = &s->nodes[id];
  n->left = l, n->right = r;
  n->first = first, n->count = 0;
  return id;
}

static int slab(const double lo[3], const double hi[3], const double o[3], const double inv[3],
                double tmax, double *tn, int *axis) {
  double t0 = 0, t1 = tmax;
  int ax = -1;
  for (int k = 0; k < 3; k++) {
    double a = (lo[k] - o[k]) * inv[k], b = (hi[k] - o[k]) * inv[k];
    if (a > b) {
      double t = a;
      a = b, b = t;
    }
    if (a > t0) t0 = a, ax = k;
    if (b < t1) t1 = b;
    if (t0 > t1) return 0;
  }
  *tn = t0;
  if (axis) *axis = ax;
  return 1;
}

/* Hit of one primitive beyond t=eps and before tmax; normal not yet faced. */
static int prim_hit(const struct prim *p, const double o[3], const double d[3],
                    const double inv[3], double tmax, double *t, double n[3]) {
  const double eps = 1e-6;
  if (p->kind == PRIM_BOX) {
    /* from inside (room shell seen from within is never inside: shells are
     * outside the room) rays exit; we only need entry hits */
    double tn;
    int ax;
    if (!slab(p->lo, p->hi, o, inv, tmax, &tn, &ax) || ax < 0 || tn <= eps) return 0;
    *t = tn;
    n[0] = n[1] = n[2] = 0;
    n[ax] = d[ax] > 0 ? -1 : 1;
    return 1;
  }
  double best = tmax;
  int hit = 0;
  /* side: |o + t d - c|^2 = r^2 in xy */
  double ox = o[0] - p->cx, oy = o[1] - p->cy;
  double a = d[0] * d[0] + d[1] * d[1];
  if (a > 1e-18) {
    double b = ox * d[0] + oy * d[1], c = ox * ox + oy * oy - p->r * p->r;
    double disc = b * b - a * c;
    if (disc >= 0) {
      double tt = (-b - sqrt(disc)) / a;
      double z = o[2] + tt * d[2];
      if (tt > eps && tt < best && z >= p->lo[2] && z <= p->hi[2]) {
        best = tt, hit = 1;
        n[0] = (ox + tt * d[0]) / p->r, n[1] = (oy + tt * d[1]) / p->r, n[2] = 0;
      }
    }
  }
  if (fabs(d[2]) > 1e-18) {
    double zc = d[2] > 0 ? p->lo[2] : p->hi[2];
    double tt = (zc - o[2]) / d[2];
    double x = ox + tt * d[0], y = oy + tt * d[1];
    if (tt > eps && tt < best && x * x + y * y <= p->r * p->r) {
      best = tt, hit = 1;
      n[0] = n[1] = 0, n[2] = d[2] > 0 ? -1 : 1;
    }
  }
  if (hit) *t = best;
  return hit;
}

static double cast(const struct sim_world *s, const double o[3], const double d[3], int *prim,
                   double n[3]) {
  double inv[3];
  for (int k = 0; k < 3; k++) inv[k] = d[k] != 0 ? 1.0 / d[k] : copysign(1e300, d[k]);
  double best = 1e30;
  int bp = -1;
  double bn[3] = {0, 0, 1};
  int stack[64], sp = 0;
  if (s->count) stack[sp++] = 0;
  while (sp) {
    const struct bvh_node *nd = &s->nodes[stack[--sp]];
    double tn;
    /* the slab from t=0 rejects nodes behind; a node containing o passes */
    if (!slab(nd->lo, nd->hi, o, inv, best, &tn, NULL)) continue;
    if (nd->left < 0) {
      for (int i = nd->first; i < nd->first + nd->count; i++) {
        double t, nn[3];
        if (prim_hit(&s->prims[s->order[i]], o, d, inv, best, &t, nn)) {
          best = t, bp = s->order[i];
          memcpy(bn, nn, sizeof bn);
        }
      }
    } else if (sp + 2 <= 64) {
      stack[sp++] = nd->left;
      stack[sp++] = nd->right;
    }
  }
  if (bp < 0) return -1;
  if (prim) *prim = bp;
  if (n) memcpy(n, bn, sizeof bn);
  return best;
}

static const struct sim_world *world_at(const struct vlff_sim *s, double t);

long long vlff_sim_stream_frame(const struct vlff_sim *s, long long id) {
  if (s->cfg.change_count > 0) return id;
  long long n = s->cfg.range_count > 0 ? s->cfg.range_count : s->cfg.frames;
  long long f = id % n;
  return (f < 0 ? f + n : f) + (s->cfg.range_count > 0 ? s->cfg.range_first : 0);
}

double vlff_sim_raycast(const struct vlff_sim *s, const double o[3], const double d[3],
                        int *label, double normal[3]) {
  return vlff_sim_raycast_at(s, 0, o, d, label, normal);
}

double vlff_sim_raycast_at(const struct vlff_sim *s, double time_s, const double o[3], const double d[3], int *label,
                           double normal[3]) {
  int p;
  double t = cast(world_at(s, time_s), o, d, &p, normal);
  if (t >= 0 && label) *label = s->prims[p].label;
  if (t < 0 && label) *label = VLFF_SIM_UNLABELLED;
  return t;
}

/* ---- a changing world (sim.changes) -------------------------------------- */

/* The world in force at sim time t: the last whose from_s is at or before t. */
static const struct sim_world *world_at(const struct vlff_sim *s, double t) {
  int w = 0;
  while (w + 1 < s->nworlds && s->worlds[w + 1].from_s <= t) w++;
  return &s->worlds[w];
}

/* The object a change names, "<class>" or "<class>#<n>": the n-th (from 1)
 * object holding a primitive of that class, in the order the scene was
 * built. Its id, or -1 with err naming the change. */
static int find_object(const struct vlff_sim *s, int ci, const char *name, char *err, size_t errlen) {
  char cls[VLFF_SIM_OBJECT_LEN], what[48] = "object";
  if (ci >= 0) snprintf(what, sizeof what, "sim.changes[%d].object", ci);
  snprintf(cls, sizeof cls, "%s", name);
  long nth = 1;
  char *hash = strchr(cls, '#');
  if (hash) {
    char *end;
    *hash = 0;
    nth = strtol(hash + 1, &end, 10);
    if (end == hash + 1 || *end || nth < 1 || nth > 10000) {
      vlff_errf(err, errlen, "sim: %s '%s': expected class#n with n a whole number from 1", what,
                VLFF_Q(name));
      return -1;
    }
  }
  int c = vlff_sim_class_of(cls);
  if (c < 0) {
    vlff_errf(err, errlen, "sim: %s '%s': '%s' is not a class of the simulator (wall, chair, "
                           "table, ...)", what, VLFF_Q(name), VLFF_Q(cls));
    return -1;
  }
  int seen = 0, last = -1;
  for (int i = 0; i < s->nprims; i++) {
    if (s->prims[i].label != c || s->prims[i].obj == last) continue;
    bool before = false; /* an object's primitives need not be adjacent */
    for (int j = 0; j < i && !before; j++) before = s->prims[j].label == c && s->prims[j].obj == s->prims[i].obj;
    last = s->prims[i].obj;
    if (!before && ++seen == nth) return s->prims[i].obj;
  }
  vlff_errf(err, errlen, "sim: %s '%s': this scene has %d %s object%s", what, VLFF_Q(name), seen,
            VLFF_Q(cls), seen == 1 ? "" : "s");
  return -1;
}

/* The worlds: the scene as built, then one after each change in time order
 * (changes at one time in the order written). An object whose first change
 * adds it is absent before it. */
static int build_worlds(struct vlff_sim *s, char *err, size_t errlen) {
  const int nc = s->cfg.change_count, nobj = s->cur_obj + 1;
  int order[VLFF_SIM_MAX_CHANGES], obj[VLFF_SIM_MAX_CHANGES];
  for (int i = 0; i < nc; i++) {
    int j = i;
    for (; j > 0 && s->cfg.changes[order[j - 1]].time_s > s->cfg.changes[i].time_s; j--) order[j] = order[j - 1];
    order[j] = i;
    if ((obj[i] = find_object(s, i, s->cfg.changes[i].object, err, errlen)) < 0) return -1;
  }
  bool *present = malloc((size_t)nobj * sizeof *present);
  double(*off)[2] = calloc((size_t)nobj, sizeof *off);
  s->worlds = calloc((size_t)nc + 1, sizeof *s->worlds);
  int rc = -1;
  if (!present || !off || !s->worlds) goto oom;
  for (int o = 0; o < nobj; o++) present[o] = true;
  for (int k = nc - 1; k >= 0; k--) /* the first change of each object decides its start */
    present[obj[order[k]]] = s->cfg.changes[order[k]].action != VLFF_SIM_ADD;
  for (int w = 0; w <= nc; w++) {
    struct sim_world *wd = &s->worlds[w];
    wd->from_s = -INFINITY;
    if (w > 0) {
      const struct vlff_sim_change *ch = &s->cfg.changes[order[w - 1]];
      const int o = obj[order[w - 1]];
      wd->from_s = ch->time_s;
      /* A move keeps an object where it is and as it is: one removed or not yet
       * added would otherwise come back unasked. */
      if (ch->action == VLFF_SIM_MOVE && !present[o]) {
        vlff_errf(err, errlen, "sim: sim.changes[%d]: '%s' is moved at %g s while absent (removed, or not yet added): "
                               "bring it back with action add and a 'to'", order[w - 1], VLFF_Q(ch->object), ch->time_s);
        goto out;
      }
      present[o] = ch->action != VLFF_SIM_REMOVE;
      if (ch->has_to) {
        /* The object's footprint as built, and where its centre goes. */
        double lo[2] = {INFINITY, INFINITY}, hi[2] = {-INFINITY, -INFINITY};
        for (int i = 0; i < s->nprims; i++)
          for (int a = 0; a < 2 && s->prims[i].obj == o; a++)
            lo[a] = fmin(lo[a], s->prims[i].lo[a]), hi[a] = fmax(hi[a], s->prims[i].hi[a]);
        for (int a = 0; a < 2; a++) {
          off[o][a] = ch->to[a] - 0.5 * (lo[a] + hi[a]);
          if (lo[a] + off[o][a] < s->bbox_lo[a] || hi[a] + off[o][a] > s->bbox_hi[a]) {
            vlff_errf(err, errlen, "sim: sim.changes[%d]: '%s' at (%.2f, %.2f) would stand outside the scene "
                                   "(x %.2f..%.2f, y %.2f..%.2f m)", order[w - 1], VLFF_Q(ch->object), ch->to[0],
                      ch->to[1], s->bbox_lo[0], s->bbox_hi[0], s->bbox_lo[1], s->bbox_hi[1]);
            goto out;
          }
        }
      }
    }
    wd->prims = malloc((size_t)s->nprims * sizeof *wd->prims);
    wd->order = malloc((size_t)s->nprims * sizeof *wd->order);
    wd->nodes = malloc((size_t)2 * s->nprims * sizeof *wd->nodes);
    s->nworlds = w + 1;
    if (!wd->prims || !wd->order || !wd->nodes) goto oom;
    memcpy(wd->prims, s->prims, (size_t)s->nprims * sizeof *wd->prims);
    for (int i = 0; i < s->nprims; i++) {
      struct prim *p = &wd->prims[i];
      const double *d = off[p->obj];
      for (int a = 0; a < 2; a++) p->lo[a] += d[a], p->hi[a] += d[a];
      p->cx += d[0], p->cy += d[1];
      if (present[p->obj]) wd->order[wd->count++] = i;
    }
    if (wd->count) bvh_build(wd, 0, wd->count);
  }
  rc = 0;
  goto out;
oom:
  vlff_errf(err, errlen, "sim: out of memory");
out:
  free(present);
  free(off);
  return rc;
}

/* ---- textures and shading ---------------------------------------------- */

static double lattice(uint32_t seed, int x, int y, int z) {
  return (double)(hash3(seed, ((uint64_t)(uint32_t)x << 32) | (uint32_t)y, (uint32_t)z) >> 11) *
         0x1.0p-53;
}

static double smooth(double t) { return t * t * (3 - 2 * t); }

/* The eight lattice values of the last cell one octave of one texture
 * looked up: neighbouring pixels mostly fall in the same cell (cells are
 * 3-33 cm, pixels about 1 cm), and each value costs three 64-bit hashes. */
struct lattice_cache {
  int valid;
  uint32_t seed;
  int ix, iy, iz;
  double v[8];
};

static double value_noise(struct lattice_cache *lc, uint32_t seed, double x, double y, double z) {
  int ix = (int)floor(x), iy = (int)floor(y), iz = (int)floor(z);
  double fx = smooth(x - ix), fy = smooth(y - iy), fz = smooth(z - iz);
  if (!lc->valid || lc->seed != seed || lc->ix != ix || lc->iy != iy || lc->iz != iz) {
    for (int c = 0; c < 8; c++) lc->v[c] = lattice(seed, ix + (c & 1), iy + ((c >> 1) & 1), iz + (c >> 2));
    lc->valid = 1, lc->seed = seed, lc->ix = ix, lc->iy = iy, lc->iz = iz;
  }
  double v = 0;
  for (int c = 0; c < 8; c++) {
    int dx = c & 1, dy = (c >> 1) & 1, dz = c >> 2;
    double w = (dx ? fx : 1 - fx) * (dy ? fy : 1 - fy) * (dz ? fz : 1 - fz);
    v += w * lc->v[c];
  }
  return v;
}

static double pattern(struct lattice_cache lc[2], const struct prim *p, const double x[3]) {
  double sc = p->tex_scale;
  double a = x[0] * sc, b = x[1] * sc, c = x[2] * sc;
  double n = 0.65 * value_noise(&lc[0], p->tex_seed, a, b, c) +
             0.35 * value_noise(&lc[1], p->tex_seed + 1, 3 * a, 3 * b, 3 * c);
  switch (p->pattern) {
  case 1: return 0.55 + 0.45 * sin((a + b + c) * 1.7 + 2 * n);
  case 2: return (((int)floor(a * 0.5) + (int)floor(b * 0.5) + (int)floor(c * 0.5)) & 1) ? 0.35 + 0.3 * n : 0.75 + 0.25 * n;
  case 3: return 0.6 + 0.4 * sin(8 * n + a * 0.3);
  default: return n;
  }
}

static void shade(const struct vlff_sim *s, struct lattice_cache lc[2], const struct prim *p, const double x[3],
                  const double n[3], float rgb[3]) {
  double light[3] = {0.5 * (s->room_lo[0] + s->room_hi[0]), 0.5 * (s->room_lo[1] + s->room_hi[1]),
                     s->room_hi[2] - 0.2};
  /* the flat: each room has its own ceiling light */
  for (int k = 0; k < s->nrooms; k++) {
    const double *rm = s->rooms[k];
    if (x[0] >= rm[0] - 0.1 && x[0] <= rm[2] + 0.1 && x[1] >= rm[1] - 0.1 && x[1] <= rm[3] + 0.1) {
      light[0] = 0.5 * (rm[0] + rm[2]), light[1] = 0.5 * (rm[1] + rm[3]);
      break;
    }
  }
  double l[3] = {light[0] - x[0], light[1] - x[1], light[2] - x[2]};
  double dist2 = l[0] * l[0] + l[1] * l[1] + l[2] * l[2];
  norm3(l);
  double ndl = fabs(n[0] * l[0] + n[1] * l[1] + n[2] * l[2]);
  double lum = 0.35 + 0.9 * ndl / (1.0 + 0.08 * dist2);
  double tex = 0.55 + 0.6 * pattern(lc, p, x);
  for (int i = 0; i < 3; i++) {
    double v = p->albedo[i] * tex * lum;
    rgb[i] = (float)(v > 1 ? 1 : v);
  }
}

/* ---- trajectories ------------------------------------------------------- */

static void look_at(const double eye[3], const double target[3], double c2w[16]) {
  double f[3] = {target[0] - eye[0], target[1] - eye[1], target[2] - eye[2]};
  norm3(f);
  double up[3] = {0, 0, 1}, r[3], d[3];
  cross3(f, up, r);
  if (r[0] * r[0] + r[1] * r[1] + r[2] * r[2] < 1e-12) r[0] = 1, r[1] = r[2] = 0;
  norm3(r);
  cross3(f, r, d);
  double m[16] = {r[0], d[0], f[0], eye[0], r[1], d[1], f[1], eye[1],
                  r[2], d[2], f[2], eye[2], 0,    0,    0,    1};
  memcpy(c2w, m, sizeof m);
}

/* Position on the flat's closed walk at arc length d (any real). */
static void way_at(const struct vlff_sim *s, double d, double p[2]) {
  double L = s->way_len[s->nway];
  d = fmod(d, L);
  if (d < 0) d += L;
  int i = 0;
  while (i + 1 < s->nway && s->way_len[i + 1] <= d) i++;
  const double *a = s->way[i], *b = s->way[(i + 1) % s->nway];
  double seg = s->way_len[i + 1] - s->way_len[i], f = seg > 0 ? (d - s->way_len[i]) / seg : 0;
  p[0] = a[0] + f * (b[0] - a[0]), p[1] = a[1] + f * (b[1] - a[1]);
}

/* The flat's walk: one loop through every room per sim.frames frames,
 * heading along the path (smoothed over a metre) and sweeping from side to
 * side so the walls and what stands against them are seen, straight
 * through doorways. */
static void flat_pose(const struct vlff_sim *s, long long index, double c2w[16]) {
  double L = s->way_len[s->nway];
  double d = L * (double)(index % s->cfg.frames) / s->cfg.frames;
  double eye[3], tgt[3], a[2], b[2];
  way_at(s, d, eye);
  way_at(s, d - 0.5, a);
  way_at(s, d + 0.5, b);
  double head = atan2(b[1] - a[1], b[0] - a[0]);
  double near = 1e9;
  for (int k = 0; k < s->ndoors; k++) near = fmin(near, hypot(eye[0] - s->doors[k][0], eye[1] - s->doors[k][1]));
  double sweep = fmin(1.0, fmax(0.0, (near - 0.4) / 1.2));
  double yaw = head + sweep * 1.0 * sin(2 * M_PI * d / 4.5);
  double fz = s->room_lo[2];
  eye[2] = fz + 1.35 + 0.1 * sin(1.3 * d);
  tgt[0] = eye[0] + 2.0 * cos(yaw), tgt[1] = eye[1] + 2.0 * sin(yaw);
  tgt[2] = fz + 0.75 + 0.3 * sin(0.9 * d);
  look_at(eye, tgt, c2w);
}

static void true_pose(const struct vlff_sim *s, long long index, double c2w[16]) {
  if (s->nway > 1) {
    flat_pose(s, index, c2w);
    return;
  }
  double cxr = 0.5 * (s->room_lo[0] + s->room_hi[0]), cyr = 0.5 * (s->room_lo[1] + s->room_hi[1]);
  double ax = 0.5 * (s->room_hi[0] - s->room_lo[0]), ay = 0.5 * (s->room_hi[1] - s->room_lo[1]);
  double fz = s->room_lo[2];
  double t = (double)index / s->cfg.rate_hz;
  double dist = t * s->cfg.speed_mps;
  double eye[3], tgt[3];
  if (s->cfg.trajectory == VLFF_TRAJ_ORBIT) {
    double rad = 0.55 * fmin(ax, ay);
    double th = dist / rad;
    eye[0] = cxr + rad * cos(th), eye[1] = cyr + rad * sin(th), eye[2] = fz + 1.6;
    tgt[0] = cxr - 0.3 * rad * cos(th), tgt[1] = cyr - 0.3 * rad * sin(th), tgt[2] = fz + 0.5;
  } else {
    /* Walk a wobbly ellipse through the room, looking across it at a point
     * that sweeps along the far walls: every wall and object is seen from
     * several distances and directions per loop. */
    double rx = 0.45 * ax, ry = 0.45 * ay;
    double per = 2 * M_PI * sqrt(0.5 * (rx * rx + ry * ry));
    double th = 2 * M_PI * dist / per;
    double wob = 1.0 + 0.15 * sin(3 * th + 0.7);
    eye[0] = cxr + wob * rx * cos(th), eye[1] = cyr + wob * ry * sin(th);
    eye[2] = fz + 1.35 + 0.12 * sin(2.3 * th);
    double ph = th + M_PI + 1.1 * sin(1.7 * th + 0.3);
    tgt[0] = cxr + 0.85 * ax * cos(ph), tgt[1] = cyr + 0.85 * ay * sin(ph);
    tgt[2] = fz + 0.55 + 0.35 * sin(1.3 * th);
  }
  look_at(eye, tgt, c2w);
}

static int is_bad_pose(const struct vlff_sim *s, long long index) {
  if (s->cfg.bad_pose_frac <= 0) return 0;
  struct rng r = rng_make(s->seed, 7, (uint64_t)index);
  return rng_uniform(&r) < s->cfg.bad_pose_frac;
}

/* A corrupted pose: 0.2-0.5 m off and rotated 5-15 degrees about z, like a
 * SLAM relocalisation glitch. */
static void corrupt_pose(const struct vlff_sim *s, long long index, double c2w[16]) {
  struct rng r = rng_make(s->seed, 8, (uint64_t)index);
  double ang = rng_range(&r, 5, 15) * M_PI / 180 * (rng_uniform(&r) < 0.5 ? -1 : 1);
  double c = cos(ang), sn = sin(ang), m[16];
  memcpy(m, c2w, sizeof m);
  for (int col = 0; col < 3; col++) {
    double x = m[0 * 4 + col], y = m[1 * 4 + col];
    c2w[0 * 4 + col] = c * x - sn * y;
    c2w[1 * 4 + col] = sn * x + c * y;
  }
  double off = rng_range(&r, 0.2, 0.5), dir = rng_range(&r, 0, 2 * M_PI);
  c2w[3] += off * cos(dir);
  c2w[7] += off * sin(dir);
}

void vlff_sim_pose(const struct vlff_sim *s, long long index, double c2w[16]) {
  true_pose(s, index, c2w);
  if (is_bad_pose(s, index)) corrupt_pose(s, index, c2w);
}

/* ---- features ----------------------------------------------------------- */

/* Similarity structure of the feature space: each class is a mix of a
 * component shared by everything, its group's component, components shared
 * with specific look-alike partners and its own. */
static const int class_group[NPROTO] = {
    /* wall floor cabinet bed chair sofa table door window bookshelf */
    0, 1, 2, 3, 3, 3, 4, 0, 0, 2,
    /* picture counter desk curtain fridge shower toilet sink bathtub other ceiling */
    0, 2, 4, 5, 2, 5, 6, 6, 6, 2, 0};
#define NGROUPS 7

static const int close_pairs[][2] = {
    {C_DESK, C_TABLE},     {C_CURTAIN, C_SHOWER},  {C_CABINET, C_COUNTER}, {C_CABINET, C_OTHER},
    {C_COUNTER, C_OTHER},  {C_WALL, C_PICTURE},    {C_CHAIR, C_SOFA},      {C_SOFA, C_BED},
    {C_WALL, C_DOOR},      {C_WINDOW, C_CURTAIN},  {C_SINK, C_COUNTER},    {C_TOILET, C_SINK},
    {C_BATHTUB, C_TOILET}, {C_BOOKSHELF, C_CABINET}, {C_FRIDGE, C_CABINET}, {C_WALL, P_CEIL},
    {C_OTHER, C_TABLE},    {C_DOOR, C_CABINET}};
#define NPAIRS ((int)(sizeof close_pairs / sizeof close_pairs[0]))

static int build_features(struct vlff_sim *s) {
  int D = s->dim;
  s->proto = calloc((size_t)NPROTO * D, sizeof(float));
  s->text = calloc((size_t)VLFF_SIM_CLASSES * D, sizeof(float));
  s->generic = calloc((size_t)D, sizeof(float));
  float *groups = calloc((size_t)NGROUPS * D, sizeof(float));
  float *pairs = calloc((size_t)NPAIRS * D, sizeof(float));
  float *u = calloc((size_t)D, sizeof(float));
  float *text_common = calloc((size_t)D, sizeof(float));
  if (!s->proto || !s->text || !s->generic || !groups || !pairs || !u || !text_common) {
    free(groups), free(pairs), free(u), free(text_common);
    return -1;
  }
  struct rng r = rng_make(FEATURE_SPACE_SEED, (uint64_t)D, 0);
  random_unit(&r, s->generic, D);
  random_unit(&r, text_common, D);
  for (int g = 0; g < NGROUPS; g++) random_unit(&r, groups + (size_t)g * D, D);
  for (int p = 0; p < NPAIRS; p++) random_unit(&r, pairs + (size_t)p * D, D);
  for (int c = 0; c < NPROTO; c++) {
    float *v = s->proto + (size_t)c * D;
    random_unit(&r, u, D);
    for (int i = 0; i < D; i++)
      v[i] = 0.45f * s->generic[i] + 0.5f * groups[(size_t)class_group[c] * D + i] + 0.75f * u[i];
    for (int p = 0; p < NPAIRS; p++)
      if (close_pairs[p][0] == c || close_pairs[p][1] == c)
        for (int i = 0; i < D; i++) v[i] += 0.55f * pairs[(size_t)p * D + i];
    normalize_f(v, D);
  }
  for (int c = 0; c < VLFF_SIM_CLASSES; c++) {
    float *t = s->text + (size_t)c * D;
    random_unit(&r, u, D);
    for (int i = 0; i < D; i++) t[i] = s->proto[(size_t)c * D + i] + 0.3f * text_common[i] + 0.35f * u[i];
    normalize_f(t, D);
  }
  /* Confusion partner: the most similar other prototype. */
  for (int c = 0; c < NPROTO; c++) {
    double best = -2;
    for (int o = 0; o < VLFF_SIM_CLASSES; o++) {
      if (o == c) continue;
      double dot = 0;
      for (int i = 0; i < D; i++) dot += (double)s->proto[(size_t)c * D + i] * s->proto[(size_t)o * D + i];
      if (dot > best) best = dot, s->partner[c] = o;
    }
    s->view_strength[c] = (float)rng_range(&r, 0.4, 1.0);
    s->view_phase[c] = (float)rng_range(&r, 0, 2 * M_PI);
  }
  free(groups), free(pairs), free(u), free(text_common);
  return 0;
}

/* Per-object bias (sim.object_bias): every view of an object sees its
 * features lean toward one other class by a fixed weight, plus a fixed
 * offset of its own. Fusion averages views of the same object, so neither
 * averages out; most objects lean a little, a few a lot, like a
 * vision-language model that is sure of the wrong thing for some objects. */
static int build_objects(struct vlff_sim *s) {
  const int D = s->dim;
  const double b = s->cfg.object_bias;
  s->nobj = s->cur_obj + 1;
  s->obj_vec = calloc((size_t)s->nobj * D, sizeof(float));
  s->obj_mix = calloc((size_t)s->nobj, sizeof(float));
  s->obj_to = calloc((size_t)s->nobj, sizeof(int));
  if (!s->obj_vec || !s->obj_mix || !s->obj_to) return -1;
  int *cls = malloc((size_t)s->nobj * sizeof(int));
  if (!cls) return -1;
  for (int o = 0; o < s->nobj; o++) cls[o] = P_CEIL;
  for (int i = s->nprims - 1; i >= 0; i--)
    cls[s->prims[i].obj] = s->prims[i].label < VLFF_SIM_CLASSES ? s->prims[i].label : P_CEIL;
  for (int o = 0; o < s->nobj; o++) {
    struct rng r = rng_make(s->seed, 10, (uint64_t)o);
    double u = rng_uniform(&r);
    s->obj_mix[o] = (float)(b * 0.8 * u * u);
    s->obj_to[o] = rng_uniform(&r) < 0.6 ? s->partner[cls[o]] : (int)(rng_u64(&r) % VLFF_SIM_CLASSES);
    if (s->obj_to[o] == cls[o]) s->obj_to[o] = s->partner[cls[o]];
    float *v = s->obj_vec + (size_t)o * D;
    random_unit(&r, v, D);
    for (int i = 0; i < D; i++) v[i] *= (float)(0.35 * b);
  }
  free(cls);
  return 0;
}

void vlff_sim_prototype(const struct vlff_sim *s, int c, float *out) {
  if (c < 0 || c > VLFF_SIM_CLASSES) c = VLFF_SIM_CLASSES;
  memcpy(out, s->proto + (size_t)c * s->dim, (size_t)s->dim * sizeof(float));
}

const char *vlff_sim_class_name(int c) { return c >= 0 && c < VLFF_SIM_CLASSES ? class_names[c] : NULL; }

int vlff_sim_class_of(const char *name) {
  if (!name) return -1;
  while (*name == ' ') name++;
  size_t n = strlen(name);
  while (n && name[n - 1] == ' ') n--;
  for (int c = 0; c < VLFF_SIM_CLASSES; c++)
    if (strlen(class_names[c]) == n && !strncasecmp(class_names[c], name, n)) return c;
  return -1;
}

void vlff_sim_text_embedding(const struct vlff_sim *s, const char *text, float *out) {
  int D = s->dim;
  int c = vlff_sim_class_of(text);
  if (c >= 0) {
    memcpy(out, s->text + (size_t)c * D, (size_t)D * sizeof(float));
    return;
  }
  if (!text) text = "";
  /* Keyed from 1469598103934665603, not FNV's offset basis: the start the
   * generated vectors of unknown prompts have always had, so a scene and
   * what was measured on it stay bit-identical. */
  uint64_t h = vlff_fnv1a64(1469598103934665603ull, text, strlen(text));
  struct rng r = rng_make(FEATURE_SPACE_SEED, h, 1);
  for (int i = 0; i < D; i++) out[i] = (float)(0.45 * s->generic[i] + 0.9 * rng_normal(&r) / sqrt(D));
  normalize_f(out, D);
}

/* A confusion patch: a disc where the features drift toward another class. */
struct patch {
  double x, y, rad, w;
  int to, from;  /* from = -1: any class inside */
};

/* v[d] = scale off[d] + sigma n_d. n_d is approximately normal: Irwin-Hall
 * of the four 16-bit parts of the d-th draw of rng_u64 from state s0, scaled
 * to unit variance (its tails do not matter). D draws per feature pixel make
 * this most of a frame's cost, so it is written for the vectoriser: the
 * generator is a counter (draw k mixes s0 + k gamma), so no draw waits for
 * the one before. */
VLFF_HOT
static void feature_noise(uint64_t s0, float scale, const float *off, float sigma, float *v, int D) {
  for (int d = 0; d < D; d++) {
    uint64_t z = vlff_mix64(s0 + (uint64_t)d * VLFF_RNG_GAMMA);
    uint32_t sum = (uint32_t)(z & 0xffff) + (uint32_t)((z >> 16) & 0xffff) + (uint32_t)((z >> 32) & 0xffff) +
                   (uint32_t)(z >> 48);
    float n = (float)(((double)sum / 65536.0 - 2.0) * 1.7320508075688772);
    v[d] = scale * off[d] + sigma * n;
  }
}

VLFF_HOT
static void feature_mix(float w, const float *p, float *v, int D) {
  for (int d = 0; d < D; d++) v[d] += w * p[d];
}

static void render_features(const struct vlff_sim *s, long long index, struct vlff_sim_frame *f,
                            const float *cosview, const int *primbuf, float *acc) {
  const int D = s->dim, W = s->width, H = s->height, fw = s->fw, fh = s->fh;
  const double diff = s->cfg.difficulty;
  struct rng fr = rng_make(s->seed, 3, (uint64_t)index);
  struct patch patches[16];
  int np = (int)floor(diff * 8 + rng_uniform(&fr));
  if (np > 16) np = 16;
  for (int i = 0; i < np; i++) {
    patches[i].x = rng_range(&fr, 0, fw);
    patches[i].y = rng_range(&fr, 0, fh);
    patches[i].rad = rng_range(&fr, 0.06, 0.2) * fw;
    patches[i].w = rng_range(&fr, 0.5, 1.0);
    patches[i].to = (int)(rng_u64(&fr) % VLFF_SIM_CLASSES);
    patches[i].from = rng_uniform(&fr) < 0.7 ? -2 : -1; /* -2: to the partner of what is there */
  }
  /* Camera heading: view-dependent errors depend on where the camera looks. */
  double yaw = atan2(f->c2w_true[6], f->c2w_true[2]);
  float offset_scale = (float)(0.25 * diff);
  float *frame_offset = acc + (size_t)NPROTO; /* scratch after the weights */
  random_unit(&fr, frame_offset, D);
  float *w = acc; /* [NPROTO] class weights of one feature pixel */
  const double sx = (double)W / fw, sy = (double)H / fh;
  /* Boundary blur: the window spans ~1.5 feature pixels, like LSeg's
   * upsampled low-resolution decoder output. */
  const int rad = (int)ceil(0.75 * sx);
  const float sigma = (float)(0.9 * diff / sqrt((double)D) * 1.0);
  for (int j = 0; j < fh; j++) {
    for (int i = 0; i < fw; i++) {
      memset(w, 0, NPROTO * sizeof(float));
      int u0 = (int)((i + 0.5) * sx), v0 = (int)((j + 0.5) * sy);
      float tot = 0;
      for (int dv = -rad; dv <= rad; dv += 2)
        for (int du = -rad; du <= rad; du += 2) {
          int u = u0 + du, v = v0 + dv;
          if (u < 0 || v < 0 || u >= W || v >= H) continue;
          int l = f->label[(size_t)v * W + u];
          w[l < VLFF_SIM_CLASSES ? l : P_CEIL] += 1;
          tot += 1;
        }
      if (tot > 0)
        for (int c = 0; c < NPROTO; c++) w[c] /= tot;
      int uc = u0 < W ? u0 : W - 1, vc = v0 < H ? v0 : H - 1;
      int lc = f->label[(size_t)vc * W + uc];
      int cc = lc < VLFF_SIM_CLASSES ? lc : P_CEIL;
      /* View-dependent confusion toward the partner class: strongest at
       * grazing angles and from some headings, consistent within a view. */
      double cv = cosview[(size_t)vc * W + uc];
      double view = s->view_strength[cc] * 0.5 * (1 + sin(2 * yaw + s->view_phase[cc]));
      double graze = (1 - cv) * (1 - cv);
      double dist = f->depth_gt[(size_t)vc * W + uc];
      double far = dist > 3.5 ? fmin(1.0, (dist - 3.5) / 2.5) : 0;
      double m = diff * (0.9 * view + 0.6 * graze + 0.5 * far);
      if (m > 0.85) m = 0.85;
      int pc = s->partner[cc];
      w[pc] += (float)m * w[cc];
      w[cc] *= (float)(1 - m);
      int pi = primbuf[(size_t)vc * W + uc], obj = pi >= 0 && s->cfg.object_bias > 0 ? s->prims[pi].obj : -1;
      if (obj >= 0) {
        float om = s->obj_mix[obj];
        w[s->obj_to[obj]] += om * w[cc];
        w[cc] *= 1 - om;
      }
      for (int k = 0; k < np; k++) {
        double dx = i + 0.5 - patches[k].x, dy = j + 0.5 - patches[k].y;
        double q = (dx * dx + dy * dy) / (patches[k].rad * patches[k].rad);
        if (q >= 1) continue;
        double a = patches[k].w * (1 - q * q);
        int to = patches[k].from == -2 ? s->partner[cc] : patches[k].to;
        for (int c = 0; c < NPROTO; c++) w[c] *= (float)(1 - a);
        w[to] += (float)a;
      }
      uint16_t *out = f->features + ((size_t)j * fw + i) * D;
      struct rng pr = rng_make(s->seed, 4, ((uint64_t)index << 24) ^ ((uint64_t)j << 12) ^ (uint64_t)i);
      float *v = frame_offset + D; /* scratch: one feature vector */
      feature_noise(pr.s, offset_scale, frame_offset, sigma, v, D);
      for (int c = 0; c < NPROTO; c++)
        if (w[c] != 0) feature_mix(w[c], s->proto + (size_t)c * D, v, D);
      if (obj >= 0) feature_mix(1.0f, s->obj_vec + (size_t)obj * D, v, D);
      vlff_f32_to_f16_n(v, out, (size_t)D);
    }
  }
}

/* ---- rendering ---------------------------------------------------------- */

int vlff_sim_render(const struct vlff_sim *s, long long index, unsigned what,
                    struct vlff_sim_frame *f, char *err, size_t errlen) {
  if (index < 0) {
    vlff_errf(err, errlen, "sim: frame index %lld is negative", index);
    return -1;
  }
  if (!f || f->width != s->width || f->height != s->height || f->feature_dim != s->dim) {
    vlff_errf(err, errlen, "sim: frame buffer does not match this sim's sizes");
    return -1;
  }
  const int W = s->width, H = s->height;
  f->index = index;
  f->time_s = (double)index / s->cfg.rate_hz;
  f->fx = s->fx, f->fy = s->fy, f->cx = s->cx, f->cy = s->cy;
  true_pose(s, index, f->c2w_true);
  memcpy(f->c2w, f->c2w_true, sizeof f->c2w);
  f->bad_pose = is_bad_pose(s, index);
  if (f->bad_pose) corrupt_pose(s, index, f->c2w);
  const double *M = f->c2w_true;
  const double o[3] = {M[3], M[7], M[11]};
  const struct sim_world *w = world_at(s, f->time_s);
  float *cosview = malloc((size_t)W * H * sizeof(float));
  int *primbuf = malloc((size_t)W * H * sizeof(int));
  float *scratch = malloc((size_t)(NPROTO + 2 * s->dim) * sizeof(float));
  if (!cosview || !scratch || !primbuf) {
    free(cosview), free(scratch), free(primbuf);
    vlff_errf(err, errlen, "sim: out of memory rendering frame %lld", index);
    return -1;
  }
  struct rng nr = rng_make(s->seed, 2, (uint64_t)index);
  const double dn = s->cfg.depth_noise_m, holes = s->cfg.depth_hole_frac,
               dmax = s->cfg.depth_max_m;
  /* Holes come in small blobs, like stereo matching failures: seed blob
   * centres so the expected invalid fraction is depth_hole_frac. */
  int nblob = (int)(holes * W * H / 18.0 + 0.5);
  struct lattice_cache lc[2] = {{0}, {0}};
  for (int v = 0; v < H; v++) {
    for (int u = 0; u < W; u++) {
      size_t k = (size_t)v * W + u;
      double dc[3] = {(u + 0.5 - s->cx) / s->fx, (v + 0.5 - s->cy) / s->fy, 1.0};
      double d[3] = {M[0] * dc[0] + M[1] * dc[1] + M[2] * dc[2],
                     M[4] * dc[0] + M[5] * dc[1] + M[6] * dc[2],
                     M[8] * dc[0] + M[9] * dc[1] + M[10] * dc[2]};
      int pi;
      double n[3];
      double t = cast(w, o, d, &pi, n);
      if (t < 0) {
        f->label[k] = VLFF_SIM_UNLABELLED;
        f->depth_gt[k] = 0;
        f->rgb[3 * k] = f->rgb[3 * k + 1] = f->rgb[3 * k + 2] = 0;
        cosview[k] = 1;
        primbuf[k] = -1;
        continue;
      }
      const struct prim *p = &w->prims[pi];
      double x[3] = {o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]};
      f->label[k] = (uint8_t)p->label;
      primbuf[k] = pi;
      f->depth_gt[k] = (float)t; /* d has unit z in the camera frame */
      double dl = sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
      cosview[k] = (float)fabs((n[0] * d[0] + n[1] * d[1] + n[2] * d[2]) / dl);
      if (what & VLFF_SIM_RGBD) {
        float c[3];
        shade(s, lc, p, x, n, c);
        for (int i = 0; i < 3; i++) {
          double val = c[i] * 255.0 + 1.5 * rng_normal(&nr);
          f->rgb[3 * k + i] = (uint8_t)(val < 0 ? 0 : val > 255 ? 255 : val + 0.5);
        }
      }
    }
  }
  if (what & VLFF_SIM_RGBD) {
    for (size_t k = 0; k < (size_t)W * H; k++) {
      double z = f->depth_gt[k];
      double m = z + dn * z * z * rng_normal(&nr);
      /* grazing surfaces fail more often in stereo */
      if (z <= 0 || z > dmax || m <= 0 || rng_uniform(&nr) < 0.02 * holes / (0.05 + cosview[k])) m = 0;
      f->depth[k] = (float)m;
    }
    for (int b = 0; b < nblob; b++) {
      int bu = (int)(rng_uniform(&nr) * W), bv = (int)(rng_uniform(&nr) * H);
      int br = 1 + (int)(rng_uniform(&nr) * 2);
      for (int v = bv - br; v <= bv + br; v++)
        for (int u = bu - br; u <= bu + br; u++)
          if (u >= 0 && v >= 0 && u < W && v < H) f->depth[(size_t)v * W + u] = 0;
    }
    for (size_t k = 0; k < (size_t)W * H; k++) {
      double mm = f->depth[k] * 1000.0 + 0.5;
      f->depth_mm[k] = (uint16_t)(mm > 65535 ? 0 : mm);
    }
  }
  if (what & VLFF_SIM_FEATURES) render_features(s, index, f, cosview, primbuf, scratch);
  free(cosview);
  free(primbuf);
  free(scratch);
  return 0;
}

int vlff_sim_object_box(const struct vlff_sim *s, const char *name, double time_s, double lo[3], double hi[3],
                        char *err, size_t errlen) {
  int o = find_object(s, -1, name, err, errlen);
  if (o < 0) return -1;
  const struct sim_world *w = world_at(s, time_s);
  for (int k = 0; k < 3; k++) lo[k] = INFINITY, hi[k] = -INFINITY;
  for (int i = 0; i < s->nprims; i++)
    for (int k = 0; k < 3 && s->prims[i].obj == o; k++)
      lo[k] = fmin(lo[k], w->prims[i].lo[k]), hi[k] = fmax(hi[k], w->prims[i].hi[k]);
  for (int i = 0; i < w->count; i++)
    if (w->prims[w->order[i]].obj == o) return 1;
  return 0;
}

/* ---- lifetime ----------------------------------------------------------- */

struct vlff_sim *vlff_sim_create(const struct vlff_cfg_sim *sim, const struct vlff_cfg_field *field, char *err,
                                 size_t errlen) {
  double bl[3], bh[3];
  vlff_config_sim_box(sim, field, bl, bh);
  for (int k = 0; k < 3; k++)
    if (!(bh[k] - bl[k] >= 2.6)) {
      vlff_errf(err, errlen,
                "sim: the world's box (sim.scene_min/max, else field.scene_min/max) axis %d spans %.2f m; the room "
                "needs at least 2.6 m",
                k, bh[k] - bl[k]);
      return NULL;
    }
  if (sim->width < 16 || sim->height < 16 || field->feature_dim < 1 || sim->rate_hz <= 0) {
    vlff_errf(err, errlen, "sim: invalid sizes (%dx%d, D=%d) or rate %.3f", sim->width, sim->height,
           field->feature_dim, sim->rate_hz);
    return NULL;
  }
  if (sim->layout == VLFF_LAYOUT_FLAT) {
    double ax = bh[0] - bl[0] - 0.2, ay = bh[1] - bl[1] - 0.2;
    if (ax < 6 || ay < 6 || ax * ay < 60) {
      vlff_errf(err, errlen,
                "sim: sim.layout flat fills the world's box (sim.scene_min/max, else field.scene_min/max): its "
                "floor is %.1f x %.1f m; it needs at least 6 m each way and 60 m^2",
                ax, ay);
      return NULL;
    }
  }
  if (sim->layout == VLFF_LAYOUT_BUILDING) {
    if (sim->flats < 2 || sim->flats > MAX_FLATS) {
      vlff_errf(err, errlen, "sim: sim.flats is %d; the building holds 2 to %d flats", sim->flats, MAX_FLATS);
      return NULL;
    }
    /* the floor: the flats (less their interior walls) and the corridor */
    double ax = bh[0] - bl[0] - 0.2, ay = bh[1] - bl[1] - 0.2;
    double wf = (ax - (sim->flats - 1) * 0.1) / sim->flats, df = ay - CORRIDOR_M - 0.1;
    double floor = sim->flats * (wf - 0.1) * (df - 0.1) + ax * CORRIDOR_M;
    if (wf < 6 || df < 6 || floor < 200) {
      vlff_errf(err, errlen,
                "sim: sim.layout building fills the world's box (sim.scene_min/max, else field.scene_min/max) with "
                "%d flats of %.1f x %.1f m off a %.1f m corridor, %.0f m^2 of floor; each flat needs at least 6 m "
                "each way and the building 200 m^2",
                sim->flats, wf, df, CORRIDOR_M, floor);
      return NULL;
    }
  }
  struct vlff_sim *s = calloc(1, sizeof *s);
  if (!s) {
    vlff_errf(err, errlen, "sim: out of memory");
    return NULL;
  }
  s->cfg = *sim;
  s->seed = (uint32_t)sim->seed;
  s->width = sim->width, s->height = sim->height, s->dim = field->feature_dim;
  s->fw = s->width / 4 > 0 ? s->width / 4 : 1;
  s->fh = s->height / 4 > 0 ? s->height / 4 : 1;
  /* ~65 degrees horizontal field of view, square pixels, centred. */
  s->fx = s->fy = 0.5 * s->width / tan(0.5 * 65.0 * M_PI / 180.0);
  s->cx = 0.5 * s->width, s->cy = 0.5 * s->height;
  struct rng r = rng_make(s->seed, 0, 0);
  const int flat = sim->layout == VLFF_LAYOUT_FLAT || sim->layout == VLFF_LAYOUT_BUILDING;
  void (*build)(struct vlff_sim *, int) = sim->layout == VLFF_LAYOUT_FLAT       ? build_flat
                                          : sim->layout == VLFF_LAYOUT_BUILDING ? build_building
                                                                                : build_room;
  for (int k = 0; k < 2; k++) {
    double c = 0.5 * (bl[k] + bh[k]);
    double half = fmin(0.5 * (bh[k] - bl[k]) - 0.1, 4.0) * rng_range(&r, 0.8, 1.0);
    if (flat) half = 0.5 * (bh[k] - bl[k]) - 0.1; /* the flat or building fills the box */
    s->room_lo[k] = c - half, s->room_hi[k] = c + half;
  }
  double cz = 0.5 * (bl[2] + bh[2]);
  double hgt = fmin(rng_range(&r, 2.4, 2.8), bh[2] - bl[2] - 0.2);
  s->room_lo[2] = cz - 0.5 * hgt, s->room_hi[2] = cz + 0.5 * hgt;
  /* Re-draw crowded layouts that could not place every class; keep the
   * fullest if none manages all twenty. */
  int best_attempt = 0, best_classes = -1;
  for (int attempt = 0; attempt < (sim->layout == VLFF_LAYOUT_BUILDING ? 1 : 16); attempt++) {
    build(s, attempt);
    int have[VLFF_SIM_CLASSES] = {0}, nc = 0;
    for (int i = 0; i < s->nprims; i++)
      if (s->prims[i].label < VLFF_SIM_CLASSES && !have[s->prims[i].label]++) nc++;
    if (nc > best_classes) best_classes = nc, best_attempt = attempt;
    if (nc == VLFF_SIM_CLASSES) break;
  }
  build(s, best_attempt);
  if (s->nprims < 6) {
    vlff_sim_destroy(s);
    vlff_errf(err, errlen, "sim: out of memory building the room");
    return NULL;
  }
  for (int k = 0; k < 3; k++) s->bbox_lo[k] = s->room_lo[k] - 0.1, s->bbox_hi[k] = s->room_hi[k] + 0.1;
  for (int i = 0; i < s->nprims; i++)
    if (s->prims[i].label < VLFF_SIM_CLASSES) s->class_counts[s->prims[i].label]++;
  if (build_features(s) < 0 || build_objects(s) < 0) {
    vlff_sim_destroy(s);
    vlff_errf(err, errlen, "sim: out of memory");
    return NULL;
  }
  if (build_worlds(s, err, errlen)) {
    vlff_sim_destroy(s);
    return NULL;
  }
  return s;
}

void vlff_sim_destroy(struct vlff_sim *s) {
  if (!s) return;
  for (int i = 0; i < s->nworlds; i++) VLFF_FREE_ALL(s->worlds[i].prims, s->worlds[i].nodes, s->worlds[i].order);
  VLFF_FREE_ALL(s->worlds, s->prims, s->proto, s->text, s->generic, s->obj_vec, s->obj_mix,
                s->obj_to, s);
}

struct vlff_sim_frame *vlff_sim_frame_new(const struct vlff_sim *s) {
  struct vlff_sim_frame *f = calloc(1, sizeof *f);
  if (!f) return NULL;
  size_t n = (size_t)s->width * s->height;
  f->width = s->width, f->height = s->height;
  f->feat_width = s->fw, f->feat_height = s->fh, f->feature_dim = s->dim;
  f->rgb = calloc(n * 3, 1);
  f->depth = calloc(n, sizeof(float));
  f->depth_gt = calloc(n, sizeof(float));
  f->depth_mm = calloc(n, sizeof(uint16_t));
  f->label = calloc(n, 1);
  f->features = calloc((size_t)s->fw * s->fh * s->dim, sizeof(uint16_t));
  if (!f->rgb || !f->depth || !f->depth_gt || !f->depth_mm || !f->label || !f->features) {
    vlff_sim_frame_free(f);
    return NULL;
  }
  return f;
}

void vlff_sim_frame_free(struct vlff_sim_frame *f) {
  if (!f) return;
  free(f->rgb), free(f->depth), free(f->depth_gt), free(f->depth_mm), free(f->label), free(f->features);
  free(f);
}

void vlff_sim_intrinsics(const struct vlff_sim *s, double *fx, double *fy, double *cx, double *cy) {
  *fx = s->fx, *fy = s->fy, *cx = s->cx, *cy = s->cy;
}

void vlff_sim_size(const struct vlff_sim *s, int *width, int *height, int *feat_width,
                   int *feat_height, int *feature_dim) {
  if (width) *width = s->width;
  if (height) *height = s->height;
  if (feat_width) *feat_width = s->fw;
  if (feat_height) *feat_height = s->fh;
  if (feature_dim) *feature_dim = s->dim;
}

void vlff_sim_bounds(const struct vlff_sim *s, double lo[3], double hi[3]) {
  memcpy(lo, s->room_lo, 3 * sizeof(double));
  memcpy(hi, s->room_hi, 3 * sizeof(double));
}

int vlff_sim_rooms(const struct vlff_sim *s, struct vlff_sim_room *out, int max) {
  for (int i = 0; i < s->nrooms && i < max; i++) {
    const double *rm = s->rooms[i];
    out[i] = (struct vlff_sim_room){{rm[0], rm[1]}, {rm[2], rm[3]}, s->room_flat[i]};
  }
  return s->nrooms;
}

int vlff_sim_flat_count(const struct vlff_sim *s) { return s->nflats; }

int vlff_sim_flat_at(const struct vlff_sim *s, double x, double y) {
  for (int k = 0; k < s->nflats; k++) {
    const double *f = s->flats[k];
    if (x >= f[0] && x <= f[2] && y >= f[1] && y <= f[3]) return k;
  }
  return -1;
}

double vlff_sim_walk_length(const struct vlff_sim *s) { return s->nway > 1 ? s->way_len[s->nway] : 0; }

void vlff_sim_class_counts(const struct vlff_sim *s, int counts[VLFF_SIM_CLASSES]) {
  memcpy(counts, s->class_counts, sizeof s->class_counts);
}

/* ---- ground-truth point set -------------------------------------------- */

struct vox_entry {
  uint64_t key;
  uint32_t idx;
};

int vlff_sim_points(const struct vlff_sim *s, int nframes, int step, double voxel,
                    struct vlff_sim_points *out, char *err, size_t errlen) {
  return vlff_sim_points_budget(s, nframes, step, voxel, UINT64_MAX, out, err, errlen);
}

int vlff_sim_points_budget(const struct vlff_sim *s, int nframes, int step, double voxel, uint64_t max_rays,
                           struct vlff_sim_points *out, char *err, size_t errlen) {
  memset(out, 0, sizeof *out);
  if (nframes < 1 || step < 1 || !(voxel > 0) || max_rays < 16) {
    vlff_errf(err, errlen, "sim: points need nframes >= 1, step >= 1, voxel > 0 and 16 rays or more");
    return -1;
  }
  size_t cap = 1 << 16, n = 0;
  size_t hcap = 1 << 18;
  struct vox_entry *tab = calloc(hcap, sizeof *tab);
  out->xyz = malloc(cap * 3 * sizeof(float));
  out->label = malloc(cap);
  if (!tab || !out->xyz || !out->label) goto oom;
  /* Every second pixel of each chosen view; one point per voxel keeps the
   * density roughly uniform whatever the number of views. The scene as it
   * stands at the last of those frames (sim.changes). Within the ray budget:
   * a view of at most a sixteenth of it, then as many views as it holds. */
  int px = 2;
  while ((uint64_t)((s->width + px - 1) / px) * (uint64_t)((s->height + px - 1) / px) > max_rays / 16)
    px *= 2;
  const uint64_t per_view = (uint64_t)((s->width + px - 1) / px) * (uint64_t)((s->height + px - 1) / px);
  while (step < nframes && (uint64_t)((nframes + step - 1) / step) * per_view > max_rays)
    step = step > nframes / 2 ? nframes : 2 * step;
  const struct sim_world *w = world_at(s, (double)(nframes - 1) / s->cfg.rate_hz);
  for (int fi = 0; fi < nframes; fi += step) {
    double M[16];
    true_pose(s, fi, M);
    const double o[3] = {M[3], M[7], M[11]};
    out->rays += per_view;
    for (int v = 0; v < s->height; v += px)
      for (int u = 0; u < s->width; u += px) {
        double dc[3] = {(u + 0.5 - s->cx) / s->fx, (v + 0.5 - s->cy) / s->fy, 1.0};
        double d[3] = {M[0] * dc[0] + M[1] * dc[1] + M[2] * dc[2], M[4] * dc[0] + M[5] * dc[1] + M[6] * dc[2],
                       M[8] * dc[0] + M[9] * dc[1] + M[10] * dc[2]};
        int pi;
        double t = cast(w, o, d, &pi, NULL);
        if (t < 0 || t > s->cfg.depth_max_m) continue;
        double x[3] = {o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]};
        int64_t ix = (int64_t)floor(x[0] / voxel), iy = (int64_t)floor(x[1] / voxel),
                iz = (int64_t)floor(x[2] / voxel);
        uint64_t key = ((uint64_t)(ix & 0x1fffff) << 42) | ((uint64_t)(iy & 0x1fffff) << 21) |
                       (uint64_t)(iz & 0x1fffff);
        uint64_t h = vlff_mix64(key) & (hcap - 1);
        int found = 0;
        while (tab[h].key) {
          if (tab[h].key == key + 1) {
            found = 1;
            break;
          }
          h = (h + 1) & (hcap - 1);
        }
        if (found) continue;
        if (n == cap) {
          cap *= 2;
          float *nx = realloc(out->xyz, cap * 3 * sizeof(float));
          if (!nx) goto oom;
          out->xyz = nx;
          uint8_t *nl = realloc(out->label, cap);
          if (!nl) goto oom;
          out->label = nl;
        }
        if (2 * (n + 1) > hcap) {
          size_t ncap = hcap * 2;
          struct vox_entry *nt = calloc(ncap, sizeof *nt);
          if (!nt) goto oom;
          for (size_t i = 0; i < hcap; i++)
            if (tab[i].key) {
              uint64_t hh = vlff_mix64(tab[i].key - 1) & (ncap - 1);
              while (nt[hh].key) hh = (hh + 1) & (ncap - 1);
              nt[hh] = tab[i];
            }
          free(tab);
          tab = nt, hcap = ncap;
          h = vlff_mix64(key) & (hcap - 1);
          while (tab[h].key) h = (h + 1) & (hcap - 1);
        }
        tab[h].key = key + 1;
        tab[h].idx = (uint32_t)n;
        for (int k = 0; k < 3; k++) out->xyz[3 * n + k] = (float)x[k];
        out->label[n] = (uint8_t)s->prims[pi].label;
        n++;
      }
  }
  free(tab);
  out->n = n;
  return 0;
oom:
  free(tab);
  vlff_sim_points_free(out);
  vlff_errf(err, errlen, "sim: out of memory sampling points");
  return -1;
}

void vlff_sim_points_free(struct vlff_sim_points *p) {
  if (!p) return;
  free(p->xyz), free(p->label);
  p->xyz = NULL, p->label = NULL, p->n = 0;
}
