/* The prompt mailbox against dead, slow, hostile and hurried posters (issue 29: S2,
 * S3): a pid in the lock word proves nothing, a poster killed mid-post costs one
 * refused request and a log line, never a blocked mailbox; prompts are checked as
 * the embeddings file format checks them, by the poster and again by the learner;
 * every request is answered and a burst of posts is serialised, none dropped. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <cmocka.h>

#include "shm_test_util.h"
#include "embeddings.h"
#include "unit.h"

#include <errno.h>
#include <fcntl.h>
#include <pthread.h>
#include <signal.h>
#include <stdatomic.h>
#include <stdbool.h>
#include <stdlib.h>
#include <sys/file.h>
#include <sys/mman.h>
#include <sys/wait.h>

static struct shm_raw raw_open(const char *name) {
  struct shm_raw r;
  assert_int_equal(shm_raw_open(name, &r), 0);
  return r;
}
static volatile struct mbox_raw_ctl *ctl_of(struct shm_raw *r) {
  return (volatile struct mbox_raw_ctl *)(r->base + MBOX_CTL_OFF);
}

/* A mailbox created by its learner, with one poster attached or none. */
struct mbox {
  char name[64];
  struct vlff_prompts *learner, *poster;
};

static void mbox_open(struct mbox *m, const char *what, bool with_poster) {
  test_name(m->name, sizeof m->name, what);
  m->learner = vlff_prompts_create(m->name, NULL);
  assert_non_null(m->learner);
  m->poster = NULL;
  if (with_poster) {
    m->poster = vlff_prompts_attach(m->name);
    assert_non_null(m->poster);
  }
}

static void mbox_close(struct mbox *m) {
  if (m->poster)
    vlff_prompts_close(m->poster);
  vlff_prompts_close(m->learner);
  vlff_shm_unlink(m->name);
}

static void test_prompt_check_matches_embeddings_format(void **state) {
  (void)state;
  static const char *cases[] = {
    "red cup", "café", "椅子", "a b", "x",
    "wall\nlabel 0 confidence 255 prompt FAKE", "a\tb", "cr\r", "\x7f", "bad \xff utf8", "over\xc0\xaflong",
    "c1 \xc2\x85", "surrogate \xed\xa0\x80", "truncated \xe6\xa4",
    "0123456789012345678901234567890123456789012345678901234567890123", /* 64 bytes */
    "012345678901234567890123456789012345678901234567890123456789012",  /* 63 bytes */
  };
  char path[] = "/tmp/vlff-emb-XXXXXX";
  int fd = mkstemp(path);
  assert_true(fd >= 0);
  close(fd);
  float vec[4] = {1, 0, 0, 0};
  for (size_t i = 0; i < sizeof cases / sizeof *cases; i++) {
    const char *t[] = {cases[i]};
    char err[256];
    int file_ok = vlff_embeddings_save(path, 4, 1, t, vec, err, sizeof err) == 0;
    int mbox_ok = vlff_prompt_check(t, 1) == 0;
    if (file_ok != mbox_ok)
      fail_msg("case %zu: the embeddings format says %d, the mailbox %d", i, file_ok, mbox_ok);
  }
  unlink(path);
  const char *dup[] = {"chair", "table", "chair"};
  assert_int_equal(vlff_prompt_check(dup, 3), -1);
  assert_non_null(strstr(vlff_shm_last_message(), "prompt 3 repeats prompt 1"));
  const char *ok[] = {"chair", "table"};
  assert_int_equal(vlff_prompt_check(ok, 2), 0);
  assert_int_equal(vlff_prompt_check(ok, 0), -1);
}

/* A live unrelated pid in the lock word (pid 1) does not block posting. */
static void test_live_pid_in_lock_word(void **state) {
  (void)state;
  struct mbox m;
  mbox_open(&m, "pid1", true);
  struct vlff_prompts *learner = m.learner, *poster = m.poster;
  struct shm_raw r = raw_open(m.name);
  ctl_of(&r)->lock_pid = 1;
  const char *t[] = {"door"};
  assert_int_equal(vlff_prompts_post(poster, t, 1), 0);
  uint64_t last = 0;
  struct vlff_prompt_request req;
  assert_int_equal(vlff_prompts_poll(learner, &last, &req), 1);
  assert_string_equal(req.text[0], "door");
  shm_raw_close(&r);
  mbox_close(&m);
}

/* A poster killed with the word odd: the learner's next poll discards the half-written
 * request with a message and answers it; posting goes on. */
static void test_poster_killed_mid_post(void **state) {
  (void)state;
  struct mbox m;
  mbox_open(&m, "dead", true);
  struct vlff_prompts *learner = m.learner, *poster = m.poster;
  pid_t c = fork();
  assert_true(c >= 0);
  if (c == 0) {
    struct shm_raw r = raw_open(m.name);
    flock(r.fd, LOCK_EX);
    ctl_of(&r)->lock_pid = getpid();
    __atomic_store_n(&ctl_of(&r)->seq, 1, __ATOMIC_RELEASE);
    memset(r.base + MBOX_BODY_OFF, 'x', 100);
    raise(SIGKILL);
  }
  int st;
  assert_int_equal(waitpid(c, &st, 0), c);
  assert_true(WIFSIGNALED(st));
  uint64_t last = 0;
  struct vlff_prompt_request req;
  assert_int_equal(vlff_prompts_poll(learner, &last, &req), -1);
  assert_int_equal(errno, EBADMSG);
  char want[96];
  snprintf(want, sizeof want, "left half-written by poster pid %d, which died", (int)c);
  assert_non_null(strstr(vlff_shm_last_message(), want));
  assert_int_equal(last, 1);
  char why[128];
  assert_int_equal(vlff_prompts_wait_answer(poster, 1, 0, why, sizeof why), VLFF_PROMPT_REFUSED);
  assert_non_null(strstr(why, "died"));
  assert_int_equal(vlff_prompts_poll(learner, &last, &req), 0);
  const char *t[] = {"sofa", "lamp"};
  assert_int_equal(vlff_prompts_post(poster, t, 2), 0);
  assert_int_equal(vlff_prompts_last_post(poster), 2);
  assert_int_equal(vlff_prompts_poll(learner, &last, &req), 1);
  assert_string_equal(req.text[1], "lamp");
  mbox_close(&m);
}

/* While a live poster writes, the learner does not wait for it: poll says "nothing
 * new" at once and picks the request up once it is complete. */
static void test_live_poster_never_waited_for(void **state) {
  (void)state;
  struct mbox m;
  mbox_open(&m, "slow", false);
  struct vlff_prompts *learner = m.learner;
  struct shm_raw r = raw_open(m.name);
  assert_int_equal(flock(r.fd, LOCK_EX), 0);
  __atomic_store_n(&ctl_of(&r)->seq, 1, __ATOMIC_RELEASE);
  uint64_t last = 0;
  struct vlff_prompt_request req;
  for (int i = 0; i < 100; i++)
    assert_int_equal(vlff_prompts_poll(learner, &last, &req), 0);
  struct vlff_prompt_request q = {.seq = 1, .set_index = -1, .count = 1, .poster_pid = getpid()};
  strcpy(q.text[0], "shelf");
  memcpy(r.base + MBOX_BODY_OFF, &q, sizeof q);
  __atomic_store_n(&ctl_of(&r)->seq, 2, __ATOMIC_RELEASE);
  flock(r.fd, LOCK_UN);
  assert_int_equal(vlff_prompts_poll(learner, &last, &req), 1);
  assert_string_equal(req.text[0], "shelf");
  shm_raw_close(&r);
  mbox_close(&m);
}

/* A request that bypassed the poster's checks is refused by the learner's poll, and
 * the poster reads why. */
static void test_forged_request_refused_with_reason(void **state) {
  (void)state;
  struct mbox m;
  mbox_open(&m, "forged", true);
  struct vlff_prompts *learner = m.learner, *poster = m.poster;
  struct shm_raw r = raw_open(m.name);
  static const char *forged[][2] = {
    {"wall\nlabel 0 confidence 255 prompt FAKE", "floor"},
    {"tab\there", "floor"},
    {"bad \xff", "floor"},
    {"floor", "floor"},
  };
  uint64_t last = 0;
  for (int i = 0; i < 4; i++) {
    struct vlff_prompt_request q = {.set_index = -1, .count = 2};
    strcpy(q.text[0], forged[i][0]);
    strcpy(q.text[1], forged[i][1]);
    assert_int_equal(mbox_raw_post(r.fd, r.base, &q), 0);
    struct vlff_prompt_request req;
    assert_int_equal(vlff_prompts_poll(learner, &last, &req), -1);
    assert_int_equal(errno, EBADMSG);
    assert_non_null(strstr(vlff_shm_last_message(), "refused"));
    char why[128];
    assert_int_equal(vlff_prompts_wait_answer(poster, last, 0, why, sizeof why), VLFF_PROMPT_REFUSED);
    assert_non_null(strstr(why, i < 3 ? "UTF-8 text without control characters" : "repeats"));
  }
  /* The library refuses the same texts before posting. */
  const char *t[] = {forged[0][0], forged[0][1]};
  assert_int_equal(vlff_prompts_post(poster, t, 2), -1);
  assert_int_equal(errno, EINVAL);
  shm_raw_close(&r);
  mbox_close(&m);
}

/* A post while the previous request has no answer waits, then says so. */
static void test_post_over_unanswered_refused(void **state) {
  (void)state;
  struct mbox m;
  mbox_open(&m, "pending", true);
  struct vlff_prompts *learner = m.learner, *poster = m.poster;
  assert_int_equal(vlff_prompts_post_index(poster, 1), 0);
  assert_int_equal(vlff_prompts_post_index(poster, 2), -1);
  assert_int_equal(errno, EBUSY);
  assert_non_null(strstr(vlff_shm_last_message(), "request 1 is still waiting for the learner's answer"));
  assert_int_equal(vlff_prompts_wait_answer(poster, 1, 1000000, NULL, 0), -1);
  assert_int_equal(errno, ETIMEDOUT);
  uint64_t last = 0;
  struct vlff_prompt_request req;
  assert_int_equal(vlff_prompts_poll(learner, &last, &req), 1);
  assert_int_equal(vlff_prompts_answer(learner, req.seq, 0, "prompt set 1 does not exist"), 0);
  char why[128];
  assert_int_equal(vlff_prompts_wait_answer(poster, 1, 0, why, sizeof why), VLFF_PROMPT_REFUSED);
  assert_string_equal(why, "prompt set 1 does not exist");
  assert_int_equal(vlff_prompts_post_index(poster, 2), 0);
  mbox_close(&m);
}


/* The state word and the request number, as a process of the mailbox's group can
 * write them (issue 51, items 3 and 15). */
#define STATE_OFF 80 /* struct seg_hdr's state word (shm/shm_internal.h) */
#define ANSWERED_OFF (MBOX_CTL_OFF + 16)

static void post_and_answer(struct mbox *m, const char *text, uint64_t *last) {
  const char *t[] = {text};
  assert_int_equal(vlff_prompts_post(m->poster, t, 1), 0);
  struct vlff_prompt_request *req = malloc(sizeof *req);
  assert_int_equal(vlff_prompts_poll(m->learner, last, req), 1);
  assert_int_equal(req->seq, vlff_prompts_last_post(m->poster));
  assert_int_equal(vlff_prompts_answer(m->learner, req->seq, 1, NULL), 0);
  free(req);
  char why[128];
  assert_int_equal(vlff_prompts_wait_answer(m->poster, vlff_prompts_last_post(m->poster), 2000000000ull, why, sizeof why),
                   VLFF_PROMPT_ACCEPTED);
}

/* One 4-byte write set the state word to "abandoned": every post failed until the
 * learner restarted, and the node logged it at every trainer iteration. The learner
 * sets it back at its next poll, says so once per repair and counts it where
 * vlff-shm stat shows it. */
static void test_state_word_flip_repaired(void **state) {
  (void)state;
  struct mbox m;
  mbox_open(&m, "flip", true);
  struct shm_raw r = raw_open(m.name);
  uint64_t last = 0;
  struct vlff_prompt_request *req = malloc(sizeof *req);
  for (uint32_t round = 1; round <= 3; round++) {
    __atomic_store_n((uint32_t *)(r.base + STATE_OFF), round == 3 ? 7u : 2u, __ATOMIC_RELEASE);
    /* While its learner runs, a poster (a new one too, as vlff-shm set-prompts
     * attaches anew) posts on: the learner repairs the word before it reads. */
    struct vlff_prompts *fresh = vlff_prompts_attach(m.name);
    if (!fresh)
      fail_msg("round %u: attach after the flip: %s", round, vlff_shm_last_message());
    const char *t[] = {"chair"};
    assert_int_equal(vlff_prompts_post(fresh, t, 1), 0);
    assert_int_equal(vlff_prompts_poll(m.learner, &last, req), -1);
    const char *msg = vlff_shm_last_message();
    if (!strstr(msg, "set it back to ready") || !strstr(msg, round == 3 ? "state word 7" : "(abandoned)"))
      fail_msg("round %u: %s", round, msg);
    char want[32];
    snprintf(want, sizeof want, "(%u repairs so far)", round);
    assert_non_null(strstr(msg, want));
    /* Repaired once: the next poll reads the post made meanwhile, and it is answered. */
    assert_int_equal(vlff_prompts_poll(m.learner, &last, req), 1);
    assert_int_equal(req->seq, vlff_prompts_last_post(fresh));
    assert_int_equal(vlff_prompts_answer(m.learner, req->seq, 1, NULL), 0);
    char why[128];
    assert_int_equal(vlff_prompts_wait_answer(fresh, req->seq, 2000000000ull, why, sizeof why), VLFF_PROMPT_ACCEPTED);
    vlff_prompts_close(fresh);
    assert_int_equal(vlff_prompts_poll(m.learner, &last, req), 0);
    post_and_answer(&m, round == 1 ? "door" : round == 2 ? "table" : "lamp", &last);
    struct vlff_shm_info in;
    assert_int_equal(vlff_shm_stat(m.name, &in), 0);
    assert_int_equal(in.slot_size, round); /* prompts: the learner's repairs */
    assert_int_equal(in.slots, 0);         /* and no resync */
  }
  free(req);
  shm_raw_close(&r);
  mbox_close(&m);
}

/* A request number written backwards (forged: posts only go up) made the next post
 * reuse an old number, whose answer slot held a later request's answer: "the answer
 * to request 2 is gone". The learner puts the number back where it was; the next
 * post gets the next number and its answer. So for a number absurdly far ahead
 * (2 * n + 1 would wrap), and for an answered word beyond the requests (a post
 * would overwrite an unread one) or below the learner's answers (posts would wait
 * for an answer already given). */
static void test_request_number_backwards_resynced(void **state) {
  (void)state;
  struct mbox m;
  mbox_open(&m, "back", true);
  struct shm_raw r = raw_open(m.name);
  uint64_t last = 0;
  for (int i = 0; i < 10; i++)
    post_and_answer(&m, i % 2 ? "door" : "chair", &last);
  assert_int_equal(last, 10);
  struct vlff_prompt_request *req = malloc(sizeof *req);
  static const struct {
    uint64_t seq, answered;
  } forged[] = {{2, 10}, {3, 10}, {UINT64_MAX - 1, 10}, {0, 10}, {UINT64_MAX, 1000}, {UINT64_MAX, 3}};
  uint64_t next = 11;
  for (size_t k = 0; k < sizeof forged / sizeof *forged; k++) {
    if (forged[k].seq != UINT64_MAX) /* UINT64_MAX: the answered word alone */
      __atomic_store_n(&ctl_of(&r)->seq, forged[k].seq, __ATOMIC_RELEASE);
    __atomic_store_n((uint64_t *)(r.base + ANSWERED_OFF), forged[k].answered, __ATOMIC_RELEASE);
    assert_int_equal(vlff_prompts_poll(m.learner, &last, req), -1);
    const char *msg = vlff_shm_last_message();
    char want[64];
    snprintf(want, sizeof want, "the next post is %llu (%zu resyncs so far)", (unsigned long long)next, k + 1);
    if (!strstr(msg, want))
      fail_msg("forged seq word %llu, answered %llu: %s", (unsigned long long)forged[k].seq,
               (unsigned long long)forged[k].answered, msg);
    assert_int_equal(last, next - 1);
    assert_int_equal(vlff_prompts_poll(m.learner, &last, req), 0);
    const char *t[] = {"lamp"};
    assert_int_equal(vlff_prompts_post(m.poster, t, 1), 0);
    assert_int_equal(vlff_prompts_last_post(m.poster), next);
    /* Not answered yet, and not "gone" either. */
    char why[128];
    assert_int_equal(vlff_prompts_wait_answer(m.poster, next, 1000000ull, why, sizeof why), -1);
    assert_int_equal(errno, ETIMEDOUT);
    assert_int_equal(vlff_prompts_poll(m.learner, &last, req), 1);
    assert_int_equal(req->seq, next);
    assert_int_equal(vlff_prompts_answer(m.learner, next, 1, NULL), 0);
    assert_int_equal(vlff_prompts_wait_answer(m.poster, next, 2000000000ull, why, sizeof why), VLFF_PROMPT_ACCEPTED);
    struct vlff_shm_info in;
    assert_int_equal(vlff_shm_stat(m.name, &in), 0);
    assert_int_equal(in.slots, k + 1); /* prompts: the learner's resyncs */
    next++;
  }
  free(req);
  shm_raw_close(&r);
  mbox_close(&m);
}

/* Several posters in a burst against a learner polling at its own pace: every post
 * either succeeds and is seen and answered, or fails with a message; none vanishes. */
#define POSTERS 3
#define POSTS 20
struct burst {
  const char *name;
  atomic_bool stop;
  atomic_int seen[POSTERS * POSTS + 1];
  int posted_ok[POSTERS];
  int answered_ok[POSTERS];
  int poster;
};

static void *learner_main(void *arg) {
  struct burst *b = arg;
  struct vlff_prompts *l = vlff_prompts_create(b->name, NULL);
  if (!l)
    return NULL;
  uint64_t last = 0;
  while (!atomic_load(&b->stop)) {
    struct vlff_prompt_request req;
    if (vlff_prompts_poll(l, &last, &req) == 1) {
      if (req.seq <= POSTERS * POSTS)
        atomic_fetch_add(&b->seen[req.seq], 1);
      vlff_prompts_answer(l, req.seq, 1, NULL);
    }
    nanosleep(&(struct timespec){0, 2000000}, NULL); /* a training step */
  }
  vlff_prompts_close(l);
  return NULL;
}

static atomic_int next_poster;
static struct burst *the_burst;
static void *poster_main(void *arg) {
  (void)arg;
  struct burst *b = the_burst;
  int me = atomic_fetch_add(&next_poster, 1);
  struct vlff_prompts *p = NULL;
  for (int i = 0; i < 1000 && !p; i++) {
    p = vlff_prompts_attach(b->name);
    if (!p)
      nanosleep(&(struct timespec){0, 1000000}, NULL);
  }
  if (!p)
    return NULL;
  for (int i = 0; i < POSTS; i++) {
    char text[32];
    snprintf(text, sizeof text, "poster %d post %d", me, i);
    const char *t[] = {text};
    int rc = -1;
    for (int tries = 0; tries < 20 && rc < 0; tries++)
      rc = vlff_prompts_post(p, t, 1);
    if (rc < 0)
      continue;
    b->posted_ok[me]++;
    if (vlff_prompts_wait_answer(p, vlff_prompts_last_post(p), 10000000000ull, NULL, 0) == VLFF_PROMPT_ACCEPTED)
      b->answered_ok[me]++;
  }
  vlff_prompts_close(p);
  return NULL;
}

static void test_burst_never_dropped(void **state) {
  (void)state;
  char name[64];
  test_name(name, sizeof name, "burst");
  struct burst *b = calloc(1, sizeof *b);
  b->name = name;
  the_burst = b;
  atomic_store(&next_poster, 0);
  pthread_t lt, pt[POSTERS];
  assert_int_equal(pthread_create(&lt, NULL, learner_main, b), 0);
  for (int i = 0; i < POSTERS; i++)
    assert_int_equal(pthread_create(&pt[i], NULL, poster_main, NULL), 0);
  for (int i = 0; i < POSTERS; i++)
    pthread_join(pt[i], NULL);
  atomic_store(&b->stop, true);
  pthread_join(lt, NULL);
  int posted = 0, answered = 0;
  for (int i = 0; i < POSTERS; i++) {
    posted += b->posted_ok[i];
    answered += b->answered_ok[i];
  }
  assert_true(posted > 0);
  assert_int_equal(answered, posted);
  for (int s = 1; s <= posted; s++)
    if (atomic_load(&b->seen[s]) != 1)
      fail_msg("request %d seen %d times by the learner", s, atomic_load(&b->seen[s]));
  free(b);
  vlff_shm_unlink(name);
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(test_prompt_check_matches_embeddings_format),
    cmocka_unit_test(test_live_pid_in_lock_word), cmocka_unit_test(test_poster_killed_mid_post),
    cmocka_unit_test(test_live_poster_never_waited_for),
    cmocka_unit_test(test_forged_request_refused_with_reason),
    cmocka_unit_test(test_post_over_unanswered_refused),
    cmocka_unit_test(test_state_word_flip_repaired), cmocka_unit_test(test_request_number_backwards_resynced),
    cmocka_unit_test(test_burst_never_dropped))
