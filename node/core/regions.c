#include "regions.h"

#include <math.h>
#include <stdbool.h>
#include <stdlib.h>
#include <string.h>

#include "best.h"

/* Edge weight per unit of colour distance (rgb in 0..1) and per metre
 * between the cells' surface points beyond the sensor's noise (regions.h). */
#define COLOUR_WEIGHT 2.0f
#define METRE_WEIGHT 1.0f
/* The noise a step must pass, in sigmas of the farther point's depth (the
 * band depth-guided training and the snap use, field_internal.h). */
#define NOISE_SIGMAS 3.0f
/* A cell's weight in its region's mean is its margin (best minus second
 * sum) plus this: cells whose own reading is clear say more about what
 * their surface is, and a region of cells with no margin still averages. */
#define MARGIN_FLOOR 0.02f
/* Felzenszwalb's k for a grid of this many cells; scaled with the grid. */
#define K_CELLS 2400.0
/* Two regions join only when their mean colours (rgb in 0..1, Euclidean)
 * are at most this far apart: Felzenszwalb's rule looks at edges alone,
 * and a chain of small steps leaks one surface into the next (a checkered
 * door into its wall through squares like the wall's). */
#define MEAN_COLOUR_MAX 0.1f

struct edge {
  float w;
  uint32_t a, b; /* surface cell numbers */
};

struct vlff_regions {
  int lw, lh;
  size_t ncell;
  int32_t *at;      /* [ncell] the surface cell number of a grid cell, -1 none */
  float *sigma;     /* [ncell] per surface cell: its depth noise sigma (m) */
  uint32_t *parent, *size, *root_id;
  float *inner;     /* [ncell] a region's largest internal edge (at its root) */
  float *csum;      /* [ncell][3] a region's colour sum (at its root) */
  struct edge *edges;
  uint32_t *region; /* [ncell] per surface cell, after build */
  size_t n, nregions;
  float *sum;       /* [regions][K] */
  size_t sum_cap;
};

struct vlff_regions *vlff_regions_create(int lw, int lh) {
  if (lw < 1 || lh < 1 || (size_t)lw > SIZE_MAX / 8 / (size_t)lh) return NULL;
  struct vlff_regions *r = calloc(1, sizeof *r);
  if (!r) return NULL;
  size_t n = (size_t)lw * lh;
  r->lw = lw, r->lh = lh, r->ncell = n;
  r->at = malloc(n * sizeof *r->at);
  r->sigma = malloc(n * sizeof *r->sigma);
  r->parent = malloc(n * sizeof *r->parent);
  r->size = malloc(n * sizeof *r->size);
  r->root_id = malloc(n * sizeof *r->root_id);
  r->inner = malloc(n * sizeof *r->inner);
  r->csum = malloc(n * 3 * sizeof *r->csum);
  r->edges = malloc(n * 4 * sizeof *r->edges);
  r->region = malloc(n * sizeof *r->region);
  if (!r->at || !r->sigma || !r->parent || !r->size || !r->root_id || !r->inner || !r->csum || !r->edges ||
      !r->region) {
    vlff_regions_destroy(r);
    return NULL;
  }
  for (size_t i = 0; i < n; i++) r->at[i] = -1;
  return r;
}

void vlff_regions_destroy(struct vlff_regions *r) {
  if (!r) return;
  free(r->at), free(r->sigma), free(r->parent), free(r->size), free(r->root_id);
  free(r->inner), free(r->csum);
  free(r->edges), free(r->region), free(r->sum);
  free(r);
}

/* The mean colours of two regions (colour sums over sizes) further apart
 * than MEAN_COLOUR_MAX. */
static bool mean_colours_apart(const float *sa, uint32_t na, const float *sb, uint32_t nb) {
  float d = 0;
  for (int c = 0; c < 3; c++) {
    const float q = sa[c] / (float)na - sb[c] / (float)nb;
    d += q * q;
  }
  return d > MEAN_COLOUR_MAX * MEAN_COLOUR_MAX;
}

static uint32_t find(uint32_t *parent, uint32_t x) {
  while (parent[x] != x) parent[x] = parent[parent[x]], x = parent[x];
  return x;
}

static int edge_cmp(const void *x, const void *y) {
  const struct edge *a = x, *b = y;
  if (a->w != b->w) return a->w < b->w ? -1 : 1;
  /* ties in a fixed order: the same image always gives the same regions */
  if (a->a != b->a) return a->a < b->a ? -1 : 1;
  return (a->b > b->b) - (a->b < b->b);
}

void vlff_regions_colours(const uint8_t *rgb, int width, int height, int lw, int lh, const uint32_t *pix, size_t n,
                          float *col) {
  for (size_t i = 0; i < n; i++) {
    float *out = col + 3 * i;
    if (!rgb || width < 1 || height < 1 || lw < 1 || lh < 1 || pix[i] >= (uint64_t)lw * (uint64_t)lh) {
      out[0] = out[1] = out[2] = 0;
      continue;
    }
    const int cx = (int)(pix[i] % (uint32_t)lw), cy = (int)(pix[i] / (uint32_t)lw);
    int x0 = (int)((long)cx * width / lw), x1 = (int)((long)(cx + 1) * width / lw);
    int y0 = (int)((long)cy * height / lh), y1 = (int)((long)(cy + 1) * height / lh);
    if (x1 <= x0) x1 = x0 + 1; /* a grid finer than the image: the pixel under the cell */
    if (y1 <= y0) y1 = y0 + 1;
    double s[3] = {0, 0, 0};
    for (int y = y0; y < y1; y++)
      for (int x = x0; x < x1; x++)
        for (int c = 0; c < 3; c++) s[c] += rgb[((size_t)y * width + x) * 3 + c];
    const double cnt = (double)(x1 - x0) * (y1 - y0) * 255.0;
    for (int c = 0; c < 3; c++) out[c] = (float)(s[c] / cnt);
  }
}

size_t vlff_regions_build(struct vlff_regions *r, const float *col, const uint32_t *pix, const float *xyz, size_t n,
                          const double origin[3], float noise_1m) {
  if (r->n) /* the last build's cells are forgotten */
    for (size_t i = 0; i < r->ncell; i++) r->at[i] = -1;
  if (n > r->ncell) n = r->ncell;
  r->n = 0;
  const int lw = r->lw, lh = r->lh;
  for (size_t i = 0; i < n; i++) {
    if (pix[i] >= r->ncell || r->at[pix[i]] >= 0) continue; /* outside the grid, or twice: a region of its own */
    r->at[pix[i]] = (int32_t)i;
  }
  r->n = n;
  if (!(noise_1m >= 0) || !isfinite(noise_1m)) noise_1m = 0;
  for (size_t i = 0; i < n; i++) {
    r->parent[i] = (uint32_t)i, r->size[i] = 1, r->inner[i] = 0;
    for (int c = 0; c < 3; c++) r->csum[3 * i + c] = col ? col[3 * i + c] : 0.0f;
    /* the depth noise's sigma at the point's range: noise_1m d^2 */
    float d2 = 0;
    for (int c = 0; c < 3; c++) {
      const float q = xyz[3 * i + c] - (float)origin[c];
      d2 += q * q;
    }
    const float sg = noise_1m * d2;
    /* a camera position that is not a number tells no range: every step
     * counts, as without a noise */
    r->sigma[i] = isfinite(sg) ? sg : 0.0f;
  }
  /* the edges to the right, down, down-right and down-left neighbours */
  size_t ne = 0;
  static const int off[4][2] = {{1, 0}, {0, 1}, {1, 1}, {-1, 1}};
  for (size_t i = 0; i < n; i++) {
    if (pix[i] >= r->ncell || r->at[pix[i]] != (int32_t)i) continue;
    int cx = (int)(pix[i] % (uint32_t)lw), cy = (int)(pix[i] / (uint32_t)lw);
    for (int t = 0; t < 4; t++) {
      int nx = cx + off[t][0], ny = cy + off[t][1];
      if (nx < 0 || nx >= lw || ny >= lh) continue;
      int32_t j = r->at[(size_t)ny * lw + nx];
      if (j < 0) continue;
      float dc = 0, dp = 0;
      for (int c = 0; c < 3; c++) {
        float q = col ? col[3 * i + c] - col[3 * (size_t)j + c] : 0.0f;
        dc += q * q;
        q = xyz[3 * i + c] - xyz[3 * (size_t)j + c];
        dp += q * q;
      }
      /* two measurements of one surface differ by their noise: only a step
       * beyond it separates (a stereo camera's is a decimetre at 3 m) */
      const float sig = r->sigma[i] > r->sigma[j] ? r->sigma[i] : r->sigma[j];
      float step = sqrtf(dp) - NOISE_SIGMAS * sig;
      if (step < 0) step = 0;
      float w = COLOUR_WEIGHT * sqrtf(dc) + METRE_WEIGHT * step;
      if (!isfinite(w)) continue; /* a point that is not one joins nothing */
      r->edges[ne++] = (struct edge){w, (uint32_t)i, (uint32_t)j};
    }
  }
  qsort(r->edges, ne, sizeof *r->edges, edge_cmp);
  const float k = (float)((double)r->ncell / K_CELLS);
  for (size_t t = 0; t < ne; t++) {
    uint32_t a = find(r->parent, r->edges[t].a), b = find(r->parent, r->edges[t].b);
    if (a == b) continue;
    const float w = r->edges[t].w;
    if (w > r->inner[a] + k / (float)r->size[a] || w > r->inner[b] + k / (float)r->size[b]) continue;
    if (col && mean_colours_apart(r->csum + 3 * a, r->size[a], r->csum + 3 * b, r->size[b])) continue;
    if (r->size[a] < r->size[b]) {
      uint32_t q = a;
      a = b, b = q;
    }
    r->parent[b] = a, r->size[a] += r->size[b];
    for (int c = 0; c < 3; c++) r->csum[3 * a + c] += r->csum[3 * b + c];
    r->inner[a] = w; /* edges come in increasing weight: the largest so far */
  }
  size_t nr = 0;
  for (size_t i = 0; i < n; i++) r->root_id[i] = UINT32_MAX;
  for (size_t i = 0; i < n; i++) {
    uint32_t root = find(r->parent, (uint32_t)i);
    if (r->root_id[root] == UINT32_MAX) r->root_id[root] = (uint32_t)nr++;
    r->region[i] = r->root_id[root];
  }
  r->nregions = nr;
  return nr;
}

uint32_t vlff_regions_of(const struct vlff_regions *r, size_t i) { return i < r->n ? r->region[i] : UINT32_MAX; }

int vlff_regions_vote(struct vlff_regions *r, const float *scores, size_t n, int K, float beta, int *label,
                      float *score) {
  if (n > r->n) n = r->n;
  if (K < 1 || n == 0 || r->nregions == 0) return 0;
  /* beta 0, negative or not a number: each cell's own best; the vote
   * itself compares own / beta + mean for beta > 1 (the same order), so
   * that a huge beta cannot overflow into infinities */
  if (!(beta > 0)) beta = 0;
  const float own_w = beta > 1 ? 1.0f / beta : 1.0f, mean_w = beta > 1 ? 1.0f : beta;
  const size_t need = r->nregions * (size_t)K;
  if (need > r->sum_cap) {
    float *s = realloc(r->sum, need * sizeof *s);
    if (!s) return -1;
    r->sum = s, r->sum_cap = need;
  }
  memset(r->sum, 0, need * sizeof *r->sum);
  float *wsum = r->inner; /* free after build: the weight per region */
  memset(wsum, 0, r->nregions * sizeof *wsum);
  uint8_t *skip = (uint8_t *)r->root_id; /* free after build too: cells that neither vote nor are voted */
  for (size_t i = 0; i < n; i++) {
    const float *own = scores + i * (size_t)K;
    bool finite = true;
    for (int c = 0; c < K; c++) finite &= isfinite(own[c]) != 0;
    /* nothing scored it, or a score that is not a number (which would
     * take its whole region with it): it keeps its label */
    skip[i] = label[i] < 0 || !finite;
    if (skip[i]) continue;
    float gap;
    vlff_best_of(own, K, &gap);
    const float wt = (K > 1 ? gap : 1.0f) + MARGIN_FLOOR;
    /* finite scores whose margin is not (near FLT_MAX apart): as one
     * that is not a number */
    if (!isfinite(wt)) {
      skip[i] = 1;
      continue;
    }
    wsum[r->region[i]] += wt;
    float *s = r->sum + (size_t)r->region[i] * K;
    for (int c = 0; c < K; c++) s[c] += wt * own[c];
  }
  for (size_t i = 0; i < n; i++) {
    if (skip[i]) continue;
    const uint32_t g = r->region[i];
    const float *s = r->sum + (size_t)g * K, *own = scores + i * (size_t)K;
    const float wr = mean_w / wsum[g];
    int best = 0;
    float bv = -INFINITY;
    bool sane = isfinite(wr);
    for (int c = 0; c < K; c++) {
      const float m = wr * s[c];
      sane &= isfinite(m) != 0;
      const float v = own_w * own[c] + m;
      if (v > bv) bv = v, best = c;
    }
    /* a region whose sums overflowed says nothing: the cell's own best */
    label[i] = sane ? best : vlff_best_of(own, K, NULL);
    if (score) score[i] = own[label[i]];
  }
  return 0;
}
