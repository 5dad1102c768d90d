/* vlff-pose against hostile input, end to end: the program reads real UDP
 * datagrams on loopback (and files), writes the real pose ring, and the
 * test reads the ring back and the program's log. A forged future line
 * does not lock the tracker out, a bound peer refuses other senders, and
 * NULs, hexadecimal stamps and overlong lines are refused and counted. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>
#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include "unit.h"
#include "vlff/shm.h"

static char dir[256];

static int setup(void **state) {
  (void)state;
  snprintf(dir, sizeof dir, "/tmp/test_pose_input.XXXXXX");
  return mkdtemp(dir) ? 0 : -1;
}

static int teardown(void **state) {
  (void)state;
  char cmd[300];
  snprintf(cmd, sizeof cmd, "rm -rf '%s'", dir);
  return system(cmd) == 0 ? 0 : -1;
}

static void sleep_s(double s) {
  struct timespec ts = {(time_t)s, (long)((s - (double)(time_t)s) * 1e9)};
  nanosleep(&ts, NULL);
}

/* The whole file, NUL-terminated (static: one at a time). */
static const char *slurp(const char *path) {
  static char buf[1 << 20];
  buf[0] = 0;
  FILE *f = fopen(path, "r");
  if (!f) return buf;
  size_t n = fread(buf, 1, sizeof buf - 1, f);
  buf[n] = 0;
  fclose(f);
  return buf;
}

static int count_of(const char *text, const char *needle) {
  int n = 0;
  for (const char *p = text; (p = strstr(p, needle)); p += strlen(needle)) n++;
  return n;
}

static int wait_for_text(const char *path, const char *text, double timeout_s) {
  for (double t = 0; t < timeout_s; t += 0.02) {
    if (strstr(slurp(path), text)) return 1;
    sleep_s(0.02);
  }
  return 0;
}

/* vlff-pose with args (one shell word each, no quoting needed), its
 * stdout and stderr into log. */
static pid_t spawn_pose(const char *args, const char *log) {
  char prog[512], cmd[2048];
  vlff_test_prog(prog, sizeof prog, "drivers/pose/vlff-pose");
  snprintf(cmd, sizeof cmd, "exec %s %s >'%s' 2>&1 </dev/null", prog, args, log);
  pid_t pid = fork();
  assert_true(pid >= 0);
  if (pid == 0) {
    execl("/bin/sh", "sh", "-c", cmd, (char *)NULL);
    _exit(127);
  }
  return pid;
}

static int stop_pose(pid_t pid) {
  kill(pid, SIGTERM);
  int st;
  assert_int_equal(waitpid(pid, &st, 0), pid);
  return WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st);
}

/* A UDP socket on addr with a port the kernel chose; its port in *port. */
static int udp_socket(const char *addr, int *port) {
  int s = socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0);
  assert_true(s >= 0);
  struct sockaddr_in sa = {.sin_family = AF_INET};
  assert_int_equal(inet_pton(AF_INET, addr, &sa.sin_addr), 1);
  assert_int_equal(bind(s, (struct sockaddr *)&sa, sizeof sa), 0);
  socklen_t len = sizeof sa;
  assert_int_equal(getsockname(s, (struct sockaddr *)&sa, &len), 0);
  *port = ntohs(sa.sin_port);
  return s;
}

/* A free port on 127.0.0.1 for vlff-pose to listen on. */
static int free_port(void) {
  int port;
  close(udp_socket("127.0.0.1", &port));
  return port;
}

static void send_to(int s, int port, const char *data, size_t len) {
  struct sockaddr_in sa = {.sin_family = AF_INET, .sin_port = htons((uint16_t)port)};
  inet_pton(AF_INET, "127.0.0.1", &sa.sin_addr);
  assert_true(sendto(s, data, len, 0, (struct sockaddr *)&sa, sizeof sa) == (ssize_t)len);
}

static void send_line(int s, int port, uint64_t t_ns) {
  char line[128];
  snprintf(line, sizeof line, "%llu.%09llu 0 0 0 0 0 0 1\n", (unsigned long long)(t_ns / 1000000000ull),
           (unsigned long long)(t_ns % 1000000000ull));
  send_to(s, port, line, strlen(line));
}

/* A config whose pose ring is ring, listening on port (0: no UDP), with
 * extra lines under pose:. */
static void write_config(const char *path, const char *ring, int port, const char *pose_extra) {
  FILE *f = fopen(path, "w");
  assert_non_null(f);
  fprintf(f, "shm:\n  pose_ring: \"%s\"\n", ring);
  if (port || pose_extra) fprintf(f, "pose:\n");
  if (port) fprintf(f, "  udp: \"127.0.0.1:%d\"\n", port);
  fprintf(f, "%s", pose_extra ? pose_extra : "");
  fclose(f);
}

/* Waits until the ring holds n records (generous: a hang fails, slowness does not). */
static void wait_head(struct vlff_ring *r, uint64_t n) {
  for (int i = 0; i < 1000 && vlff_ring_head(r) < n; i++) sleep_s(0.01);
  assert_int_equal(vlff_ring_head(r), n);
}

static int has_pose(struct vlff_ring *r, uint64_t t_ns) {
  struct vlff_pose_rec rec;
  return vlff_pose_lookup(r, t_ns, 0, &rec) == 0;
}

/* One vlff-pose on UDP writing a ring of its own: named after tag, its
 * config with pose_extra (YAML under pose:, or NULL), started and attached. */
struct pose_run {
  char cfg[300], log[300], ring[64];
  int port;
  pid_t pid;
  struct vlff_ring *r;
};

static void pose_start(struct pose_run *u, const char *tag, const char *pose_extra) {
  char args[400];
  snprintf(u->ring, sizeof u->ring, "/pin-%s-%d", tag, (int)getpid());
  snprintf(u->cfg, sizeof u->cfg, "%s/%s.yaml", dir, tag);
  snprintf(u->log, sizeof u->log, "%s/%s.log", dir, tag);
  u->port = free_port();
  write_config(u->cfg, u->ring, u->port, pose_extra);
  snprintf(args, sizeof args, "--config '%s'", u->cfg);
  u->pid = spawn_pose(args, u->log);
  if (!wait_for_text(u->log, "-> pose ring", 10)) fail_msg("vlff-pose did not start:\n%s", slurp(u->log));
  u->r = vlff_ring_attach(u->ring, VLFF_RECORD_POSE);
  assert_non_null(u->r);
}

/* One line forged far ahead of the clock is refused as a clock error, and
 * so is one 3 s ahead (a clock off by that much, which the default
 * tolerance of 5 s took before, each frame then posed from 3 s earlier).
 * One forged newer than the tracker's lines but not ahead of the clock is
 * taken, and then the tracker's own lines, older, restart the order after
 * ten of them instead of being refused until their stamps catch up. */
static void test_forged_future_line(void **state) {
  (void)state;
  struct pose_run u;
  pose_start(&u, "future", NULL);
  const char *log = u.log, *ring = u.ring;
  int port = u.port;
  pid_t pid = u.pid;
  struct vlff_ring *r = u.r;
  int tracker_port, forger_port;
  int tracker = udp_socket("127.0.0.1", &tracker_port), forger = udp_socket("127.0.0.1", &forger_port);

  uint64_t now = vlff_shm_now_ns(), t = now - 2000000000ull, step = 10000000ull;
  send_line(tracker, port, t);
  wait_head(r, 1);
  send_line(forger, port, now + 1000000ull * 1000000000ull); /* 11.6 days ahead */
  for (int i = 1; i <= 3; i++) send_line(tracker, port, t + (uint64_t)i * step);
  wait_head(r, 4);
  assert_true(has_pose(r, t + 3 * step));
  assert_true(wait_for_text(log, "udp datagram 2 line 1: refused, clock error: stamp", 10));
  assert_non_null(strstr(slurp(log), "s ahead of the clock"));

  /* 3 s ahead: refused too, with its reason and the default tolerance. */
  send_line(forger, port, vlff_shm_now_ns() + 3000000000ull);
  assert_true(wait_for_text(log, "udp datagram 6 line 1: refused, clock error: stamp", 10));
  assert_non_null(strstr(slurp(log), "tolerance 0.050 s): a wrong clock or clock offset, or a forged line"));

  /* Newer than the tracker's lines, not ahead of the clock: taken. The
   * tracker's next nine lines are refused out of order, the tenth restarts
   * the order. */
  send_line(forger, port, t + 1000000000ull);
  wait_head(r, 5);
  for (int i = 4; i < 4 + 12; i++) send_line(tracker, port, t + (uint64_t)i * step);
  wait_head(r, 5 + 3);
  for (int i = 4; i < 4 + 9; i++) assert_false(has_pose(r, t + (uint64_t)i * step));
  for (int i = 4 + 9; i < 4 + 12; i++) assert_true(has_pose(r, t + (uint64_t)i * step));
  assert_int_equal(stop_pose(pid), 0);
  const char *text = slurp(log);
  assert_non_null(strstr(text, "10 lines in a row were older than the last accepted stamp"));
  assert_non_null(strstr(text, "the order restarts at this line's"));
  char want[200];
  snprintf(want, sizeof want, "8 poses written to %s, 11 lines refused (out of order 9, clock error 2), order "
           "restarted 1 times", ring);
  if (!strstr(text, want)) fail_msg("no '%s' in:\n%s", want, text);
  vlff_ring_close(r);
  close(tracker);
  close(forger);
  shm_unlink(ring);
}

/* pose.udp_peer: with a port, only that socket's datagrams are taken; with
 * an address only, any port of it. Others are refused and counted. */
static void test_bound_peer(void **state) {
  (void)state;
  char cfg[300], log[300], ring[64], args[400], extra[200];
  snprintf(ring, sizeof ring, "/pin-p-%d", (int)getpid());
  snprintf(cfg, sizeof cfg, "%s/peer.yaml", dir);
  snprintf(log, sizeof log, "%s/peer.log", dir);
  int tracker_port, other_port;
  int tracker = udp_socket("127.0.0.1", &tracker_port), other = udp_socket("127.0.0.1", &other_port);
  int port = free_port();
  snprintf(extra, sizeof extra, "  udp_peer: \"127.0.0.1:%d\"\n", tracker_port);
  write_config(cfg, ring, port, extra);
  snprintf(args, sizeof args, "--config '%s'", cfg);
  pid_t pid = spawn_pose(args, log);
  if (!wait_for_text(log, "-> pose ring", 10)) fail_msg("vlff-pose did not start:\n%s", slurp(log));
  char start[120];
  snprintf(start, sizeof start, "(from 127.0.0.1:%d only)", tracker_port);
  assert_non_null(strstr(slurp(log), start));
  struct vlff_ring *r = vlff_ring_attach(ring, VLFF_RECORD_POSE);
  assert_non_null(r);
  uint64_t t = vlff_shm_now_ns() - 1000000000ull;
  send_line(other, port, t + 1000000000ull / 2); /* forged, from another port */
  send_line(tracker, port, t);
  send_line(tracker, port, t + 1000000);
  wait_head(r, 2);
  assert_true(has_pose(r, t) && has_pose(r, t + 1000000));
  assert_false(has_pose(r, t + 1000000000ull / 2));
  assert_int_equal(stop_pose(pid), 0);
  const char *text = slurp(log);
  char want[200];
  snprintf(want, sizeof want, "udp datagram 1 from 127.0.0.1:%d: refused, foreign sender", other_port);
  if (!strstr(text, want)) fail_msg("no '%s' in:\n%s", want, text);
  snprintf(want, sizeof want, "2 poses written to %s, 1 lines refused (foreign sender 1)", ring);
  if (!strstr(text, want)) fail_msg("no '%s' in:\n%s", want, text);
  vlff_ring_close(r);
  shm_unlink(ring);

  /* The address only (--udp-peer overrides the key): 127.0.0.2 is another
   * sender, every port of 127.0.0.1 is the peer. */
  int far_port, far = udp_socket("127.0.0.2", &far_port);
  port = free_port();
  snprintf(log, sizeof log, "%s/peer2.log", dir);
  write_config(cfg, ring, port, extra);
  snprintf(args, sizeof args, "--config '%s' --udp-peer 127.0.0.1", cfg);
  pid = spawn_pose(args, log);
  assert_true(wait_for_text(log, "-> pose ring", 10));
  r = vlff_ring_attach(ring, VLFF_RECORD_POSE);
  assert_non_null(r);
  send_line(far, port, t);
  send_line(other, port, t + 1);
  wait_head(r, 1);
  assert_true(has_pose(r, t + 1));
  assert_int_equal(stop_pose(pid), 0);
  text = slurp(log);
  snprintf(want, sizeof want, "udp datagram 1 from 127.0.0.2:%d: refused, foreign sender", far_port);
  if (!strstr(text, want)) fail_msg("no '%s' in:\n%s", want, text);
  assert_non_null(strstr(text, "1 lines refused (foreign sender 1)"));
  vlff_ring_close(r);
  shm_unlink(ring);

  /* A peer that is no numeric address is a start-up error. */
  snprintf(log, sizeof log, "%s/peer3.log", dir);
  snprintf(args, sizeof args, "--config '%s' --udp-peer tracker.example", cfg);
  pid = spawn_pose(args, log);
  int st;
  assert_int_equal(waitpid(pid, &st, 0), pid);
  assert_true(WIFEXITED(st) && WEXITSTATUS(st) == 1);
  assert_non_null(strstr(slurp(log), "udp peer 'tracker.example': expected a numeric address"));
  close(tracker);
  close(other);
  close(far);
  shm_unlink(ring);
}

/* A datagram holding a NUL is refused whole and counted: the line after the
 * NUL used to vanish without a word. */
static void test_datagram_with_nul(void **state) {
  (void)state;
  struct pose_run u;
  pose_start(&u, "nul", NULL);
  const char *log = u.log, *ring = u.ring;
  int port = u.port;
  pid_t pid = u.pid;
  struct vlff_ring *r = u.r;
  int sp, s = udp_socket("127.0.0.1", &sp);
  uint64_t t = vlff_shm_now_ns() - 1000000000ull;
  char d[160];
  int n = snprintf(d, sizeof d, "%llu.5 0 0 0 0 0 0 1\n", (unsigned long long)(t / 1000000000ull));
  d[n++] = 0;
  n += snprintf(d + n, sizeof d - (size_t)n, "%llu.6 0 0 0 0 0 0 1\n", (unsigned long long)(t / 1000000000ull));
  send_to(s, port, d, (size_t)n);
  send_line(s, port, t + 1000000000ull); /* a sentinel that is taken */
  wait_head(r, 1);
  assert_int_equal(stop_pose(pid), 0);
  const char *text = slurp(log);
  assert_non_null(strstr(text, "udp datagram 1: refused, NUL byte: a NUL byte at offset"));
  char want[200];
  snprintf(want, sizeof want, "1 poses written to %s, 1 lines refused (NUL byte 1)", ring);
  if (!strstr(text, want)) fail_msg("no '%s' in:\n%s", want, text);
  vlff_ring_close(r);
  close(s);
  shm_unlink(ring);
}

/* A file: a 70 KiB line is refused and counted in the summary, a line with
 * a NUL and one with a hexadecimal stamp are refused, and a flood of one
 * refusal is printed five times, counted in full. */
static void test_file_refusals_counted(void **state) {
  (void)state;
  char cfg[300], log[300], ring[64], args[700], traj[300];
  snprintf(ring, sizeof ring, "/pin-l-%d", (int)getpid());
  snprintf(cfg, sizeof cfg, "%s/file.yaml", dir);
  snprintf(log, sizeof log, "%s/file.log", dir);
  snprintf(traj, sizeof traj, "%s/traj.txt", dir);
  write_config(cfg, ring, 0, NULL);
  FILE *f = fopen(traj, "w");
  assert_non_null(f);
  fputs("1.0 0 0 0 0 0 0 1\n", f);
  for (int i = 0; i < 70 * 1024; i++) fputc('7', f);
  fputs("\n2.0 0 0 0 0 0 0 1\n", f);
  fputs("3.0 0 0 0 0 0 0 1", f);
  fputc(0, f);
  fputs(" 4.0\n", f);
  fputs("0x10 0 0 0 0 0 0 1\n", f);
  for (int i = 0; i < 20; i++) fputs("5 0 0\n", f);
  fputs("6.0 0 0 0 0 0 0 1\n", f);
  fclose(f);
  snprintf(args, sizeof args, "--config '%s' '%s'", cfg, traj);
  pid_t pid = spawn_pose(args, log);
  int st;
  assert_int_equal(waitpid(pid, &st, 0), pid);
  assert_true(WIFEXITED(st) && WEXITSTATUS(st) == 0);
  const char *text = slurp(log);
  assert_non_null(strstr(text, "traj.txt:2: refused, too long: a line of 65536 bytes or more"));
  assert_non_null(strstr(text, "traj.txt:4: refused, NUL byte: a NUL byte at column 18"));
  assert_non_null(strstr(text, "traj.txt:5: refused, malformed: field 1 '0x10' is not a decimal number"));
  assert_int_equal(count_of(text, "refused, malformed: 3 fields"), 4); /* 5 malformed printed, one the hex */
  char want[200];
  snprintf(want, sizeof want, "3 poses written to %s, 23 lines refused (malformed 21, NUL byte 1, too long 1)", ring);
  if (!strstr(text, want)) fail_msg("no '%s' in:\n%s", want, text);
  struct vlff_ring *r = vlff_ring_attach(ring, VLFF_RECORD_POSE);
  assert_non_null(r);
  assert_int_equal(vlff_ring_head(r), 3);
  assert_true(has_pose(r, 1000000000ull) && has_pose(r, 2000000000ull) && has_pose(r, 6000000000ull));
  assert_false(has_pose(r, 16000000000ull));
  vlff_ring_close(r);
  shm_unlink(ring);
}

VLFF_UNIT_MAIN(setup, teardown, cmocka_unit_test(test_forged_future_line), cmocka_unit_test(test_bound_peer),
               cmocka_unit_test(test_datagram_with_nul), cmocka_unit_test(test_file_refusals_counted))
