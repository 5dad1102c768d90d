/* The writer's status block in the map segment: set and read back whole, refused
 * when malformed, independent of the map's versions, and never torn: readers
 * hammer it while the writer replaces it as fast as it can, every field of
 * update k a function of k (threads in one process, so ThreadSanitizer checks the
 * protocol). Blocks written past the library (a forged reason count, a word left
 * odd by a writer that died mid-write) are refused or waited out, never trusted. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <cmocka.h>

#include "shm_test_util.h"
#include "unit.h"

#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <pthread.h>
#include <stdatomic.h>
#include <stdlib.h>
#include <sys/mman.h>

/* Where the library keeps the block (shm/map.c): a forger's view of the file. */
#define STATUS_OFFSET 1024u

static char name[64];
static _Atomic int stop;

static void fill(struct vlff_map_status *s, uint64_t k) {
  memset(s, 0, sizeof *s);
  s->state = (int32_t)(k % 7);
  s->error_flags = (uint32_t)(k * 3);
  snprintf(s->state_name, sizeof s->state_name, "state-%llu", (unsigned long long)(k % 100000));
  s->frames_in = k * 11;
  s->frames_lost = k * 2;
  s->frames_refused = k * 5;
  s->keyframes = k % 97;
  s->keyframes_evicted = k / 3;
  s->iterations = k * 101;
  s->iterations_per_s = (double)k * 0.5;
  s->fps_in = (double)k * 0.25;
  s->loss = 1.0 / (double)(k + 1);
  s->loss_rgb = s->loss / 2;
  s->loss_depth = s->loss / 4;
  s->loss_feat = s->loss / 8;
  s->psnr = (double)k + 0.125;
  s->frame_to_map_ms_p50 = (double)k * 3;
  s->frame_to_map_ms_p99 = (double)k * 9;
  s->publish_interval_s = 1.0 + 1.0 / (double)(k + 1);
  s->label_flips = k * 7;
  s->label_flips_refresh = k * 13;
  s->label_flips_total = k * 17;
  s->label_flip_frac = 1.0 / (double)(k + 2);
  s->mem_keyframes_mb = (double)k * 0.5, s->mem_keyframes_limit_mb = 1024;
  s->mem_evidence_mb = (double)k * 0.25, s->mem_evidence_limit_mb = 64;
  s->mem_field_mb = 300 + (double)k, s->mem_rss_mb = 1000 + (double)k * 2;
  s->keyframes_paged = k * 19, s->keyframes_paged_out = k * 23, s->keyframes_paged_in = k * 29;
  s->keyframes_dropped = k * 31;
  s->keyframes_page_mb = (double)k * 0.75, s->keyframes_page_limit_mb = 4096;
  s->evidence_paged = k * 37, s->evidence_paged_out = k * 41, s->evidence_paged_in = k * 43;
  s->evidence_dropped = k * 47;
  for (int a = 0; a < 3; a++) s->box_lo[a] = -2.5 - (double)(k % 50) * (a + 1), s->box_hi[a] = 2.5 + (double)k * a;
  s->box_growths = k * 53, s->box_refused = k * 59;
  s->reason_count = (uint32_t)(k % (VLFF_SHM_MAX_REASONS + 1));
  for (uint32_t r = 0; r < s->reason_count; r++) {
    snprintf(s->reason[r].name, sizeof s->reason[r].name, "reason %u of %u", r % 16u,
             (unsigned)(k % 1000));
    s->reason[r].count = k * 1000 + r;
  }
}

/* Every field of a status read back against update k; t_ns and updates aside. */
static int matches(const struct vlff_map_status *got, uint64_t k) {
  struct vlff_map_status want;
  fill(&want, k);
  want.t_ns = got->t_ns;
  want.updates = got->updates;
  return memcmp(&want, got, sizeof want) == 0;
}

/* The k a status was filled for, from its frames_in. */
static uint64_t k_of(const struct vlff_map_status *s) { return s->frames_in / 11; }

static struct vlff_map *make_map(const char *what) {
  test_name(name, sizeof name, what);
  struct vlff_map_params p = {.max_voxels = 64};
  struct vlff_map *w = vlff_map_create(name, &p);
  assert_non_null(w);
  return w;
}

static void set_and_read_back(void **state) {
  (void)state;
  struct vlff_map *w = make_map("status");
  struct vlff_map *r = vlff_map_attach(name);
  assert_non_null(r);
  struct vlff_map_status got;
  memset(&got, 0xab, sizeof got);
  assert_int_equal(vlff_map_get_status(r, &got), -1);
  assert_int_equal(errno, ENOENT);
  assert_int_equal(got.frames_in, 0); /* zeroed, not left as garbage */

  struct vlff_map_status s;
  fill(&s, 13); /* 13 reasons */
  uint64_t t0 = vlff_shm_now_ns();
  assert_int_equal(vlff_map_set_status(w, &s), 0);
  assert_int_equal(vlff_map_get_status(r, &got), 0);
  assert_true(matches(&got, 13));
  assert_int_equal(got.updates, 1);
  assert_true(got.t_ns >= t0 && got.t_ns <= vlff_shm_now_ns());
  assert_string_equal(got.reason[12].name, "reason 12 of 13");
  assert_int_equal(got.reason[12].count, 13012);
  /* The block's last fields (ABI 8) reach the reader too. */
  assert_int_equal(got.keyframes_dropped, 13 * 31);
  assert_int_equal(got.evidence_dropped, 13 * 47);
  assert_true(got.box_hi[2] == 2.5 + 26 && got.box_refused == 13 * 59);

  /* Fewer reasons next time: the entries no longer used read as empty. */
  fill(&s, 2);
  memset(&s.reason[5], 0x41, sizeof s.reason[5]); /* beyond reason_count: ignored */
  assert_int_equal(vlff_map_set_status(w, &s), 0);
  assert_int_equal(vlff_map_get_status(r, &got), 0);
  assert_int_equal(got.updates, 2);
  assert_int_equal(got.reason_count, 2);
  assert_string_equal(got.reason[2].name, "");
  assert_int_equal(got.reason[5].count, 0);
  assert_string_equal(got.reason[5].name, "");

  /* The status and the map are independent: neither changes the other. */
  assert_int_equal(vlff_map_version(r), 0);
  uint16_t labels[64] = {0};
  struct vlff_map_grid g = {.voxel_size = 0.1, .dims = {4, 4, 4}, .labels = labels};
  struct vlff_map_update u = {.grid = &g, .prompt_count = -1};
  assert_int_equal(vlff_map_publish(w, &u), 0);
  assert_int_equal(vlff_map_version(r), 1);
  assert_int_equal(vlff_map_get_status(r, &got), 0);
  assert_true(matches(&got, 2));
  assert_int_equal(got.updates, 2);
  /* The writer reads its own status too. */
  assert_int_equal(vlff_map_get_status(w, &got), 0);
  assert_true(matches(&got, 2));

  vlff_map_detach(r);
  vlff_map_detach(w);
  vlff_shm_unlink(name);
}

static void malformed_status_refused(void **state) {
  (void)state;
  struct vlff_map *w = make_map("status-bad");
  struct vlff_map *r = vlff_map_attach(name);
  struct vlff_map_status s, got;
  fill(&s, 3);
  assert_int_equal(vlff_map_set_status(w, &s), 0);

  fill(&s, 4);
  s.reason_count = VLFF_SHM_MAX_REASONS + 1;
  assert_int_equal(vlff_map_set_status(w, &s), -1);
  assert_int_equal(errno, EINVAL);
  assert_non_null(strstr(vlff_shm_last_message(), "17 reasons"));

  fill(&s, 4);
  s.reason[1].name[0] = 0;
  assert_int_equal(vlff_map_set_status(w, &s), -1);
  assert_int_equal(errno, EINVAL);
  assert_non_null(strstr(vlff_shm_last_message(), "reason 1 is unnamed"));

  fill(&s, 4);
  memset(s.reason[0].name, 'x', sizeof s.reason[0].name);
  assert_int_equal(vlff_map_set_status(w, &s), -1);
  assert_int_equal(errno, EINVAL);

  fill(&s, 4);
  memset(s.state_name, 'y', sizeof s.state_name);
  assert_int_equal(vlff_map_set_status(w, &s), -1);
  assert_int_equal(errno, EINVAL);
  assert_non_null(strstr(vlff_shm_last_message(), "state name"));

  /* Only the writer sets it. */
  fill(&s, 4);
  assert_int_equal(vlff_map_set_status(r, &s), -1);
  assert_int_equal(errno, EINVAL);
  assert_int_equal(vlff_map_set_status(NULL, &s), -1);
  assert_int_equal(vlff_map_get_status(r, NULL), -1);

  /* Nothing refused reached the readers. */
  assert_int_equal(vlff_map_get_status(r, &got), 0);
  assert_true(matches(&got, 3));
  assert_int_equal(got.updates, 1);
  vlff_map_detach(r);
  vlff_map_detach(w);
  vlff_shm_unlink(name);
}

/* A writer restarted on its segment (a take-over) does not inherit the dead
 * one's status: a controller must not read "iteration 303" from a node that
 * has not trained yet. The update count goes on. */
static void takeover_withdraws_status(void **state) {
  (void)state;
  struct vlff_map *w = make_map("status-takeover");
  struct vlff_map *r = vlff_map_attach(name);
  struct vlff_map_status s, got;
  fill(&s, 3);
  assert_int_equal(vlff_map_set_status(w, &s), 0);
  assert_int_equal(vlff_map_set_status(w, &s), 0);
  vlff_map_detach(w);
  assert_int_equal(vlff_map_get_status(r, &got), 0); /* the writer gone: its last status stays */
  assert_true(matches(&got, 3));
  w = vlff_map_create(name, &(struct vlff_map_params){.max_voxels = 64}); /* this process is the creator */
  assert_non_null(w);
  assert_int_equal(vlff_map_generation(r), 2);
  memset(&got, 0xab, sizeof got);
  assert_int_equal(vlff_map_get_status(r, &got), -1);
  assert_int_equal(errno, ENOENT);
  assert_int_equal(got.iterations, 0);
  fill(&s, 4);
  assert_int_equal(vlff_map_set_status(w, &s), 0);
  assert_int_equal(vlff_map_get_status(r, &got), 0);
  assert_true(matches(&got, 4));
  assert_int_equal(got.updates, 3);
  vlff_map_detach(r);
  vlff_map_detach(w);
  vlff_shm_unlink(name);
}

/* The block as anyone with write access to the file could leave it. */
static uint8_t *map_block(int *fd) {
  char path[128];
  snprintf(path, sizeof path, "/dev/shm%s", name);
  *fd = open(path, O_RDWR);
  assert_true(*fd >= 0);
  void *p = mmap(NULL, 4096, PROT_READ | PROT_WRITE, MAP_SHARED, *fd, 0);
  assert_true(p != MAP_FAILED);
  return (uint8_t *)p + STATUS_OFFSET;
}

static void forged_blocks_not_trusted(void **state) {
  (void)state;
  struct vlff_map *w = make_map("status-forged");
  struct vlff_map *r = vlff_map_attach(name);
  struct vlff_map_status s, got;
  fill(&s, 16);
  assert_int_equal(vlff_map_set_status(w, &s), 0);
  int fd;
  uint8_t *blk = map_block(&fd);
  struct vlff_map_status *raw = (struct vlff_map_status *)(blk + 64);
  _Atomic uint64_t *seq = (_Atomic uint64_t *)blk;

  /* Names and the state without their NUL: read back terminated. */
  memset(raw->state_name, 'z', sizeof raw->state_name);
  memset(raw->reason[15].name, 'q', sizeof raw->reason[15].name);
  assert_int_equal(vlff_map_get_status(r, &got), 0);
  assert_int_equal(strlen(got.state_name), VLFF_SHM_STATE_LEN - 1);
  assert_int_equal(strlen(got.reason[15].name), VLFF_SHM_REASON_LEN - 1);

  /* More reasons than the block holds: refused, not read past. */
  raw->reason_count = 1000;
  assert_int_equal(vlff_map_get_status(r, &got), -1);
  assert_int_equal(errno, EBADMSG);
  assert_non_null(strstr(vlff_shm_last_message(), "1000 reasons"));

  /* A writer that died mid-write left the word odd: readers give up after their
   * retries rather than read it; the next writer goes on from it. */
  atomic_store(seq, atomic_load(seq) | 1);
  assert_int_equal(vlff_map_get_status(r, &got), -1);
  assert_int_equal(errno, EAGAIN);
  fill(&s, 5);
  assert_int_equal(vlff_map_set_status(w, &s), 0);
  assert_int_equal(atomic_load(seq) & 1, 0);
  assert_int_equal(vlff_map_get_status(r, &got), 0);
  assert_true(matches(&got, 5));

  munmap(blk - STATUS_OFFSET, 4096);
  close(fd);
  vlff_map_detach(r);
  vlff_map_detach(w);
  vlff_shm_unlink(name);
}

/* ---- torn reads ---- */

static void *writer(void *arg) {
  struct vlff_map *w = arg;
  struct vlff_map_status s;
  uint64_t *done = calloc(1, sizeof *done);
  for (uint64_t k = 1; !atomic_load(&stop); k++) {
    fill(&s, k);
    if (vlff_map_set_status(w, &s) != 0)
      return done;
    *done = k;
  }
  return done;
}

struct reader_res {
  uint64_t reads, bad, backwards, busy;
};

static void *reader(void *arg) {
  struct reader_res *res = arg;
  struct vlff_map *m = vlff_map_attach(name);
  if (!m) {
    res->bad++;
    return NULL;
  }
  uint64_t last_k = 0, last_updates = 0;
  struct vlff_map_status got;
  while (!atomic_load(&stop) || res->reads < 20) {
    if (vlff_map_get_status(m, &got) != 0) {
      if (errno == EAGAIN)
        res->busy++; /* a writer this fast may outrun a reader: never a torn result */
      else if (errno != ENOENT)
        res->bad++;
      continue;
    }
    res->reads++;
    uint64_t k = k_of(&got);
    if (!matches(&got, k) || got.updates != k)
      res->bad++;
    if (k < last_k || got.updates < last_updates)
      res->backwards++;
    last_k = k;
    last_updates = got.updates;
  }
  vlff_map_detach(m);
  return NULL;
}

static void reads_never_torn(void **state) {
  (void)state;
  struct vlff_map *w = make_map("status-stress");
  enum { READERS = 3 };
  pthread_t wt, rt[READERS];
  struct reader_res res[READERS] = {{0}};
  atomic_store(&stop, 0);
  assert_int_equal(pthread_create(&wt, NULL, writer, w), 0);
  for (int i = 0; i < READERS; i++)
    assert_int_equal(pthread_create(&rt[i], NULL, reader, &res[i]), 0);
  nanosleep(&(struct timespec){1, 0}, NULL);
  atomic_store(&stop, 1);
  for (int i = 0; i < READERS; i++)
    pthread_join(rt[i], NULL);
  void *done;
  pthread_join(wt, &done);
  assert_non_null(done);
  print_message("writer set %llu statuses\n", (unsigned long long)*(uint64_t *)done);
  for (int i = 0; i < READERS; i++) {
    print_message("reader %d: %llu reads verified, %llu gave up on a busy writer\n", i,
                  (unsigned long long)res[i].reads, (unsigned long long)res[i].busy);
    assert_int_equal(res[i].bad, 0);
    assert_int_equal(res[i].backwards, 0);
    assert_true(res[i].reads >= 20);
  }
  assert_true(*(uint64_t *)done > 20);
  free(done);
  vlff_map_detach(w);
  vlff_shm_unlink(name);
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(set_and_read_back), cmocka_unit_test(malformed_status_refused), cmocka_unit_test(takeover_withdraws_status),
    cmocka_unit_test(forged_blocks_not_trusted), cmocka_unit_test(reads_never_torn))
