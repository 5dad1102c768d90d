/*
 * A minimal fork-join thread pool. The learner runs one parallel region per
 * stage of a step, so the pool is built for low per-run overhead: workers
 * wait on a condition variable for a new generation, take their statically
 * assigned tasks (t % threads == worker, which keeps results bit-identical
 * from run to run) and the caller, worker 0, works too and then waits for the
 * others.
 */
#include <pthread.h>
#include <stdlib.h>
#include <unistd.h>

#include "field_internal.h"

struct vlff_pool {
  int threads;
  pthread_t *tid;
  pthread_mutex_t mu;
  pthread_cond_t start, done;
  unsigned long gen;      /* bumped per run */
  int pending;            /* workers still busy in this run */
  int quit;
  int ntasks;
  vlff_task_fn fn;
  void *ctx;
};

struct worker_arg {
  struct vlff_pool *p;
  int id;
};

static void run_share(struct vlff_pool *p, int id, int ntasks, vlff_task_fn fn, void *ctx) {
  for (int t = id; t < ntasks; t += p->threads) fn(ctx, t, id);
}

static void *worker(void *arg) {
  struct worker_arg *wa = arg;
  struct vlff_pool *p = wa->p;
  int id = wa->id;
  free(wa);
  unsigned long seen = 0;
  pthread_mutex_lock(&p->mu);
  for (;;) {
    while (!p->quit && p->gen == seen) pthread_cond_wait(&p->start, &p->mu);
    if (p->quit) break;
    seen = p->gen;
    int ntasks = p->ntasks;
    vlff_task_fn fn = p->fn;
    void *ctx = p->ctx;
    pthread_mutex_unlock(&p->mu);
    run_share(p, id, ntasks, fn, ctx);
    pthread_mutex_lock(&p->mu);
    if (--p->pending == 0) pthread_cond_signal(&p->done);
  }
  pthread_mutex_unlock(&p->mu);
  return NULL;
}

struct vlff_pool *vlff_pool_create(int threads) {
  if (threads <= 0) {
    long n = sysconf(_SC_NPROCESSORS_ONLN);
    threads = n > 0 ? (int)n : 1;
  }
  if (threads > 256) threads = 256;
  struct vlff_pool *p = calloc(1, sizeof(*p));
  if (!p) return NULL;
  p->threads = threads;
  pthread_mutex_init(&p->mu, NULL);
  pthread_cond_init(&p->start, NULL);
  pthread_cond_init(&p->done, NULL);
  p->tid = calloc((size_t)threads, sizeof(pthread_t));
  if (!p->tid) goto fail;
  for (int i = 1; i < threads; i++) {
    struct worker_arg *wa = malloc(sizeof(*wa));
    if (!wa) goto fail_threads;
    wa->p = p;
    wa->id = i;
    if (pthread_create(&p->tid[i], NULL, worker, wa)) {
      free(wa);
      goto fail_threads;
    }
    continue;
  fail_threads:
    p->threads = i;  /* join only those started */
    vlff_pool_destroy(p);
    return NULL;
  }
  return p;
fail:
  pthread_cond_destroy(&p->start);
  pthread_cond_destroy(&p->done);
  pthread_mutex_destroy(&p->mu);
  free(p);
  return NULL;
}

void vlff_pool_destroy(struct vlff_pool *p) {
  if (!p) return;
  pthread_mutex_lock(&p->mu);
  p->quit = 1;
  pthread_cond_broadcast(&p->start);
  pthread_mutex_unlock(&p->mu);
  for (int i = 1; i < p->threads; i++) pthread_join(p->tid[i], NULL);
  pthread_cond_destroy(&p->start);
  pthread_cond_destroy(&p->done);
  pthread_mutex_destroy(&p->mu);
  free(p->tid);
  free(p);
}

int vlff_pool_threads(const struct vlff_pool *p) { return p->threads; }

void vlff_pool_run(struct vlff_pool *p, int ntasks, vlff_task_fn fn, void *ctx) {
  if (p->threads == 1 || ntasks <= 1) {
    for (int t = 0; t < ntasks; t++) fn(ctx, t, 0);
    return;
  }
  pthread_mutex_lock(&p->mu);
  p->ntasks = ntasks;
  p->fn = fn;
  p->ctx = ctx;
  p->pending = p->threads - 1;
  p->gen++;
  pthread_cond_broadcast(&p->start);
  pthread_mutex_unlock(&p->mu);
  run_share(p, 0, ntasks, fn, ctx);
  pthread_mutex_lock(&p->mu);
  while (p->pending > 0) pthread_cond_wait(&p->done, &p->mu);
  pthread_mutex_unlock(&p->mu);
}
