/* Internals shared by the shm/ sources: the common segment header every vlff segment
 * starts with, creation/attach with validation, and error recording. */
#ifndef VLFF_SHM_INTERNAL_H
#define VLFF_SHM_INTERNAL_H

#include "vlff/shm.h"
#include "vlff/escape.h" /* VLFF_Q: names and texts quoted in messages */

#include <stdatomic.h>
#include <stdbool.h>
#include <stdint.h>
#include <string.h>
#include <sys/types.h>

#define API __attribute__((visibility("default")))

/* "VLFFSHM" + NUL as a little-endian word. */
#define SEG_MAGIC 0x004D485346464C56ull

/* SEG_MOVED: the creator put a larger segment under the name (ABI 9, a map
 * growing past its capacity: vlff_map_reserve); a reader attaches the name
 * again and reads on there. */
enum seg_state { SEG_INIT = 0, SEG_READY = 1, SEG_ABANDONED = 2, SEG_MOVED = 3 };

/* Every segment starts with these 128 bytes. The geometry words are immutable after
 * creation and covered by geom_check, so a reader can tell a corrupt header from a
 * segment of another shape. */
struct seg_hdr {
  uint64_t magic;
  uint32_t abi_version;
  uint32_t kind;        /* enum vlff_shm_kind */
  uint32_t record_kind; /* rings */
  uint32_t geom_check;
  uint64_t total_size;
  uint64_t geom[6];     /* kind-specific */
  _Atomic uint32_t state;
  _Atomic int32_t creator_pid;
  _Atomic uint32_t generation;
  uint32_t pad0;
  _Atomic uint64_t last_ns;
  /* The creator's start time (/proc/PID/task/PID/stat, clock ticks since boot; 0 =
   * unknown, as written before this field): a creator PID that is alive but
   * started at another time is a later process that reused the PID. */
  _Atomic uint64_t creator_start;
  uint8_t pad1[128 - 32 - 48 - 32];
};
_Static_assert(sizeof(struct seg_hdr) == 128, "segment header is 128 bytes");

/* Kind-specific description used to validate and create. compute_total returns the
 * expected total size from the geometry, or 0 if the geometry is not sane. */
/* What one kind of segment is: the module that owns the kind (ring.c, map.c,
 * prompts.c) fills it, so seg.c never needs to know the kinds. */
struct seg;
struct vlff_shm_info;
struct seg_spec {
  uint32_t kind;
  uint32_t record_kind; /* 0 = any on attach */
  uint64_t (*compute_total)(const uint64_t geom[6]); /* the size its geometry implies */
  void (*stat)(const struct seg *s, struct vlff_shm_info *info); /* its part of vlff_shm_stat */
};

/* What an attacher demands of the segment's file (struct stat) before reading it. */
struct seg_trust {
  bool check_owner;
  uid_t uid;
  mode_t mode; /* allowed permission bits; 0 = any but world-writable */
};

/* One mapped segment. */
struct seg {
  char name[256];
  int fd;
  bool writable;
  uint8_t *base;
  uint64_t size;
  struct seg_hdr *h;
  /* Set by the SIGBUS guard when the file shrank under the mapping (guard.c). */
  _Atomic uint32_t fault;
  int guard_slot; /* registry entry + 1, 0 = none */
  /* A creator keeps what it needs to replace a damaged segment by a new one. */
  bool creator;
  struct seg_spec spec;
  uint64_t geom[6];
  mode_t mode;
  char group[64];
  /* A creator whose replacement failed (no space left in /dev/shm, ...): the handle
   * keeps the above, and shm_seg_retry tries again after a growing delay. */
  bool failed;
  uint64_t retry_ns, retry_delay_ns, retries;
  int why_code;
  char why[320];
};

void shm_err(int code, int errnum, const char *fmt, ...) __attribute__((format(printf, 3, 4)));
uint32_t shm_geom_check(const struct seg_hdr *h);
int shm_pid_alive(int32_t pid);
/* Start time of process pid (clock ticks since boot), 0 if unreadable. */
uint64_t shm_proc_start(int32_t pid);
/* Whether the creator pid started at start (0: unknown) is still running:
 * its PID alive and, where both are known, its start time the same. */
int shm_creator_alive(int32_t pid, uint64_t start);
/* The same for a mapped header's creator. */
int shm_hdr_creator_alive(const struct seg_hdr *h);
uint64_t shm_now(void);

/* Attach: maps the whole segment after validating it against spec. */
int shm_seg_attach(struct seg *s, const char *name, const struct seg_spec *spec, bool writable,
                   const struct seg_trust *trust);
/* Create: returns 1 if a fresh segment was created (header written, state INIT: the
 * caller initialises its body then calls shm_seg_ready), 0 if a dead creator's
 * segment of identical geometry was taken over (generation bumped, state READY). */
int shm_seg_create(struct seg *s, const char *name, const struct seg_spec *spec, const uint64_t geom[6],
                   const struct vlff_shm_perm *perm);
void shm_seg_ready(struct seg *s);
/* Moves the mapped segment src into dst (the SIGBUS guard follows it); src is
 * left unmapped. */
void shm_seg_move(struct seg *dst, struct seg *src);
/* Gives the segment created as s under a temporary name the name `name`
 * (rename in /dev/shm: whoever attaches the name from then on gets it, and
 * whoever has the old file mapped keeps it). 0, or -1 with the error set. */
int shm_seg_rename(struct seg *s, const char *name);
void shm_seg_close(struct seg *s);
/* 0 if the mapping is still backed by the whole file; -1 (VLFF_SHM_ERR_TRUNCATED,
 * EPIPE) if the SIGBUS guard fired on it or, with stat_it, if the file is now smaller
 * than the mapping; with stat_it, -1 (VLFF_SHM_ERR_ABANDONED, EPIPE) for a reader
 * whose file was removed from /dev/shm. */
int shm_seg_check(struct seg *s, bool stat_it);
/* Creator: abandons a damaged segment (its name is unlinked if it still names it) and
 * creates a new one of the same geometry and permissions. Returns as shm_seg_create;
 * on failure the handle is closed. */
int shm_seg_replace(struct seg *s);
/* Creator whose replacement failed (s->failed): before the retry delay has passed,
 * -1 (EPIPE, the failure's code, its message with when the next try comes); after,
 * shm_seg_replace again, the delay doubling (0.1 s up to 5 s) while it fails. */
int shm_seg_retry(struct seg *s);

/* The SIGBUS guard (guard.c): registers a mapping so that a fault inside it is
 * survived and flags s->fault. */
int shm_guard_register(struct seg *s, int prot);
void shm_guard_unregister(struct seg *s);

/* Copies that may race with a writer in another thread by design (seqlock: the reader
 * validates afterwards and discards torn data). Kept out of ThreadSanitizer's view;
 * the sequence words around them are real atomics that TSan does check. */
void shm_racy_copy(void *dst, const void *src, size_t n);
void shm_racy_fill(void *dst, int c, size_t n);
/* The fences between a seqlock's sequence words and its racy copies. Out of line:
 * GCC refuses some inlined fences under -fsanitize=thread (-Wtsan). */
void shm_fence_release(void);
void shm_fence_acquire(void);

/* The header of a named segment, read with pread and checked for the magic
 * only: which kind to attach it as (stat.c). */
int shm_seg_peek(const char *name, struct seg_hdr *out);

/* Each kind's spec (record_kind 0: any ring). */
struct seg_spec shm_ring_spec(uint32_t record_kind);
extern const struct seg_spec shm_map_spec, shm_prompts_spec;

int shm_ring_peek(struct vlff_ring *r, uint64_t n, void *out, size_t want);

static inline uint64_t align64(uint64_t v) { return (v + 63) & ~(uint64_t)63; }

#endif
