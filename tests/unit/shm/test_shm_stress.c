/* Multi-process ring stress: one producer process, three consumer processes (one of
 * them deliberately slow so that it is lapped), >= 10^6 records of varying length
 * with payloads derived from the record number. Every accepted record must verify,
 * record numbers must only go up, and for every consumer "delivered + lost" must
 * account for every record number exactly, checked after each read and at the end.
 * VLFF_SHM_STRESS_FRAMES overrides the count (the TSan build defaults to fewer). */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <cmocka.h>

#include "shm_test_util.h"
#include "unit.h"

#include <errno.h>
#include <signal.h>
#include <stdlib.h>
#include <sys/wait.h>
#include <time.h>

#if defined(__SANITIZE_THREAD__) || defined(__SANITIZE_ADDRESS__)
#define DEFAULT_FRAMES 200000
#else
#define DEFAULT_FRAMES 1000000
#endif
#define SLOT 512
#define NCONS 3

struct cons_result {
  uint64_t delivered, lost, bad, reordered, accounting, last_seq;
};

static uint64_t frames(void) {
  const char *e = getenv("VLFF_SHM_STRESS_FRAMES");
  return e && atoll(e) > 0 ? (uint64_t)atoll(e) : DEFAULT_FRAMES;
}

static void consumer(const char *name, int idx, uint64_t total, int out_fd) {
  struct vlff_ring *r = vlff_ring_attach(name, VLFF_RECORD_RAW);
  struct cons_result res = {0};
  if (!r)
    _exit(10);
  /* The producer waits for all consumers to attach, so every consumer starts at 0. */
  (void)!write(out_fd, &res, sizeof res);
  uint8_t buf[SLOT];
  uint64_t expect = 0;
  while (expect < total) {
    struct vlff_ring_view v;
    if (vlff_ring_read_begin(r, &v, 5000000000ull) < 0)
      _exit(11); /* 5 s without a record: the producer is gone */
    memcpy(buf, v.data, v.len < SLOT ? v.len : SLOT);
    size_t len = v.len;
    uint64_t lost_before = vlff_ring_lost(r);
    int ok = vlff_ring_read_end(r, &v) == 0;
    uint64_t lost = vlff_ring_lost(r);
    if (!ok) {
      if (lost != lost_before + 1)
        res.accounting++;
      res.lost = lost;
      expect = v.seq + 1;
      continue;
    }
    if (v.seq < expect)
      res.reordered++;
    /* Every record number skipped since the previous delivery was counted as lost. */
    if (v.seq - expect != lost - (res.lost))
      res.accounting++;
    res.lost = lost;
    if (test_rec_check(buf, len, v.seq) != 0)
      res.bad++;
    res.delivered++;
    res.last_seq = v.seq;
    expect = v.seq + 1;
    if (idx == NCONS - 1 && res.delivered % 2000 == 0)
      nanosleep(&(struct timespec){0, 1000000}, NULL); /* the slow one */
  }
  res.lost = vlff_ring_lost(r);
  if (res.delivered + res.lost != total)
    res.accounting++;
  (void)!write(out_fd, &res, sizeof res);
  vlff_ring_close(r);
  _exit(0);
}

static void stress_1_producer_3_consumers(void **state) {
  (void)state;
  char name[64];
  test_name(name, sizeof name, "stress");
  uint64_t total = frames();
  struct vlff_ring_params p = {.record_kind = VLFF_RECORD_RAW, .slots = 8, .slot_size = SLOT};
  struct vlff_ring *w = vlff_ring_create(name, &p);
  assert_non_null(w);
  int fds[NCONS][2];
  pid_t pids[NCONS];
  for (int i = 0; i < NCONS; i++) {
    assert_int_equal(pipe(fds[i]), 0);
    pids[i] = fork();
    assert_true(pids[i] >= 0);
    if (pids[i] == 0) {
      vlff_ring_close(w);
      consumer(name, i, total, fds[i][1]);
    }
    close(fds[i][1]);
    struct cons_result hello;
    assert_int_equal(read(fds[i][0], &hello, sizeof hello), (ssize_t)sizeof hello);
  }
  uint64_t t0 = vlff_shm_now_ns();
  for (uint64_t id = 0; id < total; id++) {
    size_t len = test_rec_len(id, SLOT);
    uint64_t seq;
    uint8_t *s = vlff_ring_reserve(w, &seq);
    assert_true(s && seq == id);
    test_rec_fill(s, id, len);
    if (vlff_ring_commit(w, len) != 0)
      fail_msg("commit %llu failed", (unsigned long long)id);
  }
  double secs = (double)(vlff_shm_now_ns() - t0) / 1e9;
  uint64_t sum_lost = 0;
  for (int i = 0; i < NCONS; i++) {
    struct cons_result res;
    ssize_t n = read(fds[i][0], &res, sizeof res);
    int st;
    waitpid(pids[i], &st, 0);
    assert_true(WIFEXITED(st));
    assert_int_equal(WEXITSTATUS(st), 0);
    assert_int_equal(n, (ssize_t)sizeof res);
    print_message("consumer %d: delivered %llu lost %llu bad %llu reordered %llu accounting %llu\n", i,
                  (unsigned long long)res.delivered, (unsigned long long)res.lost, (unsigned long long)res.bad,
                  (unsigned long long)res.reordered, (unsigned long long)res.accounting);
    assert_int_equal(res.bad, 0);
    assert_int_equal(res.reordered, 0);
    assert_int_equal(res.accounting, 0);
    assert_int_equal(res.delivered + res.lost, total);
    assert_true(res.delivered > 0);
    sum_lost += res.lost;
    close(fds[i][0]);
  }
  print_message("%llu records in %.2f s\n", (unsigned long long)total, secs);
  /* The slow consumer sleeps 1 ms every 2000 records while the producer never waits. */
  assert_true(sum_lost > 0);
  vlff_ring_close(w);
  vlff_shm_unlink(name);
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(stress_1_producer_3_consumers))
