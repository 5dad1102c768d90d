/*
 * vlff_prompts_try_post, the post of an event loop (issue 51: vlff-view's loop
 * waited up to 2 s in each post): it posts when the mailbox is free, and answers
 * EBUSY at once, without posting, when a request still waits for the learner's
 * answer or another poster holds the lock; vlff_prompts_wait_answer with timeout 0
 * is its non-blocking look for the answer.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <cmocka.h>

#include "shm_test_util.h"
#include "unit.h"

#include <errno.h>
#include <fcntl.h>
#include <stdlib.h>
#include <string.h>
#include <sys/file.h>
#include <time.h>

static double now_s(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (double)ts.tv_sec + ts.tv_nsec / 1e9;
}

static void test_try_post(void **state) {
  (void)state;
  char name[64];
  test_name(name, sizeof name, "trypost");
  struct vlff_prompts *learner = vlff_prompts_create(name, NULL), *poster = vlff_prompts_attach(name);
  assert_non_null(learner);
  assert_non_null(poster);
  const char *texts[] = {"chair", "table"};
  char reason[128];

  /* bad arguments */
  assert_int_equal(vlff_prompts_try_post(poster, NULL, 0, -1), -1);
  assert_int_equal(errno, EINVAL);
  assert_int_equal(vlff_prompts_try_post(NULL, texts, 2, -1), -1);
  assert_int_equal(errno, EINVAL);
  const char *bad[] = {"a\nb"};
  assert_int_equal(vlff_prompts_try_post(poster, bad, 1, -1), -1);
  assert_int_equal(errno, EINVAL);

  /* free: posted */
  assert_int_equal(vlff_prompts_try_post(poster, texts, 2, -1), 0);
  assert_int_equal(vlff_prompts_last_post(poster), 1);
  assert_int_equal(vlff_prompts_wait_answer(poster, 1, 0, reason, sizeof reason), -1);
  assert_int_equal(errno, ETIMEDOUT);

  /* unanswered: busy at once, nothing posted */
  double t0 = now_s();
  assert_int_equal(vlff_prompts_try_post(poster, texts, 2, -1), -1);
  assert_int_equal(errno, EBUSY);
  assert_true(now_s() - t0 < 1.0); /* vlff_prompts_post waits 2 s here */
  assert_non_null(strstr(vlff_shm_last_message(), "request 1 is still waiting for the learner's answer"));
  assert_int_equal(vlff_prompts_last_post(poster), 1);

  /* answered: the index form posts */
  uint64_t last = 0;
  struct vlff_prompt_request *req = malloc(sizeof *req);
  assert_non_null(req);
  assert_int_equal(vlff_prompts_poll(learner, &last, req), 1);
  assert_int_equal(req->count, 2);
  assert_int_equal(vlff_prompts_answer(learner, req->seq, 1, NULL), 0);
  assert_int_equal(vlff_prompts_wait_answer(poster, 1, 0, reason, sizeof reason), VLFF_PROMPT_ACCEPTED);
  assert_int_equal(vlff_prompts_try_post(poster, NULL, 0, 3), 0);
  assert_int_equal(vlff_prompts_last_post(poster), 2);
  assert_int_equal(vlff_prompts_poll(learner, &last, req), 1);
  assert_int_equal(req->set_index, 3);
  assert_int_equal(vlff_prompts_answer(learner, req->seq, 0, "no such set"), 0);
  assert_int_equal(vlff_prompts_wait_answer(poster, 2, 0, reason, sizeof reason), VLFF_PROMPT_REFUSED);
  assert_string_equal(reason, "no such set");

  /* another poster holds the lock (its own open file): busy at once */
  char path[128];
  snprintf(path, sizeof path, "/dev/shm%s", name);
  int fd = open(path, O_RDWR | O_CLOEXEC);
  assert_true(fd >= 0);
  assert_int_equal(flock(fd, LOCK_EX), 0);
  t0 = now_s();
  assert_int_equal(vlff_prompts_try_post(poster, texts, 2, -1), -1);
  assert_int_equal(errno, EBUSY);
  assert_true(now_s() - t0 < 1.0);
  assert_non_null(strstr(vlff_shm_last_message(), "mailbox busy"));
  close(fd);
  /* and the lock it took for a moment is given back: a post goes through */
  assert_int_equal(vlff_prompts_try_post(poster, texts, 2, -1), 0);
  assert_int_equal(vlff_prompts_last_post(poster), 3);

  free(req);
  vlff_prompts_close(poster);
  vlff_prompts_close(learner);
  vlff_shm_unlink(name);
}

VLFF_UNIT_MAIN(NULL, NULL, cmocka_unit_test(test_try_post))
