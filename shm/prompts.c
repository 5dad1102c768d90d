/* The prompt mailbox: controllers post prompt sets, the learner polls and answers.
 *
 * Unlike the other segments it has several writers. Posts are serialised by flock()
 * on the segment's file: the kernel drops the lock with its holder's last descriptor,
 * so a poster killed mid-post never blocks the next one, and no pid word has to be
 * trusted (a pid can be reused by an unrelated live process, or written by anyone
 * with write access). The request sits under a seqlock so that the learner's poll
 * never waits for a poster and never sees a half-written set; an odd sequence word
 * whose lock is free was left by a dead poster, and the poll recovers it at once.
 *
 * Every request gets an answer (accepted, or refused with the reason) in a second
 * seqlocked block that only the learner writes, and a post waits until the previous
 * request has its answer, so a burst of posts is serialised instead of overwriting
 * unread requests. What a poster wrote is external input for the learner: texts are
 * validated exactly as the embeddings file format validates prompts. */
#include "shm_internal.h"

#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <sys/file.h>
#include <time.h>
#include <unistd.h>

#define BODY_OFFSET 256u
#define LOCK_WAIT_NS 2000000000ull
#define ANSWER_REASON_LEN 104
/* Answers are kept per request number, several at once, so that a poster slow to
 * read its answer does not lose it to the next poster's. */
#define ANSWER_SLOTS 8u
#define ANSWERS_OFFSET (BODY_OFFSET + align64(sizeof(struct vlff_prompt_request)))

struct mbox_ctl {
  _Atomic uint64_t seq;      /* 2 * posts, odd while a post is being written */
  _Atomic int32_t lock_pid;  /* the poster writing, for messages only (0 = none) */
  uint32_t pad;
  _Atomic uint64_t answered; /* the newest request answered */
  /* Written by the learner only, for vlff_shm_stat (zeros in mailboxes made before
   * them): how often it set its state word back to ready, and how often it put a
   * request number that went backwards (or absurdly far) back where it was. */
  _Atomic uint64_t repairs;
  _Atomic uint64_t resyncs;
};
_Static_assert(sizeof(struct mbox_ctl) <= BODY_OFFSET - sizeof(struct seg_hdr), "mailbox control block fits");

struct answer {
  _Atomic uint64_t word;    /* 2 * writes, odd while the learner writes it */
  _Atomic uint64_t seq;     /* the request it answers */
  _Atomic int32_t status;   /* enum vlff_prompt_answer */
  uint32_t pad;
  char reason[ANSWER_REASON_LEN];
};
_Static_assert(sizeof(struct answer) == 128, "answer slots are two cache lines");

struct vlff_prompts {
  struct seg seg;
  struct mbox_ctl *ctl;
  struct vlff_prompt_request *body;
  struct answer *answers;
  uint64_t posted; /* this handle's last post */
  bool broken;     /* learner: the mailbox could not be replaced */
  uint64_t repairs, resyncs; /* learner: its own counts, copied into the control block */
  uint64_t answered;         /* learner: the newest request it answered */
};

/* Beyond any number posts reach (a thousand a second for nine thousand years), and
 * far enough from 2^64 that 2 * number + 1 never wraps. */
#define SEQ_LIMIT (1ull << 48)

static uint64_t prompts_total(const uint64_t g[6]) {
  if (g[0] != sizeof(struct vlff_prompt_request) || g[1] != BODY_OFFSET || g[2] != ANSWER_SLOTS ||
      g[3] != ANSWERS_OFFSET || g[4] || g[5])
    return 0;
  return ANSWERS_OFFSET + ANSWER_SLOTS * sizeof(struct answer);
}

static void prompts_stat(const struct seg *s, struct vlff_shm_info *info) {
  const struct mbox_ctl *c = (const struct mbox_ctl *)(s->base + sizeof(struct seg_hdr));
  info->head = atomic_load((_Atomic uint64_t *)&c->seq) / 2;
  uint64_t resyncs = atomic_load((_Atomic uint64_t *)&c->resyncs);
  info->slots = resyncs > UINT32_MAX ? UINT32_MAX : (uint32_t)resyncs;
  info->slot_size = atomic_load((_Atomic uint64_t *)&c->repairs);
}

static void bind(struct vlff_prompts *p) {
  p->ctl = (struct mbox_ctl *)(p->seg.base + sizeof(struct seg_hdr));
  p->body = (struct vlff_prompt_request *)(p->seg.base + BODY_OFFSET);
  p->answers = (struct answer *)(p->seg.base + ANSWERS_OFFSET);
}

const struct seg_spec shm_prompts_spec = {.kind = VLFF_SHM_KIND_PROMPTS, .compute_total = prompts_total, .stat = prompts_stat};

API struct vlff_prompts *vlff_prompts_create(const char *name, const struct vlff_shm_perm *perm) {
  struct vlff_prompts *p = calloc(1, sizeof *p);
  if (!p) {
    shm_err(VLFF_SHM_ERR_SYS, ENOMEM, "out of memory");
    return NULL;
  }
  uint64_t geom[6] = {sizeof(struct vlff_prompt_request), BODY_OFFSET, ANSWER_SLOTS, ANSWERS_OFFSET, 0, 0};
  int fresh = shm_seg_create(&p->seg, name, &shm_prompts_spec, geom, perm);
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
  if (shm_seg_attach(&p->seg, name, &shm_prompts_spec, true, NULL) < 0) {
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

API uint64_t vlff_prompts_last_post(const struct vlff_prompts *p) { return p ? p->posted : 0; }

/* Valid UTF-8 without control characters (C0 with tabs and newlines, DEL, C1), the
 * rule of the embeddings file format (node/vlm/embeddings.c). */
static bool utf8_text_ok(const char *s, size_t n) {
  for (size_t i = 0; i < n;) {
    uint8_t c = (uint8_t)s[i];
    if (c < 0x20 || c == 0x7F)
      return false;
    size_t len = c < 0x80 ? 1 : (c >= 0xC2 && c <= 0xDF) ? 2 : (c >= 0xE0 && c <= 0xEF) ? 3 : (c >= 0xF0 && c <= 0xF4) ? 4 : 0;
    if (!len || i + len > n)
      return false;
    uint32_t cp = len == 1 ? c : len == 2 ? (c & 0x1Fu) : len == 3 ? (c & 0x0Fu) : (c & 0x07u);
    for (size_t k = 1; k < len; k++) {
      uint8_t cc = (uint8_t)s[i + k];
      if ((cc & 0xC0) != 0x80)
        return false;
      cp = cp << 6 | (cc & 0x3Fu);
    }
    if ((len == 3 && (cp < 0x800 || (cp >= 0xD800 && cp <= 0xDFFF))) || (len == 4 && (cp < 0x10000 || cp > 0x10FFFF)))
      return false;
    if (cp >= 0x80 && cp <= 0x9F)
      return false;
    i += len;
  }
  return n > 0;
}

/* Writes why a set of texts is refused into why; 0 if it is acceptable. */
static int check_texts(const char *const *texts, int count, size_t cap, char *why, size_t len) {
  if (count < 1 || count > VLFF_SHM_MAX_PROMPTS) {
    snprintf(why, len, "%d prompts (expected 1..%d)", count, VLFF_SHM_MAX_PROMPTS);
    return -1;
  }
  for (int i = 0; i < count; i++) {
    const char *t = texts[i];
    size_t n = t ? strnlen(t, cap) : 0;
    if (n == 0 || n >= VLFF_SHM_PROMPT_LEN) {
      snprintf(why, len, "prompt %d is empty or longer than %d bytes", i + 1, VLFF_SHM_PROMPT_LEN - 1);
      return -1;
    }
    if (!utf8_text_ok(t, n)) {
      snprintf(why, len, "prompt %d is not UTF-8 text without control characters (tabs and newlines included)",
               i + 1);
      return -1;
    }
    for (int j = 0; j < i; j++)
      if (!strcmp(texts[j], t)) {
        snprintf(why, len, "prompt %d repeats prompt %d ('%s')", i + 1, j + 1, VLFF_Q(t));
        return -1;
      }
  }
  return 0;
}

API int vlff_prompt_check(const char *const *texts, int count) {
  char why[160];
  if (!texts || check_texts(texts, count, VLFF_SHM_PROMPT_LEN, why, sizeof why) < 0) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "prompts refused: %s", texts ? why : "no texts");
    return -1;
  }
  return 0;
}

/* The answer to request seq, read consistently: 1 (found), 0 (not answered yet),
 * -1 (its slot holds a later request's answer, or it kept changing). */
/* Out of line: GCC refuses the fence below when it is inlined into the wait loop
 * under -fsanitize=thread. */
__attribute__((noinline)) static int read_answer(struct vlff_prompts *p, uint64_t seq, int *status, char *reason, size_t len) {
  struct answer *a = &p->answers[seq % ANSWER_SLOTS];
  for (int i = 0; i < 1000; i++) {
    uint64_t w1 = atomic_load_explicit(&a->word, memory_order_acquire);
    if (w1 & 1) {
      nanosleep(&(struct timespec){0, 20000}, NULL);
      continue;
    }
    char r[ANSWER_REASON_LEN];
    uint64_t aseq = atomic_load_explicit(&a->seq, memory_order_relaxed);
    int st = atomic_load_explicit(&a->status, memory_order_relaxed);
    shm_racy_copy(r, a->reason, sizeof r);
    atomic_thread_fence(memory_order_acquire);
    if (atomic_load_explicit(&a->word, memory_order_relaxed) != w1)
      continue;
    if (aseq != seq)
      return aseq > seq ? -1 : 0;
    r[sizeof r - 1] = 0;
    *status = st;
    if (reason && len)
      snprintf(reason, len, "%s", r);
    return 1;
  }
  return -1;
}

static int write_answer(struct vlff_prompts *p, uint64_t seq, int status, const char *reason) {
  char r[ANSWER_REASON_LEN] = {0};
  if (reason)
    snprintf(r, sizeof r, "%s", reason);
  struct answer *a = &p->answers[seq % ANSWER_SLOTS];
  uint64_t odd = atomic_load_explicit(&a->word, memory_order_relaxed) | 1;
  atomic_store_explicit(&a->word, odd, memory_order_relaxed);
  atomic_thread_fence(memory_order_release);
  atomic_store_explicit(&a->seq, seq, memory_order_relaxed);
  atomic_store_explicit(&a->status, status, memory_order_relaxed);
  shm_racy_copy(a->reason, r, sizeof r);
  atomic_store_explicit(&a->word, odd + 1, memory_order_release);
  if (atomic_load_explicit(&p->ctl->answered, memory_order_relaxed) < seq)
    atomic_store_explicit(&p->ctl->answered, seq, memory_order_release);
  if (p->answered < seq)
    p->answered = seq;
  return 0;
}

static int check_live(struct vlff_prompts *p, bool stat_it) {
  if (p->broken) {
    shm_err(VLFF_SHM_ERR_SYS, EPIPE, "%s: could not be replaced after a truncation; create it again",
            VLFF_Q(p->seg.name));
    return -1;
  }
  if (shm_seg_check(&p->seg, stat_it) < 0)
    return -1;
  /* A live learner repairs a forged state word at its next poll (shm_seg_validate). */
  if (atomic_load(&p->seg.h->state) == SEG_ABANDONED && !shm_hdr_creator_alive(p->seg.h)) {
    shm_err(VLFF_SHM_ERR_ABANDONED, EPIPE, "%s: abandoned by the learner; attach again", VLFF_Q(p->seg.name));
    return -1;
  }
  return 0;
}

/* The number of the newest request that has no answer yet, 0 if none. */
static uint64_t unanswered(struct vlff_prompts *p) {
  uint64_t posted = atomic_load_explicit(&p->ctl->seq, memory_order_acquire) / 2;
  return atomic_load_explicit(&p->ctl->answered, memory_order_acquire) >= posted ? 0 : posted;
}

static int post(struct vlff_prompts *p, const struct vlff_prompt_request *req) {
  if (!p->seg.writable) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "%s: handle is not writable", VLFF_Q(p->seg.name));
    return -1;
  }
  uint64_t t0 = shm_now();
  for (;;) {
    /* The file's size too: a mailbox fits in one page, and a write past the end of
     * file inside the last page vanishes without a fault. */
    if (check_live(p, true) < 0)
      return -1;
    uint64_t waiting = unanswered(p);
    if (!waiting && flock(p->seg.fd, LOCK_EX | LOCK_NB) == 0) {
      /* Under the lock: another poster may have posted since we looked. */
      if (!unanswered(p))
        break;
      flock(p->seg.fd, LOCK_UN);
    }
    if (shm_now() - t0 > LOCK_WAIT_NS) {
      int32_t holder = atomic_load(&p->ctl->lock_pid);
      int32_t learner = atomic_load(&p->seg.h->creator_pid);
      if (waiting)
        shm_err(VLFF_SHM_ERR_EXISTS, EBUSY,
                "%s: request %llu is still waiting for the learner's answer (learner pid %d %s); not posting over it",
                VLFF_Q(p->seg.name), (unsigned long long)waiting, (int)learner,
                shm_creator_alive(learner, atomic_load(&p->seg.h->creator_start)) ? "running" : "not running");
      else
        shm_err(VLFF_SHM_ERR_EXISTS, EBUSY, "%s: mailbox busy (pid %d posting)", VLFF_Q(p->seg.name), (int)holder);
      return -1;
    }
    nanosleep(&(struct timespec){0, 1000000}, NULL);
  }
  atomic_store_explicit(&p->ctl->lock_pid, (int32_t)getpid(), memory_order_relaxed);
  /* An odd word here was left by a poster that died mid-post: write over it. */
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
  atomic_store_explicit(&p->ctl->lock_pid, 0, memory_order_relaxed);
  flock(p->seg.fd, LOCK_UN);
  if (check_live(p, true) < 0)
    return -1;
  p->posted = r.seq;
  return 0;
}

API int vlff_prompts_post(struct vlff_prompts *p, const char *const *texts, int count) {
  if (!p || vlff_prompt_check(texts, count) < 0) {
    if (!p)
      shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_prompts_post: NULL mailbox");
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

/* The post of an event loop, which must not wait: with the lock taken here without
 * waiting and no request unanswered, post() (whose flock on the same open file only
 * confirms the lock this handle holds) passes its loop at once. */
API int vlff_prompts_try_post(struct vlff_prompts *p, const char *const *texts, int count, int set_index) {
  if (!p || (texts ? count < 1 : set_index < 0)) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_prompts_try_post: %s", p ? "no texts and no set index" : "NULL mailbox");
    return -1;
  }
  if (!p->seg.writable) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "%s: handle is not writable", VLFF_Q(p->seg.name));
    return -1;
  }
  if (check_live(p, true) < 0)
    return -1;
  if (flock(p->seg.fd, LOCK_EX | LOCK_NB) != 0) {
    shm_err(VLFF_SHM_ERR_EXISTS, EBUSY, "%s: mailbox busy (pid %d posting)", VLFF_Q(p->seg.name),
            (int)atomic_load(&p->ctl->lock_pid));
    return -1;
  }
  uint64_t waiting = unanswered(p);
  int rc;
  if (waiting) {
    int32_t learner = atomic_load(&p->seg.h->creator_pid);
    shm_err(VLFF_SHM_ERR_EXISTS, EBUSY,
            "%s: request %llu is still waiting for the learner's answer (learner pid %d %s); not posting over it",
            VLFF_Q(p->seg.name), (unsigned long long)waiting, (int)learner,
            shm_creator_alive(learner, atomic_load(&p->seg.h->creator_start)) ? "running" : "not running");
    rc = -1;
  } else {
    rc = texts ? vlff_prompts_post(p, texts, count) : vlff_prompts_post_index(p, set_index);
  }
  int e = errno;
  flock(p->seg.fd, LOCK_UN); /* post() unlocks too; unless it failed before locking */
  errno = e;
  return rc;
}

/* What a poster wrote is external input for the learner. */
static bool request_sane(struct vlff_prompt_request *r, char *why, size_t len) {
  if (r->set_index >= 0) {
    if (r->count != 0) {
      snprintf(why, len, "a set index with %d texts", r->count);
      return false;
    }
    return true;
  }
  if (r->set_index != -1) {
    snprintf(why, len, "set index %d", (int)r->set_index);
    return false;
  }
  if (r->count < 1 || r->count > VLFF_SHM_MAX_PROMPTS) {
    snprintf(why, len, "%d prompts (expected 1..%d)", r->count, VLFF_SHM_MAX_PROMPTS);
    return false;
  }
  const char *texts[VLFF_SHM_MAX_PROMPTS];
  for (int i = 0; i < r->count; i++) {
    if (!memchr(r->text[i], 0, VLFF_SHM_PROMPT_LEN)) {
      snprintf(why, len, "prompt %d is not terminated", i + 1);
      return false;
    }
    texts[i] = r->text[i];
  }
  return check_texts(texts, r->count, VLFF_SHM_PROMPT_LEN, why, len) == 0;
}

/* Learner: the file shrank under us. A new mailbox goes on from the same request
 * number, so that posters' numbers never repeat. */
static int learner_replace(struct vlff_prompts *p, uint64_t last_seq) {
  char msg[320];
  if (p->broken)
    snprintf(msg, sizeof msg, "%s: made again after its replacement had failed", VLFF_Q(p->seg.name));
  else
    snprintf(msg, sizeof msg, "%s", vlff_shm_last_message());
  /* After a failed replacement (no space left in /dev/shm), again after a growing delay. */
  if ((p->broken ? shm_seg_retry(&p->seg) : shm_seg_replace(&p->seg)) < 0) {
    p->broken = true;
    return -1;
  }
  p->broken = false;
  bind(p);
  if (atomic_load(&p->ctl->seq) / 2 < last_seq) {
    atomic_store(&p->ctl->seq, 2 * last_seq);
    write_answer(p, last_seq, VLFF_PROMPT_REFUSED, "the mailbox was truncated and replaced");
  }
  shm_seg_ready(&p->seg);
  shm_err(VLFF_SHM_ERR_TRUNCATED, EPIPE, "%s", msg);
  return -1;
}

/* Posts only ever go up, by one per answered request, and an odd word belongs to a
 * post in progress whose number is (s1 + 1) / 2: a number at or below the learner's
 * last (floor), or beyond any real count, was written by something else. */
static bool seq_bad(uint64_t s1, uint64_t floor) {
  return s1 >= 2 * SEQ_LIMIT || (s1 & 1 ? (s1 + 1) / 2 <= floor : s1 / 2 < floor);
}
/* The answered word is the learner's alone: never beyond the newest request, never
 * below what this learner answered. */
static bool answered_bad(const struct vlff_prompts *p, uint64_t ans, uint64_t s1) {
  return ans > s1 / 2 || ans < p->answered;
}

/* Learner: the mailbox is group-writable, so any poster's process can write any
 * word of it, and two words can disable it for everyone: the state word (posters
 * refuse an "abandoned" mailbox) and the request number (a number that goes back
 * makes posters wait for answers that a later request's answer fills). The learner
 * is alive and knows both: it sets them back, counts it, and says so once per
 * repair. 0 if both were fine, -1 with the message (EBADMSG) if one was repaired,
 * 1 if a poster holds the lock (look again at the next poll). */
static int learner_repair(struct vlff_prompts *p, uint64_t *last_seq) {
  uint32_t st = atomic_load(&p->seg.h->state);
  if (st != SEG_READY) {
    atomic_store(&p->seg.h->state, SEG_READY);
    atomic_store(&p->ctl->repairs, ++p->repairs);
    shm_err(VLFF_SHM_ERR_CORRUPT, EBADMSG,
            "%s: state word %u (%s) written by a process with write access to the mailbox (its group); the learner "
            "is alive and set it back to ready (%llu repairs so far)",
            VLFF_Q(p->seg.name), st, st == SEG_ABANDONED ? "abandoned" : st == SEG_INIT ? "not ready" : "no state",
            (unsigned long long)p->repairs);
    return -1;
  }
  uint64_t floor = *last_seq < SEQ_LIMIT ? *last_seq : 0;
  uint64_t s1 = atomic_load_explicit(&p->ctl->seq, memory_order_acquire);
  uint64_t ans = atomic_load_explicit(&p->ctl->answered, memory_order_acquire);
  if (!seq_bad(s1, floor) && !answered_bad(p, ans, s1))
    return 0;
  if (flock(p->seg.fd, LOCK_EX | LOCK_NB) < 0)
    return 1;
  s1 = atomic_load_explicit(&p->ctl->seq, memory_order_acquire);
  ans = atomic_load_explicit(&p->ctl->answered, memory_order_acquire);
  bool bad_seq = seq_bad(s1, floor), bad_ans = answered_bad(p, ans, bad_seq ? 2 * floor : s1);
  if (!bad_seq && !bad_ans) {
    flock(p->seg.fd, LOCK_UN);
    return 0;
  }
  if (bad_seq) {
    atomic_store_explicit(&p->ctl->seq, 2 * floor, memory_order_release);
    atomic_store_explicit(&p->ctl->lock_pid, 0, memory_order_relaxed);
  }
  uint64_t posted = bad_seq ? floor : s1 / 2, fixed = ans;
  if (bad_ans) {
    /* What the learner itself answered last, never beyond the newest request: a
     * word beyond it lets a post overwrite an unread request, one below it makes
     * every post wait for an answer that was given. */
    fixed = p->answered < posted ? p->answered : posted;
    atomic_store_explicit(&p->ctl->answered, fixed, memory_order_release);
  }
  atomic_store(&p->ctl->resyncs, ++p->resyncs);
  flock(p->seg.fd, LOCK_UN);
  *last_seq = floor;
  char what[160];
  if (bad_seq)
    snprintf(what, sizeof what, "request number %llu%s after request %llu", (unsigned long long)(s1 / 2),
             s1 & 1 ? " (being written)" : "", (unsigned long long)floor);
  else
    snprintf(what, sizeof what, "answered word %llu with requests up to %llu answered up to %llu",
             (unsigned long long)ans, (unsigned long long)posted, (unsigned long long)fixed);
  shm_err(VLFF_SHM_ERR_CORRUPT, EBADMSG,
          "%s: %s, written by a process with write access to the mailbox, not by a post; set it back so that "
          "the next post is %llu (%llu resyncs so far)",
          VLFF_Q(p->seg.name), what, (unsigned long long)(posted + 1), (unsigned long long)p->resyncs);
  return -1;
}

API int vlff_prompts_poll(struct vlff_prompts *p, uint64_t *last_seq, struct vlff_prompt_request *req) {
  if (!p || !last_seq || !req) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_prompts_poll: NULL argument");
    return -1;
  }
  if (p->seg.creator && (p->broken || shm_seg_check(&p->seg, true) < 0))
    return learner_replace(p, *last_seq);
  if (p->seg.creator && !p->broken) {
    int r = learner_repair(p, last_seq);
    if (r)
      return r < 0 ? -1 : 0;
  }
  if (check_live(p, false) < 0)
    return -1;
  for (int i = 0; i < 16; i++) {
    uint64_t s1 = atomic_load_explicit(&p->ctl->seq, memory_order_acquire);
    if (s1 & 1) {
      /* A live poster holds the lock while it writes: come back at the next poll
       * rather than wait for it. A free lock means the poster died mid-post. */
      if (!p->seg.creator || flock(p->seg.fd, LOCK_EX | LOCK_NB) < 0)
        return 0;
      int32_t dead = atomic_load(&p->ctl->lock_pid);
      bool still = atomic_load_explicit(&p->ctl->seq, memory_order_acquire) == s1;
      if (still) {
        struct vlff_prompt_request z = {.seq = (s1 + 1) / 2, .set_index = -1};
        shm_racy_copy(p->body, &z, sizeof z);
        atomic_store_explicit(&p->ctl->seq, s1 + 1, memory_order_release);
        atomic_store_explicit(&p->ctl->lock_pid, 0, memory_order_relaxed);
        write_answer(p, (s1 + 1) / 2, VLFF_PROMPT_REFUSED, "its poster died while writing it");
        *last_seq = (s1 + 1) / 2;
      }
      flock(p->seg.fd, LOCK_UN);
      if (still) {
        shm_err(VLFF_SHM_ERR_CORRUPT, EBADMSG,
                "%s: request %llu was left half-written by poster pid %d, which died; discarded it",
                  VLFF_Q(p->seg.name),
                (unsigned long long)((s1 + 1) / 2), (int)dead);
        return -1;
      }
      continue;
    }
    if (s1 / 2 == *last_seq)
      return 0;
    shm_racy_copy(req, p->body, sizeof *req);
    atomic_thread_fence(memory_order_acquire);
    if (check_live(p, false) < 0)
      return -1;
    if (atomic_load_explicit(&p->ctl->seq, memory_order_relaxed) != s1)
      continue;
    *last_seq = s1 / 2;
    char why[160];
    if (req->seq != s1 / 2) {
      snprintf(why, sizeof why, "its number %llu does not match the mailbox's", (unsigned long long)req->seq);
    } else if (request_sane(req, why, sizeof why)) {
      return 1;
    }
    if (p->seg.creator)
      write_answer(p, s1 / 2, VLFF_PROMPT_REFUSED, why);
    shm_err(VLFF_SHM_ERR_CORRUPT, EBADMSG, "%s: request %llu from pid %d refused: %s", VLFF_Q(p->seg.name),
            (unsigned long long)(s1 / 2), (int)req->poster_pid, why);
    return -1;
  }
  return 0;
}

API int vlff_prompts_answer(struct vlff_prompts *p, uint64_t seq, int accepted, const char *reason) {
  if (!p || !p->seg.creator || !seq) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_prompts_answer: not the learner's handle, or no request");
    return -1;
  }
  if (check_live(p, false) < 0)
    return -1;
  return write_answer(p, seq, accepted ? VLFF_PROMPT_ACCEPTED : VLFF_PROMPT_REFUSED,
                      accepted ? "" : reason && reason[0] ? reason : "refused");
}

API int vlff_prompts_wait_answer(struct vlff_prompts *p, uint64_t seq, uint64_t timeout_ns, char *reason,
                                 size_t len) {
  if (!p || !seq) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_prompts_wait_answer: no mailbox or no request");
    return -1;
  }
  uint64_t t0 = shm_now();
  for (;;) {
    if (check_live(p, false) < 0)
      return -1;
    int st = 0;
    int got = read_answer(p, seq, &st, reason, len);
    if (got == 1 && (st == VLFF_PROMPT_ACCEPTED || st == VLFF_PROMPT_REFUSED))
      return st;
    if (got < 0) {
      shm_err(VLFF_SHM_OK, ENOENT, "%s: the answer to request %llu is gone (%u later requests were answered since)",
              VLFF_Q(p->seg.name), (unsigned long long)seq, ANSWER_SLOTS);
      return -1;
    }
    if (timeout_ns != UINT64_MAX && shm_now() - t0 >= timeout_ns) {
      int32_t learner = atomic_load(&p->seg.h->creator_pid);
      shm_err(VLFF_SHM_OK, ETIMEDOUT, "%s: no answer to request %llu yet (learner pid %d %s)", VLFF_Q(p->seg.name),
              (unsigned long long)seq, (int)learner,
              shm_creator_alive(learner, atomic_load(&p->seg.h->creator_start)) ? "running" : "not running");
      return -1;
    }
    nanosleep(&(struct timespec){0, 1000000}, NULL);
  }
}
