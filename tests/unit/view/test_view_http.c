/*
 * The viewer's page files and request-head check (page.h), in-process: the files
 * listed from a www directory (regular files with plain names only, no link, FIFO
 * or hidden file), and heads judged whole and byte by byte: passed, refused with
 * each status, or waited for.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <unistd.h>

#include "files.h"
#include "page.h"
#include "unit.h"
#include "view.h"

static char dir[64];
static struct vlff_page page;

static void put(const char *rel, const char *text) {
  char p[256];
  snprintf(p, sizeof p, "%s/%s", dir, rel);
  assert_int_equal(vlff_write_file_atomic(p, text, strlen(text), NULL, 0), 0);
}

static int setup(void **state) {
  (void)state;
  snprintf(dir, sizeof dir, "/tmp/vlff-test-page-XXXXXX");
  if (!mkdtemp(dir)) return -1;
  char p[256];
  snprintf(p, sizeof p, "%s/three", dir);
  mkdir(p, 0755);
  snprintf(p, sizeof p, "%s/.git", dir);
  mkdir(p, 0755);
  put("index.html", "<!doctype html>");
  put("view.js", "export {};");
  put("three/three.module.js", "export const t = 1;");
  put("three/LICENSE", "MIT");
  put(".git/config", "secret");
  put(".env", "secret");
  put("with space.js", "x");
  snprintf(p, sizeof p, "%s/passwd.js", dir);
  if (symlink("/etc/passwd", p) != 0) return -1;
  snprintf(p, sizeof p, "%s/pipe.js", dir);
  if (mkfifo(p, 0600) != 0) return -1;
  return vlff_page_load(&page, dir);
}

static int teardown(void **state) {
  (void)state;
  vlff_page_free(&page);
  char cmd[128];
  snprintf(cmd, sizeof cmd, "rm -rf %s", dir);
  return system(cmd);
}

static void test_files(void **state) {
  (void)state;
  assert_int_equal(page.n, 4);
  const struct vlff_page_file *f = vlff_page_find(&page, "/", 1);
  assert_non_null(f);
  assert_string_equal(f->path, "/index.html");
  assert_string_equal(f->mime, "text/html; charset=utf-8");
  assert_int_equal(f->len, strlen("<!doctype html>"));
  f = vlff_page_find(&page, "/three/three.module.js", 22);
  assert_non_null(f);
  assert_string_equal(f->mime, "text/javascript; charset=utf-8");
  assert_memory_equal(f->data, "export const t = 1;", f->len);
  assert_string_equal(vlff_page_find(&page, "/three/LICENSE", 14)->mime, "text/plain; charset=utf-8");
  const char *absent[] = {"/passwd.js", "/pipe.js", "/.env", "/.git/config", "/with space.js", "/three", "/three/",
                          "/index.htm", "//index.html"};
  for (size_t i = 0; i < sizeof absent / sizeof *absent; i++)
    assert_null(vlff_page_find(&page, absent[i], strlen(absent[i])));

  /* a directory without index.html is no page */
  struct vlff_page other;
  char p[128];
  snprintf(p, sizeof p, "%s/three", dir);
  assert_int_equal(vlff_page_load(&other, p), -1);
  assert_int_equal(other.n, 0);
}

static struct vlff_allow allow = {.port = 8765, .n_names = 3, .names = {"127.0.0.1", "localhost", "[::1]"},
                                   .n_origins = 1, .origins = {"https://robot.lan"}};

static enum vlff_head_verdict check(const char *req, struct vlff_head *h) {
  return vlff_head_check(req, strlen(req), &page, &allow, h);
}

#define HOST "Host: 127.0.0.1:8765\r\n"
#define WS "Upgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Version: 13\r\n"
#define KEY "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"

static void test_heads(void **state) {
  (void)state;
  char big[VLFF_HTTP_HEAD_MAX + 64], target[VLFF_HTTP_URI_MAX + 2];
  memset(target, 'a', sizeof target - 1);
  target[0] = '/';
  target[sizeof target - 1] = 0;
  static const struct {
    const char *req;
    enum vlff_head_verdict verdict;
    int status;
    const char *why;
  } cases[] = {
      {"GET / HTTP/1.1\r\n" HOST "\r\n", VLFF_HEAD_PASS, 0, ""},
      {"HEAD /view.js?v=2 HTTP/1.0\r\n" HOST "\r\n", VLFF_HEAD_PASS, 0, ""},
      {"GET / HTTP/1.1\r\n" HOST "Upgrade: WebSocket \r\nConnection: keep-alive, Upgrade\r\n"
       "Sec-WebSocket-Version:13\r\n" KEY "\r\n", VLFF_HEAD_PASS, 0, ""},
      {"GET / HTTP/1.1\r\n" HOST "Content-Length: 0\r\n\r\n", VLFF_HEAD_PASS, 0, ""},
      /* Host and Origin (issue 51): the viewer's own names and port, or configured */
      {"GET / HTTP/1.1\r\n\r\n", VLFF_HEAD_REFUSE, 400, "no Host header"},
      {"GET / HTTP/1.1\r\n" HOST HOST "\r\n", VLFF_HEAD_REFUSE, 400, "header Host given twice"},
      {"GET / HTTP/1.1\r\nHost: evil.example:8765\r\n\r\n", VLFF_HEAD_REFUSE, 403, "Host \"evil.example:8765\""},
      {"GET / HTTP/1.1\r\nHost: 127.0.0.1:8766\r\n\r\n", VLFF_HEAD_REFUSE, 403, "is not this viewer's"},
      {"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n", VLFF_HEAD_REFUSE, 403, "is not this viewer's"},
      {"GET / HTTP/1.1\r\nHost: 127.0.0.1:8765x\r\n\r\n", VLFF_HEAD_REFUSE, 403, "is not this viewer's"},
      {"GET / HTTP/1.1\r\nHost: LocalHost:8765\r\n\r\n", VLFF_HEAD_PASS, 0, ""},
      {"GET / HTTP/1.1\r\nHost: [::1]:8765\r\n\r\n", VLFF_HEAD_PASS, 0, ""},
      {"GET / HTTP/1.1\r\nHost: robot.lan\r\n\r\n", VLFF_HEAD_PASS, 0, ""},
      {"GET / HTTP/1.1\r\nHost: robot.lan:8765\r\n\r\n", VLFF_HEAD_REFUSE, 403, "Host"},
      {"GET / HTTP/1.1\r\n" HOST "Origin: http://127.0.0.1:8765\r\n\r\n", VLFF_HEAD_PASS, 0, ""},
      {"GET / HTTP/1.1\r\n" HOST "Origin: https://robot.lan\r\n\r\n", VLFF_HEAD_PASS, 0, ""},
      {"GET / HTTP/1.1\r\n" HOST "Origin: http://evil.example\r\n\r\n", VLFF_HEAD_REFUSE, 403, "Origin \"http://evil"},
      {"GET / HTTP/1.1\r\n" HOST "Origin: null\r\n\r\n", VLFF_HEAD_REFUSE, 403, "Origin \"null\""},
      {"GET / HTTP/1.1\r\n" HOST "Origin: https://127.0.0.1:8765\r\n\r\n", VLFF_HEAD_REFUSE, 403, "Origin"},
      {"GET / HTTP/1.1\r\n" HOST "Origin: http://127.0.0.1:8765/x\r\n\r\n", VLFF_HEAD_REFUSE, 403, "Origin"},
      {"GET / HTTP/1.1\r\n" HOST "Origin: http://127.0.0.1:876\r\n" WS KEY "\r\n", VLFF_HEAD_REFUSE, 403, "Origin"},
      /* WebSocket upgrades without what RFC 6455 requires */
      {"GET / HTTP/1.1\r\n" HOST WS "\r\n", VLFF_HEAD_REFUSE, 400, "Sec-WebSocket-Key of 16 bytes"},
      {"GET / HTTP/1.1\r\n" HOST WS "Sec-WebSocket-Key: abc\r\n\r\n", VLFF_HEAD_REFUSE, 400, "Sec-WebSocket-Key"},
      {"GET / HTTP/1.1\r\n" HOST WS "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZR==\r\n\r\n", VLFF_HEAD_REFUSE, 400,
       "Sec-WebSocket-Key"},
      {"GET / HTTP/1.1\r\n" HOST WS KEY KEY "\r\n", VLFF_HEAD_REFUSE, 400, "given twice"},
      {"GET / HTTP/1.1\r\n" HOST "Upgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Version: 99\r\n" KEY
       "\r\n", VLFF_HEAD_REFUSE, 426, "version \"99\" is not supported; this server speaks 13"},
      {"GET / HTTP/1.1\r\n" HOST "Upgrade: websocket\r\nConnection: Upgrade\r\n" KEY "\r\n", VLFF_HEAD_REFUSE, 426,
       "version \"\" is not supported"},
      {"GET / HTTP/1.1\r\n" HOST "Upgrade: websocket\r\nSec-WebSocket-Version: 13\r\n" KEY "\r\n", VLFF_HEAD_REFUSE,
       400, "Connection: Upgrade"},
      {"GET / HTTP/1.1\r\nHost: x\r\n", VLFF_HEAD_MORE, 0, ""},
      {"GET /index.ht", VLFF_HEAD_MORE, 0, ""},
      {"", VLFF_HEAD_MORE, 0, ""},
      {"POST / HTTP/1.1\r\n", VLFF_HEAD_REFUSE, 405, "method POST is not allowed"},
      {"OPTIONS * HTTP/1.1\r\n\r\n", VLFF_HEAD_REFUSE, 405, "method OPTIONS"},
      {"get / HTTP/1.1\r\n\r\n", VLFF_HEAD_REFUSE, 405, "method get"},
      {"\x16\x03\x01\x02", VLFF_HEAD_REFUSE, 400, "does not start with a method"},
      {" GET / HTTP/1.1\r\n\r\n", VLFF_HEAD_REFUSE, 400, "does not start with a method"},
      {"GET\t/ HTTP/1.1\r\n\r\n", VLFF_HEAD_REFUSE, 400, "does not start with a method"},
      {"GET / HTTP/1.1 \r\n\r\n", VLFF_HEAD_REFUSE, 400, "HTTP version"},
      {"GET  / HTTP/1.1\r\n\r\n", VLFF_HEAD_REFUSE, 400, "METHOD, a target and a version"},
      {"GET /\x01 HTTP/1.1\r\n\r\n", VLFF_HEAD_REFUSE, 400, "METHOD, a target and a version"},
      {"GET / HTTP/1.1\n\n", VLFF_HEAD_REFUSE, 400, "CRLF"},
      {"GET / HTTP/1.1\r\nHost: x\n\r\n", VLFF_HEAD_REFUSE, 400, "header line 1 does not end in CRLF"},
      {"GET http://x/ HTTP/1.1\r\n\r\n", VLFF_HEAD_REFUSE, 400, "must be a path"},
      {"GET / HTTP/1.1\r\n folded\r\n\r\n", VLFF_HEAD_REFUSE, 400, "is not \"Name: value\""},
      {"GET / HTTP/1.1\r\nName : v\r\n\r\n", VLFF_HEAD_REFUSE, 400, "is not \"Name: value\""},
      {"GET / HTTP/1.1\r\nX: a\x01" "b\r\n\r\n", VLFF_HEAD_REFUSE, 400, "header X holds a control character"},
      {"GET / HTTP/1.1\r\nUpgrade: h2c\r\n\r\n", VLFF_HEAD_REFUSE, 400, "only an upgrade to WebSocket"},
      {"GET / HTTP/1.1\r\nContent-Length: 3\r\n\r\n", VLFF_HEAD_REFUSE, 400, "carries no body"},
      {"GET / HTTP/1.1\r\nTransfer-Encoding: chunked\r\n\r\n", VLFF_HEAD_REFUSE, 400, "carries no body"},
      {"GET / HTTP/1.1\r\n\r\nGET / HTTP/1.1\r\n\r\n", VLFF_HEAD_REFUSE, 400, "no pipelining"},
      {"GET / HTTP/2.0\r\n\r\n", VLFF_HEAD_REFUSE, 505, "HTTP/2.0 is not supported"},
      {"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n", VLFF_HEAD_REFUSE, 505, "HTTP/2.0"},
      {"GET / HTTP/1.1x\r\n\r\n", VLFF_HEAD_REFUSE, 400, "HTTP version"},
      {"GET /nope.html HTTP/1.1\r\n\r\n", VLFF_HEAD_REFUSE, 404, "/nope.html is not a file of this page"},
      /* the target quoted through vlff/escape.h (only printable ASCII gets this far) */
      {"GET /a'b\\c\" HTTP/1.1\r\n\r\n", VLFF_HEAD_REFUSE, 404, "/a\\'b\\\\c\\\" is not a file"},
      {"GET /../etc/passwd HTTP/1.1\r\n\r\n", VLFF_HEAD_REFUSE, 404, "not a file"},
      {"GET /%69ndex.html HTTP/1.1\r\n\r\n", VLFF_HEAD_REFUSE, 404, "not a file"},
      {"GET /passwd.js HTTP/1.1\r\n\r\n", VLFF_HEAD_REFUSE, 404, "not a file"},
      {"GET /.env HTTP/1.1\r\n\r\n", VLFF_HEAD_REFUSE, 404, "not a file"},
      {"GET /view.js HTTP/1.1\r\nUpgrade: websocket\r\n\r\n", VLFF_HEAD_REFUSE, 404, "served at /"},
      {"GET /?t=1 HTTP/1.1\r\n" HOST WS KEY "\r\n", VLFF_HEAD_PASS, 0, ""},
      {"HEAD / HTTP/1.1\r\nUpgrade: websocket\r\n\r\n", VLFF_HEAD_REFUSE, 400, "is a GET, not a HEAD"},
  };
  struct vlff_head h;
  for (size_t i = 0; i < sizeof cases / sizeof *cases; i++) {
    enum vlff_head_verdict got = check(cases[i].req, &h);
    if (got != cases[i].verdict || h.status != cases[i].status || !strstr(h.why, cases[i].why))
      fail_msg("case %zu \"%.40s\": verdict %d status %d \"%s\"", i, cases[i].req, got, h.status, h.why);
  }
  assert_int_equal(check("GET / HTTP/1.1\r\n" HOST WS KEY "\r\n", &h), VLFF_HEAD_PASS);
  assert_true(h.upgrade);
  assert_int_equal(check("HEAD /nope HTTP/1.1\r\n\r\n", &h), VLFF_HEAD_REFUSE);
  assert_true(h.is_head);

  /* sizes: a target of the limit passes the length check, one byte more is 414 */
  snprintf(big, sizeof big, "GET %.*s HTTP/1.1\r\n\r\n", VLFF_HTTP_URI_MAX, target);
  assert_int_equal(check(big, &h), VLFF_HEAD_REFUSE);
  assert_int_equal(h.status, 404);
  snprintf(big, sizeof big, "GET %s HTTP/1.1\r\n\r\n", target);
  assert_int_equal(check(big, &h), VLFF_HEAD_REFUSE);
  assert_int_equal(h.status, 414);
  snprintf(big, sizeof big, "GET %s", target); /* unfinished, long: not waited for */
  strcat(big, "aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa");
  assert_int_equal(check(big, &h), VLFF_HEAD_REFUSE);
  assert_int_equal(h.status, 414);
  int n = snprintf(big, sizeof big, "GET / HTTP/1.1\r\n" HOST "X-Pad: ");
  memset(big + n, 'p', VLFF_HTTP_HEAD_MAX - n - 4);
  memcpy(big + VLFF_HTTP_HEAD_MAX - 4, "\r\n\r\n", 5);
  assert_int_equal(check(big, &h), VLFF_HEAD_PASS); /* exactly the limit */
  assert_int_equal(h.head_len, VLFF_HTTP_HEAD_MAX);
  memcpy(big + VLFF_HTTP_HEAD_MAX - 4, "p\r\n\r\n", 6);
  assert_int_equal(check(big, &h), VLFF_HEAD_REFUSE);
  assert_int_equal(h.status, 431);
  big[VLFF_HTTP_HEAD_MAX - 1000] = 0; /* still unfinished below the limit: wait */
  assert_int_equal(check(big, &h), VLFF_HEAD_MORE);
  n = snprintf(big, sizeof big, "GET / HTTP/1.1\r\n");
  for (int k = 0; k < VLFF_HTTP_HEADERS_MAX + 1; k++) n += snprintf(big + n, sizeof big - (size_t)n, "X-A: b\r\n");
  assert_int_equal(check(big, &h), VLFF_HEAD_REFUSE);
  assert_int_equal(h.status, 431);

  /* byte by byte: more, more, ..., then passed at the last byte */
  const char *req = "GET /three/three.module.js HTTP/1.1\r\nHost: 127.0.0.1:8765\r\nAccept: */*\r\n\r\n";
  for (size_t k = 1; k < strlen(req); k++)
    assert_int_equal(vlff_head_check(req, k, &page, &allow, &h), VLFF_HEAD_MORE);
  assert_int_equal(check(req, &h), VLFF_HEAD_PASS);
  assert_int_equal(h.head_len, strlen(req));
}

/* A passed head reaches libwebsockets with the request line and the headers the
 * server uses only: a one-letter header (issue 51: "X: a" left libwebsockets
 * waiting) or any other is left out. */
static void test_canon(void **state) {
  (void)state;
  const char *req = "GET /?a HTTP/1.1\r\nX: a\r\n" HOST "Accept: */*\r\nOrigin: http://localhost:8765\r\n" WS KEY
                    "Sec-WebSocket-Protocol: foxglove.websocket.v1\r\nCookie: c=1\r\n\r\n";
  struct vlff_head h;
  assert_int_equal(check(req, &h), VLFF_HEAD_PASS);
  char out[1024];
  size_t n = vlff_head_canon(req, &h, out, sizeof out);
  out[n] = 0;
  assert_string_equal(out, "GET /?a HTTP/1.1\r\n" HOST "Origin: http://localhost:8765\r\n" WS KEY
                           "Sec-WebSocket-Protocol: foxglove.websocket.v1\r\n\r\n");
  assert_int_equal(vlff_head_canon(req, &h, out, 20), 0); /* too small: nothing */
}

/* The configured origins: http(s)://HOST[:PORT] only. */
static void test_origins(void **state) {
  (void)state;
  struct vlff_allow a = {.port = 80};
  char why[200];
  assert_int_equal(vlff_allow_origin(&a, "HTTP://Robot.Lan:9000", why, sizeof why), 0);
  assert_string_equal(a.origins[0], "http://robot.lan:9000");
  assert_int_equal(vlff_allow_origin(&a, "https://[fd00::1]", why, sizeof why), 0);
  static const char *const bad[] = {"robot.lan", "http://", "http://a/b", "http://u@h", "ftp://h", "http://h:",
                                    "http://h:123456", "http://h h", "*", "null"};
  for (size_t i = 0; i < sizeof bad / sizeof *bad; i++) {
    if (vlff_allow_origin(&a, bad[i], why, sizeof why) == 0) fail_msg("origin '%s' accepted", bad[i]);
    assert_non_null(strstr(why, "is not an origin"));
  }
  assert_int_equal(a.n_origins, 2);
  vlff_allow_name(&a, "robot");
  assert_true(vlff_allow_host_ok(&a, "robot", 5));      /* port 80: no port needed */
  assert_true(vlff_allow_host_ok(&a, " robot:80 ", 10));
  assert_true(vlff_allow_host_ok(&a, "ROBOT.LAN:9000", 14));
  assert_false(vlff_allow_host_ok(&a, "robot.lan", 9));
  assert_true(vlff_allow_origin_ok(&a, "http://robot", 12));
  assert_false(vlff_allow_origin_ok(&a, "https://robot", 13));
  assert_true(vlff_allow_origin_ok(&a, "https://[FD00::1]", 17));
}

static void test_refusal(void **state) {
  (void)state;
  char out[512];
  size_t n = vlff_http_refusal(out, sizeof out, 405, "method POST is not allowed", 0);
  assert_int_equal(n, strlen(out));
  assert_non_null(strstr(out, "HTTP/1.1 405 Method Not Allowed\r\n"));
  assert_non_null(strstr(out, "\r\nAllow: GET, HEAD\r\n"));
  assert_non_null(strstr(out, "\r\nConnection: close\r\n"));
  assert_non_null(strstr(out, "\r\nContent-Length: 27\r\n"));
  assert_string_equal(strstr(out, "\r\n\r\n") + 4, "method POST is not allowed\n");
  vlff_http_refusal(out, sizeof out, 404, "/x is not a file of this page", 1);
  assert_string_equal(strstr(out, "\r\n\r\n") + 4, ""); /* HEAD: no body, the length it would have */
  assert_non_null(strstr(out, "\r\nContent-Length: 30\r\n"));
  assert_null(strstr(out, "Allow:"));
  for (int i = 0; i < VLFF_VIEW_HTTP_N; i++) {
    assert_string_not_equal(vlff_http_reason(vlff_view_http_status(i)), "Error");
    assert_int_equal(vlff_view_http_index(vlff_view_http_status(i)), i); /* one counter per status */
  }
  assert_int_equal(vlff_view_http_index(200), -1);
  assert_string_equal(vlff_http_reason(200), "Error");
}

VLFF_UNIT_MAIN(setup, teardown, cmocka_unit_test(test_files), cmocka_unit_test(test_heads),
               cmocka_unit_test(test_canon), cmocka_unit_test(test_origins), cmocka_unit_test(test_refusal))
