/* SPDX-License-Identifier: BSD-3-Clause */
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
 *       an upgrade to something other than WebSocket, no Host or two, a WebSocket
 *       upgrade without "Connection: Upgrade" or a 16-byte Sec-WebSocket-Key),
 *   403 a Host or an Origin the allow-list (struct vlff_allow) does not name,
 *   404 a path that names no listed file,
 *   405 a method other than GET or HEAD,
 *   414 a request target longer than VLFF_HTTP_URI_MAX,
 *   431 a head longer than VLFF_HTTP_HEAD_MAX or with more than
 *       VLFF_HTTP_HEADERS_MAX header lines,
 *   426 a WebSocket upgrade whose Sec-WebSocket-Version is not 13 (or missing;
 *       the answer names 13 in its own Sec-WebSocket-Version header),
 *   505 an HTTP version other than 1.0 and 1.1.
 * A passed head is handed to libwebsockets rewritten by vlff_head_canon: the
 * request line and only the headers the server uses, so that no other header line
 * reaches libwebsockets' parser.
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

/* Who may address the viewer (the defence against a foreign web page, or a DNS
 * name rebound to the robot, reaching it through a browser): the Host of every
 * request must be one of the viewer's own names (names[], with ":port" or, for
 * port 80, without) or the authority of a configured origin; an Origin, when the
 * request has one, must be "http://" and such a Host, or a configured origin. A
 * request without Origin (Foxglove desktop, curl, any non-browser client) passes on
 * its Host. Comparisons ignore case. */
#define VLFF_ALLOW_MAX 64
#define VLFF_ALLOW_LEN 128
struct vlff_allow {
  int port;                                  /* the viewer's port */
  int n_names;                               /* own names: "127.0.0.1", "localhost", "[::1]" */
  char names[VLFF_ALLOW_MAX][VLFF_ALLOW_LEN];
  int n_origins;                             /* configured: "http://robot.lan:8765" */
  char origins[VLFF_ALLOW_MAX][VLFF_ALLOW_LEN];
};
/* Adds an own name (0) or -1 when full or too long. */
int vlff_allow_name(struct vlff_allow *a, const char *name);
/* Checks and adds a configured origin "http[s]://host[:port]" (no path, no
 * userinfo), lowercased: 0, or -1 with the reason in why[len]. */
int vlff_allow_origin(struct vlff_allow *a, const char *origin, char *why, size_t len);
/* Whether the Host value v[n] (spaces around it ignored) is allowed. */
int vlff_allow_host_ok(const struct vlff_allow *a, const char *v, size_t n);
/* Whether the Origin value v[n] is allowed. */
int vlff_allow_origin_ok(const struct vlff_allow *a, const char *v, size_t n);

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
  int forbidden;   /* REFUSE 403: the Host (1) or the Origin (2) was refused */
};

/* Checks the len bytes a connection sent so far; allow NULL skips the Host and
 * Origin checks (a Host is still required). */
enum vlff_head_verdict vlff_head_check(const char *buf, size_t len, const struct vlff_page *pg,
                                       const struct vlff_allow *allow, struct vlff_head *h);
/* The passed head buf (h from its check) rewritten into out[cap] with only the
 * request line and the Host, Origin, Upgrade, Connection and Sec-WebSocket-Key,
 * -Version and -Protocol lines, then the empty line. Its length, 0 if cap is too
 * small (a cap of h->head_len always suffices). */
size_t vlff_head_canon(const char *buf, const struct vlff_head *h, char *out, size_t cap);
/* The reason phrase of a status the check or the server refuses with. */
const char *vlff_http_reason(int status);
/* A whole refusal response in out (cap bytes, NUL-terminated): status line, plain
 * headers, "Connection: close", "Allow" for 405, "Sec-WebSocket-Version: 13" for
 * 426, the sentence as the body (not for
 * a HEAD request, whose answer has none). Returns its length. */
size_t vlff_http_refusal(char *out, size_t cap, int status, const char *why, int is_head);

#endif
