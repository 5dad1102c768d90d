/* The seed corpus of fuzz_shm_header against this library: every checked-in seed
 * (tests/fuzz/seeds/shm_header/) must still pass the header checks (magic, ABI
 * version, checksum, kind) and get as far into the readers as it was made to, or
 * the fuzzer spends its time on inputs refused at the first check. A seed written
 * for an older ABI fails here with the command that writes new ones. The same
 * checks run on a fresh output of the generator (tests/fuzz/gen_shm_seeds.c). */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <cmocka.h>

#include "shm_test_util.h"
#include "unit.h"

#include <dirent.h>
#include <errno.h>
#include <fcntl.h>
#include <stdlib.h>
#include <sys/mman.h>
#include <sys/wait.h>

#define REGENERATE "regenerate them: gen_shm_seeds " VLFF_SHM_SEEDS

/* The segment of the seed being checked, removed after each test even when a
 * check failed. */
static char cur[64];

static int remove_cur(void **state) {
  (void)state;
  if (cur[0])
    vlff_shm_unlink(cur);
  cur[0] = 0;
  return 0;
}

/* Loads path into a new segment, as the fuzzer does. */
static void load(const char *path, const char *name) {
  FILE *f = fopen(path, "rb");
  if (!f)
    fail_msg("%s: %s", path, strerror(errno));
  static uint8_t buf[1 << 20];
  size_t n = fread(buf, 1, sizeof buf, f);
  fclose(f);
  int fd = shm_open(name, O_RDWR | O_CREAT | O_EXCL, 0600);
  assert_true(fd >= 0);
  snprintf(cur, sizeof cur, "%s", name);
  assert_int_equal(write(fd, buf, n), (ssize_t)n);
  close(fd);
}

static void check_map(const char *name) {
  struct vlff_map *m = vlff_map_attach(name);
  assert_non_null(m);
  assert_true(vlff_map_version(m) >= 1);
  uint16_t label;
  assert_int_equal(vlff_map_label_at(m, 0.1, 0.1, 0.1, &label, NULL), 0);
  assert_true(label <= VLFF_LABEL_MAX);
  char text[VLFF_SHM_PROMPT_LEN];
  assert_int_equal(vlff_map_prompt(m, label, text, sizeof text), 0);
  struct vlff_map_snapshot *s = vlff_map_snapshot_new(m);
  struct vlff_map_info info;
  assert_int_equal(vlff_map_snapshot_take(m, s), 0);
  assert_int_equal(vlff_map_snapshot_info(s, &info), 0);
  assert_true(info.has_label_image);
  vlff_map_snapshot_free(s);
  struct vlff_map_status st;
  assert_int_equal(vlff_map_get_status(m, &st), 0);
  assert_true(st.reason_count > 0);
  vlff_map_detach(m);
}

/* Past the header; the map readers refuse its metadata. */
static void check_dims_overflow(const char *name) {
  struct vlff_map *m = vlff_map_attach(name);
  assert_non_null(m);
  uint16_t label;
  assert_int_equal(vlff_map_label_at(m, 0.1, 0.1, 0.1, &label, NULL), -1);
  assert_int_equal(errno, EBADMSG);
  struct vlff_map_snapshot *s = vlff_map_snapshot_new(m);
  assert_int_equal(vlff_map_snapshot_take(m, s), -1);
  assert_int_equal(errno, EBADMSG);
  vlff_map_snapshot_free(s);
  vlff_map_detach(m);
}

/* The mailbox attached as a poster, and what its first poll gives. */
static struct vlff_prompts *poll_mailbox(const char *name, int want, struct vlff_prompt_request *req) {
  struct vlff_prompts *p = vlff_prompts_attach(name);
  assert_non_null(p);
  uint64_t last = 0;
  int got = vlff_prompts_poll(p, &last, req), e = errno;
  if (got != want)
    fail_msg("%s: poll gave %d, expected %d (%s)", name, got, want, vlff_shm_last_message());
  errno = e;
  return p;
}

/* A pending request of texts, and answers to earlier ones. */
static void check_prompts(const char *name) {
  struct vlff_prompt_request req;
  struct vlff_prompts *p = poll_mailbox(name, 1, &req);
  assert_int_equal(req.set_index, -1);
  assert_true(req.count >= 1);
  char why[128];
  assert_int_equal(vlff_prompts_wait_answer(p, 1, 0, why, sizeof why), VLFF_PROMPT_ACCEPTED);
  assert_int_equal(vlff_prompts_wait_answer(p, 2, 0, why, sizeof why), VLFF_PROMPT_REFUSED);
  assert_true(why[0]);
  vlff_prompts_close(p);
}

/* A poster sees a post in progress; a learner taking the mailbox over discards it. */
static void check_dead_poster(const char *name) {
  struct vlff_prompt_request req;
  vlff_prompts_close(poll_mailbox(name, 0, &req));
  struct vlff_prompts *learner = vlff_prompts_create(name, NULL);
  if (!learner)
    fail_msg("taking the mailbox over: %s", vlff_shm_last_message());
  uint64_t last = 0;
  assert_int_equal(vlff_prompts_poll(learner, &last, &req), -1);
  assert_int_equal(errno, EBADMSG);
  assert_non_null(strstr(vlff_shm_last_message(), "left half-written by poster pid 1"));
  vlff_prompts_close(learner);
}

static void check_forged(const char *name) {
  struct vlff_prompt_request req;
  struct vlff_prompts *p = poll_mailbox(name, -1, &req);
  assert_int_equal(errno, EBADMSG);
  assert_non_null(strstr(vlff_shm_last_message(), "without control characters"));
  vlff_prompts_close(p);
}

/* The ring attached as a consumer; the producer lapped it. */
static struct vlff_ring *attach_lapped(const char *name, uint32_t kind) {
  struct vlff_ring *r = vlff_ring_attach(name, kind);
  assert_non_null(r);
  assert_true(vlff_ring_head(r) > vlff_ring_slots(r));
  return r;
}

/* The slots hold the newest frames, all well-formed. */
static void check_ring_frame(const char *name) {
  struct vlff_ring *r = attach_lapped(name, VLFF_RECORD_FRAME);
  vlff_ring_seek_oldest(r);
  static uint8_t rec[1 << 16];
  struct vlff_ring_view v;
  for (uint32_t i = 0; i < vlff_ring_slots(r); i++) {
    ssize_t n = vlff_ring_read_copy(r, rec, sizeof rec, &v, 0);
    assert_true(n > 0);
    assert_int_equal(vlff_frame_validate(rec, (size_t)n), 0);
  }
  vlff_ring_close(r);
}

static void check_ring_pose(const char *name) {
  struct vlff_ring *r = attach_lapped(name, VLFF_RECORD_POSE);
  struct vlff_pose_rec newest, at;
  assert_int_equal(vlff_ring_read_latest(r, &newest, sizeof newest, NULL), (ssize_t)sizeof newest);
  assert_int_equal(vlff_pose_lookup(r, newest.t_ns, 0, &at), 0);
  assert_memory_equal(at.pose, newest.pose, sizeof at.pose);
  vlff_ring_close(r);
}

static const struct {
  const char *seed;
  uint32_t kind, record_kind;
  void (*check)(const char *name);
} seeds[] = {
  {"map", VLFF_SHM_KIND_MAP, 0, check_map},
  {"regress-dims-overflow", VLFF_SHM_KIND_MAP, 0, check_dims_overflow},
  {"prompts", VLFF_SHM_KIND_PROMPTS, 0, check_prompts},
  {"prompts-dead-poster", VLFF_SHM_KIND_PROMPTS, 0, check_dead_poster},
  {"prompts-forged", VLFF_SHM_KIND_PROMPTS, 0, check_forged},
  {"ring_frame", VLFF_SHM_KIND_RING, VLFF_RECORD_FRAME, check_ring_frame},
  {"ring_pose", VLFF_SHM_KIND_RING, VLFF_RECORD_POSE, check_ring_pose},
};
#define NSEEDS (sizeof seeds / sizeof seeds[0])

/* Every file of dir is a seed above, every seed above is in dir, and each passes
 * the header checks and its own. */
static void check_dir(const char *dir) {
  DIR *d = opendir(dir);
  if (!d)
    fail_msg("%s: %s", dir, strerror(errno));
  int found[NSEEDS] = {0};
  struct dirent *e;
  while ((e = readdir(d))) {
    if (e->d_name[0] == '.')
      continue;
    size_t i = 0;
    while (i < NSEEDS && strcmp(seeds[i].seed, e->d_name))
      i++;
    if (i == NSEEDS)
      fail_msg("%s/%s: a seed without a check in test_shm_seeds.c; add one", dir, e->d_name);
    found[i] = 1;
  }
  closedir(d);
  for (size_t i = 0; i < NSEEDS; i++) {
    if (!found[i])
      fail_msg("%s/%s: missing; " REGENERATE, dir, seeds[i].seed);
    char path[4096], name[64];
    snprintf(path, sizeof path, "%s/%s", dir, seeds[i].seed);
    test_name(name, sizeof name, "seed");
    load(path, name);
    struct vlff_shm_info info;
    if (vlff_shm_stat(name, &info) < 0)
      fail_msg("%s: refused at the header (%s); " REGENERATE, path, vlff_shm_last_message());
    if (info.abi_version != VLFF_SHM_ABI_VERSION || info.kind != seeds[i].kind ||
        (seeds[i].record_kind && info.record_kind != seeds[i].record_kind))
      fail_msg("%s: ABI %u kind %u record kind %u, expected ABI %u kind %u record kind %u; " REGENERATE, path,
               info.abi_version, info.kind, info.record_kind, VLFF_SHM_ABI_VERSION, seeds[i].kind,
               seeds[i].record_kind);
    print_message("%s: kind %u, ABI %u\n", seeds[i].seed, info.kind, info.abi_version);
    seeds[i].check(name);
    remove_cur(NULL);
  }
}

static void test_checked_in_seeds(void **state) {
  (void)state;
  check_dir(VLFF_SHM_SEEDS);
}

static void test_generated_seeds(void **state) {
  (void)state;
  char dir[] = "/tmp/vlff-seeds-XXXXXX";
  assert_non_null(mkdtemp(dir));
  char prog[4096], cmd[4200];
  snprintf(cmd, sizeof cmd, "%s %s >/dev/null", vlff_test_prog(prog, sizeof prog, "tests/fuzz/gen_shm_seeds"), dir);
  int st = system(cmd);
  assert_true(WIFEXITED(st) && WEXITSTATUS(st) == 0);
  check_dir(dir);
  snprintf(cmd, sizeof cmd, "rm -rf %s", dir);
  assert_int_equal(system(cmd), 0);
}

VLFF_UNIT_MAIN(NULL, NULL, cmocka_unit_test_teardown(test_checked_in_seeds, remove_cur),
               cmocka_unit_test_teardown(test_generated_seeds, remove_cur))
