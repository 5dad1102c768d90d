/* The single-producer / multi-consumer ring.
 *
 * Record n lives in slot n % N. Each slot has a sequence word that is 2n+1 while
 * record n is being written and 2n+2 once it is committed (a seqlock per slot). The
 * producer never looks at consumers: it marks the slot odd, fills it, marks it even,
 * then advances the shared head and bumps a 32-bit futex word that waiting consumers
 * sleep on. A consumer expecting record n reads the slot's word before and after
 * using the data; anything but 2n+2 both times means the producer lapped it and the
 * record is counted as lost. Because record numbers never repeat (a restarted
 * producer continues from the head it finds), a consumer can always tell how many
 * records it missed, exactly.
 *
 * Only the producer writes to the segment; consumers map it read-only, so a
 * misbehaving consumer cannot disturb the producer or the other consumers. */
#include "shm_internal.h"

#include <errno.h>
#include <limits.h>
#include <stdio.h>
#include <linux/futex.h>
#include <stdlib.h>
#include <sys/syscall.h>
#include <time.h>
#include <unistd.h>

#define RING_SLOTS_OFFSET 4096u
#define SLOT_HDR 64u
#define WAIT_STEP_NS 100000000ull

struct ring_ctl {
  _Atomic uint64_t head;      /* records committed */
  _Atomic uint32_t futex;     /* low 32 bits of head, the word consumers sleep on */
  uint32_t pad;
};

struct slot_hdr {
  _Atomic uint64_t seq;
  _Atomic uint64_t len;
  _Atomic uint32_t gen;
};

struct vlff_ring {
  struct seg seg;
  struct ring_ctl *ctl;
  uint8_t *slots;
  uint32_t nslots;
  uint64_t slot_size, stride;
  bool producer;
  /* producer */
  bool reserved;
  uint64_t wseq;
  /* consumer */
  uint64_t next;
  uint64_t lost;
  uint32_t last_gen;
  bool reading;
  uint64_t read_s1;
};

static uint64_t ring_total(const uint64_t g[6]) {
  uint64_t slots = g[0], size = g[1], stride = g[2], off = g[3];
  if (slots < 2 || slots > (1u << 24) || size == 0 || size > (1ull << 36))
    return 0;
  if (stride != align64(SLOT_HDR + size) || off != RING_SLOTS_OFFSET || g[4] || g[5])
    return 0;
  if (stride > (UINT64_MAX - off) / slots)
    return 0;
  return off + slots * stride;
}

static void ring_stat(const struct seg *s, struct vlff_shm_info *info) {
  const struct ring_ctl *c = (const struct ring_ctl *)(s->base + sizeof(struct seg_hdr));
  info->slots = (uint32_t)s->h->geom[0];
  info->slot_size = s->h->geom[1];
  info->head = atomic_load((_Atomic uint64_t *)&c->head);
}

static struct slot_hdr *slot(const struct vlff_ring *r, uint64_t n) {
  return (struct slot_hdr *)(r->slots + (n % r->nslots) * r->stride);
}
static uint8_t *slot_data(const struct vlff_ring *r, uint64_t n) { return (uint8_t *)slot(r, n) + SLOT_HDR; }

static void bind(struct vlff_ring *r) {
  r->ctl = (struct ring_ctl *)(r->seg.base + sizeof(struct seg_hdr));
  r->nslots = (uint32_t)r->seg.h->geom[0];
  r->slot_size = r->seg.h->geom[1];
  r->stride = r->seg.h->geom[2];
  r->slots = r->seg.base + r->seg.h->geom[3];
}

struct seg_spec shm_ring_spec(uint32_t rk) {
  return (struct seg_spec){.kind = VLFF_SHM_KIND_RING, .record_kind = rk, .compute_total = ring_total, .stat = ring_stat};
}

API struct vlff_ring *vlff_ring_create(const char *name, const struct vlff_ring_params *p) {
  if (!p || p->record_kind == VLFF_RECORD_ANY || p->record_kind > VLFF_RECORD_POSE || p->slots < 2 ||
      p->slot_size == 0) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "%s: ring needs a record kind, >= 2 slots and a slot size",
            VLFF_Q(name ? name : "(null)"));
    return NULL;
  }
  struct vlff_ring *r = calloc(1, sizeof *r);
  if (!r) {
    shm_err(VLFF_SHM_ERR_SYS, ENOMEM, "out of memory");
    return NULL;
  }
  uint64_t geom[6] = {p->slots, p->slot_size, align64(SLOT_HDR + p->slot_size), RING_SLOTS_OFFSET, 0, 0};
  struct seg_spec spec = shm_ring_spec(p->record_kind);
  int fresh = shm_seg_create(&r->seg, name, &spec, geom, &p->perm);
  if (fresh < 0) {
    free(r);
    return NULL;
  }
  bind(r);
  r->producer = true;
  if (fresh)
    shm_seg_ready(&r->seg);
  /* A dead producer may have left its reserved slot odd; reserve() rewrites exactly
   * that slot next, since head only counts committed records. */
  r->wseq = atomic_load(&r->ctl->head);
  return r;
}

static struct vlff_ring *attach(const char *name, uint32_t record_kind, const struct seg_trust *trust) {
  struct vlff_ring *r = calloc(1, sizeof *r);
  if (!r) {
    shm_err(VLFF_SHM_ERR_SYS, ENOMEM, "out of memory");
    return NULL;
  }
  struct seg_spec spec = shm_ring_spec(record_kind);
  if (shm_seg_attach(&r->seg, name, &spec, false, trust) < 0) {
    free(r);
    return NULL;
  }
  bind(r);
  r->next = atomic_load_explicit(&r->ctl->head, memory_order_acquire);
  r->last_gen = atomic_load(&r->seg.h->generation);
  return r;
}

API struct vlff_ring *vlff_ring_attach(const char *name, uint32_t record_kind) {
  return attach(name, record_kind, NULL);
}

API struct vlff_ring *vlff_ring_attach_owned(const char *name, uint32_t record_kind, uid_t uid, mode_t mode) {
  struct seg_trust t = {.check_owner = true, .uid = uid, .mode = mode};
  return attach(name, record_kind, &t);
}

/* Producer: the file shrank under us. The ring is replaced by a new one that goes on
 * numbering records where this one stopped, and the caller is told (EPIPE). */
/* The new segment goes on numbering from this handle's records. */
static void producer_rebind(struct vlff_ring *r) {
  bind(r);
  if (atomic_load(&r->ctl->head) < r->wseq) {
    atomic_store(&r->ctl->head, r->wseq);
    atomic_store(&r->ctl->futex, (uint32_t)r->wseq);
  }
  r->wseq = atomic_load(&r->ctl->head);
  shm_seg_ready(&r->seg);
}

static int producer_replace(struct vlff_ring *r) {
  char msg[320];
  shm_seg_check(&r->seg, false);
  snprintf(msg, sizeof msg, "%s", vlff_shm_last_message());
  r->reserved = false;
  if (shm_seg_replace(&r->seg) < 0) {
    r->ctl = NULL;
    return -1;
  }
  producer_rebind(r);
  shm_err(VLFF_SHM_ERR_TRUNCATED, EPIPE, "%s; the record was lost", msg);
  return -1;
}

static bool producer_ok(struct vlff_ring *r, const char *fn) {
  if (!r || !r->producer) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "%s: not a producer handle", fn);
    return false;
  }
  /* Its replacement failed (no space left in /dev/shm): tried again after a
   * growing delay, failing with EPIPE until then, so a producer that goes on
   * producing neither spins on creation nor has to create the ring itself. */
  if (!r->ctl) {
    if (shm_seg_retry(&r->seg) < 0)
      return false;
    producer_rebind(r);
  }
  return true;
}

API void vlff_ring_close(struct vlff_ring *r) {
  if (!r)
    return;
  shm_seg_close(&r->seg);
  free(r);
}

API uint32_t vlff_ring_slots(const struct vlff_ring *r) { return r->nslots; }
API uint64_t vlff_ring_slot_size(const struct vlff_ring *r) { return r->slot_size; }
API uint32_t vlff_ring_generation(const struct vlff_ring *r) {
  return r->ctl ? atomic_load(&r->seg.h->generation) : 0;
}
API uint64_t vlff_ring_head(const struct vlff_ring *r) { return r->ctl ? atomic_load(&r->ctl->head) : r->wseq; }
API uint64_t vlff_ring_lost(const struct vlff_ring *r) { return r->lost; }

API void *vlff_ring_reserve(struct vlff_ring *r, uint64_t *seq) {
  if (!producer_ok(r, "vlff_ring_reserve"))
    return NULL;
  if (!r->reserved) {
    /* Checked once per record: a slot handed out of a shrunk file would be written
     * into nothing. */
    if (shm_seg_check(&r->seg, true) < 0) {
      producer_replace(r);
      return NULL;
    }
    struct slot_hdr *s = slot(r, r->wseq);
    atomic_store_explicit(&s->seq, 2 * r->wseq + 1, memory_order_relaxed);
    /* Orders the odd mark before every store into the slot's data. */
    atomic_thread_fence(memory_order_release);
    r->reserved = true;
  }
  if (seq)
    *seq = r->wseq;
  return slot_data(r, r->wseq);
}

static long futex(_Atomic uint32_t *w, int op, uint32_t val, const struct timespec *ts) {
  return syscall(SYS_futex, (uint32_t *)w, op, val, ts, NULL, 0);
}

API int vlff_ring_commit(struct vlff_ring *r, size_t len) {
  if (!producer_ok(r, "vlff_ring_commit"))
    return -1;
  if (!r->reserved) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_ring_commit: nothing reserved");
    return -1;
  }
  if (len > r->slot_size) {
    shm_err(VLFF_SHM_ERR_SIZE, EMSGSIZE, "%s: record of %zu bytes, slots hold %llu", VLFF_Q(r->seg.name), len,
            (unsigned long long)r->slot_size);
    return -1;
  }
  /* The record was written through the caller's pointer: if the guard fired on it,
   * it went nowhere. */
  if (shm_seg_check(&r->seg, false) < 0)
    return producer_replace(r);
  struct slot_hdr *s = slot(r, r->wseq);
  atomic_store_explicit(&s->len, len, memory_order_relaxed);
  atomic_store_explicit(&s->gen, atomic_load_explicit(&r->seg.h->generation, memory_order_relaxed),
                        memory_order_relaxed);
  atomic_store_explicit(&s->seq, 2 * r->wseq + 2, memory_order_release);
  r->wseq++;
  r->reserved = false;
  atomic_store_explicit(&r->ctl->head, r->wseq, memory_order_release);
  atomic_store_explicit(&r->ctl->futex, (uint32_t)r->wseq, memory_order_release);
  atomic_store_explicit(&r->seg.h->last_ns, shm_now(), memory_order_relaxed);
  /* Consumers map the segment read-only and cannot register as waiters, so the
   * producer always wakes; without sleepers this is a cheap hash lookup. */
  futex(&r->ctl->futex, FUTEX_WAKE, INT_MAX, NULL);
  return 0;
}

API int vlff_ring_write(struct vlff_ring *r, const void *data, size_t len) {
  if (r && len > r->slot_size) {
    shm_err(VLFF_SHM_ERR_SIZE, EMSGSIZE, "%s: record of %zu bytes, slots hold %llu", VLFF_Q(r->seg.name), len,
            (unsigned long long)r->slot_size);
    return -1;
  }
  void *p = vlff_ring_reserve(r, NULL);
  if (!p)
    return -1;
  shm_racy_copy(p, data, len);
  return vlff_ring_commit(r, len);
}

static int check_consumer(struct vlff_ring *r, const char *fn) {
  if (!r || r->producer) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "%s: not a consumer handle", fn);
    return -1;
  }
  if (shm_seg_check(&r->seg, false) < 0)
    return -1;
  if (atomic_load_explicit(&r->seg.h->state, memory_order_acquire) == SEG_ABANDONED) {
    shm_err(VLFF_SHM_ERR_ABANDONED, EPIPE, "%s: abandoned by its creator; attach again", VLFF_Q(r->seg.name));
    return -1;
  }
  return 0;
}

/* Sleeps until the futex word moves off `seen` or the deadline passes. */
static int wait_for(struct vlff_ring *r, uint32_t seen, uint64_t deadline) {
  struct timespec ts;
  uint64_t now = shm_now();
  if (now >= deadline) {
    shm_err(VLFF_SHM_OK, ETIMEDOUT, "%s: no record within the timeout", VLFF_Q(r->seg.name));
    return -1;
  }
  /* A sleeper on a truncated file is never woken (the producer's wake goes to the
   * new segment), so it sleeps in bounded steps and looks at the file in between. */
  if (shm_seg_check(&r->seg, true) < 0)
    return -1;
  uint64_t d = deadline - now;
  if (d > WAIT_STEP_NS)
    d = WAIT_STEP_NS;
  ts.tv_sec = (time_t)(d / 1000000000u);
  ts.tv_nsec = (long)(d % 1000000000u);
  if (futex(&r->ctl->futex, FUTEX_WAIT, seen, &ts) < 0 && errno == EINTR) {
    shm_err(VLFF_SHM_OK, EINTR, "%s: wait interrupted", VLFF_Q(r->seg.name));
    return -1;
  }
  return 0;
}

API int vlff_ring_read_begin(struct vlff_ring *r, struct vlff_ring_view *v, uint64_t timeout_ns) {
  if (check_consumer(r, "vlff_ring_read_begin") < 0)
    return -1;
  if (!v) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_ring_read_begin: view is NULL");
    return -1;
  }
  uint64_t deadline = UINT64_MAX;
  if (timeout_ns != UINT64_MAX) {
    uint64_t now = shm_now();
    deadline = timeout_ns > UINT64_MAX - now - 1 ? UINT64_MAX - 1 : now + timeout_ns;
  }
  r->reading = false;
  for (;;) {
    /* The futex word is read before head so that a commit landing in between makes
     * FUTEX_WAIT return at once instead of sleeping through it. */
    uint32_t f = atomic_load_explicit(&r->ctl->futex, memory_order_acquire);
    uint64_t h = atomic_load_explicit(&r->ctl->head, memory_order_acquire);
    if (h < r->next) {
      /* The head went backwards: only a corrupt or re-created segment does that. */
      r->next = h;
    }
    if (r->next == h) {
      if (timeout_ns == 0) {
        /* A poller is told, as a waiter is, when its file is gone from /dev/shm. */
        if (shm_seg_check(&r->seg, true) < 0)
          return -1;
        shm_err(VLFF_SHM_OK, EAGAIN, "%s: nothing new", VLFF_Q(r->seg.name));
        return -1;
      }
      if (atomic_load_explicit(&r->seg.h->state, memory_order_acquire) == SEG_ABANDONED)
        return check_consumer(r, "vlff_ring_read_begin");
      if (wait_for(r, f, deadline) < 0)
        return -1;
      continue;
    }
    if (h - r->next > r->nslots) {
      r->lost += h - r->nslots - r->next;
      r->next = h - r->nslots;
    }
    uint64_t n = r->next;
    struct slot_hdr *s = slot(r, n);
    uint64_t s1 = atomic_load_explicit(&s->seq, memory_order_acquire);
    if (s1 != 2 * n + 2) {
      /* Overwritten or being overwritten by a newer lap (or, in a damaged segment,
       * never written): lost either way. */
      r->lost++;
      r->next++;
      continue;
    }
    uint64_t len = atomic_load_explicit(&s->len, memory_order_relaxed);
    uint32_t gen = atomic_load_explicit(&s->gen, memory_order_relaxed);
    if (len > r->slot_size) {
      r->lost++;
      r->next++;
      continue;
    }
    v->data = slot_data(r, n);
    v->len = (size_t)len;
    v->seq = n;
    v->generation = gen;
    v->new_generation = gen != r->last_gen;
    r->reading = true;
    r->read_s1 = s1;
    return 0;
  }
}

API int vlff_ring_read_end(struct vlff_ring *r, const struct vlff_ring_view *v) {
  if (!r || r->producer || !r->reading || !v || v->seq != r->next) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_ring_read_end: no read in progress for this view");
    return -1;
  }
  /* Orders every load of the record's data before the re-check below. */
  atomic_thread_fence(memory_order_acquire);
  uint64_t s2 = atomic_load_explicit(&slot(r, v->seq)->seq, memory_order_relaxed);
  r->reading = false;
  r->next = v->seq + 1;
  if (shm_seg_check(&r->seg, false) < 0) {
    r->lost++;
    return -1;
  }
  if (s2 != r->read_s1) {
    r->lost++;
    shm_err(VLFF_SHM_OK, ESTALE, "%s: record %llu overwritten while read", VLFF_Q(r->seg.name),
            (unsigned long long)v->seq);
    return -1;
  }
  r->last_gen = v->generation;
  return 0;
}

API ssize_t vlff_ring_read_copy(struct vlff_ring *r, void *buf, size_t cap, struct vlff_ring_view *info,
                                uint64_t timeout_ns) {
  struct vlff_ring_view v;
  for (;;) {
    if (vlff_ring_read_begin(r, &v, timeout_ns) < 0)
      return -1;
    if (v.len > cap) {
      if (vlff_ring_read_end(r, &v) == 0)
        r->lost++; /* intact but undeliverable: skipped, so counted (a torn one already was) */
      shm_err(VLFF_SHM_ERR_SIZE, EMSGSIZE, "%s: record of %zu bytes, buffer holds %zu", VLFF_Q(r->seg.name), v.len,
              cap);
      return -1;
    }
    shm_racy_copy(buf, v.data, v.len);
    if (vlff_ring_read_end(r, &v) == 0)
      break;
  }
  if (info)
    *info = v;
  return (ssize_t)v.len;
}

API ssize_t vlff_ring_read_latest(struct vlff_ring *r, void *buf, size_t cap, struct vlff_ring_view *info) {
  if (check_consumer(r, "vlff_ring_read_latest") < 0)
    return -1;
  for (int tries = 0; tries < 64; tries++) {
    uint64_t h = atomic_load_explicit(&r->ctl->head, memory_order_acquire);
    if (h == 0) {
      shm_err(VLFF_SHM_OK, EAGAIN, "%s: ring is empty", VLFF_Q(r->seg.name));
      return -1;
    }
    uint64_t n = h - 1;
    struct slot_hdr *s = slot(r, n);
    uint64_t s1 = atomic_load_explicit(&s->seq, memory_order_acquire);
    if (s1 != 2 * n + 2)
      continue;
    uint64_t len = atomic_load_explicit(&s->len, memory_order_relaxed);
    uint32_t gen = atomic_load_explicit(&s->gen, memory_order_relaxed);
    if (len > r->slot_size)
      continue;
    if (len > cap) {
      shm_err(VLFF_SHM_ERR_SIZE, EMSGSIZE, "%s: record of %llu bytes, buffer holds %zu", VLFF_Q(r->seg.name),
              (unsigned long long)len, cap);
      return -1;
    }
    shm_racy_copy(buf, slot_data(r, n), len);
    atomic_thread_fence(memory_order_acquire);
    if (shm_seg_check(&r->seg, false) < 0)
      return -1;
    if (atomic_load_explicit(&s->seq, memory_order_relaxed) != s1)
      continue;
    if (info)
      *info = (struct vlff_ring_view){.data = buf, .len = len, .seq = n, .generation = gen};
    return (ssize_t)len;
  }
  shm_err(VLFF_SHM_OK, EAGAIN, "%s: producer kept overwriting the newest record", VLFF_Q(r->seg.name));
  return -1;
}

API void vlff_ring_seek_oldest(struct vlff_ring *r) {
  uint64_t h = atomic_load_explicit(&r->ctl->head, memory_order_acquire);
  r->next = h > r->nslots ? h - r->nslots : 0;
  r->reading = false;
}

API void vlff_ring_seek_newest(struct vlff_ring *r) {
  r->next = atomic_load_explicit(&r->ctl->head, memory_order_acquire);
  r->reading = false;
}

/* Copies record n into out (exactly want bytes) if it is intact. 1 ok, 0 not. */
int shm_ring_peek(struct vlff_ring *r, uint64_t n, void *out, size_t want) {
  struct slot_hdr *s = slot(r, n);
  uint64_t s1 = atomic_load_explicit(&s->seq, memory_order_acquire);
  if (s1 != 2 * n + 2 || atomic_load_explicit(&s->len, memory_order_relaxed) != want)
    return 0;
  shm_racy_copy(out, slot_data(r, n), want);
  atomic_thread_fence(memory_order_acquire);
  return atomic_load_explicit(&s->seq, memory_order_relaxed) == s1;
}

/* A consumer with nothing left to read sleeps on the futex word, so a FUTEX_WAKE of
 * one waiter that finds somebody proves a consumer is caught up. Nothing else tells
 * the producer: consumers map the segment read-only and leave no cursor in it. The
 * woken consumer re-reads head, finds it unchanged and waits again. */
API int vlff_ring_wait_reader(struct vlff_ring *r, uint64_t timeout_ns) {
  if (!producer_ok(r, "vlff_ring_wait_reader"))
    return -1;
  uint64_t t0 = shm_now();
  for (;;) {
    if (futex(&r->ctl->futex, FUTEX_WAKE, 1, NULL) > 0)
      return 0;
    if (shm_now() - t0 >= timeout_ns) {
      shm_err(VLFF_SHM_OK, ETIMEDOUT, "%s: no consumer caught up within the timeout", VLFF_Q(r->seg.name));
      return -1;
    }
    struct timespec ts = {0, 200 * 1000};
    nanosleep(&ts, NULL);
  }
}
