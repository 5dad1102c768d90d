/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * page.c - the page's files, read once, and the check of HTTP request heads.
 *
 * Why a check of our own in front of libwebsockets: its parser answers a request it
 * cannot take by closing the connection without a word (a head past its buffer, too
 * many headers) or with 403 (an unknown method, a path climbing out of the mount),
 * and it keeps a connection alive for more requests it alone parses. Every request
 * reaching the viewer is a head this check passed, on a connection that closes after
 * its one response, and every refusal is an HTTP status with a sentence.
 */
#include "page.h"

#include <ctype.h>
#include <errno.h>
#include <stdarg.h>
#include <fts.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <strings.h>
#include <sys/stat.h>

#include "files.h"
#include "view.h"
#include "vlff/escape.h"

#define PAGE_FILES_MAX 256
#define PAGE_FILE_MAX ((size_t)16 << 20)
#define PAGE_TOTAL_MAX ((size_t)64 << 20)

/* ------------------------------------------------------------------ files */

static const char *mime_of(const char *path) {
  static const char *const types[][2] = {
      {".html", "text/html; charset=utf-8"}, {".js", "text/javascript; charset=utf-8"},
      {".css", "text/css; charset=utf-8"},   {".json", "application/json"},
      {".png", "image/png"},                 {".svg", "image/svg+xml"},
  };
  const char *dot = strrchr(path, '.'), *slash = strrchr(path, '/');
  if (!dot || dot < slash) return "text/plain; charset=utf-8"; /* LICENSE and the like */
  for (size_t i = 0; i < sizeof types / sizeof types[0]; i++)
    if (!strcmp(dot, types[i][0])) return types[i][1];
  return "application/octet-stream";
}

/* A name a request can spell without escapes, and not hidden. */
static int plain_name(const char *s) {
  if (!*s || *s == '.') return 0;
  for (; *s; s++)
    if (!((*s >= 'a' && *s <= 'z') || (*s >= 'A' && *s <= 'Z') || (*s >= '0' && *s <= '9') || strchr("._-", *s)))
      return 0;
  return 1;
}

void vlff_page_free(struct vlff_page *pg) {
  for (int i = 0; i < pg->n; i++) {
    free(pg->files[i].path);
    free(pg->files[i].data);
  }
  free(pg->files);
  pg->files = NULL;
  pg->n = 0;
}

int vlff_page_load(struct vlff_page *pg, const char *dir) {
  memset(pg, 0, sizeof *pg);
  char *roots[] = {(char *)dir, NULL};
  /* physical: a symbolic link is listed as one and never followed */
  FTS *fts = fts_open(roots, FTS_PHYSICAL | FTS_NOCHDIR, NULL);
  if (!fts) {
    fprintf(stderr, "vlff-view: --www %s: %s\n", dir, strerror(errno));
    return -1;
  }
  size_t total = 0, rootlen = strlen(dir);
  int rc = 0;
  FTSENT *e;
  while (rc == 0 && (e = fts_read(fts))) {
    if (e->fts_level == 0) continue;
    if (e->fts_info == FTS_D && !plain_name(e->fts_name)) fts_set(fts, e, FTS_SKIP);
    if (e->fts_info == FTS_DNR || e->fts_info == FTS_ERR) {
      fprintf(stderr, "vlff-view: --www %s: %s\n", e->fts_path, strerror(e->fts_errno));
      rc = -1;
    }
    if (e->fts_info != FTS_F || !plain_name(e->fts_name)) continue;
    if (pg->n == PAGE_FILES_MAX) {
      fprintf(stderr, "vlff-view: --www %s: more than %d files\n", dir, PAGE_FILES_MAX);
      rc = -1;
      break;
    }
    struct vlff_page_file f = {0};
    char err[512];
    if (vlff_read_file(e->fts_path, PAGE_FILE_MAX, &f.data, &f.len, err, sizeof err) != 0) {
      fprintf(stderr, "vlff-view: --www: %s\n", err);
      rc = -1;
      break;
    }
    total += f.len;
    f.path = strdup(e->fts_path + rootlen);
    struct vlff_page_file *grown = realloc(pg->files, (size_t)(pg->n + 1) * sizeof *grown);
    if (!f.path || !grown || total > PAGE_TOTAL_MAX) {
      fprintf(stderr, "vlff-view: --www %s: %s\n", dir,
              total > PAGE_TOTAL_MAX ? "the files add up to more than 64 MiB" : "out of memory");
      free(f.path);
      free(f.data);
      if (grown) pg->files = grown;
      rc = -1;
      break;
    }
    pg->files = grown;
    /* fts gives "dir/x" or "dir//x" for a dir ending in '/': keep one leading '/' */
    char *p = f.path;
    while (p[0] == '/' && p[1] == '/') p++;
    memmove(f.path, p, strlen(p) + 1);
    f.mime = mime_of(f.path);
    pg->files[pg->n++] = f;
  }
  fts_close(fts);
  if (rc == 0 && !vlff_page_find(pg, "/", 1)) {
    fprintf(stderr, "vlff-view: --www %s: no index.html there\n", dir);
    rc = -1;
  }
  if (rc) vlff_page_free(pg);
  return rc;
}

const struct vlff_page_file *vlff_page_find(const struct vlff_page *pg, const char *path, size_t len) {
  if (len == 1 && path[0] == '/') path = "/index.html", len = strlen(path);
  for (int i = 0; i < pg->n; i++)
    if (strlen(pg->files[i].path) == len && !memcmp(pg->files[i].path, path, len)) return &pg->files[i];
  return NULL;
}

/* ------------------------------------------------------------ request heads */

/* Every status the viewer answers with, in the order of its counters
 * (view.h: http_refused[i]). */
static const struct {
  int code;
  const char *reason;
} statuses[VLFF_VIEW_HTTP_N] = {
    {400, "Bad Request"},          {403, "Forbidden"},
    {404, "Not Found"},            {405, "Method Not Allowed"},
    {408, "Request Timeout"},      {414, "URI Too Long"},
    {426, "Upgrade Required"},     {431, "Request Header Fields Too Large"},
    {503, "Service Unavailable"},  {505, "HTTP Version Not Supported"},
};

int vlff_view_http_index(int status) {
  for (int i = 0; i < VLFF_VIEW_HTTP_N; i++)
    if (statuses[i].code == status) return i;
  return -1;
}

const char *vlff_http_reason(int status) {
  int i = vlff_view_http_index(status);
  return i < 0 ? "Error" : statuses[i].reason;
}

int vlff_view_http_status(int i) { return i >= 0 && i < VLFF_VIEW_HTTP_N ? statuses[i].code : 0; }

size_t vlff_http_refusal(char *out, size_t cap, int status, const char *why, int is_head) {
  int n = snprintf(out, cap,
                   "HTTP/1.1 %d %s\r\nContent-Type: text/plain; charset=utf-8\r\nContent-Length: %zu\r\n%s"
                   "Cache-Control: no-store\r\nX-Content-Type-Options: nosniff\r\nConnection: close\r\n\r\n%s%s",
                   status, vlff_http_reason(status), strlen(why) + 1,
                   status == 405   ? "Allow: GET, HEAD\r\n"
                   : status == 426 ? "Sec-WebSocket-Version: 13\r\nUpgrade: websocket\r\n"
                                   : "",
                   is_head ? "" : why, is_head ? "" : "\n");
  return n < 0 ? 0 : (size_t)n < cap ? (size_t)n : cap - 1;
}

static int is_tchar(unsigned char c) {
  return (c >= '0' && c <= '9') || ((c | 0x20) >= 'a' && (c | 0x20) <= 'z') || (c && strchr("!#$%&'*+-.^_`|~", c));
}

static enum vlff_head_verdict refuse(struct vlff_head *h, int status, const char *fmt, ...)
    __attribute__((format(printf, 3, 4)));
static enum vlff_head_verdict refuse(struct vlff_head *h, int status, const char *fmt, ...) {
  h->status = status;
  va_list ap;
  va_start(ap, fmt);
  vsnprintf(h->why, sizeof h->why, fmt, ap);
  va_end(ap);
  return VLFF_HEAD_REFUSE;
}

/* A header value without the spaces around it equals want, ignoring case. */
static int value_is(const char *v, const char *e, const char *want) {
  while (v < e && (*v == ' ' || *v == '\t')) v++;
  while (e > v && (e[-1] == ' ' || e[-1] == '\t')) e--;
  return (size_t)(e - v) == strlen(want) && !strncasecmp(v, want, (size_t)(e - v));
}

/* The request line "METHOD SP target SP HTTP/x.y CRLF" in [b, nl]. */
static enum vlff_head_verdict request_line(const char *b, const char *nl, struct vlff_head *h, const char **target,
                                           size_t *tlen) {
  const char *p = b;
  while (p < nl && is_tchar((unsigned char)*p)) p++;
  if (p == b || p == nl || *p != ' ') return refuse(h, 400, "the request does not start with a method and a space");
  size_t mlen = (size_t)(p - b);
  if (mlen > 32) return refuse(h, 400, "the request does not start with a method");
  h->is_head = mlen == 4 && !memcmp(b, "HEAD", 4);
  const char *t = ++p;
  while (p < nl && *p > 0x20 && *p < 0x7f) p++;
  *target = t, *tlen = (size_t)(p - t);
  if (*tlen > VLFF_HTTP_URI_MAX)
    return refuse(h, 414, "the request target is %zu bytes, the limit is %d", *tlen, VLFF_HTTP_URI_MAX);
  if (!*tlen || *p != ' ') return refuse(h, 400, "the request line is not METHOD, a target and a version");
  const char *v = p + 1, *cr = nl - 1;
  if (cr < v || *cr != '\r') return refuse(h, 400, "the request line does not end in CRLF");
  size_t vlen = (size_t)(cr - v);
  if (vlen == 8 && (!memcmp(v, "HTTP/1.1", 8) || !memcmp(v, "HTTP/1.0", 8))) {
    /* a version this server speaks */
  } else if (vlen == 8 && !memcmp(v, "HTTP/", 5) && v[5] >= '0' && v[5] <= '9' && v[6] == '.' && v[7] >= '0' &&
             v[7] <= '9') {
    return refuse(h, 505, "HTTP/%c.%c is not supported; this server speaks HTTP/1.1", v[5], v[7]);
  } else {
    return refuse(h, 400, "the request line does not end in an HTTP version");
  }
  if (!(mlen == 3 && !memcmp(b, "GET", 3)) && !h->is_head)
    return refuse(h, 405, "method %s is not allowed; this server answers GET and HEAD",
                  vlff_escape((char[VLFF_ESC_LEN]){0}, VLFF_ESC_LEN, b, mlen, 32));
  if (*t != '/') return refuse(h, 400, "the request target must be a path starting with '/'");
  return VLFF_HEAD_PASS;
}

static void trim(const char **v, const char **e);
static int has_token(const char *v, const char *e, const char *want);
static int ws_key_ok(const char *v, const char *e);

enum vlff_head_verdict vlff_head_check(const char *buf, size_t len, const struct vlff_page *pg,
                                       const struct vlff_allow *allow, struct vlff_head *h) {
  memset(h, 0, sizeof *h);
  const char *end = buf + len, *nl = memchr(buf, '\n', len);
  if (!nl) {
    /* judge what there is of the request line: garbage need not be waited for */
    const char *p = buf;
    while (p < end && is_tchar((unsigned char)*p)) p++;
    if ((p < end && (*p != ' ' || p == buf)) || p - buf > 32)
      return refuse(h, 400, "the request does not start with a method and a space");
    for (const char *q = p; q < end; q++)
      if ((unsigned char)*q < 0x20 && *q != '\r') return refuse(h, 400, "a control character in the request line");
    if (len > VLFF_HTTP_URI_MAX + 48) {
      h->is_head = !strncmp(buf, "HEAD ", 5);
      return refuse(h, 414, "the request line is longer than %d bytes and not finished", VLFF_HTTP_URI_MAX + 48);
    }
    return VLFF_HEAD_MORE;
  }
  const char *target = NULL;
  size_t tlen = 0;
  if (request_line(buf, nl, h, &target, &tlen) != VLFF_HEAD_PASS) return VLFF_HEAD_REFUSE;

  int lines = 0;
  /* the headers the later checks and vlff_head_canon look at: value spans */
  struct span {
    const char *v, *e;
    int n;
  } host = {0}, origin = {0}, conn = {0}, key = {0}, version = {0};
  for (const char *q = nl + 1;;) {
    const char *le = memchr(q, '\n', (size_t)(end - q));
    if ((size_t)((le ? le + 1 : end) - buf) > VLFF_HTTP_HEAD_MAX)
      return refuse(h, 431, "the request head is longer than %d bytes", VLFF_HTTP_HEAD_MAX);
    if (!le) return VLFF_HEAD_MORE;
    if (le == q || le[-1] != '\r') return refuse(h, 400, "header line %d does not end in CRLF", lines + 1);
    if (le - q == 1) {
      h->head_len = (size_t)(le + 1 - buf);
      break;
    }
    if (++lines > VLFF_HTTP_HEADERS_MAX)
      return refuse(h, 431, "more than %d header lines", VLFF_HTTP_HEADERS_MAX);
    const char *c = q;
    while (c < le && is_tchar((unsigned char)*c)) c++;
    if (c == q || *c != ':') return refuse(h, 400, "header line %d is not \"Name: value\"", lines);
    int nlen = (int)(c - q);
    for (const char *x = c + 1; x < le - 1; x++)
      if (((unsigned char)*x < 0x20 && *x != '\t') || *x == 0x7f)
        return refuse(h, 400, "header %s holds a control character",
                      vlff_escape((char[VLFF_ESC_LEN]){0}, VLFF_ESC_LEN, q, (size_t)nlen, 40));
    struct span *sp = NULL;
    if (nlen == 4 && !strncasecmp(q, "Host", 4)) sp = &host;
    else if (nlen == 6 && !strncasecmp(q, "Origin", 6)) sp = &origin;
    else if (nlen == 10 && !strncasecmp(q, "Connection", 10)) sp = &conn;
    else if (nlen == 17 && !strncasecmp(q, "Sec-WebSocket-Key", 17)) sp = &key;
    else if (nlen == 21 && !strncasecmp(q, "Sec-WebSocket-Version", 21)) sp = &version;
    if (sp && sp->n++ == 0) sp->v = c + 1, sp->e = le - 1;
    if (sp && sp != &conn && sp->n > 1)
      return refuse(h, 400, "header %s given twice", vlff_escape((char[VLFF_ESC_LEN]){0}, VLFF_ESC_LEN, q, (size_t)nlen, 40));
    if (nlen == 7 && !strncasecmp(q, "Upgrade", 7)) {
      if (!value_is(c + 1, le - 1, "websocket")) return refuse(h, 400, "only an upgrade to WebSocket is served");
      h->upgrade = 1;
    } else if ((nlen == 14 && !strncasecmp(q, "Content-Length", 14) && !value_is(c + 1, le - 1, "0")) ||
               (nlen == 17 && !strncasecmp(q, "Transfer-Encoding", 17))) {
      return refuse(h, 400, "a GET or HEAD request carries no body");
    }
    q = le + 1;
  }
  if (len > h->head_len) return refuse(h, 400, "bytes after the request head before its answer (no pipelining)");
  size_t plen = strcspn(target, "?# ");
  if (plen > tlen) plen = tlen;
  if (h->upgrade) {
    if (h->is_head) return refuse(h, 400, "a WebSocket upgrade is a GET, not a HEAD");
    if (plen != 1)
      return refuse(h, 404, "WebSocket connections are served at /, not at %s",
                    vlff_escape((char[VLFF_ESC_LEN]){0}, VLFF_ESC_LEN, target, plen, 60));
  } else if (!vlff_page_find(pg, target, plen)) {
    return refuse(h, 404, "%s is not a file of this page",
                  vlff_escape((char[VLFF_ESC_LEN]){0}, VLFF_ESC_LEN, target, plen, 60));
  }
  if (!host.n) return refuse(h, 400, "the request has no Host header");
  trim(&host.v, &host.e);
  trim(&origin.v, &origin.e);
  if (allow && !vlff_allow_host_ok(allow, host.v, (size_t)(host.e - host.v))) {
    h->forbidden = 1;
    return refuse(h, 403, "Host \"%.*s\" is not this viewer's (allow it with --allow-origin)",
                  (int)(host.e - host.v > 60 ? 60 : host.e - host.v), host.v);
  }
  if (allow && origin.n && !vlff_allow_origin_ok(allow, origin.v, (size_t)(origin.e - origin.v))) {
    h->forbidden = 2;
    return refuse(h, 403, "Origin \"%.*s\" is not allowed (allow it with --allow-origin)",
                  (int)(origin.e - origin.v > 60 ? 60 : origin.e - origin.v), origin.v);
  }
  if (h->upgrade) {
    if (!conn.n || !has_token(conn.v, conn.e, "upgrade"))
      return refuse(h, 400, "a WebSocket upgrade needs \"Connection: Upgrade\"");
    trim(&version.v, &version.e);
    if (!version.n || version.e - version.v != 2 || memcmp(version.v, "13", 2))
      return refuse(h, 426, "WebSocket version \"%.*s\" is not supported; this server speaks 13",
                    (int)(version.e - version.v > 20 ? 20 : version.e - version.v), version.n ? version.v : "");
    trim(&key.v, &key.e);
    if (!key.n || !ws_key_ok(key.v, key.e))
      return refuse(h, 400, "a WebSocket upgrade needs a Sec-WebSocket-Key of 16 bytes in base64");
  }
  return VLFF_HEAD_PASS;
}

/* ------------------------------------------------------------ canonical head */

size_t vlff_head_canon(const char *buf, const struct vlff_head *h, char *out, size_t cap) {
  static const char *const keep[] = {"Host", "Origin", "Upgrade", "Connection", "Sec-WebSocket-Key",
                                     "Sec-WebSocket-Version", "Sec-WebSocket-Protocol"};
  const char *end = buf + h->head_len, *nl = memchr(buf, '\n', h->head_len);
  if (!nl) return 0;
  size_t n = 0;
  for (const char *q = buf, *le = nl;; q = le + 1, le = memchr(q, '\n', (size_t)(end - q))) {
    if (!le) return 0;
    const char *colon = memchr(q, ':', (size_t)(le - q));
    size_t llen = (size_t)(le + 1 - q), nlen = colon ? (size_t)(colon - q) : 0;
    int take = q == buf || llen == 2; /* the request line, the empty line */
    for (size_t i = 0; !take && i < sizeof keep / sizeof keep[0]; i++)
      take = nlen == strlen(keep[i]) && !strncasecmp(q, keep[i], nlen);
    if (take) {
      if (n + llen > cap) return 0;
      memcpy(out + n, q, llen);
      n += llen;
    }
    if (llen == 2) return n;
  }
}

/* -------------------------------------------------------------- allow-list */

static void trim(const char **v, const char **e) {
  while (*v < *e && (**v == ' ' || **v == '\t')) (*v)++;
  while (*e > *v && ((*e)[-1] == ' ' || (*e)[-1] == '\t')) (*e)--;
}

/* The comma-separated list [v, e) holds token want (ignoring case). */
static int has_token(const char *v, const char *e, const char *want) {
  size_t wl = strlen(want);
  while (v < e) {
    const char *c = memchr(v, ',', (size_t)(e - v));
    const char *te = c ? c : e, *tv = v;
    trim(&tv, &te);
    if ((size_t)(te - tv) == wl && !strncasecmp(tv, want, wl)) return 1;
    v = c ? c + 1 : e;
  }
  return 0;
}

/* A Sec-WebSocket-Key: 16 bytes in base64, 24 characters ending in "==". */
static int ws_key_ok(const char *v, const char *e) {
  if (e - v != 24 || v[22] != '=' || v[23] != '=') return 0;
  for (int i = 0; i < 22; i++)
    if (!(isalnum((unsigned char)v[i]) || v[i] == '+' || v[i] == '/')) return 0;
  /* the last character before the padding carries 2 bits, the other 4 are zero */
  return strchr("AQgw", v[21]) != NULL;
}

static int copy_lower(char *out, size_t cap, const char *s, size_t n) {
  if (n == 0 || n >= cap) return -1;
  for (size_t i = 0; i < n; i++) {
    unsigned char c = (unsigned char)s[i];
    if (c <= 0x20 || c >= 0x7f) return -1;
    out[i] = (char)tolower(c);
  }
  out[n] = 0;
  return 0;
}

int vlff_allow_name(struct vlff_allow *a, const char *name) {
  if (a->n_names == VLFF_ALLOW_MAX) return -1;
  for (int i = 0; i < a->n_names; i++)
    if (!strcasecmp(a->names[i], name)) return 0;
  if (copy_lower(a->names[a->n_names], VLFF_ALLOW_LEN, name, strlen(name))) return -1;
  a->n_names++;
  return 0;
}

/* An authority "host[:port]" with host a name, an IPv4 address or "[IPv6]". */
static int authority_ok(const char *s, size_t n) {
  if (!n) return 0;
  size_t hl = n;
  if (s[0] == '[') {
    const char *rb = memchr(s, ']', n);
    if (!rb) return 0;
    hl = (size_t)(rb + 1 - s);
    for (const char *p = s + 1; p < rb; p++)
      if (!isxdigit((unsigned char)*p) && *p != ':' && *p != '.') return 0;
  } else {
    const char *colon = memchr(s, ':', n);
    if (colon) hl = (size_t)(colon - s);
    for (size_t i = 0; i < hl; i++)
      if (!isalnum((unsigned char)s[i]) && !strchr("-._", s[i])) return 0;
  }
  if (hl == 0) return 0;
  if (hl == n) return 1;
  if (s[hl] != ':' || n - hl - 1 < 1 || n - hl - 1 > 5) return 0;
  for (size_t i = hl + 1; i < n; i++)
    if (!isdigit((unsigned char)s[i])) return 0;
  return 1;
}

int vlff_allow_origin(struct vlff_allow *a, const char *origin, char *why, size_t len) {
  size_t n = strlen(origin), skip = !strncasecmp(origin, "http://", 7) ? 7 : !strncasecmp(origin, "https://", 8) ? 8 : 0;
  if (!skip || !authority_ok(origin + skip, n - skip)) {
    snprintf(why, len, "'%.80s' is not an origin http://HOST[:PORT] or https://HOST[:PORT] (no path)", origin);
    return -1;
  }
  if (a->n_origins == VLFF_ALLOW_MAX || copy_lower(a->origins[a->n_origins], VLFF_ALLOW_LEN, origin, n)) {
    snprintf(why, len, "'%.80s': at most %d origins of fewer than %d characters", origin, VLFF_ALLOW_MAX,
             VLFF_ALLOW_LEN);
    return -1;
  }
  a->n_origins++;
  return 0;
}

/* An own authority: a listed name with the viewer's port (or none for port 80). */
static int own_authority(const struct vlff_allow *a, const char *v, size_t n) {
  if (!authority_ok(v, n)) return 0;
  size_t hl = n;
  const char *colon = v[0] == '[' ? (const char *)memchr(v, ']', n) + 1 : memchr(v, ':', n);
  if (colon && colon < v + n) {
    hl = (size_t)(colon - v);
    char port[8];
    snprintf(port, sizeof port, "%d", a->port);
    if (n - hl - 1 != strlen(port) || memcmp(colon + 1, port, n - hl - 1)) return 0;
  } else if (a->port != 80) {
    return 0;
  }
  for (int i = 0; i < a->n_names; i++)
    if (strlen(a->names[i]) == hl && !strncasecmp(a->names[i], v, hl)) return 1;
  return 0;
}

int vlff_allow_host_ok(const struct vlff_allow *a, const char *v, size_t n) {
  const char *e = v + n;
  trim(&v, &e);
  n = (size_t)(e - v);
  if (own_authority(a, v, n)) return 1;
  for (int i = 0; i < a->n_origins; i++) {
    const char *auth = strstr(a->origins[i], "://") + 3;
    if (strlen(auth) == n && !strncasecmp(auth, v, n)) return 1;
  }
  return 0;
}

int vlff_allow_origin_ok(const struct vlff_allow *a, const char *v, size_t n) {
  const char *e = v + n;
  trim(&v, &e);
  n = (size_t)(e - v);
  for (int i = 0; i < a->n_origins; i++)
    if (strlen(a->origins[i]) == n && !strncasecmp(a->origins[i], v, n)) return 1;
  return n > 7 && !strncasecmp(v, "http://", 7) && own_authority(a, v + 7, n - 7);
}
