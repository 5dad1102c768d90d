/*
 * Embeddings file. Text rather than binary so a deployment can read, diff
 * and hand-edit it; floats are written with %.9g so they round-trip
 * exactly.
 */
#include "embeddings.h"

#include <errno.h>
#include <fcntl.h>
#include <float.h>
#include <math.h>
#include <stdarg.h>
#include <stdbool.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>
#include "files.h"
#include "log.h"
#include "vlff/escape.h"

#define PROMPT_MAX 63

struct vlff_embeddings {
  int dim, count;
  char (*prompts)[PROMPT_MAX + 1];
  float *vectors;
};


/* Valid UTF-8 without control characters (tabs and newlines included). */
static bool prompt_ok(const char *s, size_t n) {
  for (size_t i = 0; i < n;) {
    uint8_t c = (uint8_t)s[i];
    if (c < 0x20 || c == 0x7F) return false;
    size_t len = c < 0x80 ? 1 : (c >= 0xC2 && c <= 0xDF) ? 2 : (c >= 0xE0 && c <= 0xEF) ? 3 : (c >= 0xF0 && c <= 0xF4) ? 4 : 0;
    if (!len || i + len > n) return false;
    uint32_t cp = len == 1 ? c : len == 2 ? (c & 0x1Fu) : len == 3 ? (c & 0x0Fu) : (c & 0x07u);
    for (size_t k = 1; k < len; k++) {
      uint8_t cc = (uint8_t)s[i + k];
      if ((cc & 0xC0) != 0x80) return false;
      cp = cp << 6 | (cc & 0x3Fu);
    }
    if ((len == 3 && (cp < 0x800 || (cp >= 0xD800 && cp <= 0xDFFF))) || (len == 4 && (cp < 0x10000 || cp > 0x10FFFF)))
      return false;
    if (cp >= 0x80 && cp <= 0x9F) return false;
    i += len;
  }
  return n > 0;
}

void vlff_embeddings_free(struct vlff_embeddings *e) {
  if (!e) return;
  free(e->prompts);
  free(e->vectors);
  free(e);
}

/* The two header lines, in order: 'vlff-embeddings 1', then 'dim N'. */
static int parse_header(struct vlff_embeddings *e, const char *line, const char *name, int lineno, int expected_dim,
                        bool *have_magic, char *err, size_t errlen) {
  if (!*have_magic) {
    if (strcmp(line, "vlff-embeddings 1")) {
      vlff_errf(err, errlen, "%s:%d: expected 'vlff-embeddings 1', got '%s'", name, lineno, VLFF_QMAX(line, 40));
      return -1;
    }
    *have_magic = true;
    return 0;
  }
  char *end;
  long d = strncmp(line, "dim ", 4) ? 0 : strtol(line + 4, &end, 10);
  if (d < 1 || d > 4096 || *end) {
    vlff_errf(err, errlen, "%s:%d: expected 'dim N' with N in 1..4096, got '%s'", name, lineno, VLFF_QMAX(line, 40));
    return -1;
  }
  if (expected_dim && d != expected_dim) {
    vlff_errf(err, errlen, "%s:%d: vectors have dim %ld, but field.feature_dim is %d", name, lineno, d, expected_dim);
    return -1;
  }
  e->dim = (int)d;
  return 0;
}

/* A vector line's prompt, up to its tab (replaced by a NUL): checked, new
 * and within the count. Its length, or -1. */
static long parse_prompt(const struct vlff_embeddings *e, char *line, const char *name, int lineno, char *err,
                         size_t errlen) {
  char *tab = strchr(line, '\t');
  if (!tab) {
    vlff_errf(err, errlen, "%s:%d: expected 'prompt<TAB>numbers'", name, lineno);
    return -1;
  }
  size_t pl = (size_t)(tab - line);
  if (pl > PROMPT_MAX || !prompt_ok(line, pl)) {
    vlff_errf(err, errlen, "%s:%d: prompt must be 1..%d bytes of UTF-8 without control characters", name, lineno,
              PROMPT_MAX);
    return -1;
  }
  *tab = 0;
  for (int i = 0; i < e->count; i++)
    if (!strcmp(e->prompts[i], line)) {
      vlff_errf(err, errlen, "%s:%d: duplicate prompt '%s'", name, lineno, VLFF_Q(line));
      return -1;
    }
  if (e->count == VLFF_EMBEDDINGS_MAX) {
    vlff_errf(err, errlen, "%s:%d: more than %d prompts", name, lineno, VLFF_EMBEDDINGS_MAX);
    return -1;
  }
  return (long)pl;
}

/* Room for more prompts and vectors: 0, or -1 out of memory. */
static int grow(struct vlff_embeddings *e, int *cap) {
  int nc = *cap ? *cap * 2 : 16;
  if (nc > VLFF_EMBEDDINGS_MAX) nc = VLFF_EMBEDDINGS_MAX;
  void *np = realloc(e->prompts, (size_t)nc * sizeof *e->prompts);
  if (!np) return -1;
  e->prompts = np;
  float *nv = realloc(e->vectors, (size_t)nc * e->dim * sizeof *nv);
  if (!nv) return -1;
  e->vectors = nv;
  *cap = nc;
  return 0;
}

/* A vector of squared length ss is an embedding's. Only its direction
 * matters (it is compared by cosine), but a length this far from any
 * encoder's is no embedding, and products of such values overflow or flush
 * to zero in float. The parser and the writer hold vectors to it alike. */
static bool length_ok(double ss) {
  const double norm = sqrt(ss);
  return norm >= VLFF_EMBEDDINGS_MIN_NORM && norm <= VLFF_EMBEDDINGS_MAX_NORM;
}

/* The numbers at p of prompt's line: dim finite floats separated by single
 * spaces, not all zero, into v. */
static int parse_vector(const char *prompt, const char *p, int dim, float *v, const char *name, int lineno, char *err,
                        size_t errlen) {
  double ss = 0;
  for (int k = 0; k < dim; k++) {
    if (k && *p++ != ' ') {
      vlff_errf(err, errlen, "%s:%d: expected %d numbers separated by single spaces, got %d", name, lineno, dim, k);
      return -1;
    }
    if (*p == ' ' || *p == 0 || *p == '\t') {
      vlff_errf(err, errlen, "%s:%d: expected %d numbers, got %d", name, lineno, dim, k);
      return -1;
    }
    char *end;
    errno = 0;
    float f = strtof(p, &end);
    /* ERANGE with a finite result is underflow (1e-45 is a subnormal
     * float, 1e-50 rounds to zero): a valid, tiny number. */
    if (end == p || (*end && *end != ' ') || !isfinite(f) || (errno == ERANGE && fabsf(f) > FLT_MIN)) {
      vlff_errf(err, errlen, "%s:%d: number %d is not a finite float", name, lineno, k + 1);
      return -1;
    }
    v[k] = f;
    ss += (double)f * f;
    p = end;
  }
  if (*p) {
    vlff_errf(err, errlen, "%s:%d: more than %d numbers", name, lineno, dim);
    return -1;
  }
  if (!(ss > 0)) {
    vlff_errf(err, errlen, "%s:%d: zero vector for '%s'", name, lineno, VLFF_Q(prompt));
    return -1;
  }
  if (!length_ok(ss)) {
    vlff_errf(err, errlen, "%s:%d: vector for '%s' has length %.3g, expected %g to %g", name, lineno, VLFF_Q(prompt),
              sqrt(ss), VLFF_EMBEDDINGS_MIN_NORM, VLFF_EMBEDDINGS_MAX_NORM);
    return -1;
  }
  return 0;
}

struct vlff_embeddings *vlff_embeddings_parse(const char *buf, size_t len, const char *name, int expected_dim,
                                              char *err, size_t errlen) {
  if (!name) name = "embeddings";
  name = VLFF_Q(name); /* the file's name, only ever quoted in messages below */
  if (!buf || len > VLFF_EMBEDDINGS_MAX_BYTES) {
    vlff_errf(err, errlen, "%s: larger than %u MiB", name, VLFF_EMBEDDINGS_MAX_BYTES >> 20);
    return NULL;
  }
  struct vlff_embeddings *e = calloc(1, sizeof *e);
  char *line = NULL;
  if (!e) goto oom;
  int lineno = 0, cap = 0;
  bool have_magic = false;
  for (size_t pos = 0; pos < len;) {
    const char *nl = memchr(buf + pos, '\n', len - pos);
    size_t ll = nl ? (size_t)(nl - (buf + pos)) : len - pos;
    lineno++;
    free(line);
    if (!(line = malloc(ll + 1))) goto oom;
    memcpy(line, buf + pos, ll);
    line[ll] = 0;
    pos += ll + (nl ? 1 : 0);
    if (memchr(line, 0, ll)) {
      vlff_errf(err, errlen, "%s:%d: NUL byte", name, lineno);
      goto fail;
    }
    /* Said plainly: otherwise the invisible '\r' makes every later check
     * quote a line that looks right. */
    if (ll && line[ll - 1] == '\r') {
      vlff_errf(err, errlen, "%s:%d: CRLF line end (the format uses '\\n' alone)", name, lineno);
      goto fail;
    }
    if (!have_magic || !e->dim) {
      if (parse_header(e, line, name, lineno, expected_dim, &have_magic, err, errlen)) goto fail;
      continue;
    }
    if (!ll || line[0] == '#') continue;
    long pl = parse_prompt(e, line, name, lineno, err, errlen);
    if (pl < 0) goto fail;
    if (e->count == cap && grow(e, &cap)) goto oom;
    float *v = e->vectors + (size_t)e->count * e->dim;
    if (parse_vector(line, line + pl + 1, e->dim, v, name, lineno, err, errlen)) goto fail;
    memcpy(e->prompts[e->count], line, (size_t)pl + 1);
    e->count++;
  }
  if (!have_magic || !e->dim) {
    vlff_errf(err, errlen, "%s: missing '%s' header line", name, have_magic ? "dim N" : "vlff-embeddings 1");
    goto fail;
  }
  if (!e->count) {
    vlff_errf(err, errlen, "%s: no prompts", name);
    goto fail;
  }
  free(line);
  return e;
oom:
  vlff_errf(err, errlen, "%s: out of memory", name);
fail:
  free(line);
  vlff_embeddings_free(e);
  return NULL;
}

struct vlff_embeddings *vlff_embeddings_load(const char *path, int expected_dim, char *err, size_t errlen) {
  char why[384];
  int fd = vlff_open_regular(path, why, sizeof why);
  FILE *f = fd >= 0 ? fdopen(fd, "rb") : NULL;
  if (!f) {
    if (fd >= 0) close(fd);
    vlff_errf(err, errlen, "cannot open embeddings file %s", fd >= 0 ? strerror(errno) : why);
    return NULL;
  }
  size_t cap = 1u << 16, n = 0;
  char *buf = malloc(cap);
  while (buf) {
    if (n == cap) {
      if (cap > VLFF_EMBEDDINGS_MAX_BYTES) break;
      char *nb = realloc(buf, cap * 2);
      if (!nb) {
        free(buf);
        buf = NULL;
        break;
      }
      buf = nb, cap *= 2;
    }
    size_t r = fread(buf + n, 1, cap - n, f);
    n += r;
    if (!r) break;
  }
  bool io = ferror(f);
  fclose(f);
  if (!buf || io) {
    vlff_errf(err, errlen, "%s: %s", VLFF_Q(path), buf ? "read error" : "out of memory");
    free(buf);
    return NULL;
  }
  struct vlff_embeddings *e = vlff_embeddings_parse(buf, n, path, expected_dim, err, errlen);
  free(buf);
  return e;
}

int vlff_embeddings_dim(const struct vlff_embeddings *e) { return e->dim; }
int vlff_embeddings_count(const struct vlff_embeddings *e) { return e->count; }
const char *vlff_embeddings_prompt(const struct vlff_embeddings *e, int i) {
  return i >= 0 && i < e->count ? e->prompts[i] : NULL;
}
const float *vlff_embeddings_vector(const struct vlff_embeddings *e, int i) {
  return i >= 0 && i < e->count ? e->vectors + (size_t)i * e->dim : NULL;
}

const float *vlff_embeddings_lookup(const struct vlff_embeddings *e, const char *prompt) {
  for (int i = 0; i < e->count; i++)
    if (!strcmp(e->prompts[i], prompt)) return e->vectors + (size_t)i * e->dim;
  return NULL;
}

int vlff_embeddings_save(const char *path, int dim, int count, const char *const *prompts, const float *vectors,
                         char *err, size_t errlen) {
  if (!path || dim < 1 || dim > 4096 || count < 1 || count > VLFF_EMBEDDINGS_MAX || !prompts || !vectors) {
    vlff_errf(err, errlen, "%s: bad arguments (dim %d, count %d)", VLFF_Q(path ? path : "embeddings"), dim,
             count);
    return -1;
  }
  for (int i = 0; i < count; i++) {
    if (!prompts[i] || strlen(prompts[i]) > PROMPT_MAX || !prompt_ok(prompts[i], strlen(prompts[i]))) {
      vlff_errf(err, errlen, "%s: prompt %d is not 1..%d bytes of UTF-8 without control characters", VLFF_Q(path), i,
                PROMPT_MAX);
      return -1;
    }
    double ss = 0;
    for (int k = 0; k < dim; k++) {
      const float x = vectors[(size_t)i * dim + k];
      if (!isfinite(x)) {
        vlff_errf(err, errlen, "%s: non-finite value in the vector of '%s'", VLFF_Q(path), VLFF_Q(prompts[i]));
        return -1;
      }
      ss += (double)x * x;
    }
    if (!length_ok(ss)) { /* what the parser would refuse is not written */
      vlff_errf(err, errlen, "%s: the vector of '%s' has length %.3g, expected %g to %g", VLFF_Q(path),
                VLFF_Q(prompts[i]), sqrt(ss), VLFF_EMBEDDINGS_MIN_NORM, VLFF_EMBEDDINGS_MAX_NORM);
      return -1;
    }
  }
  struct vlff_atomic a;
  if (vlff_atomic_begin(&a, path, 0644, err, errlen) < 0) return -1;
  int fd = dup(a.fd); /* the stream's own; the commit syncs the file through a.fd */
  FILE *f = fd >= 0 ? fdopen(fd, "w") : NULL;
  if (!f) {
    vlff_errf(err, errlen, "%s: cannot create: %s", VLFF_Q(a.tmp), strerror(errno));
    if (fd >= 0) close(fd);
    vlff_atomic_abort(&a);
    return -1;
  }
  fprintf(f, "vlff-embeddings 1\ndim %d\n", dim);
  for (int i = 0; i < count; i++) {
    fprintf(f, "%s\t", prompts[i]);
    for (int k = 0; k < dim; k++) fprintf(f, k ? " %.9g" : "%.9g", (double)vectors[(size_t)i * dim + k]);
    fputc('\n', f);
  }
  bool ok = fflush(f) == 0;
  ok &= fclose(f) == 0;
  if (!ok) {
    vlff_errf(err, errlen, "%s: write failed: %s", VLFF_Q(path), strerror(errno));
    vlff_atomic_abort(&a);
    return -1;
  }
  return vlff_atomic_commit(&a, err, errlen);
}
