/* libFuzzer target: any bytes a client can send before its request head ends
 * go through vlff-view's head check (page.h) without crashing or reading past
 * them, and its verdicts keep their promises: a head handed on to
 * libwebsockets is a GET or HEAD of a listed file or a WebSocket upgrade of
 * "/", ends in the empty line within the limits; a refusal carries one of the
 * statuses page.h lists and a sentence, and its response fits its buffer. The
 * input is checked whole, then cut at every line break, as a client sending it
 * in pieces would be. Host and Origin are checked against an allow-list (the
 * viewer's own names on port 8765 and one configured origin): a passed head has
 * exactly one Host the list allows and at most one Origin it allows; its
 * rewritten form (vlff_head_canon), what libwebsockets gets, passes the check
 * again unchanged but for the header lines left out. */
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <strings.h>

#include "page.h"

static uint8_t index_html[] = "<!doctype html>";
static uint8_t three_js[] = "export {}";
static struct vlff_page_file files[] = {
    {"/index.html", "text/html", index_html, sizeof index_html - 1},
    {"/three/three.module.js", "text/javascript", three_js, sizeof three_js - 1},
};
static const struct vlff_page page = {files, 2};
static const struct vlff_allow allow = {.port = 8765, .n_names = 3, .names = {"127.0.0.1", "localhost", "[::1]"},
                                        .n_origins = 1, .origins = {"https://robot.lan"}};

/* The value of the only header name[] in the passed head, or NULL. */
static const char *header(const char *buf, size_t len, const char *name, size_t *n) {
  size_t nl = strlen(name);
  for (const char *q = memchr(buf, '\n', len) + 1; q < buf + len;) {
    const char *le = memchr(q, '\n', (size_t)(buf + len - q));
    if (!le) break;
    if ((size_t)(le - q) > nl && q[nl] == ':' && !strncasecmp(q, name, nl)) {
      *n = (size_t)(le - 1 - (q + nl + 1));
      return q + nl + 1;
    }
    q = le + 1;
  }
  return NULL;
}

static void check(const char *buf, size_t len) {
  struct vlff_head h;
  enum vlff_head_verdict v = vlff_head_check(buf, len, &page, &allow, &h);
  switch (v) {
  case VLFF_HEAD_MORE: break;
  case VLFF_HEAD_PASS:
    if (h.head_len < 4 || h.head_len > len || h.head_len > VLFF_HTTP_HEAD_MAX) __builtin_trap();
    if (memcmp(buf + h.head_len - 4, "\r\n\r\n", 4)) __builtin_trap();
    if (strncmp(buf, "GET ", 4) && strncmp(buf, "HEAD ", 5)) __builtin_trap();
    /* an upgrade is a GET of "/", a query or fragment after it allowed */
    if (h.upgrade && (strncmp(buf, "GET /", 5) || !strchr(" ?#", buf[5]))) __builtin_trap();
    {
      size_t n;
      const char *host = header(buf, h.head_len, "Host", &n);
      if (!host || !vlff_allow_host_ok(&allow, host, n)) __builtin_trap();
      const char *origin = header(buf, h.head_len, "Origin", &n);
      if (origin && !vlff_allow_origin_ok(&allow, origin, n)) __builtin_trap();
      char *canon = malloc(h.head_len);
      if (!canon) break;
      size_t cn = vlff_head_canon(buf, &h, canon, h.head_len);
      struct vlff_head h2;
      if (!cn || cn > h.head_len || vlff_head_check(canon, cn, &page, &allow, &h2) != VLFF_HEAD_PASS ||
          h2.head_len != cn || h2.upgrade != h.upgrade || h2.is_head != h.is_head)
        __builtin_trap();
      free(canon);
    }
    break;
  case VLFF_HEAD_REFUSE: {
    static const int listed[] = {400, 403, 404, 405, 408, 414, 426, 431, 505};
    int ok = 0;
    for (size_t i = 0; i < sizeof listed / sizeof listed[0]; i++) ok |= h.status == listed[i];
    if (!ok || !h.why[0] || !memchr(h.why, 0, sizeof h.why)) __builtin_trap();
    char out[512];
    size_t n = vlff_http_refusal(out, sizeof out, h.status, h.why, h.is_head);
    if (n == 0 || n >= sizeof out || strncmp(out, "HTTP/1.1 ", 9)) __builtin_trap();
    break;
  }
  default: __builtin_trap();
  }
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  /* a copy of exactly size bytes, so that ASan sees any read past them */
  char *buf = malloc(size ? size : 1);
  if (!buf) return 0;
  memcpy(buf, data, size);
  check(buf, size);
  for (size_t i = 0; i < size; i++)
    if (buf[i] == '\n') check(buf, i + 1);
  free(buf);
  return 0;
}
