/*
 * vlff-view over real sockets on loopback (issue 51): the program runs as users run
 * it, and each test speaks raw HTTP and WebSocket frames to it, so that requests no
 * well-behaved client library would send can be sent:
 *   - Host and Origin: a foreign Host or Origin gets 403, for a page file and an
 *     upgrade alike; the viewer's own, a configured one, or no Origin at all pass;
 *   - heads libwebsockets mishandled: a one-letter header, an upgrade without
 *     Sec-WebSocket-Key (400) or of version 99 (426 naming version 13);
 *   - frames: a text frame that is not UTF-8 closes with 1007; a request with bytes
 *     after its JSON is refused;
 *   - the prompt mailbox: while a post waits for a learner that does not answer,
 *     further posts are answered "busy" at once and another client's requests are
 *     answered; the learner's answer then reaches the poster;
 *   - slots: a client that answers no ping is closed after --idle-timeout while one
 *     that answers stays; a head never finished gets 408 after --head-timeout;
 *   - libwebsockets' own log lines are rate-limited like the viewer's.
 * No learner and no camera: the status channel alone streams (once a second).
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <arpa/inet.h>
#include <errno.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include <vlff/shm.h>

#include "unit.h"

#define TOKEN "test-token-51"

struct view {
  pid_t pid;
  int port;
  char log[128];
};

static char tag[32];
static const char *view_prefix = ""; /* shell words before the program: a ulimit */
/* the viewers running, so that a test that fails midway leaves none behind */
static struct view running[4]; /* copies; pid 0: a free slot */

static double now_s(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (double)ts.tv_sec + ts.tv_nsec / 1e9;
}

/* Starts vlff-view on a free port with extra arguments (a NULL-terminated list);
 * its stderr goes to a log file. */
static void view_start(struct view *v, const char *const *extra) {
  char prog[512], cmd[2048], dir[] = "/tmp/vlff-test-view-XXXXXX";
  assert_non_null(mkdtemp(dir));
  snprintf(v->log, sizeof v->log, "%s/view.log", dir);
  char token[128];
  snprintf(token, sizeof token, "%s/token", dir);
  FILE *t = fopen(token, "w");
  assert_non_null(t);
  fprintf(t, TOKEN "\n");
  fclose(t);
  int n = snprintf(cmd, sizeof cmd,
                   "%sexec %s --port 0 --map /%s-map --frames '' --prompts /%s-prompts --token-file %s",
                   view_prefix, vlff_test_prog(prog, sizeof prog, "node/view/vlff-view"), tag, tag, token);
  for (; extra && *extra; extra++) n += snprintf(cmd + n, sizeof cmd - (size_t)n, " %s", *extra);
  snprintf(cmd + n, sizeof cmd - (size_t)n, " 2>%s", v->log);
  int out[2];
  assert_int_equal(pipe(out), 0);
  v->pid = fork();
  assert_true(v->pid >= 0);
  if (v->pid == 0) {
    dup2(out[1], 1);
    close(out[0]);
    execl("/bin/sh", "sh", "-c", cmd, (char *)NULL);
    _exit(127);
  }
  close(out[1]);
  /* "vlff-view: serving http://127.0.0.1:PORT/ ..." */
  char line[512] = "";
  size_t got = 0;
  struct pollfd pfd = {out[0], POLLIN, 0};
  while (got < sizeof line - 1 && !strchr(line, '\n') && poll(&pfd, 1, 20000) == 1) {
    ssize_t r = read(out[0], line + got, sizeof line - 1 - got);
    if (r <= 0) break;
    got += (size_t)r;
    line[got] = 0;
  }
  close(out[0]);
  const char *p = strstr(line, "http://127.0.0.1:");
  if (!p) fail_msg("vlff-view did not start: \"%s\"", line);
  v->port = atoi(p + strlen("http://127.0.0.1:"));
  assert_true(v->port > 0);
  for (size_t i = 0; i < sizeof running / sizeof *running; i++)
    if (!running[i].pid) {
      running[i] = *v;
      break;
    }
}

static void view_cleanup(struct view *v) {
  char dir[128];
  snprintf(dir, sizeof dir, "%s", v->log);
  unlink(v->log);
  *strrchr(dir, '/') = 0;
  char tok[160];
  snprintf(tok, sizeof tok, "%s/token", dir);
  unlink(tok);
  rmdir(dir);
  for (size_t i = 0; i < sizeof running / sizeof *running; i++)
    if (running[i].pid == v->pid) running[i].pid = 0;
}

/* Each test's teardown: a viewer a failed test left running is killed, its files
 * and the test's mailbox removed. */
static int leftovers(void **state) {
  (void)state;
  for (size_t i = 0; i < sizeof running / sizeof *running; i++)
    if (running[i].pid) {
      struct view v = running[i];
      kill(v.pid, SIGKILL);
      waitpid(v.pid, NULL, 0);
      view_cleanup(&v);
    }
  char name[64];
  snprintf(name, sizeof name, "/%s-prompts", tag);
  vlff_shm_unlink(name);
  return 0;
}

static char *read_log(const struct view *v);

/* Stops it: it must exit 0 on SIGTERM, with no sanitizer report in its log (in
 * the sanitizer builds). */
static void view_stop(struct view *v) {
  kill(v->pid, SIGTERM);
  int st;
  waitpid(v->pid, &st, 0);
  const char *log = read_log(v);
  int bad = !WIFEXITED(st) || WEXITSTATUS(st) != 0 || strstr(log, "runtime error") || strstr(log, "Sanitizer");
  char msg[2100];
  snprintf(msg, sizeof msg, "%.2000s", log);
  view_cleanup(v);
  if (bad) fail_msg("vlff-view ended with status 0x%x: %s", st, msg);
}

static char *read_log(const struct view *v) {
  static char buf[1 << 16];
  FILE *f = fopen(v->log, "r");
  size_t n = f ? fread(buf, 1, sizeof buf - 1, f) : 0;
  if (f) fclose(f);
  buf[n] = 0;
  return buf;
}

static int tcp(int port) {
  int fd = socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  assert_true(fd >= 0);
  struct sockaddr_in a = {.sin_family = AF_INET, .sin_port = htons((uint16_t)port)};
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  assert_int_equal(connect(fd, (struct sockaddr *)&a, sizeof a), 0);
  return fd;
}

static void send_all(int fd, const void *b, size_t n) {
  const char *p = b;
  while (n) {
    ssize_t w = send(fd, p, n, MSG_NOSIGNAL);
    assert_true(w > 0);
    p += w;
    n -= (size_t)w;
  }
}

/* Reads until the peer closes or timeout_s passes: the bytes, NUL-terminated. */
static size_t read_all(int fd, char *buf, size_t cap, double timeout_s) {
  size_t n = 0;
  double end = now_s() + timeout_s;
  while (n < cap - 1) {
    struct pollfd p = {fd, POLLIN, 0};
    int ms = (int)((end - now_s()) * 1000);
    if (ms <= 0 || poll(&p, 1, ms) != 1) break;
    ssize_t r = recv(fd, buf + n, cap - 1 - n, 0);
    if (r <= 0) break;
    n += (size_t)r;
  }
  buf[n] = 0;
  return n;
}

/* One request on its own connection: the answer's status (0 for none within
 * timeout_s), the answer in resp. */
static int http(const struct view *v, const char *req, char *resp, size_t cap, double timeout_s) {
  int fd = tcp(v->port);
  send_all(fd, req, strlen(req));
  read_all(fd, resp, cap, timeout_s);
  close(fd);
  return !strncmp(resp, "HTTP/1.1 ", 9) ? atoi(resp + 9) : 0;
}

/* ------------------------------------------------------------- WebSocket */

struct ws {
  int fd;
  unsigned char buf[1 << 18];
  size_t len;
  int answer_pings;
};

static const char *ws_head(const char *origin, const char *host) {
  static char h[512];
  snprintf(h, sizeof h,
           "GET / HTTP/1.1\r\nHost: %s\r\n%s%s%sUpgrade: websocket\r\nConnection: Upgrade\r\n"
           "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
           "Sec-WebSocket-Protocol: foxglove.websocket.v1\r\n\r\n",
           host, origin ? "Origin: " : "", origin ? origin : "", origin ? "\r\n" : "");
  return h;
}

/* Opens a WebSocket with the given head: the HTTP status of the answer (101 when
 * open; the bytes after the answer's head stay in w->buf). */
static int ws_open(struct ws *w, const struct view *v, const char *head) {
  memset(w, 0, sizeof *w);
  w->fd = tcp(v->port);
  send_all(w->fd, head, strlen(head));
  double end = now_s() + 10;
  char *e = NULL;
  while (!(e = memmem(w->buf, w->len, "\r\n\r\n", 4)) && now_s() < end) {
    struct pollfd p = {w->fd, POLLIN, 0};
    if (poll(&p, 1, 200) != 1) continue;
    ssize_t r = recv(w->fd, w->buf + w->len, sizeof w->buf - w->len, 0);
    if (r <= 0) break;
    w->len += (size_t)r;
  }
  if (!e) return 0;
  int status = atoi((char *)w->buf + 9);
  size_t hl = (size_t)(e + 4 - (char *)w->buf);
  memmove(w->buf, w->buf + hl, w->len - hl);
  w->len -= hl;
  return status;
}

static void ws_send(struct ws *w, int opcode, const void *data, size_t n, int masked) {
  unsigned char h[14];
  size_t hl = 2;
  h[0] = (unsigned char)(0x80 | opcode);
  if (n < 126) {
    h[1] = (unsigned char)n;
  } else {
    h[1] = 126;
    h[2] = (unsigned char)(n >> 8);
    h[3] = (unsigned char)n;
    hl = 4;
  }
  unsigned char key[4] = {0x12, 0x34, 0x56, 0x78};
  if (masked) {
    h[1] |= 0x80;
    memcpy(h + hl, key, 4);
    hl += 4;
  }
  unsigned char *f = malloc(hl + n);
  assert_non_null(f);
  memcpy(f, h, hl);
  for (size_t i = 0; i < n; i++) f[hl + i] = ((const unsigned char *)data)[i] ^ (masked ? key[i % 4] : 0);
  send_all(w->fd, f, hl + n);
  free(f);
}

/* The next frame from the server within timeout_s: its opcode (-1 none, -2 the
 * connection closed), its payload NUL-terminated in out. Pings are answered when
 * w->answer_pings. */
static int ws_next(struct ws *w, char *out, size_t cap, size_t *outlen, double timeout_s) {
  double end = now_s() + timeout_s;
  for (;;) {
    if (w->len >= 2) {
      size_t n = w->buf[1] & 0x7f, hl = 2;
      if (n == 126 && w->len >= 4) n = (size_t)w->buf[2] << 8 | w->buf[3], hl = 4;
      else if (n == 127 && w->len >= 10) {
        n = 0;
        for (int i = 0; i < 8; i++) n = n << 8 | w->buf[2 + i];
        hl = 10;
      }
      if ((w->buf[1] & 0x7f) < 126 || hl > 2) {
        if (w->len >= hl + n) {
          int op = w->buf[0] & 0x0f;
          size_t c = n < cap - 1 ? n : cap - 1;
          memcpy(out, w->buf + hl, c);
          out[c] = 0;
          if (outlen) *outlen = n;
          memmove(w->buf, w->buf + hl + n, w->len - hl - n);
          w->len -= hl + n;
          if (op == 9 && w->answer_pings) {
            ws_send(w, 10, out, c, 1);
            continue;
          }
          return op;
        }
      }
    }
    int ms = (int)((end - now_s()) * 1000);
    struct pollfd p = {w->fd, POLLIN, 0};
    if (ms <= 0 || poll(&p, 1, ms) != 1) return -1;
    ssize_t r = recv(w->fd, w->buf + w->len, sizeof w->buf - w->len, 0);
    if (r <= 0) return -2;
    w->len += (size_t)r;
  }
}

/* Waits for a text frame holding want; its text in out. 0, or -1 (none in time,
 * or closed). */
static int ws_wait_text(struct ws *w, const char *want, char *out, size_t cap, double timeout_s) {
  double end = now_s() + timeout_s;
  while (now_s() < end) {
    int op = ws_next(w, out, cap, NULL, end - now_s());
    if (op < 0) return -1;
    if (op == 1 && strstr(out, want)) return 0;
  }
  return -1;
}

/* ----------------------------------------------------------------- tests */

static void test_host_origin(void **state) {
  (void)state;
  struct view v;
  view_start(&v, (const char *const[]){"--allow-origin", "https://robot.example", NULL});
  char host[64], own[64], resp[8192], req[1024];
  snprintf(host, sizeof host, "127.0.0.1:%d", v.port);
  snprintf(own, sizeof own, "http://localhost:%d", v.port);

  /* page files: foreign Host refused, own and configured Hosts served */
  snprintf(req, sizeof req, "GET /index.html HTTP/1.1\r\nHost: evil.example:%d\r\n\r\n", v.port);
  assert_int_equal(http(&v, req, resp, sizeof resp, 10), 403);
  assert_non_null(strstr(resp, "Host \"evil.example:"));
  snprintf(req, sizeof req, "GET /index.html HTTP/1.1\r\nHost: %s\r\nOrigin: http://evil.example\r\n\r\n", host);
  assert_int_equal(http(&v, req, resp, sizeof resp, 10), 403);
  assert_non_null(strstr(resp, "Origin \"http://evil.example\" is not allowed"));
  assert_int_equal(http(&v, "GET /index.html HTTP/1.1\r\n\r\n", resp, sizeof resp, 10), 400);
  snprintf(req, sizeof req, "GET /index.html HTTP/1.1\r\nHost: localhost:%d\r\n\r\n", v.port);
  assert_int_equal(http(&v, req, resp, sizeof resp, 10), 200);
  assert_int_equal(http(&v, "GET /index.html HTTP/1.1\r\nHost: robot.example\r\n\r\n", resp, sizeof resp, 10), 200);

  /* WebSocket upgrades: a foreign page (DNS rebinding: its own name as Host) or a
   * foreign Origin never gets 101 */
  struct ws *w = malloc(sizeof *w);
  assert_non_null(w);
  char evil_host[64];
  snprintf(evil_host, sizeof evil_host, "evil.example:%d", v.port);
  char evil_origin[64];
  snprintf(evil_origin, sizeof evil_origin, "http://evil.example:%d", v.port);
  assert_int_equal(ws_open(w, &v, ws_head(evil_origin, evil_host)), 403);
  close(w->fd);
  assert_int_equal(ws_open(w, &v, ws_head("http://evil.example", host)), 403);
  close(w->fd);
  assert_int_equal(ws_open(w, &v, ws_head("null", host)), 403);
  close(w->fd);
  /* the viewer's own page, a configured origin, a client without Origin: open */
  assert_int_equal(ws_open(w, &v, ws_head(own, host)), 101);
  close(w->fd);
  assert_int_equal(ws_open(w, &v, ws_head("https://robot.example", host)), 101);
  close(w->fd);
  assert_int_equal(ws_open(w, &v, ws_head(NULL, host)), 101);
  close(w->fd);
  free(w);
  assert_non_null(strstr(read_log(&v), "[HTTP 403 Forbidden"));
  view_stop(&v);

  /* a bad --allow-origin is refused at start */
  char prog[512], cmd[1024];
  snprintf(cmd, sizeof cmd, "%s --allow-origin http://x/path --port 0 2>/dev/null",
           vlff_test_prog(prog, sizeof prog, "node/view/vlff-view"));
  assert_int_equal(WEXITSTATUS(system(cmd)), 2);
}

static void test_heads(void **state) {
  (void)state;
  struct view v;
  view_start(&v, NULL);
  char resp[8192], req[1024];
  /* a legal one-letter header: served at once, not after a timeout */
  snprintf(req, sizeof req, "GET /index.html HTTP/1.1\r\nX: a\r\nHost: 127.0.0.1:%d\r\n\r\n", v.port);
  assert_int_equal(http(&v, req, resp, sizeof resp, 5), 200);
  /* an upgrade without a key: 400; of version 99: 426 with the version spoken */
  snprintf(req, sizeof req,
           "GET / HTTP/1.1\r\nHost: 127.0.0.1:%d\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
           "Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: foxglove.websocket.v1\r\n\r\n",
           v.port);
  assert_int_equal(http(&v, req, resp, sizeof resp, 5), 400);
  assert_non_null(strstr(resp, "Sec-WebSocket-Key"));
  snprintf(req, sizeof req,
           "GET / HTTP/1.1\r\nHost: 127.0.0.1:%d\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
           "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 99\r\n"
           "Sec-WebSocket-Protocol: foxglove.websocket.v1\r\n\r\n",
           v.port);
  assert_int_equal(http(&v, req, resp, sizeof resp, 5), 426);
  assert_non_null(strstr(resp, "\r\nSec-WebSocket-Version: 13\r\n"));
  view_stop(&v);
}

static void test_frames(void **state) {
  (void)state;
  struct view v;
  view_start(&v, NULL);
  char host[64], out[65536];
  snprintf(host, sizeof host, "127.0.0.1:%d", v.port);
  struct ws *w = malloc(sizeof *w);
  assert_non_null(w);
  assert_int_equal(ws_open(w, &v, ws_head(NULL, host)), 101);
  assert_int_equal(ws_wait_text(w, "\"advertise\"", out, sizeof out, 10), 0);
  /* trailing bytes after a JSON request: refused with a status, not acted on */
  const char *trail = "{\"op\":\"subscribe\",\"subscriptions\":[{\"id\":1,\"channelId\":6}]} junk";
  ws_send(w, 1, trail, strlen(trail), 1);
  assert_int_equal(ws_wait_text(w, "\"op\":\"status\"", out, sizeof out, 10), 0);
  if (!strstr(out, "bytes after the JSON value")) fail_msg("trailing bytes: %s", out);
  /* invalid UTF-8 in a text frame: closed with 1007 */
  const char bad[] = "{\"op\":\"\xff\xfe\"}";
  ws_send(w, 1, bad, sizeof bad - 1, 1);
  int op;
  size_t n = 0;
  do op = ws_next(w, out, sizeof out, &n, 10);
  while (op >= 0 && op != 8);
  assert_int_equal(op, 8);
  assert_true(n >= 2);
  assert_int_equal(((unsigned char)out[0] << 8) | (unsigned char)out[1], 1007);
  close(w->fd);
  /* a client frame that is not masked (RFC 6455 5.1): closed with 1002, not served
   * (the parent answered it as a request) */
  assert_int_equal(ws_open(w, &v, ws_head(NULL, host)), 101);
  assert_int_equal(ws_wait_text(w, "\"advertise\"", out, sizeof out, 10), 0);
  const char *bogus = "{\"op\":\"bogus\"}";
  ws_send(w, 1, bogus, strlen(bogus), 0);
  do op = ws_next(w, out, sizeof out, &n, 10);
  while (op >= 0 && op != 8 && !(op == 1 && strstr(out, "not supported")));
  if (op != 8) fail_msg("an unmasked frame: %s", op == 1 ? out : "no close");
  assert_int_equal(((unsigned char)out[0] << 8) | (unsigned char)out[1], 1002);
  assert_non_null(strstr(out + 2, "must be masked"));
  assert_int_equal(ws_next(w, out, sizeof out, &n, 10), -2); /* and the connection ends */
  close(w->fd);
  free(w);
  view_stop(&v);
}

/* A learner that does not answer: one post waits, the next ones are answered
 * "busy" at once, another client is answered meanwhile; then the learner answers
 * and the poster hears it. */
static void test_prompt_busy(void **state) {
  (void)state;
  char name[64];
  snprintf(name, sizeof name, "/%s-prompts", tag);
  vlff_shm_unlink(name);
  struct vlff_prompts *mb = vlff_prompts_create(name, NULL);
  assert_non_null(mb);
  struct view v;
  view_start(&v, NULL);
  char host[64], out[65536];
  snprintf(host, sizeof host, "127.0.0.1:%d", v.port);
  struct ws *a = malloc(sizeof *a), *b = malloc(sizeof *b);
  assert_non_null(a);
  assert_non_null(b);
  assert_int_equal(ws_open(a, &v, ws_head(NULL, host)), 101);
  assert_int_equal(ws_open(b, &v, ws_head(NULL, host)), 101);
  assert_int_equal(ws_wait_text(a, "\"advertise\"", out, sizeof out, 10), 0);
  assert_int_equal(ws_wait_text(b, "\"advertise\"", out, sizeof out, 10), 0);
  const char *adv = "{\"op\":\"advertise\",\"channels\":[{\"id\":7,\"topic\":\"/vlff/prompts\",\"encoding\":\"json\","
                    "\"schemaName\":\"vlff.PromptSet\"}]}";
  ws_send(a, 1, adv, strlen(adv), 1);
  unsigned char msg[256] = {1, 7, 0, 0, 0};
  int len = snprintf((char *)msg + 5, sizeof msg - 5, "{\"token\":\"" TOKEN "\",\"prompts\":[\"chair\",\"table\"]}");
  /* the first post is taken and waits for the learner */
  ws_send(a, 2, msg, 5 + (size_t)len, 1);
  assert_int_equal(ws_wait_text(a, "\"op\":\"status\"", out, sizeof out, 10), 0);
  if (!strstr(out, "posted to")) fail_msg("post 1: %s", out);
  char first[512];
  snprintf(first, sizeof first, "%.500s", out);
  /* four more in a row while it waits, then another client's request: that client
   * is answered at once (a loop blocked in each post answers it seconds later) */
  for (int i = 0; i < 4; i++) ws_send(a, 2, msg, 5 + (size_t)len, 1);
  usleep(300000);
  const char *bogus = "{\"op\":\"bogus\"}";
  double t0 = now_s();
  ws_send(b, 1, bogus, strlen(bogus), 1);
  assert_int_equal(ws_wait_text(b, "not supported", out, sizeof out, 30), 0);
  double waited = now_s() - t0;
  if (waited > 3) fail_msg("another client waited %.1f s for its answer while posts waited", waited);
  if (!strstr(first, "waiting for the learner's answer")) fail_msg("post 1: %s", first);
  for (int i = 0; i < 4; i++) {
    assert_int_equal(ws_wait_text(a, "\"op\":\"status\"", out, sizeof out, 10), 0);
    if (!strstr(out, "busy")) fail_msg("post %d: %s", i + 2, out);
  }
  /* the learner answers: the poster hears it */
  uint64_t last = 0;
  struct vlff_prompt_request *req = malloc(sizeof *req);
  assert_non_null(req);
  assert_int_equal(vlff_prompts_poll(mb, &last, req), 1);
  assert_int_equal(req->count, 2);
  assert_int_equal(vlff_prompts_answer(mb, req->seq, 1, NULL), 0);
  assert_int_equal(ws_wait_text(a, "accepted by the learner", out, sizeof out, 10), 0);
  free(req);
  close(a->fd);
  close(b->fd);
  free(a);
  free(b);
  view_stop(&v);
  vlff_prompts_close(mb);
  vlff_shm_unlink(name);
}

/* Slots: a client that answers no ping is closed after --idle-timeout, one that
 * answers stays; a head never finished is answered 408 after --head-timeout. */
static void test_timeouts(void **state) {
  (void)state;
  struct view v;
  view_start(&v, (const char *const[]){"--idle-timeout", "3", "--head-timeout", "1", NULL});
  char host[64], out[65536], resp[4096];
  snprintf(host, sizeof host, "127.0.0.1:%d", v.port);
  struct ws *mute = malloc(sizeof *mute), *live = malloc(sizeof *live);
  assert_non_null(mute);
  assert_non_null(live);
  assert_int_equal(ws_open(mute, &v, ws_head(NULL, host)), 101);
  assert_int_equal(ws_open(live, &v, ws_head(NULL, host)), 101);
  live->answer_pings = 1;
  int op, pinged = 0;
  double t0 = now_s();
  /* the mute one reads (so it is not dropped as slow) but never answers; the live
   * one reads and answers pings all along */
  int live_op = -1;
  for (;;) {
    op = ws_next(mute, out, sizeof out, NULL, 0.05);
    pinged |= op == 9;
    if (op == 8 || op == -2 || now_s() - t0 > 30) break;
    while ((live_op = ws_next(live, out, sizeof out, NULL, 0.01)) >= 0 && live_op != 8) {
    }
    if (live_op != -1) break;
  }
  double lasted = now_s() - t0;
  if (live_op != -1) fail_msg("the client answering pings was closed (%d) after %.1f s", live_op, lasted);
  assert_true(pinged);
  assert_true(op == 8 || op == -2);
  if (lasted < 2.5 || lasted > 20) fail_msg("the mute client was closed after %.1f s (timeout 3 s)", lasted);
  /* the live one is still served, two timeouts later */
  while (now_s() - t0 < 2 * 3 + 1) {
    op = ws_next(live, out, sizeof out, NULL, 0.1);
    if (op == 8 || op == -2) fail_msg("the client answering pings was closed: %s", read_log(&v));
  }
  const char *bogus = "{\"op\":\"bogus\"}";
  ws_send(live, 1, bogus, strlen(bogus), 1);
  assert_int_equal(ws_wait_text(live, "not supported", out, sizeof out, 10), 0);
  close(mute->fd);
  close(live->fd);
  free(mute);
  free(live);
  /* a partial head: 408 after a second */
  char req[128];
  snprintf(req, sizeof req, "GET / HTTP/1.1\r\nHost: %s\r\n", host);
  assert_int_equal(http(&v, req, resp, sizeof resp, 10), 408);
  assert_non_null(strstr(resp, "within 1 s"));
  view_stop(&v);
}

/* 70 connections that stall in their head: the oldest are answered 408 to make
 * room, and a request sent whole is served at once (the parent answered it 503 for
 * as long as the stalled heads lasted). */
static void test_gate_full(void **state) {
  (void)state;
  struct view v;
  view_start(&v, NULL);
  enum { N = 70 };
  int fds[N];
  char req[256], resp[8192];
  snprintf(req, sizeof req, "GET /index.html HTTP/1.1\r\nHost: 127.0.0.1:%d\r\n", v.port);
  for (int i = 0; i < N; i++) {
    fds[i] = tcp(v.port);
    send_all(fds[i], req, strlen(req)); /* no empty line: the head never ends */
  }
  usleep(300000);
  strcat(req, "\r\n");
  assert_int_equal(http(&v, req, resp, sizeof resp, 4), 200);
  int evicted = 0;
  for (int i = 0; i < N; i++) {
    struct pollfd p = {fds[i], POLLIN, 0};
    if (poll(&p, 1, 0) == 1 && read_all(fds[i], resp, sizeof resp, 0.5) &&
        strstr(resp, "408 Request Timeout") && strstr(resp, "the oldest is closed to make room"))
      evicted++;
    close(fds[i]);
  }
  /* 70 + 1 heads for 64 places: the 7 oldest made room */
  assert_int_equal(evicted, N + 1 - 64);
  view_stop(&v);
}

/* Out of descriptors (ulimit -n 64, a burst of 200 connections): the viewer pauses
 * accepting instead of spinning, logs that at the rate limit (the parent logged
 * libwebsockets' "accept: errno 24" tens of thousands of times), and serves again
 * once the connections are gone. */
static void test_out_of_descriptors(void **state) {
  (void)state;
  struct view v;
  view_prefix = "ulimit -n 64; ";
  view_start(&v, NULL);
  view_prefix = "";
  enum { N = 200 };
  int fds[N];
  for (int i = 0; i < N; i++) {
    fds[i] = socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0);
    assert_true(fds[i] >= 0);
    struct sockaddr_in a = {.sin_family = AF_INET, .sin_port = htons((uint16_t)v.port)};
    a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    int rc = connect(fds[i], (struct sockaddr *)&a, sizeof a);
    assert_true(rc == 0 || errno == EINPROGRESS || errno == EAGAIN);
  }
  sleep(2);
  for (int i = 0; i < N; i++) close(fds[i]);
  char resp[8192], req[256];
  snprintf(req, sizeof req, "GET /index.html HTTP/1.1\r\nHost: 127.0.0.1:%d\r\n\r\n", v.port);
  int status = 0;
  for (double end = now_s() + 30; status != 200 && now_s() < end;) status = http(&v, req, resp, sizeof resp, 5);
  assert_int_equal(status, 200);
  const char *log = read_log(&v);
  int lines = 0;
  for (const char *p = log; (p = strchr(p, '\n')); p++) lines++;
  if (lines > 40) fail_msg("%d log lines for a burst of %d connections: %.300s", lines, N, log);
  if (!strstr(log, "cannot accept a connection: Too many open files"))
    fail_msg("no line says the viewer ran out of descriptors: %.300s", log);
  view_stop(&v);
}

int main(void) {
  snprintf(tag, sizeof tag, "vts%d", (int)getpid());
  signal(SIGPIPE, SIG_IGN);
  const struct CMUnitTest tests[] = {
      cmocka_unit_test_teardown(test_host_origin, leftovers),
      cmocka_unit_test_teardown(test_heads, leftovers),
      cmocka_unit_test_teardown(test_frames, leftovers),
      cmocka_unit_test_teardown(test_prompt_busy, leftovers),
      cmocka_unit_test_teardown(test_timeouts, leftovers),
      cmocka_unit_test_teardown(test_gate_full, leftovers),
      cmocka_unit_test_teardown(test_out_of_descriptors, leftovers),
  };
  return cmocka_run_group_tests(tests, NULL, NULL);
}
