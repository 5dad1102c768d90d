/*
 * A minimal fork-join thread pool. The learner runs one parallel region per
 * stage of a step (three per step, back to back), so the pool is built for
 * low per-run overhead.
 *
 * Hand-offs spin before they sleep. A worker that finds no new run keeps
 * polling the generation counter for up to VLFF_POOL_SPIN_US before it waits
 * on the condition variable, and the caller polls the pending count the same
 * way before waiting for the last worker. Sleeping at once costs a futex
 * wake-up's scheduling latency per hand-off, several times a short task's
 * own length (a step makes three runs; a 3D query or a render one). The
 * spin caps what an idle pool burns at that many microseconds per run.
 *
 * Two ways to hand out tasks. vlff_pool_run assigns them statically
 * (t % threads == worker), which keeps per-thread accumulations bit-identical
 * from run to run. vlff_pool_run_dynamic lets each thread claim the next task
 * from a shared counter, which balances unequal tasks; it is for tasks whose
 * results do not depend on which thread ran them.
 */
#include <pthread.h>
#include <stdatomic.h>
#include <stdlib.h>
#include <time.h>
#include <unistd.h>

#include "field_internal.h"

#define VLFF_POOL_SPIN_US 200

struct vlff_pool {
  int threads;
  pthread_t *tid;
  pthread_mutex_t mu;
  pthread_cond_t start, done;
  atomic_ulong gen;       /* bumped per run, after the run's fields are set */
  atomic_int pending;     /* workers still busy in this run */
  atomic_int sleepers;    /* workers waiting on start (the caller must broadcast) */
  atomic_int next;        /* the next task to claim, dynamic runs */
  atomic_int quit;
  int ntasks, dynamic;
  vlff_task_fn fn;
  void *ctx;
};

struct worker_arg {
  struct vlff_pool *p;
  int id;
};

static void cpu_relax(void) {
#if defined(__x86_64__) || defined(__i386__)
  __builtin_ia32_pause();
#elif defined(__aarch64__)
  __asm__ __volatile__("yield");
#endif
}

/* Polls until done(p, arg) holds or VLFF_POOL_SPIN_US pass; returns whether
 * it holds. The clock is read every 64 polls: a read costs about as much as
 * the pause it would replace. */
static int spin_until(struct vlff_pool *p, int (*done)(struct vlff_pool *, unsigned long), unsigned long arg) {
  double end = 0;
  for (unsigned i = 0;; i++) {
    if (done(p, arg)) return 1;
    if ((i & 63) == 0) {
      double t = 1e6 * vlff_seconds();
      if (end == 0) end = t + VLFF_POOL_SPIN_US;
      else if (t >= end) return done(p, arg);
    }
    cpu_relax();
  }
}

/* Sequentially consistent: the sleep hand-off below relies on it. */
static int new_run(struct vlff_pool *p, unsigned long seen) {
  return atomic_load(&p->gen) != seen || atomic_load(&p->quit);
}

static int all_done(struct vlff_pool *p, unsigned long unused) {
  (void)unused;
  return atomic_load_explicit(&p->pending, memory_order_acquire) == 0;
}

static void run_share(struct vlff_pool *p, int id) {
  if (p->dynamic) {
    for (int t; (t = atomic_fetch_add_explicit(&p->next, 1, memory_order_relaxed)) < p->ntasks;) p->fn(p->ctx, t, id);
    return;
  }
  for (int t = id; t < p->ntasks; t += p->threads) p->fn(p->ctx, t, id);
}

static void *worker(void *arg) {
  struct worker_arg *wa = arg;
  struct vlff_pool *p = wa->p;
  int id = wa->id;
  free(wa);
  /* Named so that the node's threads can be told apart (ps -L, top -H):
   * node.cpu_budget bounds how many of these there are. */
  pthread_setname_np(pthread_self(), "vlff-pool");
  unsigned long seen = 0;
  for (;;) {
    if (!spin_until(p, new_run, seen)) {
      /* Announce the sleep, then check again under the lock: the caller
       * bumps gen before it reads sleepers (both sequentially consistent),
       * so either it sees this sleeper and broadcasts under the lock, or
       * this check sees its new generation. */
      pthread_mutex_lock(&p->mu);
      atomic_fetch_add(&p->sleepers, 1);
      while (!new_run(p, seen)) pthread_cond_wait(&p->start, &p->mu);
      atomic_fetch_sub(&p->sleepers, 1);
      pthread_mutex_unlock(&p->mu);
    }
    if (atomic_load(&p->quit)) break;
    seen = atomic_load_explicit(&p->gen, memory_order_acquire);
    run_share(p, id);
    if (atomic_fetch_sub_explicit(&p->pending, 1, memory_order_acq_rel) == 1) {
      pthread_mutex_lock(&p->mu);
      pthread_cond_signal(&p->done);
      pthread_mutex_unlock(&p->mu);
    }
  }
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
  atomic_store(&p->quit, 1);
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

static void run(struct vlff_pool *p, int ntasks, vlff_task_fn fn, void *ctx, int dynamic) {
  if (p->threads == 1 || ntasks <= 1) {
    for (int t = 0; t < ntasks; t++) fn(ctx, t, 0);
    return;
  }
  /* The workers of the last run are all done (pending reached 0), so none
   * reads these fields now; the release of gen publishes them. */
  p->ntasks = ntasks;
  p->fn = fn;
  p->ctx = ctx;
  p->dynamic = dynamic;
  atomic_store_explicit(&p->next, 0, memory_order_relaxed);
  atomic_store_explicit(&p->pending, p->threads - 1, memory_order_relaxed);
  atomic_fetch_add(&p->gen, 1);
  if (atomic_load(&p->sleepers) > 0) {
    pthread_mutex_lock(&p->mu);
    pthread_cond_broadcast(&p->start);
    pthread_mutex_unlock(&p->mu);
  }
  run_share(p, 0);
  if (!spin_until(p, all_done, 0)) {
    pthread_mutex_lock(&p->mu);
    while (!all_done(p, 0)) pthread_cond_wait(&p->done, &p->mu);
    pthread_mutex_unlock(&p->mu);
  }
}

void vlff_pool_run(struct vlff_pool *p, int ntasks, vlff_task_fn fn, void *ctx) { run(p, ntasks, fn, ctx, 0); }

void vlff_pool_run_dynamic(struct vlff_pool *p, int ntasks, vlff_task_fn fn, void *ctx) {
  run(p, ntasks, fn, ctx, 1);
}
