/*
 * Queries: prompts, 3D points and 2D renders.
 *
 * With prompts set, labels never form the D-dim feature: the prompt matrix E
 * (K x D, rows unit length) is folded into MLP3's last layer, so
 * E f = (E W) h + E b costs K x H per point instead of D x H, and the norm
 * |f|^2 = hᵀ(WᵀW)h + 2 (Wᵀb).h + |b|^2 (needed for cosine scores) costs H x H
 * and is computed only when scores or margins are requested. Rendering is
 * linear in the feature, so 2D labels fold the same way on the rendered h.
 * 3D queries run MLP3's hidden layers feature-major (points along rows) and
 * score them with a kernel that keeps a panel of points in vector lanes
 * (score_impl.h): the logits cost exactly K x H, the triangular norm skips
 * R's zeros and never stores R h, and the argmax runs across lanes.
 * Points are processed in the caller's order, in blocks of VLFF_QUERY_BLOCK;
 * callers get the best cache behaviour by passing grid (x-fastest) order,
 * which the map publisher does anyway (see the benchmark: grid vs random).
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>
#include <stdio.h>

#include "field_internal.h"

int vlff_field_set_prompts(struct vlff_field *f, const float *emb, int k, char *err, size_t errlen) {
  if (k < 0 || k > VLFF_FIELD_MAX_PROMPTS || (k > 0 && !emb)) {
    if (err && errlen) snprintf(err, errlen, "field prompts: expected 0..%d embeddings, got %d", VLFF_FIELD_MAX_PROMPTS, k);
    return -1;
  }
  const int D = f->D;
  for (int i = 0; i < k; i++) {
    double n = 0;
    for (int j = 0; j < D; j++) {
      float x = emb[(size_t)i * D + j];
      if (!isfinite(x)) {
        if (err && errlen) snprintf(err, errlen, "field prompts: embedding %d has a non-finite value at %d", i, j);
        return -1;
      }
      n += (double)x * x;
    }
    if (!(n > 1e-20)) {
      if (err && errlen) snprintf(err, errlen, "field prompts: embedding %d is zero", i);
      return -1;
    }
  }
  for (int i = 0; i < k; i++) {
    double n = 0;
    for (int j = 0; j < D; j++) n += (double)emb[(size_t)i * D + j] * emb[(size_t)i * D + j];
    float inv = (float)(1.0 / sqrt(n));
    for (int j = 0; j < D; j++) f->E_[(size_t)i * D + j] = emb[(size_t)i * D + j] * inv;
  }
  f->K = k;
  f->bal_freq[0] = 0; /* class-balanced drawing restarts its counts */
  vlff_field_refresh(f);
  return 0;
}

/* Label, score and margin from K logits and the feature norm. */
static void pick(const float *logit, int K, float norm, int *label, float *score, float *margin) {
  int best = 0;
  float b1 = -INFINITY, b2 = -INFINITY;
  for (int k = 0; k < K; k++) {
    float v = logit[k];
    if (v > b1) {
      b2 = b1;
      b1 = v;
      best = k;
    } else if (v > b2) {
      b2 = v;
    }
  }
  float inv = norm > 1e-20f ? 1.0f / norm : 0.0f;
  if (label) *label = best;
  if (score) *score = b1 * inv;
  if (margin) *margin = K > 1 ? (b1 - b2) * inv : 0.0f;
}

/* sum_j (t_j + s r_j)^2 in 16 independent partial sums, so the loop
 * vectorises (a single running sum cannot be reordered without -ffast-math);
 * the order is fixed, so results do not vary from run to run. */
VLFF_HOT
static float sumsq_shifted(const float *t, float s, const float *r, int n) {
  enum { P = 16 };
  float acc[P] = {0};
  int j = 0;
  for (; j + P <= n; j += P)
    for (int k = 0; k < P; k++) {
      float y = t[j + k] + s * r[j + k];
      acc[k] += y * y;
    }
  float q = 0;
  for (; j < n; j++) {
    float y = t[j] + s * r[j];
    q += y * y;
  }
  for (int k = 0; k < P; k++) q += acc[k];
  return q;
}

/* Feature norms of n rendered/queried hidden vectors h (weight sums ws, or
 * NULL for 1): |W h + s b|. tmp holds n x H. */
static void feat_norms(const struct vlff_field *f, const float *h, const float *ws, int n, float *tmp, float *out) {
  const int H = f->H;
  if (f->chol_ok) {
    /* tmp = h Rt + s r12, one column block at a time over only the rows of
     * Rt that are not zero for it (k >= j0). */
    enum { JB = 32 };
    for (int j0 = 0; j0 < H; j0 += JB) {
      int nb = H - j0 < JB ? H - j0 : JB;
      vlff_gemm(n, nb, H - j0, h + j0, H, 1, f->Rt + (size_t)j0 * H + j0, H, tmp + j0, H, NULL, 0, 0);
    }
    for (int i = 0; i < n; i++) {
      float s = ws ? ws[i] : 1.0f, z = s * f->r22;
      out[i] = sqrtf(sumsq_shifted(tmp + (size_t)i * H, s, f->r12, H) + z * z);
    }
    return;
  }
  vlff_gemm(n, H, H, h, H, 1, f->G, H, tmp, H, NULL, 0, 0);
  for (int i = 0; i < n; i++) {
    const float *hi = h + (size_t)i * H, *ti = tmp + (size_t)i * H;
    float s = ws ? ws[i] : 1.0f, q = 0, uh = 0;
    for (int j = 0; j < H; j++) {
      q += hi[j] * ti[j];
      uh += f->u[j] * hi[j];
    }
    float v = q + 2.0f * s * uh + s * s * f->bb;
    out[i] = sqrtf(v > 0 ? v : 0);
  }
}

struct query_ctx {
  struct vlff_field *f;
  const float *xyz;
  size_t n;
  float *density, *feature, *score, *margin;
  int *label;
  int ntasks;
  float *cosine; /* [n][K], vlff_field_query_cosines */
};

static void query_task(void *ctx, int task, int thread) {
  struct query_ctx *q = ctx;
  struct vlff_field *f = q->f;
  struct vlff_work *w = &f->work[thread];
  const int H = f->H, D = f->D, K = f->K, geo = f->geo;
  const float *pm = f->avg;
  size_t a = (size_t)task * VLFF_QUERY_BLOCK;
  int n = (int)(q->n - a < VLFF_QUERY_BLOCK ? q->n - a : VLFF_QUERY_BLOCK);
  uint32_t idx[VLFF_QUERY_BLOCK];
  unsigned char inside[VLFF_QUERY_BLOCK];
  for (int i = 0; i < n; i++) {
    idx[i] = (uint32_t)(a + i);
    inside[i] = (unsigned char)vlff_encoding_normalise(&f->enc, q->xyz + 3 * (size_t)idx[i], w->p + 3 * i);
  }
  vlff_field_density(f, w, f->avg, w->p, n);
  if (q->density)
    for (int i = 0; i < n; i++) q->density[idx[i]] = inside[i] ? w->sigma[i] : 0.0f;
  int need_h = q->feature || q->label || q->score || q->margin || q->cosine;
  if (!need_h) return;
  /* MLP3's hidden layers feature-major (points along rows), the layout the
   * scoring kernel wants: xT = the geometric codes transposed, columns past
   * n zero so the kernel's last panel reads finite values. */
  const int ldh = VLFF_QUERY_BLOCK, ncol = (n + 31) & ~31;
  const float *out1 = w->a1[f->m1.nl - 1];
  const int ld1 = f->m1.nout;
  float *xT = w->dout1;
  for (int j = 0; j < geo; j++) {
    float *row = xT + (size_t)j * ldh;
    for (int i = 0; i < n; i++) row[i] = out1[(size_t)i * ld1 + 1 + j];
    for (int i = n; i < ncol; i++) row[i] = 0.0f;
  }
  const struct vlff_mlp *m3 = &f->m3;
  const float *hT = xT;
  for (int l = 0; l < m3->nl - 1; l++) {
    float *o = l & 1 ? w->dy_b : w->dy_a;
    const float *b = pm + m3->boff[l];
    for (int i = 0; i < m3->dout[l]; i++) {
      const float bi = b[i]; /* a local and a fixed count: vectorised at -O2 */
      for (int c = 0; c < ncol; c += 32)
        for (int t = 0; t < 32; t++) o[(size_t)i * ldh + c + t] = bi;
    }
    vlff_gemm(m3->dout[l], ncol, m3->din[l], pm + m3->woff[l], 1, m3->dout[l], hT, ldh, o, ldh, NULL, 1, 1);
    hT = o;
  }
  int last = m3->nl - 1;
  if (q->cosine) {
    /* Logits through the fold, E (W h + b) = (E W) h + E b, divided by |f|
     * from the unfolded feature. */
    float *cs = q->cosine + a * (size_t)K;
    vlff_gemm(n, K, H, hT, 1, ldh, f->EWt, K, cs, K, f->Eb, 0, 0);
    vlff_gemm(n, D, H, hT, 1, ldh, pm + m3->woff[last], D, w->fray, D, pm + m3->boff[last], 0, 0);
    for (int i = 0; i < n; i++) {
      const float *fi = w->fray + (size_t)i * D;
      double nn = 0;
      for (int j = 0; j < D; j++) nn += (double)fi[j] * fi[j];
      float inv = inside[i] && nn > 0 ? (float)(1.0 / sqrt(nn)) : 0.0f;
      for (int k = 0; k < K; k++) cs[(size_t)i * K + k] *= inv;
    }
  }
  if (q->feature) {
    vlff_gemm(n, D, H, hT, 1, ldh, pm + m3->woff[last], D, w->fray, D, pm + m3->boff[last], 0, 0);
    for (int i = 0; i < n; i++) {
      float *dst = q->feature + (size_t)idx[i] * D;
      if (inside[i])
        memcpy(dst, w->fray + (size_t)i * D, (size_t)D * sizeof(float));
      else
        memset(dst, 0, (size_t)D * sizeof(float));
    }
  }
  if (!(q->label || q->score || q->margin)) return;
  const float *rt = NULL, *rv = NULL;
  float r22 = 0;
  if (q->score || q->margin) {
    rt = f->chol_ok ? f->Rt : f->G;
    rv = f->chol_ok ? f->r12 : f->u;
    r22 = f->chol_ok ? f->r22 : sqrtf(f->bb);
  }
  int *lab = q->label ? q->label + a : NULL;
  float *sc = q->score ? q->score + a : NULL, *mg = q->margin ? q->margin + a : NULL;
  vlff_score(n, H, K, hT, ldh, f->EWt, f->Eb, rt, rv, r22, !f->chol_ok, lab, sc, mg);
  for (int i = 0; i < n; i++)
    if (!inside[i]) {
      if (lab) lab[i] = -1;
      if (sc) sc[i] = 0;
      if (mg) mg[i] = 0;
    }
}

int vlff_field_query(struct vlff_field *f, const float *xyz, size_t n, float *density, float *feature, int *label,
                     float *score, float *margin) {
  if (!f || (n && !xyz)) return -1;
  if ((label || score || margin) && f->K == 0) return -1;
  if (n > UINT32_MAX) return -1;
  vlff_field_fold(f);
  /* Batches of at most 2^24 points keep task indices in int range. */
  for (size_t a = 0; a < n;) {
    size_t m = n - a > (size_t)1 << 24 ? (size_t)1 << 24 : n - a;
    struct query_ctx sub = {f, xyz + 3 * a, m, density ? density + a : NULL,
                            feature ? feature + a * (size_t)f->D : NULL, score ? score + a : NULL,
                            margin ? margin + a : NULL, label ? label + a : NULL, 0, NULL};
    sub.ntasks = (int)((m + VLFF_QUERY_BLOCK - 1) / VLFF_QUERY_BLOCK);
    vlff_pool_run(f->pool, sub.ntasks, query_task, &sub);
    a += m;
  }
  return 0;
}

int vlff_field_query_cosines(struct vlff_field *f, const float *xyz, size_t n, float *cosine) {
  if (!f || (n && (!xyz || !cosine)) || f->K == 0 || n > UINT32_MAX) return -1;
  vlff_field_fold(f);
  for (size_t a = 0; a < n;) {
    size_t m = n - a > (size_t)1 << 24 ? (size_t)1 << 24 : n - a;
    struct query_ctx sub = {.f = f, .xyz = xyz + 3 * a, .n = m, .cosine = cosine + a * (size_t)f->K};
    sub.ntasks = (int)((m + VLFF_QUERY_BLOCK - 1) / VLFF_QUERY_BLOCK);
    vlff_pool_run(f->pool, sub.ntasks, query_task, &sub);
    a += m;
  }
  return 0;
}

const float *vlff_field_prompt_embeddings(const struct vlff_field *f, int *k) {
  *k = f->K;
  return f->E_;
}

/* ---- 2D rendering --------------------------------------------------------- */

/* Rays per render task: a chunk, at most a query block (per-ray scratch). */
static size_t render_rays(const struct vlff_field *f) {
  return f->chunk_rays < VLFF_QUERY_BLOCK ? (size_t)f->chunk_rays : VLFF_QUERY_BLOCK;
}

struct render_ctx {
  struct vlff_field *f;
  const struct vlff_view *cam;
  const uint32_t *pix; /* NULL: every pixel */
  size_t n;
  float *rgb, *depth, *feature, *score;
  int *label;
};

/* Rendering marches each ray front to back in rounds of a few samples: only
 * rays still transparent get their next samples evaluated, so a ray that
 * hits a surface costs the samples up to it, not all samples_per_ray. The
 * colour head runs only when colour is requested, the feature head only on
 * samples that carry weight. */
static void render_chunk(struct vlff_field *f, struct vlff_work *w, const struct vlff_ray *rays, int nr, int want_rgb,
                         int want_feat) {
  const struct vlff_field_cfg *cfg = &f->cfg;
  const int S = f->spr, geo = f->geo, shd = f->shdim, H = f->H;
  const int in2w = geo + shd, ld1 = f->m1.nout;
  const int round = S >= 64 ? S / 8 : S >= 4 ? 4 : S;
  float bmin[3], bmax[3];
  for (int a = 0; a < 3; a++) {
    bmin[a] = (float)f->box_lo[a];
    bmax[a] = (float)f->box_hi[a];
  }
  const int uniform = cfg->train.sampling == VLFF_SAMPLING_UNIFORM;
  float *code = w->din3;       /* [nr*S][geo], per (ray, sample) */
  float *pos = w->denc;        /* [nr*S][3] normalised positions */
  float trans[VLFF_QUERY_BLOCK];
  int next[VLFF_QUERY_BLOCK];
  for (int r = 0; r < nr; r++) {
    const struct vlff_ray *ray = &rays[r];
    float *tt = w->t + (size_t)r * S, t0, t1, dt = 0;
    int cnt = 0;
    if (vlff_ray_box(ray->o, ray->d, bmin, bmax, &t0, &t1)) {
      t0 = fmaxf(t0, (float)cfg->train.near_m);
      if (t1 > t0)
        cnt = uniform ? vlff_sample_uniform(t0, t1, S, NULL, tt, &dt)
                      : vlff_sample_occupied(&f->occ, ray->o, ray->d, t0, t1, S, NULL, tt, &dt);
    }
    float dn = sqrtf(ray->d[0] * ray->d[0] + ray->d[1] * ray->d[1] + ray->d[2] * ray->d[2]);
    for (int q = 0; q < cnt; q++) {
      float x[3] = {ray->o[0] + tt[q] * ray->d[0], ray->o[1] + tt[q] * ray->d[1], ray->o[2] + tt[q] * ray->d[2]};
      vlff_encoding_normalise(&f->enc, x, pos + 3 * ((size_t)r * S + q));
      w->delta[(size_t)r * S + q] = dt * dn;
    }
    w->ray_cnt[r] = cnt;
    trans[r] = 1.0f;
    next[r] = 0;
    w->rgb[3 * r] = w->rgb[3 * r + 1] = w->rgb[3 * r + 2] = 0;
    w->depth[r] = 0;
    w->depth2[r] = 0;
    w->opac[r] = 0;
    w->wsum[r] = 0;
  }
  memset(w->hray, 0, (size_t)nr * H * sizeof(float));
  int n2 = 0, n3 = 0;
  for (;;) {
    int nb = 0;
    for (int r = 0; r < nr; r++) {
      if (next[r] >= w->ray_cnt[r] || trans[r] < VLFF_T_MIN) continue;
      int e = next[r] + round < w->ray_cnt[r] ? next[r] + round : w->ray_cnt[r];
      for (int q = next[r]; q < e; q++) {
        memcpy(w->p + 3 * nb, pos + 3 * ((size_t)r * S + q), 3 * sizeof(float));
        w->sel2[nb] = r * S + q;
        nb++;
      }
    }
    if (!nb) break;
    vlff_field_density(f, w, f->avg, w->p, nb);
    w->samples += nb;
    const float *out1 = w->a1[f->m1.nl - 1];
    for (int b = 0; b < nb; b++) {
      int id = w->sel2[b], r = id / S, q = id % S;
      next[r] = q + 1;
      if (trans[r] < VLFF_T_MIN) continue;
      float keep = expf(-w->sigma[b] * w->delta[id]);
      float wt = trans[r] * (1.0f - keep);
      trans[r] *= keep;
      w->depth[r] += wt * w->t[id];
      w->depth2[r] += wt * w->t[id] * w->t[id];
      w->opac[r] += wt;
      if (want_rgb && wt > 0) {
        float *row = w->in2 + (size_t)n2 * in2w;
        memcpy(row, out1 + (size_t)b * ld1 + 1, geo * sizeof(float));
        w->sel3[n2] = id;
        w->w[n2] = wt;
        n2++;
      }
      if (want_feat && wt >= VLFF_FEAT_WMIN) {
        memcpy(code + (size_t)n3 * geo, out1 + (size_t)b * ld1 + 1, geo * sizeof(float));
        w->ray_of[n3] = r;
        w->e[n3] = wt;
        n3++;
      }
    }
  }
  const float *pm = f->avg;
  if (n2) {
    for (int k = 0; k < n2; k++) {
      int id = w->sel3[k], r = id / S;
      const float *d = rays[r].d;
      float dn = sqrtf(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]), u[3] = {d[0] / dn, d[1] / dn, d[2] / dn};
      vlff_sh_encode(u, cfg->field.sh_degree, w->in2 + (size_t)k * in2w + geo);
    }
    vlff_mlp_forward(&f->m2, pm, w->in2, in2w, n2, f->m2.nl, w->a2);
    const float *c2 = w->a2[f->m2.nl - 1];
    for (int k = 0; k < n2; k++) {
      int r = w->sel3[k] / S;
      for (int ch = 0; ch < 3; ch++) w->rgb[3 * r + ch] += w->w[k] / (1.0f + expf(-c2[(size_t)k * 3 + ch]));
    }
  }
  if (n3) {
    vlff_mlp_forward(&f->m3, pm, code, geo, n3, f->m3.nl - 1, w->a3);
    const float *h3 = w->a3[f->m3.nl - 2];
    for (int k = 0; k < n3; k++) {
      int r = w->ray_of[k];
      float wt = w->e[k], *hr = w->hray + (size_t)r * H;
      const float *hs = h3 + (size_t)k * H;
      for (int j = 0; j < H; j++) hr[j] += wt * hs[j];
      w->wsum[r] += wt;
    }
  }
}

/* The camera rays through the centres of nr image pixels from the a-th of
 * list (NULL: the image's pixels in order); pixel[] gets their indices. */
static void pixel_rays(struct vlff_work *w, const struct vlff_view *cam, const uint32_t *list, size_t a, int nr,
                       size_t *pixel) {
  for (int r = 0; r < nr; r++) {
    size_t pix = pixel[r] = list ? list[a + r] : a + r;
    double u = (double)(pix % cam->width) + 0.5, v = (double)(pix / cam->width) + 0.5;
    struct vlff_ray *ray = &w->rbuf[r];
    vlff_camera_ray(cam, u, v, ray->o, ray->d);
    ray->depth = 0;
    ray->has_rgb = 0;
    ray->feat_index = -1;
    ray->view = 0;
  }
}

static void render_task(void *ctx, int task, int thread) {
  struct render_ctx *rc = ctx;
  struct vlff_field *f = rc->f;
  struct vlff_work *w = &f->work[thread];
  const struct vlff_view *cam = rc->cam;
  const int H = f->H, D = f->D, K = f->K;
  const size_t per = render_rays(f);
  size_t a = (size_t)task * per;
  int nr = (int)(rc->n - a < per ? rc->n - a : per);
  /* The chunk's image pixels: a slice of rc->pix, or a run of the image. */
  size_t pixel[VLFF_QUERY_BLOCK];
  pixel_rays(w, cam, rc->pix, a, nr, pixel);
  render_chunk(f, w, w->rbuf, nr, rc->rgb != NULL, rc->feature || rc->label || rc->score);
  for (int r = 0; r < nr; r++) {
    size_t pix = pixel[r];
    if (rc->rgb)
      for (int c = 0; c < 3; c++) rc->rgb[3 * pix + c] = w->rgb[3 * r + c];
    if (rc->depth) rc->depth[pix] = w->depth[r];
  }
  const float *pm = f->avg;
  const struct vlff_mlp *m3 = &f->m3;
  int last = m3->nl - 1;
  if (rc->feature) {
    vlff_gemm(nr, D, H, w->hray, H, 1, pm + m3->woff[last], D, w->fray, D, NULL, 0, 0);
    const float *b = pm + m3->boff[last];
    for (int r = 0; r < nr; r++) {
      float *dst = rc->feature + pixel[r] * (size_t)D;
      const float *src = w->fray + (size_t)r * D;
      for (int j = 0; j < D; j++) dst[j] = src[j] + w->wsum[r] * b[j];
    }
  }
  if (rc->label || rc->score) {
    vlff_gemm(nr, K, H, w->hray, H, 1, f->EWt, K, w->logits, K, NULL, 0, 0);
    float norms[VLFF_CHUNK_SAMPLES];
    if (rc->score) feat_norms(f, w->hray, w->wsum, nr, w->norm, norms);
    for (int r = 0; r < nr; r++) {
      float *lg = w->logits + (size_t)r * K;
      for (int k = 0; k < K; k++) lg[k] += w->wsum[r] * f->Eb[k];
      int lb = -1;
      float sc = 0;
      if (w->opac[r] >= 0.5f) pick(lg, K, rc->score ? norms[r] : 1.0f, &lb, &sc, NULL);
      if (rc->label) rc->label[pixel[r]] = lb;
      if (rc->score) rc->score[pixel[r]] = sc;
    }
  }
}

/* The pool tasks that march n pixels of cam (pix: their indices; NULL: the
 * whole image, n its size): 0 with *ntasks set, or -1 for a bad camera
 * (size, focal lengths, a non-finite pose), a pixel outside the image or
 * too many pixels. */
static int pixel_tasks(const struct vlff_field *f, const struct vlff_view *cam, const uint32_t *pix, size_t n,
                       int *ntasks) {
  if (!f || !cam || cam->width <= 0 || cam->height <= 0 || !(cam->fx > 0) || !(cam->fy > 0)) return -1;
  for (int k = 0; k < 16; k++)
    if (!isfinite(cam->c2w[k])) return -1;
  size_t npx = (size_t)cam->width * cam->height;
  if (!pix && n != npx) return -1;
  for (size_t i = 0; pix && i < n; i++)
    if (pix[i] >= npx) return -1;
  size_t t = (n + render_rays(f) - 1) / render_rays(f);
  if (t > (size_t)1 << 30) return -1;
  *ntasks = (int)t;
  return 0;
}

int vlff_field_render_pixels(struct vlff_field *f, const struct vlff_view *cam, const uint32_t *pix, size_t n,
                             float *rgb, float *depth, float *feature, int *label, float *score) {
  int ntasks;
  if (pixel_tasks(f, cam, pix, n, &ntasks)) return -1;
  vlff_field_fold(f);
  if ((label || score) && f->K == 0) return -1;
  struct render_ctx rc = {f, cam, pix, n, rgb, depth, feature, score, label};
  vlff_pool_run(f->pool, ntasks, render_task, &rc);
  return 0;
}

struct snap_ctx {
  struct vlff_field *f;
  const struct vlff_view *cam;
  const uint32_t *pix;
  size_t n;
  float *xyz;
  size_t *moved; /* [tasks] */
};

/* The field's surface is never known better than this along a ray (m): a
 * fraction of its finest cells, and what a sharp density's samples leave. */
#define SNAP_MIN_SPREAD 0.005

/* Density alone along each point's ray (no colour, no feature head); the
 * ray's surface is its opacity-weighted depth where it is at least half
 * opaque. */
static void snap_task(void *ctx, int task, int thread) {
  struct snap_ctx *sc = ctx;
  struct vlff_field *f = sc->f;
  struct vlff_work *w = &f->work[thread];
  const double *m = sc->cam->c2w;
  const float noise = (float)f->cfg.train.depth_noise_m;
  const size_t per = render_rays(f), a = (size_t)task * per;
  int nr = (int)(sc->n - a < per ? sc->n - a : per);
  size_t pixel[VLFF_QUERY_BLOCK], moved = 0;
  pixel_rays(w, sc->cam, sc->pix, a, nr, pixel);
  render_chunk(f, w, w->rbuf, nr, 0, 0);
  for (int r = 0; r < nr; r++) {
    float *q = sc->xyz + 3 * (a + r);
    double rel[3] = {q[0] - m[3], q[1] - m[7], q[2] - m[11]};
    double zm = rel[0] * m[2] + rel[1] * m[6] + rel[2] * m[10]; /* along the optical axis */
    if (!(w->opac[r] >= 0.5f) || !(zm > 0) || !isfinite(zm)) continue;
    double zr = w->depth[r] / w->opac[r];
    if (!(fabs(zr - zm) <= vlff_depth_band((float)zm, noise))) continue;
    /* Both depths are estimates: the measurement's variance is the
     * sensor's (noise d^2)^2, the field's its density's spread along the
     * ray. The point moves to their inverse-variance mean: a stereo
     * camera's point far out goes nearly all the way, a structured-light
     * point on a thin thing (a window on a wall, whose density the field
     * smears into the wall's) barely moves. */
    double vm = (double)noise * zm * zm, vf = w->depth2[r] / w->opac[r] - zr * zr;
    vm *= vm;
    if (!(vf > SNAP_MIN_SPREAD * SNAP_MIN_SPREAD)) vf = SNAP_MIN_SPREAD * SNAP_MIN_SPREAD;
    double z = zm + (zr - zm) * vm / (vm + vf);
    if (z == zm) continue; /* a sensor without noise: the measurement stands */
    for (int k = 0; k < 3; k++) q[k] = (float)(m[4 * k + 3] + rel[k] * (z / zm));
    moved++;
  }
  sc->moved[task] = moved;
}

size_t vlff_field_snap_surface(struct vlff_field *f, const struct vlff_view *cam, const uint32_t *pix, size_t n,
                               float *xyz) {
  int ntasks;
  if (!pix || !xyz || !n || pixel_tasks(f, cam, pix, n, &ntasks)) return 0;
  size_t *moved = calloc((size_t)ntasks, sizeof *moved), total = 0;
  if (!moved) return 0;
  struct snap_ctx sc = {f, cam, pix, n, xyz, moved};
  vlff_pool_run(f->pool, ntasks, snap_task, &sc);
  for (int t = 0; t < ntasks; t++) total += moved[t];
  free(moved);
  return total;
}

int vlff_field_render(struct vlff_field *f, const struct vlff_view *cam, float *rgb, float *depth, float *feature,
                      int *label, float *score) {
  if (!cam || cam->width <= 0 || cam->height <= 0) return -1;
  return vlff_field_render_pixels(f, cam, NULL, (size_t)cam->width * cam->height, rgb, depth, feature, label, score);
}

double vlff_field_depth_noise(const struct vlff_field *f) { return f->cfg.train.depth_noise_m; }
