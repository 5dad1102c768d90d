/* Single-process behaviour of libvlff-shm: ring protocol and exact loss counting,
 * take-over of a dead creator's segment, every attach error, records, pose lookup,
 * the map and the prompt mailbox. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <cmocka.h>

#include "shm_test_util.h"
#include "unit.h"

#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/resource.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

static struct vlff_ring *mk_ring(const char *name, uint32_t slots, uint64_t size) {
  struct vlff_ring_params p = {.record_kind = VLFF_RECORD_RAW, .slots = slots, .slot_size = size};
  return vlff_ring_create(name, &p);
}

static void ring_roundtrip_and_exact_lapping(void **state) {
  (void)state;
  char name[64];
  test_name(name, sizeof name, "ring");
  struct vlff_ring *w = mk_ring(name, 4, 256);
  assert_non_null(w);
  struct vlff_ring *r = vlff_ring_attach(name, VLFF_RECORD_RAW);
  assert_non_null(r);
  struct vlff_ring_view v;
  assert_int_equal(vlff_ring_read_begin(r, &v, 0), -1);
  assert_int_equal(errno, EAGAIN);
  assert_int_equal(vlff_ring_read_begin(r, &v, 2000000), -1);
  assert_int_equal(errno, ETIMEDOUT);

  uint8_t buf[256], out[256];
  for (uint64_t id = 0; id < 3; id++) {
    size_t len = test_rec_len(id, 256);
    test_rec_fill(buf, id, len);
    assert_int_equal(vlff_ring_write(w, buf, len), 0);
  }
  for (uint64_t id = 0; id < 3; id++) {
    ssize_t n = vlff_ring_read_copy(r, out, sizeof out, &v, 0);
    assert_int_equal(n, (ssize_t)test_rec_len(id, 256));
    assert_int_equal(v.seq, id);
    assert_int_equal(test_rec_check(out, (size_t)n, id), 0);
  }
  assert_int_equal(vlff_ring_lost(r), 0);

  /* Lap the consumer by exactly 7 records: 10 written, 4 slots, the oldest slot is
   * intact until the producer reserves the next one. */
  for (uint64_t id = 3; id < 13; id++) {
    size_t len = test_rec_len(id, 256);
    test_rec_fill(buf, id, len);
    assert_int_equal(vlff_ring_write(w, buf, len), 0);
  }
  ssize_t n = vlff_ring_read_copy(r, out, sizeof out, &v, 0);
  assert_true(n > 0);
  assert_int_equal(v.seq, 9);
  assert_int_equal(vlff_ring_lost(r), 6);
  assert_int_equal(test_rec_check(out, (size_t)n, 9), 0);

  /* A reservation overwrites the oldest record: begun reads of it must fail. */
  assert_int_equal(vlff_ring_read_begin(r, &v, 0), 0);
  assert_int_equal(v.seq, 10);
  uint8_t *slot = vlff_ring_reserve(w, NULL); /* record 13 -> slot of 9 */
  assert_non_null(slot);
  assert_int_equal(vlff_ring_read_end(r, &v), 0); /* 10 untouched */
  test_rec_fill(slot, 13, 64);
  assert_int_equal(vlff_ring_commit(w, 64), 0);
  slot = vlff_ring_reserve(w, NULL); /* record 14 overwrites slot of 10 */
  assert_int_equal(vlff_ring_read_begin(r, &v, 0), 0);
  assert_int_equal(v.seq, 11);
  assert_non_null(slot);
  (void)vlff_ring_reserve(w, NULL); /* idempotent */
  assert_int_equal(vlff_ring_commit(w, 64), 0);
  assert_int_equal(vlff_ring_commit(w, 64), -1); /* nothing reserved */
  assert_int_equal(errno, EINVAL);
  /* 11's slot is the next to be overwritten: do it while "reading" it. */
  slot = vlff_ring_reserve(w, NULL);
  assert_int_equal(vlff_ring_read_end(r, &v), -1);
  assert_int_equal(errno, ESTALE);
  assert_int_equal(vlff_ring_lost(r), 7);
  test_rec_fill(slot, 15, 64);
  assert_int_equal(vlff_ring_commit(w, 64), 0);

  /* Oversized records are refused on both sides. */
  assert_int_equal(vlff_ring_write(w, buf, 257), -1);
  assert_int_equal(errno, EMSGSIZE);
  assert_int_equal(vlff_ring_read_latest(r, out, sizeof out, &v), 64);
  assert_int_equal(v.seq, 15);
  assert_int_equal(test_rec_check(out, 64, 15), 0);

  /* A record too big for the caller's buffer is skipped and counted. */
  vlff_ring_seek_newest(r);
  uint64_t lost0 = vlff_ring_lost(r);
  test_rec_fill(buf, 16, 128);
  assert_int_equal(vlff_ring_write(w, buf, 128), 0);
  assert_int_equal(vlff_ring_read_copy(r, out, 64, &v, 0), -1);
  assert_int_equal(errno, EMSGSIZE);
  assert_int_equal(vlff_ring_lost(r), lost0 + 1);

  vlff_ring_close(r);
  vlff_ring_close(w);
  assert_int_equal(vlff_shm_unlink(name), 0);
}

static void ring_takeover_of_dead_creator(void **state) {
  (void)state;
  char name[64];
  test_name(name, sizeof name, "takeover");
  /* A live creator (this process, through a child that holds it) refuses a second. */
  int ready[2];
  assert_int_equal(pipe(ready), 0);
  pid_t pid = fork();
  if (pid == 0) {
    struct vlff_ring *w = mk_ring(name, 4, 128);
    uint8_t rec[64];
    test_rec_fill(rec, 0, 64);
    if (!w || vlff_ring_write(w, rec, 64) < 0)
      _exit(1);
    (void)!write(ready[1], "x", 1);
    pause();
    _exit(0);
  }
  char c;
  assert_int_equal(read(ready[0], &c, 1), 1);
  struct vlff_ring *r = vlff_ring_attach(name, VLFF_RECORD_ANY);
  assert_non_null(r);
  vlff_ring_seek_oldest(r);
  assert_null(mk_ring(name, 4, 128));
  assert_int_equal(vlff_shm_last_error(), VLFF_SHM_ERR_EXISTS);
  assert_int_equal(errno, EEXIST);
  kill(pid, SIGKILL);
  waitpid(pid, NULL, 0);

  /* Same geometry: taken over in place, numbering continues, consumers carry on. */
  assert_int_equal(vlff_ring_generation(r), 1);
  struct vlff_ring *w = mk_ring(name, 4, 128);
  assert_non_null(w);
  assert_int_equal(vlff_ring_generation(r), 2);
  uint8_t rec[64], out[128];
  test_rec_fill(rec, 1, 64);
  assert_int_equal(vlff_ring_write(w, rec, 64), 0);
  struct vlff_ring_view v;
  assert_int_equal(vlff_ring_read_copy(r, out, sizeof out, &v, 0), 64);
  assert_int_equal(v.seq, 0);
  assert_int_equal(v.generation, 1);
  assert_int_equal(v.new_generation, 0);
  assert_int_equal(vlff_ring_read_copy(r, out, sizeof out, &v, 0), 64);
  assert_int_equal(v.seq, 1);
  assert_int_equal(v.generation, 2);
  assert_int_equal(v.new_generation, 1);
  assert_int_equal(test_rec_check(out, 64, 1), 0);
  vlff_ring_close(w);

  /* Other geometry: the old segment is abandoned (EPIPE) and replaced. */
  w = mk_ring(name, 8, 128);
  assert_non_null(w);
  assert_int_equal(vlff_ring_read_begin(r, &v, 0), -1);
  assert_int_equal(errno, EPIPE);
  assert_int_equal(vlff_shm_last_error(), VLFF_SHM_ERR_ABANDONED);
  vlff_ring_close(r);
  r = vlff_ring_attach(name, VLFF_RECORD_RAW);
  assert_non_null(r);
  assert_int_equal(vlff_ring_slots(r), 8);
  vlff_ring_close(r);
  vlff_ring_close(w);
  vlff_shm_unlink(name);
  close(ready[0]);
  close(ready[1]);
}

/* Writes a copy of a valid segment with one modification and attaches to it. */
static int attach_modified(const char *good, const char *bad, void (*edit)(uint8_t *, size_t *), int *code) {
  int fd = shm_open(good, O_RDONLY, 0);
  struct stat st;
  fstat(fd, &st);
  size_t len = (size_t)st.st_size;
  uint8_t *copy = malloc(len);
  assert_int_equal(pread(fd, copy, len, 0), (ssize_t)len);
  close(fd);
  edit(copy, &len);
  int bfd = shm_open(bad, O_RDWR | O_CREAT | O_TRUNC, 0600);
  assert_true(bfd >= 0);
  assert_int_equal(write(bfd, copy, len), (ssize_t)len);
  close(bfd);
  free(copy);
  struct vlff_ring *r = vlff_ring_attach(bad, VLFF_RECORD_RAW);
  int e = errno;
  *code = vlff_shm_last_error();
  vlff_ring_close(r);
  shm_unlink(bad);
  errno = e;
  return r ? 0 : -1;
}

static void e_magic(uint8_t *p, size_t *n) { (void)n; p[0] ^= 0x55; }
static void e_version(uint8_t *p, size_t *n) { (void)n; p[8] = 99; }
static void e_slots(uint8_t *p, size_t *n) { (void)n; p[32] += 1; } /* geom[0] without fixing the check */
static void e_trunc(uint8_t *p, size_t *n) { (void)p; *n /= 2; }
static void e_tiny(uint8_t *p, size_t *n) { (void)p; *n = 20; }
static void e_state(uint8_t *p, size_t *n) { (void)n; p[80] = 7; }
static void e_kind(uint8_t *p, size_t *n) { (void)n; p[16] = VLFF_RECORD_POSE; }

static void attach_rejects_bad_segments(void **state) {
  (void)state;
  char good[64], bad[64];
  test_name(good, sizeof good, "good");
  test_name(bad, sizeof bad, "bad");
  struct vlff_ring *w = mk_ring(good, 4, 128);
  assert_non_null(w);
  int code;
  assert_int_equal(attach_modified(good, bad, e_magic, &code), -1);
  assert_int_equal(code, VLFF_SHM_ERR_FOREIGN);
  assert_int_equal(errno, EPROTO);
  assert_int_equal(attach_modified(good, bad, e_version, &code), -1);
  assert_int_equal(code, VLFF_SHM_ERR_VERSION);
  assert_int_equal(errno, EPROTONOSUPPORT);
  assert_non_null(strstr(vlff_shm_last_message(), "ABI version 99"));
  assert_int_equal(attach_modified(good, bad, e_slots, &code), -1);
  assert_int_equal(code, VLFF_SHM_ERR_CORRUPT);
  assert_int_equal(attach_modified(good, bad, e_trunc, &code), -1);
  assert_int_equal(code, VLFF_SHM_ERR_TRUNCATED);
  assert_int_equal(errno, EBADMSG);
  assert_int_equal(attach_modified(good, bad, e_tiny, &code), -1);
  assert_int_equal(code, VLFF_SHM_ERR_TRUNCATED);
  assert_int_equal(attach_modified(good, bad, e_state, &code), -1);
  assert_int_equal(code, VLFF_SHM_ERR_CORRUPT);
  assert_int_equal(attach_modified(good, bad, e_kind, &code), -1); /* record kind checked after checksum */
  assert_true(code == VLFF_SHM_ERR_CORRUPT || code == VLFF_SHM_ERR_KIND);

  /* Wrong record kind / segment kind. */
  assert_null(vlff_ring_attach(good, VLFF_RECORD_FRAME));
  assert_int_equal(vlff_shm_last_error(), VLFF_SHM_ERR_KIND);
  assert_null(vlff_map_attach(good));
  assert_int_equal(vlff_shm_last_error(), VLFF_SHM_ERR_KIND);
  /* Missing, bad names, world-writable mode. */
  assert_null(vlff_ring_attach("/vlff-test-does-not-exist", 0));
  assert_int_equal(vlff_shm_last_error(), VLFF_SHM_ERR_MISSING);
  assert_int_equal(errno, ENOENT);
  assert_null(vlff_ring_attach("no-slash", 0));
  assert_int_equal(errno, EINVAL);
  struct vlff_ring_params p = {.record_kind = VLFF_RECORD_RAW, .slots = 4, .slot_size = 64, .perm = {.mode = 0666}};
  assert_null(vlff_ring_create(bad, &p));
  assert_int_equal(errno, EINVAL);
  p.perm.group = "no-such-group-vlff";
  p.perm.mode = 0640;
  assert_null(vlff_ring_create(bad, &p));
  assert_int_equal(errno, EINVAL);
  /* Empty file (creator died before sizing it). */
  int fd = shm_open(bad, O_RDWR | O_CREAT, 0600);
  close(fd);
  assert_null(vlff_ring_attach(bad, 0));
  assert_int_equal(vlff_shm_last_error(), VLFF_SHM_ERR_NOTREADY);
  /* ... and a creator replaces it. */
  p.perm.group = NULL;
  struct vlff_ring *w2 = vlff_ring_create(bad, &p);
  assert_non_null(w2);
  vlff_ring_close(w2);
  shm_unlink(bad);
  /* A foreign segment is never replaced. */
  fd = shm_open(bad, O_RDWR | O_CREAT, 0600);
  assert_int_equal(write(fd, "not a vlff segment at all, just some bytes of something else.......", 64), 64);
  close(fd);
  assert_null(vlff_ring_create(bad, &p));
  assert_int_equal(vlff_shm_last_error(), VLFF_SHM_ERR_FOREIGN);
  assert_null(vlff_ring_attach(bad, 0));
  assert_int_equal(vlff_shm_last_error(), VLFF_SHM_ERR_FOREIGN);
  shm_unlink(bad);

  /* Permissions: mode is applied exactly; an unreadable segment gives EACCES for
   * a non-root user (root bypasses modes, so only check the bits there). */
  struct stat st;
  char path[128];
  snprintf(path, sizeof path, "/dev/shm%s", good);
  assert_int_equal(stat(path, &st), 0);
  assert_int_equal(st.st_mode & 0777, 0640);
  if (geteuid() != 0) {
    chmod(path, 0);
    assert_null(vlff_ring_attach(good, 0));
    assert_int_equal(vlff_shm_last_error(), VLFF_SHM_ERR_PERM);
    assert_int_equal(errno, EACCES);
  }
  vlff_ring_close(w);
  vlff_shm_unlink(good);
  assert_string_equal(vlff_shm_strerror(VLFF_SHM_ERR_TRUNCATED), "segment truncated");
}

static void frame_records(void **state) {
  (void)state;
  uint64_t sz = vlff_frame_slot_size(64, 48, VLFF_PIX_RGB8, VLFF_PIX_DEPTH_U16_MM);
  assert_int_equal(sz, 512 + 64 * 48 * 3 + 64 * 48 * 2);
  uint8_t *rec = calloc(1, sz);
  struct vlff_frame_hdr h;
  assert_int_equal(vlff_frame_layout(&h, sz, 64, 48, VLFF_PIX_RGB8, VLFF_PIX_DEPTH_U16_MM), sz);
  assert_int_equal(vlff_frame_layout(&h, sz - 1, 64, 48, VLFF_PIX_RGB8, VLFF_PIX_DEPTH_U16_MM), 0);
  assert_int_equal(vlff_frame_layout(&h, sz, 64, 48, VLFF_PIX_RGB8, VLFF_PIX_DEPTH_U16_MM), sz);
  h.flags = VLFF_FRAME_INTRINSICS_VALID | VLFF_FRAME_POSE_VALID;
  h.fx = h.fy = 50;
  h.cx = 32;
  h.cy = 24;
  h.pose[0] = h.pose[5] = h.pose[10] = h.pose[15] = 1;
  memcpy(rec, &h, sizeof h);
  assert_int_equal(vlff_frame_validate(rec, sz), 0);
  assert_ptr_equal(vlff_frame_plane(rec, 1), rec + h.plane[1].offset);
  assert_int_equal(vlff_frame_validate(rec, sz - 1), -1); /* depth plane past the end */
  struct vlff_frame_hdr b = h;
  b.plane[0].stride = 10;
  memcpy(rec, &b, sizeof b);
  assert_int_equal(vlff_frame_validate(rec, sz), -1);
  b = h;
  b.pose[3] = NAN;
  memcpy(rec, &b, sizeof b);
  assert_int_equal(vlff_frame_validate(rec, sz), -1);
  b = h;
  b.plane[0].offset = UINT64_MAX - 10;
  memcpy(rec, &b, sizeof b);
  assert_int_equal(vlff_frame_validate(rec, sz), -1);
  b = h;
  b.plane[1].format = VLFF_PIX_RGB8;
  memcpy(rec, &b, sizeof b);
  assert_int_equal(vlff_frame_validate(rec, sz), -1);
  /* a depth plane laid inside the colour plane (read from colour bytes),
   * and one off the 64-byte grid the header promises */
  b = h;
  b.plane[1].offset = h.plane[0].offset + 64;
  memcpy(rec, &b, sizeof b);
  assert_int_equal(vlff_frame_validate(rec, sz), -1);
  /* off the grid only: one more byte of record after the depth plane, the
   * plane moved onto it */
  uint8_t *big = calloc(1, sz + 1);
  b = h;
  b.plane[1].offset = h.plane[1].offset + 1;
  memcpy(big, &b, sizeof b);
  assert_int_equal(vlff_frame_validate(big, sz + 1), -1);
  assert_non_null(strstr(vlff_shm_last_message(), "not 64-aligned"));
  b.plane[1].offset = h.plane[1].offset;
  memcpy(big, &b, sizeof b);
  assert_int_equal(vlff_frame_validate(big, sz + 1), 0);
  free(big);
  free(rec);

  struct vlff_feature_hdr f;
  uint64_t fs = vlff_feature_slot_size(512, 30, 40);
  assert_int_equal(vlff_feature_layout(&f, fs, 512, 30, 40), fs);
  uint8_t *fr = calloc(1, fs);
  memcpy(fr, &f, sizeof f);
  assert_int_equal(vlff_feature_validate(fr, fs), 0);
  assert_int_equal(vlff_feature_validate(fr, fs - 2), -1);
  f.dim = 0;
  memcpy(fr, &f, sizeof f);
  assert_int_equal(vlff_feature_validate(fr, fs), -1);
  free(fr);
}

static void rot_z(double a, double tx, double out[16]) {
  double m[16] = {cos(a), -sin(a), 0, tx, sin(a), cos(a), 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};
  memcpy(out, m, sizeof m);
}

static void pose_interpolation_and_tolerance(void **state) {
  (void)state;
  char name[64];
  test_name(name, sizeof name, "poses");
  struct vlff_ring_params p = {.record_kind = VLFF_RECORD_POSE, .slots = 8, .slot_size = sizeof(struct vlff_pose_rec)};
  struct vlff_ring *w = vlff_ring_create(name, &p);
  assert_non_null(w);
  struct vlff_ring *r = vlff_ring_attach(name, VLFF_RECORD_POSE);
  assert_non_null(r);
  struct vlff_pose_rec out;
  assert_int_equal(vlff_pose_lookup(r, 100, 10, &out), -1);
  assert_int_equal(errno, ENOENT);
  /* Poses every 10 ms rotating 0.1 rad about z and moving 1 m in x per step; a gap
   * of 100 ms between t=40ms and t=140ms. */
  uint64_t times[] = {0, 10, 20, 30, 40, 140, 150};
  for (int i = 0; i < 7; i++) {
    struct vlff_pose_rec pr = {.t_ns = times[i] * 1000000ull};
    rot_z(0.01 * (double)times[i], (double)times[i] / 10.0, pr.pose);
    if (i == 2)
      pr.flags = VLFF_FRAME_POSE_UNTRUSTED;
    assert_int_equal(vlff_ring_write(w, &pr, sizeof pr), 0);
  }
  uint64_t tol = 15000000; /* 15 ms */
  assert_int_equal(vlff_pose_lookup(r, 25000000, tol, &out), 0);
  double want[16];
  rot_z(0.25, 2.5, want);
  for (int i = 0; i < 16; i++)
    assert_true(fabs(out.pose[i] - want[i]) < 1e-9);
  assert_int_equal(out.flags, VLFF_FRAME_POSE_UNTRUSTED); /* 20 ms pose was untrusted */
  assert_int_equal(out.t_ns, 25000000);
  /* Exact hit. */
  assert_int_equal(vlff_pose_lookup(r, 140000000, tol, &out), 0);
  rot_z(1.4, 14, want);
  for (int i = 0; i < 16; i++)
    assert_true(fabs(out.pose[i] - want[i]) < 1e-12);
  /* In the gap: bracketing poses 90 ms apart -> rejected. */
  assert_int_equal(vlff_pose_lookup(r, 90000000, tol, &out), -1);
  assert_int_equal(errno, ERANGE);
  /* Within tolerance of one end only is still a reject: no extrapolation. */
  assert_int_equal(vlff_pose_lookup(r, 50000000, tol, &out), -1);
  assert_int_equal(errno, ERANGE);
  /* Newer than all: may arrive later. */
  assert_int_equal(vlff_pose_lookup(r, 151000000, tol, &out), -1);
  assert_int_equal(errno, EAGAIN);
  /* Older than everything held (ring of 8 still holds all 7): before t=0 is ERANGE. */
  struct vlff_pose_rec a = {.t_ns = 0}, b = {.t_ns = 10};
  rot_z(0, 0, a.pose);
  rot_z(3.0, 0, b.pose); /* large rotation: slerp, not lerp */
  double mid[16];
  assert_int_equal(vlff_pose_interpolate(&a, &b, 5, mid), 0);
  rot_z(1.5, 0, want);
  for (int i = 0; i < 16; i++)
    assert_true(fabs(mid[i] - want[i]) < 1e-9);
  assert_int_equal(vlff_pose_interpolate(&a, &b, 11, mid), -1);
  vlff_ring_close(r);
  vlff_ring_close(w);
  vlff_shm_unlink(name);
}

/* Rotation by angle a about the unit axis u, as a pose with no translation. */
static void axis_angle(double a, const double u[3], double m[16]) {
  double c = cos(a), s = sin(a), C = 1 - c, x = u[0], y = u[1], z = u[2];
  double r[16] = {c + x * x * C,     x * y * C - z * s, x * z * C + y * s, 0, y * x * C + z * s, c + y * y * C,
                  y * z * C - x * s, 0,                 z * x * C - y * s, z * y * C + x * s, c + z * z * C, 0,
                  0,                 0,                 0,                 1};
  memcpy(m, r, sizeof r);
}

/* Each of Shepperd's four branches (trace positive; x, y or z the largest
 * diagonal term at half turns) gives cos(a/2), sin(a/2) u up to sign. */
static void pose_quaternion_every_branch(void **state) {
  (void)state;
  const double axes[][3] = {{0, 0, 1}, {1, 0, 0}, {0, 1, 0}, {0, 0, 1}, {0.48, -0.6, 0.64}};
  const double angles[] = {0.7, M_PI, M_PI, M_PI, 2.9};
  for (int i = 0; i < 5; i++) {
    double m[16], q[4];
    axis_angle(angles[i], axes[i], m);
    vlff_pose_quaternion(m, q);
    double want[4] = {cos(angles[i] / 2), sin(angles[i] / 2) * axes[i][0], sin(angles[i] / 2) * axes[i][1],
                      sin(angles[i] / 2) * axes[i][2]};
    double dot = 0;
    for (int k = 0; k < 4; k++) dot += q[k] * want[k];
    assert_true(fabs(fabs(dot) - 1) < 1e-12);
  }
}

/* A map segment of 1000 voxels and an 8 x 6 label image named for tag:
 * its writer and a reader attached to it. */
static const struct vlff_map_params small_map = {.max_voxels = 1000, .label_max_width = 8, .label_max_height = 6};
static void map_pair(const char *tag, char *name, size_t len, struct vlff_map **w, struct vlff_map **r) {
  test_name(name, len, tag);
  *w = vlff_map_create(name, &small_map);
  assert_non_null(*w);
  *r = vlff_map_attach(name);
  assert_non_null(*r);
}

/* A map that grows (field.grow; docs/shm.md "A map that grows"): the node
 * publishes a larger grid, on the same lattice, in the same segment. A
 * reader attached before keeps reading every world point's label through
 * the same handle, and a snapshot it follows takes the new geometry whole. */
static void map_grows_under_reader(void **state) {
  (void)state;
  char name[64];
  struct vlff_map *w, *r;
  map_pair("grow", name, sizeof name, &w, &r);
  struct vlff_map_snapshot *s = vlff_map_snapshot_new(r);
  assert_non_null(s);
  const char *prompts[] = {"wall", "floor", "door", "sofa"};
  /* first: 4 x 4 x 4 voxels of 0.25 m from (0, 0, 0), label = x index % 3 */
  uint16_t a[64], b[10 * 8 * 4];
  uint8_t ca[64], cb[10 * 8 * 4];
  for (int i = 0; i < 64; i++) a[i] = (uint16_t)(i % 4 % 3), ca[i] = 200;
  struct vlff_map_grid ga = {.origin = {0, 0, 0}, .voxel_size = 0.25, .dims = {4, 4, 4}, .labels = a, .confidence = ca};
  struct vlff_map_update ua = {.grid = &ga, .prompts = prompts, .prompt_count = 4};
  assert_int_equal(vlff_map_publish(w, &ua), 0);
  assert_int_equal(vlff_map_snapshot_follow(r, s), 1); /* the first: whole */
  const double old_pt[3] = {0.6, 0.3, 0.9}; /* x index 2: label 2 */
  uint16_t label;
  uint8_t conf;
  assert_int_equal(vlff_map_label_at(r, old_pt[0], old_pt[1], old_pt[2], &label, &conf), 0);
  assert_int_equal(label, 2);
  assert_int_equal(vlff_map_label_at(r, -1.2, 0.3, 0.9, &label, &conf), 0);
  assert_int_equal(label, VLFF_LABEL_UNKNOWN); /* not mapped yet */
  /* grown by 4 voxels toward -x and 2 toward +x, 4 toward +y: 10 x 8 x 4
   * from (-1, 0, 0); the old voxels where they were, the new ones sofa */
  for (int i = 0; i < 10 * 8 * 4; i++) b[i] = 3, cb[i] = 100;
  for (int z = 0; z < 4; z++)
    for (int y = 0; y < 4; y++)
      for (int x = 0; x < 4; x++) {
        b[(x + 4) + 10 * (y + 8 * z)] = a[x + 4 * (y + 4 * z)];
        cb[(x + 4) + 10 * (y + 8 * z)] = ca[x + 4 * (y + 4 * z)];
      }
  struct vlff_map_grid gb = {.origin = {-1, 0, 0}, .voxel_size = 0.25, .dims = {10, 8, 4}, .labels = b,
                             .confidence = cb};
  struct vlff_map_update ub = {.grid = &gb, .prompts = prompts, .prompt_count = 4};
  assert_int_equal(vlff_map_publish(w, &ub), 0);
  /* the same handle: old points keep their labels, new points have theirs */
  assert_int_equal(vlff_map_label_at(r, old_pt[0], old_pt[1], old_pt[2], &label, &conf), 0);
  assert_int_equal(label, 2);
  assert_int_equal(conf, 200);
  assert_int_equal(vlff_map_label_at(r, -0.9, 1.9, 0.1, &label, &conf), 0);
  assert_int_equal(label, 3);
  assert_int_equal(vlff_map_label_at(r, 1.4, 0.1, 0.1, &label, &conf), 0);
  assert_int_equal(label, 3);
  assert_int_equal(vlff_map_label_at(r, 1.6, 0.1, 0.1, &label, &conf), 0);
  assert_int_equal(label, VLFF_LABEL_UNKNOWN); /* beyond the grown grid */
  /* the followed snapshot: the new geometry, copied whole */
  assert_int_equal(vlff_map_snapshot_follow(r, s), 1);
  struct vlff_map_info info;
  assert_int_equal(vlff_map_snapshot_info(s, &info), 0);
  assert_int_equal(info.grid.dims[0], 10);
  assert_true(info.grid.origin[0] == -1.0);
  assert_memory_equal(info.grid.labels, b, sizeof b);
  assert_int_equal(vlff_map_snapshot_label_at(s, old_pt[0], old_pt[1], old_pt[2], &conf), 2);
  /* past the segment's capacity (1000 voxels): refused, the map as it was */
  uint16_t big[11 * 10 * 10] = {0};
  uint8_t cbig[11 * 10 * 10] = {0};
  struct vlff_map_grid gc = {.origin = {-1, 0, 0}, .voxel_size = 0.25, .dims = {11, 10, 10}, .labels = big,
                             .confidence = cbig};
  struct vlff_map_update uc = {.grid = &gc, .prompts = prompts, .prompt_count = 4};
  assert_int_equal(vlff_map_publish(w, &uc), -1);
  assert_int_equal(errno, EMSGSIZE);
  assert_int_equal(vlff_map_label_at(r, -0.9, 1.9, 0.1, &label, &conf), 0);
  assert_int_equal(label, 3);
  /* The segment grows (vlff_map_reserve): a new one holding the map as it is
   * takes the name; the reader, attached throughout, follows it at its next
   * call and reads the same labels, the status and the version as before. */
  struct vlff_map_status st = {.t_ns = 5, .iterations = 1234, .box_growths = 7};
  snprintf(st.state_name, sizeof st.state_name, "grown");
  assert_int_equal(vlff_map_set_status(w, &st), 0);
  const uint64_t v = vlff_map_version(w);
  struct vlff_map_snapshot *s2 = vlff_map_snapshot_new(r); /* made for the old segment, taken after */
  assert_non_null(s2);
  struct stat before, after;
  char path[96];
  snprintf(path, sizeof path, "/dev/shm%s", name);
  assert_int_equal(stat(path, &before), 0);
  assert_int_equal(vlff_map_capacity(w), 1000);
  assert_int_equal(vlff_map_reserve(w, 500), 0); /* holds that already: nothing done */
  assert_int_equal(vlff_map_capacity(w), 1000);
  assert_int_equal(vlff_map_reserve(w, 11 * 10 * 10), 0);
  assert_int_equal(vlff_map_capacity(w), 1100);
  assert_int_equal(stat(path, &after), 0);
  assert_true(after.st_ino != before.st_ino && after.st_size > before.st_size);
  assert_int_equal(vlff_map_capacity(r), 1000); /* not looked yet */
  assert_int_equal(vlff_map_snapshot_take(r, s2), 0); /* follows, reallocates, copies */
  assert_int_equal(vlff_map_snapshot_info(s2, &info), 0);
  assert_int_equal(info.version, v);
  assert_int_equal(info.grid.dims[0], 10);
  assert_memory_equal(info.grid.labels, b, sizeof b);
  vlff_map_snapshot_free(s2);
  assert_int_equal(vlff_map_label_at(r, old_pt[0], old_pt[1], old_pt[2], &label, &conf), 0);
  assert_int_equal(label, 2);
  assert_int_equal(conf, 200);
  assert_int_equal(vlff_map_capacity(r), 1100);
  assert_int_equal(vlff_map_label_at(r, -0.9, 1.9, 0.1, &label, &conf), 0);
  assert_int_equal(label, 3);
  assert_int_equal(vlff_map_version(r), v);
  char text[32];
  assert_int_equal(vlff_map_prompt(r, 3, text, sizeof text), 0);
  assert_string_equal(text, "sofa");
  struct vlff_map_status got;
  assert_int_equal(vlff_map_get_status(r, &got), 0);
  assert_int_equal(got.iterations, 1234);
  assert_int_equal(got.box_growths, 7);
  assert_true(vlff_map_writer_alive(r, 10ull * 1000 * 1000 * 1000));
  /* the grid that did not fit now does; a partial publish after it too */
  for (int i = 0; i < 11 * 10 * 10; i++) big[i] = (uint16_t)(i % 4), cbig[i] = 50;
  assert_int_equal(vlff_map_publish(w, &uc), 0);
  struct vlff_map_range one = {5, 1};
  big[5] = 1;
  uc.ranges = &one, uc.range_count = 1;
  assert_int_equal(vlff_map_publish(w, &uc), 0);
  assert_int_equal(vlff_map_version(r), v + 2);
  assert_int_equal(vlff_map_label_at(r, -1 + 5 * 0.25 + 0.1, 0.1, 0.1, &label, &conf), 0);
  assert_int_equal(label, 1);
  assert_int_equal(vlff_map_label_at(r, -1 + 6 * 0.25 + 0.1, 0.1, 0.1, &label, &conf), 0);
  assert_int_equal(label, 6 % 4);
  /* the snapshot made for the old segment follows into the new one, whole */
  assert_int_equal(vlff_map_snapshot_follow(r, s), 1);
  assert_int_equal(vlff_map_snapshot_info(s, &info), 0);
  assert_int_equal(info.grid.dims[2], 10);
  assert_memory_equal(info.grid.labels, big, sizeof big);
  assert_int_equal(vlff_map_snapshot_follow(r, s), 0); /* nothing new */
  /* a reader attached after it reads the same */
  struct vlff_map *r2 = vlff_map_attach(name);
  assert_non_null(r2);
  assert_int_equal(vlff_map_label_at(r2, -1 + 5 * 0.25 + 0.1, 0.1, 0.1, &label, &conf), 0);
  assert_int_equal(label, 1);
  vlff_map_detach(r2);
  /* only a writer grows it; past 2^32 - 1 voxels refused */
  assert_int_equal(vlff_map_reserve(r, 5000), -1);
  assert_int_equal(errno, EINVAL);
  assert_int_equal(vlff_map_reserve(w, 1ull << 33), -1);
  assert_int_equal(errno, EINVAL);
  vlff_map_snapshot_free(s);
  vlff_map_detach(r);
  vlff_map_detach(w);
  assert_int_equal(vlff_shm_unlink(name), 0);
  char tmpname[96];
  snprintf(tmpname, sizeof tmpname, "/dev/shm%s.grow%d", name, (int)getpid());
  assert_int_equal(access(tmpname, F_OK), -1); /* no temporary name left behind */
}

/* The far map (docs/shm.md "The far map"): blocks of 16^3 voxels beside the
 * grid, run-length coded. A reader attached before the segment grew room for
 * them reads them through the same handle (the segment moved), the grid
 * answers where it covers a point, the far blocks elsewhere; a followed
 * snapshot takes each new far map; writers' far maps that break the
 * contract are refused and change nothing. */
static void far_block(struct vlff_map_far_run *runs, uint32_t *nr, uint16_t label, uint8_t conf) {
  /* the block's lower half in z (8 layers: 2048 voxels) label, the rest FREE */
  runs[(*nr)++] = (struct vlff_map_far_run){.label = label, .count = 2048, .conf = conf};
  runs[(*nr)++] = (struct vlff_map_far_run){.label = VLFF_LABEL_FREE, .count = 2048, .conf = 255};
}

static void map_far_blocks(void **state) {
  (void)state;
  char name[64];
  struct vlff_map *w, *r;
  map_pair("far", name, sizeof name, &w, &r);
  struct vlff_map_snapshot *s = vlff_map_snapshot_new(r);
  assert_non_null(s);
  const char *prompts[] = {"wall", "floor", "door"};
  uint16_t a[64];
  for (int i = 0; i < 64; i++) a[i] = 1;
  struct vlff_map_grid g = {.origin = {0, 0, 0}, .voxel_size = 0.25, .dims = {4, 4, 4}, .labels = a};
  struct vlff_map_update u = {.grid = &g, .prompts = prompts, .prompt_count = 3};
  assert_int_equal(vlff_map_publish(w, &u), 0);
  assert_int_equal(vlff_map_snapshot_follow(r, s), 1);
  /* two blocks 4 m (16 voxels) apart on x, one 40 m up z: keys (5,0,0),
   * (6,0,0), (0,0,10); the lattice from the grid's corner */
  struct vlff_map_far_block blocks[3] = {{{5, 0, 0}, 0}, {{6, 0, 0}, 2}, {{0, 0, 10}, 4}};
  struct vlff_map_far_run runs[6];
  uint32_t nr = 0;
  far_block(runs, &nr, 0, 90);
  far_block(runs, &nr, 2, 91);
  far_block(runs, &nr, 1, 92);
  struct vlff_map_far far = {.origin = {0, 0, 0}, .voxel_size = 0.25, .nblocks = 3, .nruns = nr, .blocks = blocks,
                             .runs = runs};
  /* no room yet: the segment's far capacity is 0 */
  assert_int_equal(vlff_map_far_capacity(w), 0);
  assert_int_equal(vlff_map_set_far(w, &far), -1);
  assert_int_equal(errno, EMSGSIZE);
  assert_int_equal(vlff_map_reserve_far(w, 1000, vlff_map_far_bytes(3, nr)), 0);
  assert_true(vlff_map_far_capacity(w) >= vlff_map_far_bytes(3, nr));
  assert_int_equal(vlff_map_capacity(w), 1000);
  /* contract breaches refused, nothing staged */
  struct vlff_map_far bad = far;
  struct vlff_map_far_block swapped[3] = {blocks[1], blocks[0], blocks[2]};
  swapped[0].first_run = 0, swapped[1].first_run = 2;
  bad.blocks = swapped;
  assert_int_equal(vlff_map_set_far(w, &bad), -1);
  assert_int_equal(errno, EINVAL);
  assert_non_null(strstr(vlff_shm_last_message(), "sorted"));
  struct vlff_map_far_run short_runs[6];
  memcpy(short_runs, runs, sizeof runs);
  short_runs[3].count = 2047;
  bad = far, bad.runs = short_runs;
  assert_int_equal(vlff_map_set_far(w, &bad), -1);
  assert_non_null(strstr(vlff_shm_last_message(), "cover"));
  short_runs[3].count = 0;
  assert_int_equal(vlff_map_set_far(w, &bad), -1);
  bad = far, bad.voxel_size = NAN;
  assert_int_equal(vlff_map_set_far(w, &bad), -1);
  struct vlff_map_far_block edge[1] = {{{INT32_MAX, 0, 0}, 0}}; /* a key no reader could reach */
  bad = far, bad.nblocks = 1, bad.nruns = 2, bad.blocks = edge, bad.voxel_size = 1e-4;
  assert_int_equal(vlff_map_set_far(w, &bad), -1);
  assert_non_null(strstr(vlff_shm_last_message(), "beyond"));
  struct vlff_map_far_block twice[3] = {blocks[0], blocks[0], blocks[2]};
  twice[1].first_run = 2;
  bad = far, bad.blocks = twice;
  assert_int_equal(vlff_map_set_far(w, &bad), -1);
  assert_non_null(strstr(vlff_shm_last_message(), "twice"));
  /* staged, then carried by a partial publish of one voxel */
  assert_int_equal(vlff_map_set_far(w, &far), 0);
  uint16_t label;
  uint8_t conf;
  assert_int_equal(vlff_map_label_at(r, 20.5, 0.5, 0.5, &label, &conf), 0);
  assert_int_equal(label, VLFF_LABEL_UNKNOWN); /* not published yet */
  a[0] = 2;
  struct vlff_map_range one = {0, 1};
  struct vlff_map_update up = {.grid = &g, .ranges = &one, .range_count = 1};
  assert_int_equal(vlff_map_publish(w, &up), 0);
  /* block (5,0,0): x 20..24 m; its low half (z < 2 m) label 0 */
  assert_int_equal(vlff_map_label_at(r, 20.5, 0.5, 0.5, &label, &conf), 0);
  assert_int_equal(label, 0);
  assert_int_equal(conf, 90);
  assert_int_equal(vlff_map_label_at(r, 23.9, 3.9, 2.1, &label, &conf), 0);
  assert_int_equal(label, VLFF_LABEL_FREE);
  assert_int_equal(vlff_map_label_at(r, 24.1, 0.5, 1.9, &label, &conf), 0);
  assert_int_equal(label, 2); /* block (6,0,0) */
  assert_int_equal(conf, 91);
  assert_int_equal(vlff_map_label_at(r, 0.5, 3.5, 40.2, &label, &conf), 0);
  assert_int_equal(label, 1); /* block (0,0,10) */
  assert_int_equal(vlff_map_label_at(r, 28.1, 0.5, 0.5, &label, &conf), 0);
  assert_int_equal(label, VLFF_LABEL_UNKNOWN); /* no block */
  assert_int_equal(vlff_map_label_at(r, -3.9, 0.5, 0.5, &label, &conf), 0);
  assert_int_equal(label, VLFF_LABEL_UNKNOWN);
  assert_int_equal(vlff_map_label_at(r, 0.1, 0.1, 0.1, &label, &conf), 0);
  assert_int_equal(label, 2); /* the grid, its changed voxel */
  /* the follower takes the far map (whole: the segment moved for it) */
  assert_int_equal(vlff_map_snapshot_follow(r, s), 1);
  assert_int_equal(vlff_map_snapshot_label_at(s, 24.1, 0.5, 1.9, &conf), 2);
  assert_int_equal(vlff_map_snapshot_label_at(s, 0.5, 3.5, 40.2, &conf), 1);
  assert_int_equal(vlff_map_snapshot_label_at(s, 0.1, 0.1, 0.1, &conf), 2);
  struct vlff_map_far got;
  assert_int_equal(vlff_map_snapshot_far(s, &got), 0);
  assert_int_equal(got.nblocks, 3);
  assert_int_equal(got.nruns, nr);
  assert_memory_equal(got.blocks, blocks, sizeof blocks);
  assert_memory_equal(got.runs, runs, sizeof runs);
  const uint64_t fv = vlff_map_snapshot_far_version(s);
  assert_true(fv > 0 && fv <= vlff_map_version(r));
  /* publishes without a new far map keep it, in both buffers */
  for (int i = 0; i < 3; i++) {
    a[1] = (uint16_t)i;
    one.first = 1;
    assert_int_equal(vlff_map_publish(w, &up), 0);
    assert_int_equal(vlff_map_label_at(r, 24.1, 0.5, 1.9, &label, &conf), 0);
    assert_int_equal(label, 2);
  }
  assert_int_equal(vlff_map_snapshot_follow(r, s), 0);
  assert_int_equal(vlff_map_snapshot_far_version(s), fv); /* the same far map */
  /* a grid over a far block answers there itself */
  uint16_t big[16 * 4 * 4];
  for (int i = 0; i < 16 * 4 * 4; i++) big[i] = 1;
  struct vlff_map_grid g2 = {.origin = {20, 0, 0}, .voxel_size = 0.25, .dims = {16, 4, 4}, .labels = big};
  struct vlff_map_update u2 = {.grid = &g2};
  assert_int_equal(vlff_map_publish(w, &u2), 0);
  assert_int_equal(vlff_map_label_at(r, 20.5, 0.5, 0.5, &label, &conf), 0);
  assert_int_equal(label, 1);
  assert_int_equal(vlff_map_label_at(r, 24.1, 0.5, 1.9, &label, &conf), 0);
  assert_int_equal(label, 2); /* beyond the grid: the far block */
  assert_int_equal(vlff_map_snapshot_follow(r, s), 1); /* the geometry changed */
  /* a new far map of one block replaces it with a partial publish; the
   * follower copies it with the runs */
  far.nblocks = 1, far.nruns = 2, far.blocks = &blocks[2], blocks[2].first_run = 0, far.runs = &runs[4];
  assert_int_equal(vlff_map_set_far(w, &far), 0);
  struct vlff_map_update up2 = {.grid = &g2, .ranges = &one, .range_count = 1};
  assert_int_equal(vlff_map_publish(w, &up2), 0);
  assert_int_equal(vlff_map_snapshot_follow(r, s), 0);
  assert_int_equal(vlff_map_snapshot_label_at(s, 24.1, 0.5, 1.9, &conf), VLFF_LABEL_UNKNOWN);
  assert_int_equal(vlff_map_snapshot_label_at(s, 0.5, 3.5, 40.2, &conf), 1);
  assert_int_equal(vlff_map_label_at(r, 24.1, 0.5, 1.9, &label, &conf), 0);
  assert_int_equal(label, VLFF_LABEL_UNKNOWN);
  /* none: every far point unknown */
  assert_int_equal(vlff_map_set_far(w, NULL), 0);
  assert_int_equal(vlff_map_publish(w, &up2), 0);
  assert_int_equal(vlff_map_label_at(r, 0.5, 3.5, 40.2, &label, &conf), 0);
  assert_int_equal(label, VLFF_LABEL_UNKNOWN);
  assert_int_equal(vlff_map_snapshot_follow(r, s), 0);
  assert_int_equal(vlff_map_snapshot_far(s, &got), 0);
  assert_int_equal(got.nblocks, 0);
  /* an emptied far map is a new far map too, of this version */
  assert_int_equal(vlff_map_snapshot_far_version(s), vlff_map_version(r));
  assert_int_equal(vlff_map_snapshot_far_version(NULL), 0);
  /* only a writer sets one */
  assert_int_equal(vlff_map_set_far(r, &far), -1);
  assert_int_equal(errno, EINVAL);
  vlff_map_snapshot_free(s);
  vlff_map_detach(r);
  vlff_map_detach(w);
  assert_int_equal(vlff_shm_unlink(name), 0);
}

/* A writer killed in the middle of a move leaves its temporary segment
 * "<name>.grow<pid>": the next writer of that map removes it when that pid no
 * longer runs, and leaves one whose pid does. Truncated under its writer, a map
 * is not moved: what would be copied is not what was published. */
static void map_move_leftovers(void **state) {
  (void)state;
  char name[64], dead[96], live[96];
  test_name(name, sizeof name, "left");
  pid_t child = fork();
  if (child == 0)
    _exit(0);
  assert_int_equal(waitpid(child, NULL, 0), child);
  snprintf(dead, sizeof dead, "%s.grow%d", name, (int)child);
  snprintf(live, sizeof live, "%s.grow%d", name, (int)getppid());
  for (int k = 0; k < 2; k++) {
    int fd = shm_open(k ? live : dead, O_RDWR | O_CREAT | O_EXCL, 0600);
    assert_true(fd >= 0);
    assert_int_equal(ftruncate(fd, 4096), 0);
    close(fd);
  }
  struct vlff_map *w = vlff_map_create(name, &small_map);
  assert_non_null(w);
  char path[128];
  snprintf(path, sizeof path, "/dev/shm%s", dead);
  assert_int_equal(access(path, F_OK), -1);
  snprintf(path, sizeof path, "/dev/shm%s", live);
  assert_int_equal(access(path, F_OK), 0);
  assert_int_equal(shm_unlink(live), 0);
  uint16_t a[8] = {1, 1, 1, 1, 1, 1, 1, 1};
  struct vlff_map_grid g = {.origin = {0, 0, 0}, .voxel_size = 0.5, .dims = {2, 2, 2}, .labels = a};
  struct vlff_map_update u = {.grid = &g};
  assert_int_equal(vlff_map_publish(w, &u), 0);
  snprintf(path, sizeof path, "/dev/shm%s", name);
  assert_int_equal(truncate(path, 8192), 0);
  assert_int_equal(vlff_map_reserve(w, 5000), -1);
  assert_int_equal(errno, EPIPE);
  assert_non_null(strstr(vlff_shm_last_message(), "the map did not grow"));
  assert_int_equal(vlff_map_capacity(w), 1000);
  vlff_map_detach(w);
  assert_int_equal(vlff_shm_unlink(name), 0);
}

/* A reader whose writer grew the map past what the reader can allocate a
 * snapshot for is told so (ENOMEM, "out of memory"), not that the map is
 * corrupt: the seqlock loop used to turn the copy's failure into "published
 * map metadata is inconsistent". In a child under an address-space limit
 * that maps the grown segment but not a snapshot of it. */
static void map_snapshot_out_of_memory(void **state) {
  (void)state;
#if defined(__SANITIZE_ADDRESS__) || defined(__SANITIZE_THREAD__)
  skip(); /* the sanitizers' allocators abort where malloc would return NULL */
#elif defined(__has_feature)
#if __has_feature(address_sanitizer) || __has_feature(thread_sanitizer) || __has_feature(memory_sanitizer)
  skip();
#endif
#endif
  char name[64];
  struct vlff_map *w, *r;
  map_pair("oom", name, sizeof name, &w, &r);
  uint16_t labels[1000] = {0};
  uint8_t confs[1000] = {0};
  struct vlff_map_grid g = {.origin = {0, 0, 0}, .voxel_size = 0.1, .dims = {10, 10, 10}, .labels = labels,
                            .confidence = confs};
  struct vlff_map_update u = {.grid = &g, .prompt_count = -1};
  assert_int_equal(vlff_map_publish(w, &u), 0);
  struct vlff_map_snapshot *s = vlff_map_snapshot_new(r);
  assert_non_null(s);
  assert_int_equal(vlff_map_snapshot_take(r, s), 0);
  /* 8 M voxels: a segment of ~50 MB (every page reserved in /dev/shm), a
   * snapshot of 24 MB */
  const uint64_t n = 1ull << 23;
  if (vlff_map_reserve(w, n) < 0 && errno == ENOSPC) {
    vlff_shm_unlink(name);
    skip(); /* a small /dev/shm */
  }
  assert_int_equal(vlff_map_capacity(w), n);
  char path[96];
  struct stat sb;
  snprintf(path, sizeof path, "/dev/shm%s", name);
  assert_int_equal(stat(path, &sb), 0);
  pid_t child = fork();
  assert_true(child >= 0);
  if (child == 0) {
    /* room for the reader to map the grown segment, not for its snapshot */
    const double vm_kb = vlff_test_status_kb("VmSize"); /* the address space mapped now */
    if (!(vm_kb > 0))
      _exit(15); /* no VmSize line */
    unsigned long long lim = (unsigned long long)vm_kb * 1024 + (unsigned long long)sb.st_size + (4ull << 20);
    struct rlimit rl = {lim, lim};
    if (setrlimit(RLIMIT_AS, &rl))
      _exit(77); /* a lower hard limit inherited */
    if (vlff_map_snapshot_take(r, s) == 0) {
      void *more = malloc(8 * n); /* qemu-user takes RLIMIT_AS and ignores it */
      _exit(more ? 77 : 11);
    }
    if (errno != ENOMEM)
      _exit(11);
    if (!strstr(vlff_shm_last_message(), "out of memory"))
      _exit(12);
    if (vlff_map_snapshot_follow(r, s) != -1 || errno != ENOMEM)
      _exit(13);
    if (vlff_map_capacity(r) != n) /* it followed the writer: only the copy failed */
      _exit(14);
    _exit(0);
  }
  int st;
  assert_int_equal(waitpid(child, &st, 0), child);
  vlff_shm_unlink(name); /* on every path (the handles stay usable) */
  assert_true(WIFEXITED(st));
  if (WEXITSTATUS(st) == 77)
    skip(); /* no address-space limit here */
  assert_int_equal(WEXITSTATUS(st), 0);
  vlff_map_snapshot_free(s);
  vlff_map_detach(r);
  vlff_map_detach(w);
}

static void map_publish_and_read(void **state) {
  (void)state;
  char name[64];
  struct vlff_map *w, *r;
  map_pair("map", name, sizeof name, &w, &r);
  uint16_t label;
  uint8_t conf;
  assert_int_equal(vlff_map_version(r), 0);
  assert_int_equal(vlff_map_label_at(r, 0, 0, 0, &label, &conf), 0);
  assert_int_equal(label, VLFF_LABEL_UNKNOWN);
  assert_int_equal(vlff_map_age_ns(r), UINT64_MAX);
  assert_int_equal(vlff_map_writer_alive(r, 1000000000ull), 1);

  uint16_t labels[10 * 10 * 10];
  uint8_t confs[1000];
  for (int i = 0; i < 1000; i++) {
    labels[i] = (uint16_t)(i % 3);
    confs[i] = (uint8_t)i;
  }
  labels[1 + 10 * (2 + 10 * 3)] = VLFF_LABEL_FREE;
  const char *prompts[] = {"chair", "table", "door"};
  struct vlff_map_grid g = {.origin = {-1, -1, 0}, .voxel_size = 0.2, .dims = {10, 10, 10}, .labels = labels,
                            .confidence = confs};
  struct vlff_map_update u = {.grid = &g, .prompts = prompts, .prompt_count = 3};
  assert_int_equal(vlff_map_publish(w, &u), 0);
  /* World (-0.7,-0.5,0.7) -> voxel (1,2,3) = FREE. (0.05,-0.95,0.1) -> (5,0,0) = label 2. */
  assert_int_equal(vlff_map_label_at(r, -0.7, -0.5, 0.7, &label, &conf), 0);
  assert_int_equal(label, VLFF_LABEL_FREE);
  assert_int_equal(vlff_map_label_at(r, 0.05, -0.95, 0.1, &label, &conf), 0);
  assert_int_equal(label, 2);
  assert_int_equal(conf, 5);
  assert_int_equal(vlff_map_label_at(r, 5, 0, 0, &label, NULL), 0);
  assert_int_equal(label, VLFF_LABEL_UNKNOWN);
  /* A NaN or infinite coordinate is no point: refused, not "unknown". */
  const double bad[] = {NAN, INFINITY, -INFINITY};
  for (int i = 0; i < 3; i++)
    for (int axis = 0; axis < 3; axis++) {
      double p[3] = {0.05, -0.95, 0.1};
      p[axis] = bad[i];
      label = 7;
      assert_int_equal(vlff_map_label_at(r, p[0], p[1], p[2], &label, &conf), -1);
      assert_int_equal(errno, EINVAL);
      assert_int_equal(vlff_shm_last_error(), VLFF_SHM_ERR_INVAL);
      assert_non_null(strstr(vlff_shm_last_message(), "is not finite"));
      assert_int_equal(label, 7);
    }
  char text[64];
  assert_int_equal(vlff_map_prompt(r, 2, text, sizeof text), 0);
  assert_string_equal(text, "door");
  assert_int_equal(vlff_map_prompt(r, 3, text, sizeof text), -1);
  assert_int_equal(errno, ENOENT);
  assert_int_equal(vlff_map_prompt(r, VLFF_LABEL_FREE, text, sizeof text), -1);
  assert_true(vlff_map_age_ns(r) < 5000000000ull);

  /* A label-image-only update keeps the grid and prompts. */
  uint16_t li[8 * 6];
  for (int i = 0; i < 48; i++)
    li[i] = (uint16_t)(i & 1);
  struct vlff_map_label_image img = {.width = 8, .height = 6, .labels = li, .fx = 5, .fy = 5, .cx = 4, .cy = 3,
                                     .t_ns = 42};
  img.pose[0] = img.pose[5] = img.pose[10] = img.pose[15] = 1;
  struct vlff_map_update u2 = {.label_image = &img, .prompt_count = -1};
  assert_int_equal(vlff_map_publish(w, &u2), 0);
  struct vlff_map_snapshot *s = vlff_map_snapshot_new(r);
  assert_non_null(s);
  assert_int_equal(vlff_map_snapshot_take(r, s), 0);
  struct vlff_map_info info;
  assert_int_equal(vlff_map_snapshot_info(s, &info), 0);
  assert_int_equal(info.version, 2);
  assert_int_equal(info.prompt_count, 3);
  assert_int_equal(info.grid.dims[2], 10);
  assert_memory_equal(info.grid.labels, labels, sizeof labels);
  assert_memory_equal(info.grid.confidence, confs, sizeof confs);
  assert_int_equal(info.has_label_image, 1);
  assert_memory_equal(info.label_image.labels, li, sizeof li);
  assert_int_equal(info.label_image.confidence[7], 255);
  assert_int_equal(info.label_image.t_ns, 42);
  assert_int_equal(vlff_map_snapshot_label_at(s, 0.05, -0.95, 0.1, &conf), 2);
  assert_string_equal(vlff_map_snapshot_prompt(s, 1), "table");
  assert_null(vlff_map_snapshot_prompt(s, 3));

  /* Bad updates are refused and change nothing. */
  struct vlff_map_grid big = g;
  big.dims[0] = 11;
  struct vlff_map_update ub = {.grid = &big, .prompt_count = -1};
  assert_int_equal(vlff_map_publish(w, &ub), -1);
  assert_int_equal(errno, EMSGSIZE);
  struct vlff_map_grid nan = g;
  nan.voxel_size = NAN;
  ub.grid = &nan;
  assert_int_equal(vlff_map_publish(w, &ub), -1);
  assert_int_equal(errno, EINVAL);
  /* Finite but not physical: a reader indexing by a 1e300 m voxel wrote
   * infinite voxel centres (vlff-shm dump-map). */
  struct vlff_map_grid absurd[4] = {g, g, g, g};
  absurd[0].voxel_size = 1e300, absurd[1].voxel_size = 1e-5, absurd[2].origin[1] = -2e8;
  absurd[3].voxel_size = 900; /* within the size bound, but 10 voxels reach past 1e8 m from 1e8 - 1 */
  absurd[3].origin[0] = 1e8 - 1;
  for (int k = 0; k < 4; k++) {
    ub.grid = &absurd[k];
    assert_int_equal(vlff_map_publish(w, &ub), -1);
    assert_int_equal(errno, EINVAL);
  }
  assert_non_null(strstr(vlff_shm_last_message(), "physical bounds"));
  const char *longp[] = {"a prompt that is far too long to fit into the sixty-four bytes of a slot...."};
  struct vlff_map_update up = {.prompts = longp, .prompt_count = 1};
  assert_int_equal(vlff_map_publish(w, &up), -1);
  assert_int_equal(vlff_map_version(r), 2);
  /* Heartbeat without a new map; a reader handle cannot publish. */
  assert_int_equal(vlff_map_heartbeat(w), 0);
  assert_int_equal(vlff_map_publish(r, &u), -1);
  assert_int_equal(vlff_map_writer_alive(r, 1000000000ull), 1);
  assert_int_equal(vlff_map_writer_alive(r, 0), 0);

  /* Writer restart on the same segment: generation visible, last map kept. */
  vlff_map_snapshot_free(s);
  vlff_map_detach(w);
  assert_int_equal(vlff_map_generation(r), 1);
  /* this process is the creator: a restart of it is a take-over */
  w = vlff_map_create(name, &small_map);
  assert_non_null(w);
  assert_int_equal(vlff_map_generation(r), 2);
  assert_int_equal(vlff_map_version(r), 2);
  assert_int_equal(vlff_map_label_at(r, 0.05, -0.95, 0.1, &label, &conf), 0);
  assert_int_equal(label, 2);
  vlff_map_detach(r);
  vlff_map_detach(w);
  vlff_shm_unlink(name);
}

static void prompt_mailbox(void **state) {
  (void)state;
  char name[64];
  test_name(name, sizeof name, "prompts");
  struct vlff_shm_perm perm = {.mode = 0660};
  struct vlff_prompts *learner = vlff_prompts_create(name, &perm);
  assert_non_null(learner);
  struct vlff_prompts *ctl = vlff_prompts_attach(name);
  assert_non_null(ctl);
  uint64_t last = 0;
  struct vlff_prompt_request *req = malloc(sizeof *req);
  assert_int_equal(vlff_prompts_poll(learner, &last, req), 0);
  const char *set[] = {"red mug", "laptop"};
  assert_int_equal(vlff_prompts_post(ctl, set, 2), 0);
  assert_int_equal(vlff_prompts_poll(learner, &last, req), 1);
  assert_int_equal(last, 1);
  assert_int_equal(req->seq, 1);
  assert_int_equal(req->count, 2);
  assert_int_equal(req->set_index, -1);
  assert_string_equal(req->text[1], "laptop");
  assert_int_equal(req->poster_pid, getpid());
  assert_int_equal(vlff_prompts_poll(learner, &last, req), 0);
  assert_int_equal(vlff_prompts_answer(learner, 1, 1, NULL), 0);
  assert_int_equal(vlff_prompts_post_index(ctl, 3), 0);
  assert_int_equal(vlff_prompts_poll(learner, &last, req), 1);
  assert_int_equal(req->set_index, 3);
  assert_int_equal(req->count, 0);
  const char *bad[] = {""};
  assert_int_equal(vlff_prompts_post(ctl, bad, 1), -1);
  assert_int_equal(errno, EINVAL);
  assert_int_equal(vlff_prompts_post(ctl, set, 0), -1);
  struct vlff_shm_info in;
  assert_int_equal(vlff_shm_stat(name, &in), 0);
  assert_int_equal(in.kind, VLFF_SHM_KIND_PROMPTS);
  assert_int_equal(in.head, 2);
  free(req);
  vlff_prompts_close(ctl);
  vlff_prompts_close(learner);
  vlff_shm_unlink(name);
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(ring_roundtrip_and_exact_lapping),
    cmocka_unit_test(ring_takeover_of_dead_creator), cmocka_unit_test(attach_rejects_bad_segments),
    cmocka_unit_test(frame_records), cmocka_unit_test(pose_interpolation_and_tolerance),
    cmocka_unit_test(pose_quaternion_every_branch),
    cmocka_unit_test(map_publish_and_read), cmocka_unit_test(map_grows_under_reader), cmocka_unit_test(map_far_blocks),
    cmocka_unit_test(map_move_leftovers),
    cmocka_unit_test(map_snapshot_out_of_memory),
    cmocka_unit_test(prompt_mailbox))
