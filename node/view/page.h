/* SPDX-License-Identifier: MIT */
/*
 * page.h - the page's files and the check of every HTTP request head (page.c).
 *
 * The files: every regular file under the www directory (symbolic links, devices,
 * FIFOs, hidden names and names outside [A-Za-z0-9._-] skipped) is read once at
 * start into memory through vlff_read_file; that list is the allow-list, nothing
 * else is ever served and no path from a request reaches the file system.
 *
 * The head check runs on the bytes a connection has sent so far, before
 * libwebsockets sees any of them: it says whether more bytes are needed, whether
 * the head may be handed on (a GET or HEAD of a listed file, or a WebSocket upgrade
 * of "/"), or which HTTP status refuses it and why:
 *   400 malformed (request line, header line, a body, bytes after the head,
 *       an upgrade to something other than WebSocket),
 *   404 a path that names no listed file,
 *   405 a method other than GET or HEAD,
 *   414 a request target longer than VLFF_HTTP_URI_MAX,
 *   431 a head longer than VLFF_HTTP_HEAD_MAX or with more than
 *       VLFF_HTTP_HEADERS_MAX header lines,
 *   505 an HTTP version other than 1.0 and 1.1.
 *
 * CONTRACT
 * Errors: vlff_page_load returns -1 and writes one line naming the file and what is
 *   wrong to stderr. The check never fails; a refusal is its answer.
 * Ownership: the page owns its files; vlff_page_free frees them.
 * Threads: none; pure functions of their arguments but for vlff_page_load.
 */
#ifndef VLFF_VIEW_PAGE_H
#define VLFF_VIEW_PAGE_H

#include <stddef.h>
#include <stdint.h>

#define VLFF_HTTP_URI_MAX 2048    /* request target bytes */
#define VLFF_HTTP_HEAD_MAX 8192   /* request line, headers and the empty line */
#define VLFF_HTTP_HEADERS_MAX 64  /* header lines */

/* The Content-Security-Policy of every page response: the page's own files and
 * its own WebSocket only, no inline script or style, no plugins, no framing. */
#define VLFF_PAGE_CSP                                                                                        \
  "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self'; connect-src 'self'; "          \
  "object-src 'none'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'"

struct vlff_page_file {
  char *path;       /* "/index.html", "/three/three.module.js" */
  const char *mime; /* Content-Type */
  uint8_t *data;
  size_t len;
};

struct vlff_page {
  struct vlff_page_file *files;
  int n;
};

int vlff_page_load(struct vlff_page *pg, const char *dir);
void vlff_page_free(struct vlff_page *pg);
/* The listed file at path (len bytes, no query), "/" being "/index.html"; NULL if none. */
const struct vlff_page_file *vlff_page_find(const struct vlff_page *pg, const char *path, size_t len);

enum vlff_head_verdict { VLFF_HEAD_MORE, VLFF_HEAD_PASS, VLFF_HEAD_REFUSE };

struct vlff_head {
  int status;      /* the refusal's HTTP status */
  char why[160];   /* the refusal's sentence */
  size_t head_len; /* PASS: bytes of the head, its empty line included */
  int is_head;     /* the method is HEAD (a refusal then carries no body) */
  int upgrade;     /* PASS: a WebSocket upgrade */
};

/* Checks the len bytes a connection sent so far. */
enum vlff_head_verdict vlff_head_check(const char *buf, size_t len, const struct vlff_page *pg, struct vlff_head *h);
/* The reason phrase of a status the check or the server refuses with. */
const char *vlff_http_reason(int status);
/* A whole refusal response in out (cap bytes, NUL-terminated): status line, plain
 * headers, "Connection: close", "Allow" for 405, the sentence as the body (not for
 * a HEAD request, whose answer has none). Returns its length. */
size_t vlff_http_refusal(char *out, size_t cap, int status, const char *why, int is_head);

#endif
