/* The prompt mailbox: controllers post prompt sets, the learner polls.
 *
 * Unlike the other segments it has several writers, so posts are serialised by a
 * lock word holding the poster's pid; a poster that died holding it is detected and
 * the lock taken over. The request itself sits under a seqlock so that the learner's
 * poll never waits for a poster and never sees a half-written set. */
#include "shm_internal.h"

#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include <unistd.h>

#define BODY_OFFSET 256u
#define LOCK_SPIN_NS 200000000ull

struct mbox_ctl {
  _Atomic uint64_t seq;      /* 2 * posts, odd while a post is being written */
  _Atomic int32_t lock_pid;  /* poster holding the mailbox, 0 = free */
};

struct vlff_prompts {
  struct seg seg;
  struct mbox_ctl *ctl;
  struct vlff_prompt_request *body;
};

uint64_t shm_prompts_total(const uint64_t g[6]) {
  if (g[0] != sizeof(struct vlff_prompt_request) || g[1] != BODY_OFFSET || g[2] || g[3] || g[4] || g[5])
    return 0;
  return BODY_OFFSET + align64(sizeof(struct vlff_prompt_request));
}

void shm_prompts_stat(const struct seg *s, struct vlff_shm_info *info) {
  const struct mbox_ctl *c = (const struct mbox_ctl *)(s->base + sizeof(struct seg_hdr));
  info->head = atomic_load((_Atomic uint64_t *)&c->seq) / 2;
}

static void bind(struct vlff_prompts *p) {
  p->ctl = (struct mbox_ctl *)(p->seg.base + sizeof(struct seg_hdr));
  p->body = (struct vlff_prompt_request *)(p->seg.base + BODY_OFFSET);
}

static const struct seg_spec spec = {.kind = VLFF_SHM_KIND_PROMPTS};

API struct vlff_prompts *vlff_prompts_create(const char *name, const struct vlff_shm_perm *perm) {
  struct vlff_prompts *p = calloc(1, sizeof *p);
  if (!p) {
    shm_err(VLFF_SHM_ERR_SYS, ENOMEM, "out of memory");
    return NULL;
  }
  uint64_t geom[6] = {sizeof(struct vlff_prompt_request), BODY_OFFSET, 0, 0, 0, 0};
  int fresh = shm_seg_create(&p->seg, name, &spec, geom, perm);
  if (fresh < 0) {
    free(p);
    return NULL;
  }
  bind(p);
  if (fresh)
    shm_seg_ready(&p->seg);
  return p;
}

API struct vlff_prompts *vlff_prompts_attach(const char *name) {
  struct vlff_prompts *p = calloc(1, sizeof *p);
  if (!p) {
    shm_err(VLFF_SHM_ERR_SYS, ENOMEM, "out of memory");
    return NULL;
  }
  if (shm_seg_attach(&p->seg, name, &spec, true) < 0) {
    free(p);
    return NULL;
  }
  bind(p);
  return p;
}

API void vlff_prompts_close(struct vlff_prompts *p) {
  if (!p)
    return;
  shm_seg_close(&p->seg);
  free(p);
}

static int lock(struct vlff_prompts *p) {
  int32_t me = (int32_t)getpid();
  uint64_t t0 = shm_now();
  for (;;) {
    int32_t holder = 0;
    if (atomic_compare_exchange_strong(&p->ctl->lock_pid, &holder, me))
      return 0;
    /* Our own pid holding it means another thread of ours: wait, never steal. */
    if (holder != me && !shm_pid_alive(holder) && atomic_compare_exchange_strong(&p->ctl->lock_pid, &holder, me))
      return 0;
    if (shm_now() - t0 > LOCK_SPIN_NS) {
      shm_err(VLFF_SHM_OK, EAGAIN, "%s: mailbox busy (pid %d posting)", p->seg.name, (int)holder);
      return -1;
    }
    nanosleep(&(struct timespec){0, 50000}, NULL);
  }
}

static int post(struct vlff_prompts *p, const struct vlff_prompt_request *req) {
  if (!p->seg.writable) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "%s: handle is not writable", p->seg.name);
    return -1;
  }
  if (atomic_load(&p->seg.h->state) == SEG_ABANDONED) {
    shm_err(VLFF_SHM_ERR_ABANDONED, EPIPE, "%s: abandoned by the learner; attach again", p->seg.name);
    return -1;
  }
  if (lock(p) < 0)
    return -1;
  uint64_t odd = atomic_load_explicit(&p->ctl->seq, memory_order_relaxed) | 1;
  atomic_store_explicit(&p->ctl->seq, odd, memory_order_relaxed);
  atomic_thread_fence(memory_order_release);
  struct vlff_prompt_request r = *req;
  r.seq = (odd + 1) / 2;
  r.t_ns = shm_now();
  r.poster_pid = (int32_t)getpid();
  shm_racy_copy(p->body, &r, sizeof r);
  atomic_store_explicit(&p->ctl->seq, odd + 1, memory_order_release);
  atomic_store_explicit(&p->seg.h->last_ns, r.t_ns, memory_order_relaxed);
  atomic_store_explicit(&p->ctl->lock_pid, 0, memory_order_release);
  return 0;
}

API int vlff_prompts_post(struct vlff_prompts *p, const char *const *texts, int count) {
  if (!p || !texts || count < 1 || count > VLFF_SHM_MAX_PROMPTS) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_prompts_post: need 1..%d prompts", VLFF_SHM_MAX_PROMPTS);
    return -1;
  }
  struct vlff_prompt_request *r = calloc(1, sizeof *r);
  if (!r) {
    shm_err(VLFF_SHM_ERR_SYS, ENOMEM, "out of memory");
    return -1;
  }
  r->set_index = -1;
  r->count = count;
  for (int i = 0; i < count; i++) {
    size_t n = texts[i] ? strlen(texts[i]) : 0;
    if (n == 0 || n >= VLFF_SHM_PROMPT_LEN) {
      shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_prompts_post: prompt %d is empty or longer than %d bytes", i,
              VLFF_SHM_PROMPT_LEN - 1);
      free(r);
      return -1;
    }
    memcpy(r->text[i], texts[i], n);
  }
  int rc = post(p, r);
  free(r);
  return rc;
}

API int vlff_prompts_post_index(struct vlff_prompts *p, int set_index) {
  if (!p || set_index < 0) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_prompts_post_index: index must be >= 0");
    return -1;
  }
  struct vlff_prompt_request r = {.set_index = set_index};
  return post(p, &r);
}

/* What a poster wrote is external input for the learner. */
static bool request_sane(struct vlff_prompt_request *r) {
  if (r->set_index >= 0)
    return r->count == 0;
  if (r->set_index != -1 || r->count < 1 || r->count > VLFF_SHM_MAX_PROMPTS)
    return false;
  for (int i = 0; i < r->count; i++)
    if (!memchr(r->text[i], 0, VLFF_SHM_PROMPT_LEN) || !r->text[i][0])
      return false;
  return true;
}

API int vlff_prompts_poll(struct vlff_prompts *p, uint64_t *last_seq, struct vlff_prompt_request *req) {
  if (!p || !last_seq || !req) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_prompts_poll: NULL argument");
    return -1;
  }
  for (int i = 0; i < 1000; i++) {
    if (atomic_load(&p->seg.h->state) == SEG_ABANDONED) {
      shm_err(VLFF_SHM_ERR_ABANDONED, EPIPE, "%s: abandoned; attach again", p->seg.name);
      return -1;
    }
    uint64_t s1 = atomic_load_explicit(&p->ctl->seq, memory_order_acquire);
    if (s1 & 1) {
      nanosleep(&(struct timespec){0, 20000}, NULL);
      continue;
    }
    if (s1 / 2 == *last_seq)
      return 0;
    shm_racy_copy(req, p->body, sizeof *req);
    atomic_thread_fence(memory_order_acquire);
    if (atomic_load_explicit(&p->ctl->seq, memory_order_relaxed) != s1)
      continue;
    *last_seq = s1 / 2;
    if (req->seq != s1 / 2 || !request_sane(req)) {
      shm_err(VLFF_SHM_ERR_CORRUPT, EBADMSG, "%s: posted request %llu is malformed; ignored", p->seg.name,
              (unsigned long long)(s1 / 2));
      return -1;
    }
    return 1;
  }
  shm_err(VLFF_SHM_OK, EAGAIN, "%s: a post has been in progress for too long", p->seg.name);
  return -1;
}
