/* /dev/shm full (issue 51, item 8). On tmpfs a file's size is a promise: with
 * /dev/shm full, ftruncate still succeeded, and the first write to a page that
 * could not be had faulted; the SIGBUS guard took that for a truncation, and the
 * creators replaced their segments some 15 times a second while no frame flowed.
 * Creation reserves every page, so a full /dev/shm says so when a segment is
 * made; a segment made fits whatever fills /dev/shm later; and a creator whose
 * replacement (after a real truncation) finds no space tries again after a
 * growing delay instead of at every call.
 *
 * The test runs in a mount namespace of its own with a 1 MiB tmpfs on /dev/shm,
 * really filled: root only (unshare and mount), skipped otherwise. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <cmocka.h>

#include "shm_test_util.h"
#include "unit.h"

#include <errno.h>
#include <sched.h>
#include <stdlib.h>
#include <sys/mount.h>
#include <time.h>

#define FILLER "/dev/shm/filler"

static int state_ok;

static int private_shm(void **state) {
  (void)state;
  if (geteuid() != 0 || unshare(CLONE_NEWNS) != 0 || mount(NULL, "/", NULL, MS_REC | MS_PRIVATE, NULL) != 0 ||
      mount("tmpfs", "/dev/shm", "tmpfs", 0, "size=1m,mode=1777") != 0) {
    fprintf(stderr, "no private tmpfs on /dev/shm (root and mount namespaces needed): %s\n", strerror(errno));
    return 0; /* each test skips */
  }
  state_ok = 1;
  return 0;
}

/* Fills what is left of /dev/shm with a file of real pages. */
static void fill(void) {
  int fd = open(FILLER, O_WRONLY | O_CREAT | O_APPEND, 0600);
  assert_true(fd >= 0);
  static char page[4096];
  memset(page, 0x5a, sizeof page);
  while (write(fd, page, sizeof page) > 0) {
  }
  assert_int_equal(errno, ENOSPC);
  close(fd);
}

static void expect_nospace(const char *what) {
  const char *msg = vlff_shm_last_message();
  if (vlff_shm_last_error() != VLFF_SHM_ERR_NOSPACE || !strstr(msg, "no space left in /dev/shm (") ||
      !strstr(msg, " bytes needed)"))
    fail_msg("%s: error %d: %s", what, vlff_shm_last_error(), msg);
}

static void need_tmpfs(void) {
  if (!state_ok)
    skip();
}

/* Larger than /dev/shm: refused at creation, with the size, and nothing left behind. */
static void test_create_when_full(void **state) {
  (void)state;
  need_tmpfs();
  struct vlff_ring_params rp = {.record_kind = VLFF_RECORD_RAW, .slots = 4, .slot_size = 512 * 1024};
  assert_null(vlff_ring_create("/big", &rp));
  assert_int_equal(errno, ENOSPC);
  expect_nospace("ring create");
  assert_non_null(strstr(vlff_shm_last_message(), "/big"));
  assert_int_equal(access("/dev/shm/big", F_OK), -1);
  fill();
  struct vlff_map_params mp = {.max_voxels = 4096};
  assert_null(vlff_map_create("/map", &mp));
  expect_nospace("map create");
  assert_null(vlff_prompts_create("/box", NULL));
  expect_nospace("prompts create");
  assert_int_equal(access("/dev/shm/map", F_OK), -1);
  unlink(FILLER);
}

/* Made while there was room, it keeps working when /dev/shm fills up: every slot
 * is written and read whole, none faults. */
static void test_full_later_no_fault(void **state) {
  (void)state;
  need_tmpfs();
  struct vlff_ring_params rp = {.record_kind = VLFF_RECORD_RAW, .slots = 8, .slot_size = 64 * 1024};
  struct vlff_ring *w = vlff_ring_create("/ring", &rp);
  assert_non_null(w);
  struct vlff_ring *rd = vlff_ring_attach("/ring", VLFF_RECORD_RAW);
  assert_non_null(rd);
  fill();
  static uint8_t buf[64 * 1024];
  for (uint64_t id = 0; id < 2 * rp.slots; id++) {
    uint8_t *p = vlff_ring_reserve(w, NULL);
    if (!p)
      fail_msg("record %llu: %s", (unsigned long long)id, vlff_shm_last_message());
    test_rec_fill(p, id, rp.slot_size);
    assert_int_equal(vlff_ring_commit(w, rp.slot_size), 0);
    struct vlff_ring_view v;
    assert_int_equal(vlff_ring_read_copy(rd, buf, sizeof buf, &v, 0), (ssize_t)rp.slot_size);
    assert_int_equal(test_rec_check(buf, rp.slot_size, id), 0);
  }
  assert_int_equal(vlff_ring_generation(w), 1);
  vlff_ring_close(rd);
  vlff_ring_close(w);
  unlink(FILLER);
  vlff_shm_unlink("/ring");
}

/* Truncated by someone with write access while /dev/shm is full: the producer
 * cannot replace its ring, says why, and tries again only after a delay that
 * grows; once there is room the ring comes back and numbering goes on. */
static void test_replace_backs_off(void **state) {
  (void)state;
  need_tmpfs();
  struct vlff_ring_params rp = {.record_kind = VLFF_RECORD_RAW, .slots = 4, .slot_size = 64 * 1024};
  struct vlff_ring *w = vlff_ring_create("/trunc", &rp);
  assert_non_null(w);
  for (int i = 0; i < 3; i++)
    assert_int_equal(vlff_ring_write(w, "abc", 3), 0);
  assert_int_equal(truncate("/dev/shm/trunc", 0), 0);
  fill();
  /* The truncation is found, the replacement fails for want of space. */
  assert_null(vlff_ring_reserve(w, NULL));
  assert_int_equal(errno, EPIPE);
  expect_nospace("replace");
  assert_non_null(strstr(vlff_shm_last_message(), "next try in 0.1 s (1 tries so far)"));
  /* Calls before the delay do not try again. */
  for (int i = 0; i < 1000; i++) {
    assert_null(vlff_ring_reserve(w, NULL));
    assert_int_equal(errno, EPIPE);
    expect_nospace("gated");
  }
  assert_non_null(strstr(vlff_shm_last_message(), "(1 tries so far)"));
  /* Tries after the delay fail again, each delay longer than the last. */
  const char *want[] = {"next try in 0.2 s (2 tries so far)", "next try in 0.4 s (3 tries so far)"};
  for (int k = 0; k < 2; k++) {
    int tries = 0;
    while (!strstr(vlff_shm_last_message(), want[k])) {
      assert_true(++tries < 2000); /* 2000 x 1 ms is well past any delay here */
      nanosleep(&(struct timespec){0, 1000000}, NULL);
      assert_null(vlff_ring_reserve(w, NULL));
      expect_nospace("retry");
    }
  }
  unlink(FILLER);
  nanosleep(&(struct timespec){0, 500000000}, NULL);
  assert_int_equal(vlff_ring_write(w, "def", 3), 0);
  assert_int_equal(vlff_ring_head(w), 4); /* numbering went on: 3 before, this one */
  struct vlff_ring *rd = vlff_ring_attach("/trunc", VLFF_RECORD_RAW);
  assert_non_null(rd);
  char b[8];
  struct vlff_ring_view v;
  assert_int_equal(vlff_ring_read_latest(rd, b, sizeof b, &v), 3);
  assert_memory_equal(b, "def", 3);
  assert_int_equal(v.seq, 3);
  vlff_ring_close(rd);
  vlff_ring_close(w);
  vlff_shm_unlink("/trunc");
}

/* A map that outgrows its segment while /dev/shm is full: the larger one cannot
 * be made, the writer says so with the size, and the map stays whole in its
 * segment for its reader; nothing is left under the temporary name. With room
 * again it moves, and the reader follows. */
static void test_reserve_when_full(void **state) {
  (void)state;
  need_tmpfs();
  struct vlff_map_params mp = {.max_voxels = 1000};
  struct vlff_map *w = vlff_map_create("/gmap", &mp);
  assert_non_null(w);
  struct vlff_map *r = vlff_map_attach("/gmap");
  assert_non_null(r);
  uint16_t labels[1000];
  for (int i = 0; i < 1000; i++) labels[i] = (uint16_t)(i % 5);
  struct vlff_map_grid g = {.origin = {0, 0, 0}, .voxel_size = 0.1, .dims = {10, 10, 10}, .labels = labels};
  struct vlff_map_update u = {.grid = &g};
  assert_int_equal(vlff_map_publish(w, &u), 0);
  fill();
  assert_int_equal(vlff_map_reserve(w, 200000), -1);
  expect_nospace("map reserve");
  assert_int_equal(vlff_map_capacity(w), 1000);
  char tmp[64];
  snprintf(tmp, sizeof tmp, "/dev/shm/gmap.grow%d", (int)getpid());
  assert_int_equal(access(tmp, F_OK), -1);
  uint16_t l;
  assert_int_equal(vlff_map_label_at(r, 0.35, 0.05, 0.05, &l, NULL), 0);
  assert_int_equal(l, 3);
  assert_int_equal(vlff_map_publish(w, &u), 0); /* the writer goes on in the segment it has */
  unlink(FILLER);
  assert_int_equal(vlff_map_reserve(w, 20000), 0);
  assert_int_equal(vlff_map_label_at(r, 0.35, 0.05, 0.05, &l, NULL), 0);
  assert_int_equal(l, 3);
  assert_int_equal(vlff_map_capacity(r), 20000);
  vlff_map_detach(r);
  vlff_map_detach(w);
  vlff_shm_unlink("/gmap");
}

VLFF_UNIT_MAIN(private_shm, NULL, cmocka_unit_test(test_create_when_full), cmocka_unit_test(test_full_later_no_fault),
               cmocka_unit_test(test_replace_backs_off), cmocka_unit_test(test_reserve_when_full))
