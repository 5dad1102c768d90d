/* Helpers shared by the shm tests: unique segment names and a payload whose every
 * byte depends on the record number, so a torn or misplaced record cannot verify. */
#ifndef SHM_TEST_UTIL_H
#define SHM_TEST_UTIL_H

#include "vlff/shm.h"

#include <fcntl.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>
#include <sys/file.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

static inline void test_name(char *buf, size_t len, const char *what) {
  static int counter;
  snprintf(buf, len, "/vlff-test-%s-%d-%d", what, (int)getpid(), counter++);
}

static inline uint64_t mix64(uint64_t x) {
  x ^= x >> 33;
  x *= 0xff51afd7ed558ccdull;
  x ^= x >> 33;
  x *= 0xc4ceb9fe1a85ec53ull;
  return x ^ (x >> 33);
}

/* Record: [id][len][payload...][checksum], len derived from id. */
struct test_rec_hdr {
  uint64_t id;
  uint64_t len;
};

static inline size_t test_rec_len(uint64_t id, size_t max) {
  size_t min = 32, l = min + (size_t)(mix64(id) % (max - min + 1));
  l &= ~(size_t)7;
  return l < min ? min : l;
}

static inline void test_rec_fill(uint8_t *p, uint64_t id, size_t len) {
  struct test_rec_hdr h = {id, len};
  memcpy(p, &h, sizeof h);
  uint64_t sum = 0, x = id;
  for (size_t o = sizeof h; o + 8 <= len - 8; o += 8) {
    x = mix64(x + o);
    memcpy(p + o, &x, 8);
    sum = sum * 31 + x;
  }
  sum ^= id;
  memcpy(p + len - 8, &sum, 8);
}

/* 0 if p holds exactly record id of length len. */
static inline int test_rec_check(const uint8_t *p, size_t len, uint64_t id) {
  struct test_rec_hdr h;
  if (len < sizeof h + 8)
    return -1;
  memcpy(&h, p, sizeof h);
  if (h.id != id || h.len != len)
    return -1;
  uint64_t sum = 0, x = id, v;
  for (size_t o = sizeof h; o + 8 <= len - 8; o += 8) {
    x = mix64(x + o);
    memcpy(&v, p + o, 8);
    if (v != x)
      return -1;
    sum = sum * 31 + x;
  }
  sum ^= id;
  memcpy(&v, p + len - 8, 8);
  return v == sum ? 0 : -1;
}

/* A segment's whole file mapped read-write, as a process with write access to it
 * (a hostile one, or a test playing one) sees it. */
struct shm_raw {
  int fd;
  uint8_t *base;
  size_t size;
};

/* 0, or -1 with errno. */
static inline int shm_raw_open(const char *name, struct shm_raw *r) {
  struct stat st;
  r->fd = shm_open(name, O_RDWR, 0);
  if (r->fd < 0)
    return -1;
  if (fstat(r->fd, &st) < 0 ||
      (r->size = (size_t)st.st_size,
       (r->base = mmap(NULL, r->size, PROT_READ | PROT_WRITE, MAP_SHARED, r->fd, 0)) == MAP_FAILED)) {
    close(r->fd);
    return -1;
  }
  return 0;
}

static inline void shm_raw_close(struct shm_raw *r) {
  munmap(r->base, r->size);
  close(r->fd);
}

/* The prompt mailbox's layout as a hostile poster sees it (shm/prompts.c): the
 * control block (sequence word, odd while a post is written, and the poster's pid)
 * and the request body. */
#define MBOX_CTL_OFF 128
#define MBOX_BODY_OFF 256
struct mbox_raw_ctl {
  uint64_t seq;
  int32_t lock_pid;
};

/* Writes req into the mailbox mapped at base (descriptor fd) with the library's
 * protocol (lock, odd word, body, even word) but without its checks: what a poster
 * that bypasses libvlff-shm can leave for the learner. 0, or -1 if the lock fails. */
static inline int mbox_raw_post(int fd, uint8_t *base, const struct vlff_prompt_request *req) {
  if (flock(fd, LOCK_EX) < 0)
    return -1;
  volatile struct mbox_raw_ctl *c = (volatile struct mbox_raw_ctl *)(base + MBOX_CTL_OFF);
  uint64_t odd = c->seq | 1;
  __atomic_store_n(&c->seq, odd, __ATOMIC_RELEASE);
  struct vlff_prompt_request q = *req;
  q.seq = (odd + 1) / 2;
  q.poster_pid = getpid();
  memcpy(base + MBOX_BODY_OFF, &q, sizeof q);
  __atomic_store_n(&c->seq, odd + 1, __ATOMIC_RELEASE);
  flock(fd, LOCK_UN);
  return 0;
}

#endif
