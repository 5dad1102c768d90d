/* The SIGBUS guard: a segment shrunk under a process must not kill it.
 *
 * Any process with write access to a segment's file can ftruncate it; every page of
 * a mapping past the new end of file then raises SIGBUS on access, whether the access
 * is made by this library or by the application through a pointer the library handed
 * out (a reserved ring slot, a record view). A sigsetjmp guard around the library's
 * own copies could not cover the second kind, so the guard works at the mapping
 * instead: every mapping of a segment is registered here, and a SIGBUS whose fault
 * address falls inside one replaces that whole mapping, at the same address, with
 * private zero-filled memory, flags the handle and returns. The faulting instruction
 * then completes on the zero pages: readers see sequence words that no longer match
 * and discard what they read, writers write into memory nobody shares. The next call
 * on the handle sees the flag and reports the segment as truncated (EPIPE); a creator
 * replaces the segment by a new one.
 *
 * The handler is installed when a segment is mapped and whenever something else has
 * replaced it since (test harnesses and applications install their own). Faults
 * outside every registered mapping go to the handler that was installed before ours,
 * or to the default action, so an application's own SIGBUS handling is kept.
 *
 * The registry is a fixed table written under a mutex and read by the handler
 * without locks: each entry has a sequence word, odd while the entry changes. */
#include "shm_internal.h"

#include <errno.h>
#include <pthread.h>
#include <signal.h>
#include <sys/mman.h>
#include <sys/syscall.h>
#include <unistd.h>

#define GUARD_ENTRIES 4096

struct guard_entry {
  _Atomic uint32_t seq;
  _Atomic uintptr_t start, len;
  _Atomic int prot;
  _Atomic(_Atomic uint32_t *) flag;
};

static struct guard_entry table[GUARD_ENTRIES];
static pthread_mutex_t table_lock = PTHREAD_MUTEX_INITIALIZER;
static struct sigaction previous;
static _Atomic int previous_set;
static _Thread_local int chaining;

static void on_sigbus(int sig, siginfo_t *si, void *uc);

/* Looks the address up and, if it lies in a registered mapping, swaps the mapping for
 * anonymous memory. 1 if the fault is handled. Async-signal-safe: atomics and raw
 * system calls only. */
static int recover(uintptr_t addr) {
  for (int i = 0; i < GUARD_ENTRIES; i++) {
    struct guard_entry *e = &table[i];
    uint32_t s1 = atomic_load_explicit(&e->seq, memory_order_acquire);
    if (s1 & 1)
      continue;
    /* Acquire loads: the re-check of seq below stays after them. */
    uintptr_t start = atomic_load_explicit(&e->start, memory_order_acquire);
    uintptr_t len = atomic_load_explicit(&e->len, memory_order_acquire);
    int prot = atomic_load_explicit(&e->prot, memory_order_acquire);
    _Atomic uint32_t *flag = atomic_load_explicit(&e->flag, memory_order_acquire);
    if (atomic_load_explicit(&e->seq, memory_order_relaxed) != s1 || !start || addr < start || addr - start >= len)
      continue;
    /* The raw system call, not mmap(): sanitizer interceptors are not signal-safe. */
    long r = syscall(SYS_mmap, (void *)start, (size_t)len, prot, MAP_PRIVATE | MAP_ANONYMOUS | MAP_FIXED, -1, 0L);
    if (r == -1)
      return 0;
    atomic_store_explicit(flag, 1, memory_order_release);
    return 1;
  }
  return 0;
}

static void on_sigbus(int sig, siginfo_t *si, void *uc) {
  int saved = errno;
  if (!chaining && si && si->si_code > 0 && recover((uintptr_t)si->si_addr)) {
    errno = saved;
    return;
  }
  errno = saved;
  /* Not ours. A handler that chains back to us lands here with chaining set: then
   * the default action ends the loop. */
  if (!chaining && atomic_load_explicit(&previous_set, memory_order_acquire)) {
    if (previous.sa_flags & SA_SIGINFO) {
      if (previous.sa_sigaction && previous.sa_sigaction != on_sigbus) {
        chaining = 1;
        previous.sa_sigaction(sig, si, uc);
        chaining = 0;
        return;
      }
    } else if (previous.sa_handler != SIG_DFL && previous.sa_handler != SIG_IGN) {
      chaining = 1;
      previous.sa_handler(sig);
      chaining = 0;
      return;
    }
  }
  struct sigaction dfl = {.sa_handler = SIG_DFL};
  sigemptyset(&dfl.sa_mask);
  sigaction(SIGBUS, &dfl, NULL);
  /* A fault re-executes the access and dies of it; a sent signal is sent again. */
  if (!si || si->si_code <= 0)
    raise(SIGBUS);
}

/* Installs the handler unless it is already the current one. Under table_lock. */
static int install(void) {
  struct sigaction cur;
  if (sigaction(SIGBUS, NULL, &cur) < 0)
    return -1;
  if ((cur.sa_flags & SA_SIGINFO) && cur.sa_sigaction == on_sigbus)
    return 0;
  struct sigaction ours = {.sa_sigaction = on_sigbus, .sa_flags = SA_SIGINFO | SA_ONSTACK | SA_RESTART};
  sigemptyset(&ours.sa_mask);
  atomic_store_explicit(&previous_set, 0, memory_order_release);
  previous = cur;
  atomic_store_explicit(&previous_set, 1, memory_order_release);
  return sigaction(SIGBUS, &ours, NULL);
}

int shm_guard_register(struct seg *s, int prot) {
  pthread_mutex_lock(&table_lock);
  if (install() < 0) {
    int e = errno;
    pthread_mutex_unlock(&table_lock);
    shm_err(VLFF_SHM_ERR_SYS, e, "%s: cannot install the SIGBUS guard: %s", VLFF_Q(s->name), strerror(e));
    return -1;
  }
  for (int i = 0; i < GUARD_ENTRIES; i++) {
    struct guard_entry *e = &table[i];
    if (atomic_load_explicit(&e->start, memory_order_relaxed))
      continue;
    atomic_fetch_add_explicit(&e->seq, 1, memory_order_relaxed);
    atomic_thread_fence(memory_order_release);
    atomic_store_explicit(&e->len, (uintptr_t)s->size, memory_order_relaxed);
    atomic_store_explicit(&e->prot, prot, memory_order_relaxed);
    atomic_store_explicit(&e->flag, &s->fault, memory_order_relaxed);
    atomic_store_explicit(&e->start, (uintptr_t)s->base, memory_order_relaxed);
    atomic_fetch_add_explicit(&e->seq, 1, memory_order_release);
    s->guard_slot = i + 1;
    pthread_mutex_unlock(&table_lock);
    return 0;
  }
  pthread_mutex_unlock(&table_lock);
  shm_err(VLFF_SHM_ERR_SYS, EMFILE, "%s: more than %d segments mapped in this process", VLFF_Q(s->name), GUARD_ENTRIES);
  return -1;
}

void shm_guard_unregister(struct seg *s) {
  if (!s->guard_slot)
    return;
  pthread_mutex_lock(&table_lock);
  struct guard_entry *e = &table[s->guard_slot - 1];
  atomic_fetch_add_explicit(&e->seq, 1, memory_order_relaxed);
  atomic_thread_fence(memory_order_release);
  atomic_store_explicit(&e->start, 0, memory_order_relaxed);
  atomic_store_explicit(&e->len, 0, memory_order_relaxed);
  atomic_store_explicit(&e->flag, NULL, memory_order_relaxed);
  atomic_fetch_add_explicit(&e->seq, 1, memory_order_release);
  pthread_mutex_unlock(&table_lock);
  s->guard_slot = 0;
}
