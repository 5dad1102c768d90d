/*
 * Text encoder. The token lookup happens here, not in the graph, because
 * OpenCV 4.6's Gather only takes constant indices; the projection to D
 * happens in the graph at every position (a [77,W]x[W,D] product, cheap)
 * so the graph needs no ArgMax, and we read the row at the end-of-text
 * token, which the tokenizer already knows.
 */
#include "text_encoder.h"

#include <errno.h>
#include <math.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "dnn_shim.h"
#include "files.h"
#include "log.h"
#include "tokenizer.h"

#define TEMPLATED_MAX 512

struct cache_entry {
  char *text; /* templated prompt; NULL = empty */
  float *emb;
};

struct vlff_text_encoder {
  struct vlff_tokenizer *tok;
  struct vlff_dnn *net;
  char path[VLFF_CFG_PATH];
  char templ[VLFF_CFG_STR];
  int vocab, width, dim;
  float *table;  /* vocab * width */
  float *x;      /* 77 * width */
  struct cache_entry cache[VLFF_TEXT_CACHE];
  int cache_next;
  long hits, misses;
};


static int load_table(struct vlff_text_encoder *e, const char *path, char *err, size_t errlen) {
  char why[384];
  int fd = vlff_open_regular(path, why, sizeof why);
  FILE *f = fd >= 0 ? fdopen(fd, "rb") : NULL;
  if (!f) {
    if (fd >= 0) close(fd);
    vlff_errf(err, errlen, "cannot open token-embedding table %s", fd >= 0 ? strerror(errno) : why);
    return -1;
  }
  uint8_t hdr[16];
  int rc = -1;
  if (fread(hdr, 1, 16, f) != 16 || memcmp(hdr, "VLFFTOK1", 8)) {
    vlff_errf(err, errlen, "%s: not a token-embedding table (expected magic VLFFTOK1)", path);
    goto out;
  }
  uint32_t v = (uint32_t)hdr[8] | (uint32_t)hdr[9] << 8 | (uint32_t)hdr[10] << 16 | (uint32_t)hdr[11] << 24;
  uint32_t w = (uint32_t)hdr[12] | (uint32_t)hdr[13] << 8 | (uint32_t)hdr[14] << 16 | (uint32_t)hdr[15] << 24;
  if (v != VLFF_CLIP_VOCAB || w < 8 || w > 4096) {
    vlff_errf(err, errlen, "%s: table is %u x %u, expected %d x (8..4096)", path, v, w, VLFF_CLIP_VOCAB);
    goto out;
  }
  size_t n = (size_t)v * w;
  e->table = malloc(n * sizeof *e->table);
  if (!e->table) {
    vlff_errf(err, errlen, "%s: out of memory", path);
    goto out;
  }
  if (fread(e->table, sizeof *e->table, n, f) != n) {
    vlff_errf(err, errlen, "%s: truncated token-embedding table (expected %zu floats)", path, n);
    goto out;
  }
  if (fgetc(f) != EOF) {
    vlff_errf(err, errlen, "%s: trailing bytes after %zu floats", path, n);
    goto out;
  }
  for (size_t i = 0; i < n; i++)
    if (!isfinite(e->table[i])) {
      vlff_errf(err, errlen, "%s: non-finite value in row %zu", path, i / w);
      goto out;
    }
  e->vocab = (int)v;
  e->width = (int)w;
  rc = 0;
out:
  fclose(f);
  return rc;
}

/* Run the graph on a token context; out receives the EOT row (raw). */
static int run_ids(struct vlff_text_encoder *e, const int32_t *ids, int eot, float *out, char *err, size_t errlen) {
  for (int i = 0; i < VLFF_CLIP_CONTEXT; i++)
    memcpy(e->x + (size_t)i * e->width, e->table + (size_t)ids[i] * e->width, (size_t)e->width * sizeof *e->x);
  int shape[3] = {1, VLFF_CLIP_CONTEXT, e->width};
  struct vlff_tensor t;
  if (vlff_dnn_run(e->net, e->x, shape, 3, &t, 1, err, errlen) != 1) return -1;
  if (t.ndim != 3 || t.shape[0] != 1 || t.shape[1] != VLFF_CLIP_CONTEXT || (e->dim && t.shape[2] != e->dim)) {
    vlff_errf(err, errlen, "%s: output of %d dims (%d x %d ...), expected [1,77,D]", e->path, t.ndim, t.shape[0],
            t.ndim > 1 ? t.shape[1] : 0);
    return -1;
  }
  if (!e->dim) return t.shape[2];
  memcpy(out, t.data + (size_t)eot * e->dim, (size_t)e->dim * sizeof *out);
  return 0;
}

struct vlff_text_encoder *vlff_text_encoder_open(const struct vlff_cfg_vlm *vlm, const char *templ, int feature_dim,
                                                 char *err, size_t errlen) {
  const char *path = vlm->text_model;
  if (!path[0]) {
    vlff_errf(err, errlen, "vlm.text_model: no text model configured");
    return NULL;
  }
  struct vlff_text_encoder *e = calloc(1, sizeof *e);
  if (!e) {
    vlff_errf(err, errlen, "%s: out of memory", path);
    return NULL;
  }
  snprintf(e->path, sizeof e->path, "%s", path);
  snprintf(e->templ, sizeof e->templ, "%s", templ);
  char tpath[VLFF_CFG_PATH + 16];
  snprintf(tpath, sizeof tpath, "%s.tokemb", path);
  if (!(e->tok = vlff_tokenizer_open(vlm->bpe_vocab, err, errlen))) goto fail;
  if (load_table(e, tpath, err, errlen)) goto fail;
  e->x = malloc((size_t)VLFF_CLIP_CONTEXT * e->width * sizeof *e->x);
  if (!e->x) {
    vlff_errf(err, errlen, "%s: out of memory", path);
    goto fail;
  }
  bool cuda = false;
  if (vlff_check_regular(path, err, errlen)) goto fail;
  if (!(e->net = vlff_dnn_open(path, vlm->cuda, &cuda, err, errlen))) goto fail;
  int32_t ids[VLFF_CLIP_CONTEXT];
  char why[384];
  int eot = vlff_tokenizer_context(e->tok, "a photo of a chair.", ids, why, sizeof why);
  int d = eot < 0 ? -1 : run_ids(e, ids, eot, NULL, why, sizeof why);
  if (d < 0) {
    vlff_errf(err, errlen, "%s: probe inference failed (does the model match %s's width %d?): %s", path, tpath,
            e->width, why);
    goto fail;
  }
  if (d != feature_dim) {
    vlff_errf(err, errlen, "%s: embeddings have D=%d, but field.feature_dim is %d", path, d, feature_dim);
    goto fail;
  }
  e->dim = d;
  float *probe = malloc((size_t)d * sizeof *probe);
  int prc = probe ? run_ids(e, ids, eot, probe, why, sizeof why) : -1;
  for (int i = 0; prc == 0 && i < d; i++)
    if (!isfinite(probe[i])) prc = -1;
  free(probe);
  if (prc) {
    vlff_errf(err, errlen, "%s: probe inference gave non-finite embeddings (corrupt weights?)", path);
    goto fail;
  }
  VLFF_INFO("vlm", "%s: text encoder, width %d -> D=%d on %s", path, e->width, d, cuda ? "CUDA" : "CPU");
  return e;
fail:
  vlff_text_encoder_close(e);
  return NULL;
}

void vlff_text_encoder_close(struct vlff_text_encoder *e) {
  if (!e) return;
  vlff_tokenizer_close(e->tok);
  vlff_dnn_close(e->net);
  for (int i = 0; i < VLFF_TEXT_CACHE; i++) {
    free(e->cache[i].text);
    free(e->cache[i].emb);
  }
  free(e->table);
  free(e->x);
  free(e);
}

int vlff_text_encoder_dim(const struct vlff_text_encoder *e) { return e->dim; }

void vlff_text_encoder_cache_stats(const struct vlff_text_encoder *e, long *hits, long *misses) {
  if (hits) *hits = e->hits;
  if (misses) *misses = e->misses;
}

static int apply_template(const char *templ, const char *prompt, char *out, size_t cap) {
  size_t k = 0, pl = strlen(prompt);
  for (const char *p = templ; *p;) {
    if (p[0] == '{' && p[1] == '}') {
      if (k + pl >= cap) return -1;
      memcpy(out + k, prompt, pl);
      k += pl;
      p += 2;
    } else {
      if (k + 1 >= cap) return -1;
      out[k++] = *p++;
    }
  }
  out[k] = 0;
  return 0;
}

int vlff_text_encoder_encode(struct vlff_text_encoder *e, const char *prompt, float *out, char *err, size_t errlen) {
  if (!e || !prompt || !out) {
    vlff_errf(err, errlen, "text encoder: NULL argument");
    return -1;
  }
  char text[TEMPLATED_MAX];
  if (apply_template(e->templ, prompt, text, sizeof text)) {
    vlff_errf(err, errlen, "prompt '%.40s': longer than %d bytes with its template", prompt, TEMPLATED_MAX - 1);
    return -1;
  }
  for (int i = 0; i < VLFF_TEXT_CACHE; i++)
    if (e->cache[i].text && !strcmp(e->cache[i].text, text)) {
      memcpy(out, e->cache[i].emb, (size_t)e->dim * sizeof *out);
      e->hits++;
      return 0;
    }
  int32_t ids[VLFF_CLIP_CONTEXT];
  int eot = vlff_tokenizer_context(e->tok, text, ids, err, errlen);
  if (eot < 0) return -1;
  /* A literal <|endoftext|> would move CLIP's argmax read-out. */
  for (int i = 1; i < eot; i++)
    if (ids[i] == VLFF_CLIP_SOT || ids[i] == VLFF_CLIP_EOT) {
      vlff_errf(err, errlen, "prompt '%.40s': contains a CLIP special token", prompt);
      return -1;
    }
  if (run_ids(e, ids, eot, out, err, errlen)) return -1;
  double ss = 0;
  for (int i = 0; i < e->dim; i++) {
    if (!isfinite(out[i])) {
      vlff_errf(err, errlen, "prompt '%.40s': non-finite embedding", prompt);
      return -1;
    }
    ss += (double)out[i] * out[i];
  }
  if (ss <= 0) {
    vlff_errf(err, errlen, "prompt '%.40s': zero embedding", prompt);
    return -1;
  }
  float s = (float)(1.0 / sqrt(ss));
  for (int i = 0; i < e->dim; i++) out[i] *= s;
  e->misses++;
  struct cache_entry *c = &e->cache[e->cache_next];
  char *t = strdup(text);
  float *v = malloc((size_t)e->dim * sizeof *v);
  if (t && v) { /* a failed insert only costs a later recompute */
    free(c->text);
    free(c->emb);
    c->text = t;
    c->emb = v;
    memcpy(v, out, (size_t)e->dim * sizeof *v);
    e->cache_next = (e->cache_next + 1) % VLFF_TEXT_CACHE;
  } else {
    free(t);
    free(v);
  }
  return 0;
}
