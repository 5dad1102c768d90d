/* Segment plumbing shared by rings, the map and the prompt mailbox.
 *
 * A segment is created O_EXCL so two creators never share one by accident. A creator
 * that died leaves its segment behind; the next creator takes it over in place when
 * the geometry matches (attached readers keep their mapping and see the generation
 * change) and otherwise marks it abandoned and replaces it (readers get EPIPE and
 * re-attach). Attach never trusts the file: every header field is checked before the
 * body is mapped, and the file must be as large as the header claims; a file that
 * shrinks later is the SIGBUS guard's business (guard.c). Only files of this
 * process's uid are ever taken over or removed: another user's file at our name
 * could be truncated or rewritten by its owner under us. */
#include "shm_internal.h"

#include <errno.h>
#include <fcntl.h>
#include <grp.h>
#include <limits.h>
#include <signal.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

static _Thread_local int last_code;
static _Thread_local char last_msg[320];

void shm_err(int code, int errnum, const char *fmt, ...) {
  va_list ap;
  va_start(ap, fmt);
  vsnprintf(last_msg, sizeof last_msg, fmt, ap);
  va_end(ap);
  last_code = code;
  errno = errnum;
}

API int vlff_shm_last_error(void) { return last_code; }
API const char *vlff_shm_last_message(void) { return last_msg[0] ? last_msg : vlff_shm_strerror(last_code); }

API const char *vlff_shm_strerror(int err) {
  switch (err) {
  case VLFF_SHM_OK: return "no error";
  case VLFF_SHM_ERR_SYS: return "system call failed";
  case VLFF_SHM_ERR_INVAL: return "invalid argument";
  case VLFF_SHM_ERR_MISSING: return "no such segment";
  case VLFF_SHM_ERR_EXISTS: return "segment owned by a live creator";
  case VLFF_SHM_ERR_PERM: return "permission denied";
  case VLFF_SHM_ERR_FOREIGN: return "not a vlff segment";
  case VLFF_SHM_ERR_KIND: return "vlff segment of another kind";
  case VLFF_SHM_ERR_VERSION: return "unsupported ABI version";
  case VLFF_SHM_ERR_TRUNCATED: return "segment truncated";
  case VLFF_SHM_ERR_CORRUPT: return "corrupt segment header";
  case VLFF_SHM_ERR_NOTREADY: return "segment not initialised yet";
  case VLFF_SHM_ERR_ABANDONED: return "segment abandoned by its creator";
  case VLFF_SHM_ERR_SIZE: return "too large for the segment";
  case VLFF_SHM_ERR_NOSPACE: return "no space left in /dev/shm";
  default: return "unknown error";
  }
}

uint64_t shm_now(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (uint64_t)ts.tv_sec * 1000000000ull + (uint64_t)ts.tv_nsec;
}
API uint64_t vlff_shm_now_ns(void) { return shm_now(); }

int shm_pid_alive(int32_t pid) {
  if (pid <= 0)
    return 0;
  /* EPERM: exists but belongs to someone else - alive as far as we can tell. */
  return kill(pid, 0) == 0 || errno != ESRCH;
}

uint64_t shm_proc_start(int32_t pid) {
  char path[64], buf[1024];
  /* The thread-group leader's task entry, which natively reads as
   * /proc/PID/stat does. Why not that: qemu-user answers a process's own
   * /proc/PID/stat itself, with its parent's start time after a fork, so a
   * creator under emulation recorded a start time that others never read. */
  snprintf(path, sizeof path, "/proc/%d/task/%d/stat", (int)pid, (int)pid);
  int fd = open(path, O_RDONLY | O_CLOEXEC);
  if (fd < 0)
    return 0;
  ssize_t n = read(fd, buf, sizeof buf - 1);
  close(fd);
  if (n <= 0)
    return 0;
  buf[n] = 0;
  /* "pid (comm) state ppid ...": comm may hold spaces and ')', so count the
   * fields after its last ')'; the start time is field 22, the 20th after. */
  char *p = strrchr(buf, ')');
  for (int field = 2; p && field < 22; field++)
    p = strchr(p + 1, ' ');
  if (!p)
    return 0;
  char *end;
  unsigned long long t = strtoull(p + 1, &end, 10);
  return end > p + 1 ? (uint64_t)t : 0;
}

int shm_creator_alive(int32_t pid, uint64_t start) {
  if (!shm_pid_alive(pid))
    return 0;
  uint64_t now = start ? shm_proc_start(pid) : 0;
  return !now || now == start;
}

int shm_hdr_creator_alive(const struct seg_hdr *h) {
  return shm_creator_alive(atomic_load(&h->creator_pid), atomic_load(&h->creator_start));
}

uint32_t shm_geom_check(const struct seg_hdr *h) {
  /* FNV-1a over the immutable fields. */
  uint32_t x = 2166136261u;
  uint64_t w[10] = {h->magic, h->abi_version, h->kind, h->record_kind, h->total_size,
                    h->geom[0], h->geom[1], h->geom[2], h->geom[3], h->geom[4] ^ (h->geom[5] << 1)};
  const uint8_t *p = (const uint8_t *)w;
  for (size_t i = 0; i < sizeof w; i++)
    x = (x ^ p[i]) * 16777619u;
  return x ? x : 1;
}

#if defined(__SANITIZE_THREAD__)
#define VLFF_TSAN 1
#elif defined(__has_feature)
#if __has_feature(thread_sanitizer)
#define VLFF_TSAN 1
#endif
#endif

#ifdef VLFF_TSAN
/* Under ThreadSanitizer the seqlock's data copies are made of relaxed atomics on both
 * sides, which is the formally race-free form of the pattern, so that TSan checks the
 * protocol instead of flagging the by-design overlap of a reader with the writer. */
void shm_racy_copy(void *dst, const void *src, size_t n) {
  uint8_t *d = dst;
  const uint8_t *s = src;
  for (size_t i = 0; i < n; i++)
    __atomic_store_n(d + i, __atomic_load_n(s + i, __ATOMIC_RELAXED), __ATOMIC_RELAXED);
}
void shm_racy_fill(void *dst, int c, size_t n) {
  uint8_t *d = dst;
  for (size_t i = 0; i < n; i++)
    __atomic_store_n(d + i, (uint8_t)c, __ATOMIC_RELAXED);
}
#else
void shm_racy_copy(void *dst, const void *src, size_t n) { memcpy(dst, src, n); }
void shm_racy_fill(void *dst, int c, size_t n) { memset(dst, c, n); }
#endif

void shm_fence_release(void) { atomic_thread_fence(memory_order_release); }
void shm_fence_acquire(void) { atomic_thread_fence(memory_order_acquire); }

static int check_name(const char *name) {
  if (!name || name[0] != '/' || strlen(name) < 2 || strlen(name) >= 250 || strchr(name + 1, '/')) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "%s: a segment name is '/' followed by 1..248 characters without '/'",
            VLFF_Q(name ? name : "(null)"));
    return -1;
  }
  return 0;
}

static int open_error(const char *name, const char *what) {
  int e = errno;
  if (e == ENOENT)
    shm_err(VLFF_SHM_ERR_MISSING, e, "%s: no such segment", VLFF_Q(name));
  else if (e == EACCES || e == EPERM)
    shm_err(VLFF_SHM_ERR_PERM, EACCES, "%s: permission denied (%s)", VLFF_Q(name), what);
  else
    shm_err(VLFF_SHM_ERR_SYS, e, "%s: %s: %s", VLFF_Q(name), what, strerror(e));
  return -1;
}

/* A segment's name that leads to something other than a regular file: a FIFO
 * planted there (anyone may create one in /dev/shm) would block a plain open()
 * until a writer comes, which is why every segment is opened O_NONBLOCK and
 * looked at with fstat before a byte is read. */
static int not_regular(const char *name, const struct stat *st) {
  mode_t m = st->st_mode;
  const char *what = S_ISFIFO(m) ? "a FIFO" : S_ISDIR(m) ? "a directory" : S_ISCHR(m) ? "a character device"
                     : S_ISBLK(m) ? "a block device" : S_ISSOCK(m) ? "a socket" : "not a regular file";
  shm_err(VLFF_SHM_ERR_FOREIGN, EPROTO, "%s: is %s, expected a regular file (/dev/shm%s, owner uid %u); refusing it",
          VLFF_Q(name), what, VLFF_Q(name), (unsigned)st->st_uid);
  return -1;
}

/* shm_open of name (O_NONBLOCK added) that must be a regular file, its
 * fstat in *st: the descriptor, or -1 with the error set (errno ENOENT when
 * there is nothing at the name; error FOREIGN when something else is). */
static int open_regular(const char *name, int flags, const char *what, struct stat *st) {
  int fd = shm_open(name, flags | O_NONBLOCK, 0);
  if (fd < 0)
    return open_error(name, what);
  if (fstat(fd, st) < 0) {
    int e = errno;
    close(fd);
    errno = e;
    return open_error(name, "fstat");
  }
  if (!S_ISREG(st->st_mode)) {
    close(fd);
    return not_regular(name, st);
  }
  return fd;
}

/* The kinds by name, for messages a user reads: "segment kind 1" alone
 * does not say that a ring was named where a map was meant. */
static const char *kind_name(uint32_t k) {
  return k == VLFF_SHM_KIND_RING      ? "a ring"
         : k == VLFF_SHM_KIND_MAP     ? "a map"
         : k == VLFF_SHM_KIND_PROMPTS ? "a prompt mailbox"
                                      : "an unknown kind";
}
static const char *record_name(uint32_t k) {
  static const char *const n[] = {"any records", "raw records", "frames", "features", "poses"};
  return k < sizeof n / sizeof n[0] ? n[k] : "unknown records";
}

/* The magic word: a new segment is zeros until its creator writes the
 * header, so 0 means not yet. */
static int check_magic(const char *name, const struct seg_hdr *h) {
  if (h->magic == 0) {
    shm_err(VLFF_SHM_ERR_NOTREADY, EAGAIN, "%s: header not written yet (creator starting or died)", VLFF_Q(name));
    return -1;
  }
  if (h->magic != SEG_MAGIC) {
    shm_err(VLFF_SHM_ERR_FOREIGN, EPROTO, "%s: magic %016llx is not a vlff segment", VLFF_Q(name),
            (unsigned long long)h->magic);
    return -1;
  }
  return 0;
}

/* Validates a header copy against the file size. Returns 0 or -1 with the error set. */
static int validate(const char *name, const struct seg_hdr *h, uint64_t file_size, const struct seg_spec *spec) {
  if (check_magic(name, h) < 0)
    return -1;
  if (h->abi_version != VLFF_SHM_ABI_VERSION) {
    shm_err(VLFF_SHM_ERR_VERSION, EPROTONOSUPPORT, "%s: ABI version %u, this library speaks %u", VLFF_Q(name),
            h->abi_version, VLFF_SHM_ABI_VERSION);
    return -1;
  }
  if (h->geom_check != shm_geom_check(h)) {
    shm_err(VLFF_SHM_ERR_CORRUPT, EBADMSG, "%s: header checksum %08x does not match its fields (%08x)", VLFF_Q(name),
            h->geom_check, shm_geom_check(h));
    return -1;
  }
  if (h->kind != spec->kind) {
    shm_err(VLFF_SHM_ERR_KIND, EPROTO, "%s: segment kind %u, expected %u (%s where %s is expected)", VLFF_Q(name),
            h->kind, spec->kind, kind_name(h->kind), kind_name(spec->kind));
    return -1;
  }
  uint64_t want = spec->compute_total(h->geom);
  if (want == 0 || want != h->total_size) {
    shm_err(VLFF_SHM_ERR_CORRUPT, EBADMSG, "%s: kind %u geometry inconsistent with total size %llu", VLFF_Q(name),
            h->kind,
            (unsigned long long)h->total_size);
    return -1;
  }
  if (spec->record_kind && h->record_kind != spec->record_kind) {
    shm_err(VLFF_SHM_ERR_KIND, EPROTO, "%s: ring of record kind %u, expected %u (a ring of %s where %s are expected)",
            VLFF_Q(name), h->record_kind, spec->record_kind, record_name(h->record_kind), record_name(spec->record_kind));
    return -1;
  }
  if (file_size < h->total_size) {
    shm_err(VLFF_SHM_ERR_TRUNCATED, EBADMSG, "%s: %llu bytes, header says %llu", VLFF_Q(name),
            (unsigned long long)file_size, (unsigned long long)h->total_size);
    return -1;
  }
  uint32_t st = atomic_load_explicit(&((struct seg_hdr *)h)->state, memory_order_acquire);
  /* Every poster can write a mailbox's state word (its group has write access), and
   * its learner, while it runs, sets any other state back to ready at its next poll:
   * a poster goes on instead of losing the mailbox to a 4-byte write. */
  if (st != SEG_READY && spec->kind == VLFF_SHM_KIND_PROMPTS && shm_hdr_creator_alive(h))
    return 0;
  if (st == SEG_INIT) {
    shm_err(VLFF_SHM_ERR_NOTREADY, EAGAIN, "%s: creator pid %d has not finished initialising it", VLFF_Q(name),
            (int)h->creator_pid);
    return -1;
  }
  if (st == SEG_ABANDONED || st == SEG_MOVED) {
    shm_err(VLFF_SHM_ERR_ABANDONED, EPIPE, "%s: %s by its creator; attach again", VLFF_Q(name),
            st == SEG_MOVED ? "moved to a larger segment" : "abandoned");
    return -1;
  }
  if (st != SEG_READY) {
    shm_err(VLFF_SHM_ERR_CORRUPT, EBADMSG, "%s: state word %u is not a valid state", VLFF_Q(name), st);
    return -1;
  }
  return 0;
}

/* What every attacher demands of the file itself, before reading a byte of it: a
 * regular file, not writable by everyone (anyone could then forge or truncate it),
 * and whatever the caller's trust adds (an owner, a narrower mode). */
static int trust_check(const char *name, const struct stat *st, const struct seg_trust *t) {
  if (!S_ISREG(st->st_mode))
    return not_regular(name, st);
  if (t && t->check_owner && st->st_uid != t->uid) {
    shm_err(VLFF_SHM_ERR_PERM, EACCES, "%s: owned by uid %u, expected uid %u; refusing it", VLFF_Q(name),
            (unsigned)st->st_uid, (unsigned)t->uid);
    return -1;
  }
  mode_t bits = st->st_mode & 07777, allowed = t && t->mode ? t->mode : (0777 & ~(mode_t)0002);
  if (bits & ~allowed) {
    shm_err(VLFF_SHM_ERR_PERM, EACCES,
            "%s: mode %04o has bits beyond %04o (whoever they let in could forge or truncate it); refusing it",
            VLFF_Q(name), (unsigned)bits, (unsigned)allowed);
    return -1;
  }
  return 0;
}

static int map_checked(struct seg *s, const char *name, int fd, bool writable, const struct seg_spec *spec,
                       const struct seg_trust *trust) {
  struct stat st;
  if (fstat(fd, &st) < 0)
    return open_error(name, "fstat");
  if (trust_check(name, &st, trust) < 0)
    return -1;
  if ((uint64_t)st.st_size < sizeof(struct seg_hdr)) {
    uint64_t magic = 0;
    if (pread(fd, &magic, sizeof magic, 0) == (ssize_t)sizeof magic && magic != 0 && magic != SEG_MAGIC)
      shm_err(VLFF_SHM_ERR_FOREIGN, EPROTO, "%s: magic %016llx is not a vlff segment", VLFF_Q(name),
              (unsigned long long)magic);
    else if (st.st_size == 0)
      shm_err(VLFF_SHM_ERR_NOTREADY, EAGAIN, "%s: empty (creator starting or died)", VLFF_Q(name));
    else
      shm_err(VLFF_SHM_ERR_TRUNCATED, EBADMSG, "%s: %lld bytes, smaller than a segment header", VLFF_Q(name),
              (long long)st.st_size);
    return -1;
  }
  /* The header is read with pread, not through a mapping: the file may shrink at
   * any moment, and pread then fails where a mapped read would fault. */
  struct seg_hdr copy;
  if (pread(fd, &copy, sizeof copy, 0) != (ssize_t)sizeof copy) {
    shm_err(VLFF_SHM_ERR_TRUNCATED, EBADMSG, "%s: shrank below a segment header while attaching", VLFF_Q(name));
    return -1;
  }
  if (validate(name, &copy, (uint64_t)st.st_size, spec) < 0)
    return -1;
  int prot = PROT_READ | (writable ? PROT_WRITE : 0);
  void *p = mmap(NULL, copy.total_size, prot, MAP_SHARED, fd, 0);
  if (p == MAP_FAILED)
    return open_error(name, "mmap");
  snprintf(s->name, sizeof s->name, "%s", name);
  s->base = p;
  s->size = copy.total_size;
  s->h = p;
  atomic_store(&s->fault, 0);
  if (shm_guard_register(s, prot) < 0) {
    munmap(p, copy.total_size);
    s->base = NULL;
    return -1;
  }
  /* The mapped header must still say what the copy said (a creator replacing it in
   * between would change it, and so would a truncation, through the guard). */
  if (memcmp(s->h, &copy, offsetof(struct seg_hdr, state)) != 0 || atomic_load(&s->fault)) {
    shm_guard_unregister(s);
    munmap(p, copy.total_size);
    s->base = NULL;
    shm_err(VLFF_SHM_ERR_NOTREADY, EAGAIN, "%s: header changed while attaching", VLFF_Q(name));
    return -1;
  }
  return 0;
}

int shm_seg_peek(const char *name, struct seg_hdr *out) {
  if (check_name(name) < 0)
    return -1;
  struct stat st;
  int fd = open_regular(name, O_RDONLY, "open read-only", &st);
  if (fd < 0)
    return -1;
  ssize_t n = pread(fd, out, sizeof *out, 0);
  close(fd);
  if (n != (ssize_t)sizeof *out) {
    shm_err(VLFF_SHM_ERR_TRUNCATED, EBADMSG, "%s: no complete segment header", VLFF_Q(name));
    return -1;
  }
  return check_magic(name, out);
}

int shm_seg_attach(struct seg *s, const char *name, const struct seg_spec *spec, bool writable,
                   const struct seg_trust *trust) {
  memset(s, 0, sizeof *s);
  s->fd = -1;
  if (check_name(name) < 0)
    return -1;
  snprintf(s->name, sizeof s->name, "%s", name);
  int fd = shm_open(name, (writable ? O_RDWR : O_RDONLY) | O_NONBLOCK, 0);
  if (fd < 0)
    return open_error(name, writable ? "open read-write" : "open read-only");
  if (map_checked(s, name, fd, writable, spec, trust) < 0) {
    int e = errno;
    close(fd);
    errno = e;
    return -1;
  }
  s->fd = fd;
  s->writable = writable;
  return 0;
}

void shm_seg_close(struct seg *s) {
  shm_guard_unregister(s);
  if (s->base)
    munmap(s->base, s->size);
  if (s->fd >= 0)
    close(s->fd);
  s->base = NULL;
  s->fd = -1;
}

int shm_seg_check(struct seg *s, bool stat_it) {
  bool bad = atomic_load_explicit(&s->fault, memory_order_acquire) != 0;
  struct stat st;
  if (!bad && stat_it && s->fd >= 0 && fstat(s->fd, &st) == 0) {
    bad = (uint64_t)st.st_size < s->size;
    /* A reader's file that no name leads to any more (removed from /dev/shm by
     * hand, its creator dead, so nobody marked it abandoned) will never see
     * another record; a creator started since has made a new one under the
     * name. The reader is told to attach again instead of waiting for ever. */
    if (!bad && !s->creator && st.st_nlink == 0) {
      shm_err(VLFF_SHM_ERR_ABANDONED, EPIPE, "%s: removed from /dev/shm while attached; attach again", VLFF_Q(s->name));
      return -1;
    }
  }
  if (!bad)
    return 0;
  shm_err(VLFF_SHM_ERR_TRUNCATED, EPIPE,
          "%s: the segment shrank under this process (truncated by a process with write access to it); %s",
          VLFF_Q(s->name), s->creator ? "replacing it by a new one" : "attach again");
  return -1;
}

/* A segment's size that could not be had (errno e, what was tried): a full
 * /dev/shm is an error of its own, which creators back off from. */
static int size_failed(const char *name, int e, uint64_t total, const char *tried) {
  if (e == ENOSPC || e == EFBIG)
    shm_err(VLFF_SHM_ERR_NOSPACE, ENOSPC, "%s: no space left in /dev/shm (%llu bytes needed)", VLFF_Q(name),
            (unsigned long long)total);
  else
    shm_err(VLFF_SHM_ERR_SYS, e, "%s: cannot %s %llu bytes: %s", VLFF_Q(name), tried, (unsigned long long)total,
            strerror(e));
  return -1;
}

/* Gives the segment's pages their memory now. On tmpfs a file's size is only a
 * promise: with /dev/shm full, ftruncate still succeeds and the first write to a
 * page that cannot be had faults (SIGBUS), which the guard took for a truncation,
 * so creators replaced their segments again and again. posix_fallocate fails
 * with ENOSPC instead, here, where it can be said. */
static int reserve_pages(const char *name, int fd, uint64_t total) {
  int e;
  do
    e = posix_fallocate(fd, 0, (off_t)total);
  while (e == EINTR);
  return e == 0 ? 0 : size_failed(name, e, total, "reserve");
}

static int resolve_group(const char *name, const char *group, gid_t *gid) {
  if (!group || !group[0])
    return 0;
  char *end;
  long v = strtol(group, &end, 10);
  if (*end == 0 && v >= 0) {
    *gid = (gid_t)v;
    return 1;
  }
  char buf[4096];
  struct group gr, *res = NULL;
  if (getgrnam_r(group, &gr, buf, sizeof buf, &res) != 0 || !res) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "%s: unknown group '%s'", VLFF_Q(name), VLFF_Q(group));
    return -1;
  }
  *gid = res->gr_gid;
  return 1;
}

static int apply_perm(const char *name, int fd, mode_t mode, const char *group) {
  gid_t gid;
  int g = resolve_group(name, group, &gid);
  if (g < 0)
    return -1;
  if (g && fchown(fd, (uid_t)-1, gid) < 0) {
    shm_err(VLFF_SHM_ERR_PERM, errno, "%s: cannot give it to group %s: %s", VLFF_Q(name), VLFF_Q(group),
            strerror(errno));
    return -1;
  }
  /* Explicit chmod: the umask must not widen or narrow what the config asked for. */
  if (fchmod(fd, mode) < 0) {
    shm_err(VLFF_SHM_ERR_SYS, errno, "%s: fchmod: %s", VLFF_Q(name), strerror(errno));
    return -1;
  }
  return 0;
}

/* Looks at an existing segment: 0 = taken over in place, 1 = stale (unlinked, create
 * again), -1 = error (live creator, foreign, another owner, ...). A segment is only
 * ever taken over, or removed, when this process's uid owns it: another user's file
 * at our name is refused, never adopted (its owner could truncate it under us) and
 * never deleted. */
static int try_take_over(struct seg *s, const char *name, const struct seg_spec *spec, const uint64_t geom[6],
                         uint64_t total, mode_t mode, const char *group) {
  struct stat st;
  int fd = open_regular(name, O_RDWR, "open existing read-write", &st);
  if (fd < 0) {
    if (errno == ENOENT)
      return 1; /* nothing there: create it */
    if (vlff_shm_last_error() == VLFF_SHM_ERR_FOREIGN)
      errno = EEXIST; /* something else holds the name */
    return -1;
  }
  if (st.st_uid != geteuid()) {
    close(fd);
    shm_err(VLFF_SHM_ERR_PERM, EACCES,
            "%s: exists and belongs to uid %u, not to this process's uid %u; refusing to take it over or "
            "remove it (remove /dev/shm%s by hand if it is stale)",
            VLFF_Q(name), (unsigned)st.st_uid, (unsigned)geteuid(), VLFF_Q(name));
    return -1;
  }
  if ((uint64_t)st.st_size < sizeof(struct seg_hdr)) {
    close(fd);
    if (st.st_size != 0) {
      shm_err(VLFF_SHM_ERR_FOREIGN, EEXIST, "%s: exists with %lld bytes, which no vlff segment has; not touching it",
              VLFF_Q(name), (long long)st.st_size);
      return -1;
    }
    /* A creator died between creating and sizing it. */
    shm_unlink(name);
    return 1;
  }
  struct seg_hdr h;
  if (pread(fd, &h, sizeof h, 0) != (ssize_t)sizeof h) {
    close(fd);
    shm_err(VLFF_SHM_ERR_TRUNCATED, EBADMSG, "%s: shrank while being looked at", VLFF_Q(name));
    return -1;
  }
  if (h.magic != SEG_MAGIC && h.magic != 0) {
    close(fd);
    shm_err(VLFF_SHM_ERR_FOREIGN, EEXIST, "%s: exists and is not a vlff segment; not touching it", VLFF_Q(name));
    return -1;
  }
  int32_t pid = h.creator_pid;
  uint64_t start = h.creator_start;
  uint32_t state = h.state;
  /* A PID reused by a later process (after a crash, on a busy host) is not
   * its creator: the start times tell them apart. */
  if (state != SEG_ABANDONED && pid != getpid() && shm_creator_alive(pid, start)) {
    close(fd);
    shm_err(VLFF_SHM_ERR_EXISTS, EEXIST, "%s: owned by live process %d", VLFF_Q(name), (int)pid);
    return -1;
  }
  /* In place only when nobody beyond what the configuration allows could have opened
   * it for writing: a wider mode or another group may have let someone in who keeps
   * an open descriptor. Such a segment is replaced instead. */
  gid_t gid = st.st_gid;
  bool perm_ok = (st.st_mode & 07777 & ~mode) == 0;
  if (perm_ok && group && group[0]) {
    int g = resolve_group(name, group, &gid);
    if (g < 0) {
      close(fd);
      return -1;
    }
    perm_ok = gid == st.st_gid;
  }
  bool same = perm_ok && h.magic == SEG_MAGIC && h.abi_version == VLFF_SHM_ABI_VERSION && h.kind == spec->kind &&
              h.record_kind == spec->record_kind && h.total_size == total && !memcmp(h.geom, geom, sizeof h.geom) &&
              h.geom_check == shm_geom_check(&h) && (uint64_t)st.st_size >= total && state == SEG_READY;
  if (same) {
    memset(s, 0, sizeof *s);
    s->fd = -1;
    if (map_checked(s, name, fd, true, spec, NULL) < 0) {
      close(fd);
      return -1;
    }
    /* A segment made before pages were reserved, or by a creator that died
     * while /dev/shm filled, may still be a promise. */
    if (reserve_pages(name, fd, total) < 0) {
      shm_seg_close(s);
      return -1;
    }
    s->fd = fd;
    s->writable = true;
    /* The start time is claimed first: of two processes taking the segment
     * over at once, the one whose swap fails gives up, and a reader between
     * the two swaps sees the dead creator's PID, which it reads as dead. */
    uint64_t mine = shm_proc_start(getpid());
    if (!atomic_compare_exchange_strong(&s->h->creator_start, &start, mine) ||
        !atomic_compare_exchange_strong(&s->h->creator_pid, &pid, (int32_t)getpid())) {
      atomic_compare_exchange_strong(&s->h->creator_start, &mine, start);
      shm_seg_close(s);
      shm_err(VLFF_SHM_ERR_EXISTS, EEXIST, "%s: taken over by process %d meanwhile", VLFF_Q(name),
              (int)atomic_load(&s->h->creator_pid));
      return -1;
    }
    if (apply_perm(name, fd, mode, group) < 0 || shm_seg_check(s, true) < 0) {
      atomic_compare_exchange_strong(&s->h->creator_pid, &(int32_t){(int32_t)getpid()}, pid);
      atomic_compare_exchange_strong(&s->h->creator_start, &mine, start);
      shm_seg_close(s);
      return -1;
    }
    atomic_fetch_add(&s->h->generation, 1);
    return 0;
  }
  if (h.magic == SEG_MAGIC) {
    /* Tell attached readers to re-attach; pwrite, since the file may be short. */
    uint32_t a = SEG_ABANDONED;
    if (pwrite(fd, &a, sizeof a, offsetof(struct seg_hdr, state)) != (ssize_t)sizeof a) {
      /* Readers then find out from the guard or the next attach. */
    }
  }
  shm_unlink(name);
  close(fd);
  return 1;
}

static void remember(struct seg *s, const struct seg_spec *spec, const uint64_t geom[6], mode_t mode,
                     const char *group) {
  s->creator = true;
  s->spec = *spec;
  memcpy(s->geom, geom, sizeof s->geom);
  s->mode = mode;
  snprintf(s->group, sizeof s->group, "%s", group ? group : "");
}

int shm_seg_create(struct seg *s, const char *name, const struct seg_spec *spec, const uint64_t geom[6],
                   const struct vlff_shm_perm *perm) {
  memset(s, 0, sizeof *s);
  s->fd = -1;
  if (check_name(name) < 0)
    return -1;
  mode_t mode = perm && perm->mode ? perm->mode : 0640;
  const char *group = perm ? perm->group : NULL;
  if (mode & 0002 || mode & ~(mode_t)0777) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "%s: mode %04o refused: world-writable or not permission bits", VLFF_Q(name),
            (unsigned)mode);
    return -1;
  }
  uint64_t total = spec->compute_total(geom);
  if (total == 0) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "%s: invalid geometry", VLFF_Q(name));
    return -1;
  }
  for (int attempt = 0; attempt < 4; attempt++) {
    int fd = shm_open(name, O_RDWR | O_CREAT | O_EXCL | O_NONBLOCK, mode & 0600);
    if (fd < 0) {
      if (errno != EEXIST)
        return open_error(name, "create");
      int r = try_take_over(s, name, spec, geom, total, mode, group);
      if (r == 0)
        remember(s, spec, geom, mode, group);
      if (r <= 0)
        return r;
      continue;
    }
    snprintf(s->name, sizeof s->name, "%s", name);
    int bad = apply_perm(name, fd, mode, group);
    if (bad == 0 && ftruncate(fd, (off_t)total) < 0)
      bad = size_failed(name, errno, total, "size it to");
    if (bad == 0 && reserve_pages(name, fd, total) < 0)
      bad = -1;
    if (bad < 0) {
      int e = errno;
      close(fd);
      shm_unlink(name);
      errno = e;
      return -1;
    }
    void *p = mmap(NULL, total, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
    if (p == MAP_FAILED) {
      int e = errno;
      close(fd);
      shm_unlink(name);
      errno = e;
      return open_error(name, "mmap");
    }
    s->fd = fd;
    s->writable = true;
    s->base = p;
    s->size = total;
    s->h = p;
    if (shm_guard_register(s, PROT_READ | PROT_WRITE) < 0) {
      int e = errno;
      shm_seg_close(s);
      shm_unlink(name);
      errno = e;
      return -1;
    }
    struct seg_hdr *h = s->h;
    h->abi_version = VLFF_SHM_ABI_VERSION;
    h->kind = spec->kind;
    h->record_kind = spec->record_kind;
    h->total_size = total;
    memcpy(h->geom, geom, sizeof h->geom);
    atomic_store(&h->creator_start, shm_proc_start(getpid()));
    atomic_store(&h->creator_pid, (int32_t)getpid());
    atomic_store(&h->generation, 1);
    atomic_store(&h->state, SEG_INIT);
    h->magic = SEG_MAGIC;
    h->geom_check = shm_geom_check(h);
    remember(s, spec, geom, mode, group);
    return 1;
  }
  shm_err(VLFF_SHM_ERR_EXISTS, EEXIST, "%s: kept reappearing while being replaced", VLFF_Q(name));
  return -1;
}

int shm_seg_replace(struct seg *s) {
  char name[256];
  struct seg_spec spec = s->spec;
  uint64_t geom[6];
  char group[64];
  mode_t mode = s->mode;
  snprintf(name, sizeof name, "%s", s->name);
  memcpy(geom, s->geom, sizeof geom);
  snprintf(group, sizeof group, "%s", s->group);
  struct stat mine, named;
  bool have = s->fd >= 0 && fstat(s->fd, &mine) == 0;
  if (have && (uint64_t)mine.st_size >= sizeof(struct seg_hdr)) {
    uint32_t a = SEG_ABANDONED;
    if (pwrite(s->fd, &a, sizeof a, offsetof(struct seg_hdr, state)) != (ssize_t)sizeof a) {
      /* Readers then learn it from their own guard or their next attach. */
    }
  }
  /* Only our own file is removed: the name may already be someone else's. */
  int fd = shm_open(name, O_RDONLY | O_NONBLOCK, 0);
  if (fd >= 0) {
    if (have && fstat(fd, &named) == 0 && named.st_ino == mine.st_ino && named.st_dev == mine.st_dev)
      shm_unlink(name);
    close(fd);
  }
  shm_seg_close(s);
  struct vlff_shm_perm perm = {.mode = mode, .group = group[0] ? group : NULL};
  uint64_t delay = s->retry_delay_ns, retries = s->retries;
  int r = shm_seg_create(s, name, &spec, geom, &perm);
  if (r >= 0)
    return r;
  /* Kept as a creator that failed: shm_seg_retry tries again later. */
  int code = vlff_shm_last_error();
  char why[320];
  snprintf(why, sizeof why, "%s", vlff_shm_last_message());
  snprintf(s->name, sizeof s->name, "%s", name);
  remember(s, &spec, geom, mode, group);
  s->failed = true;
  s->retries = retries + 1;
  s->retry_delay_ns = !delay ? 100000000ull : delay >= 2500000000ull ? 5000000000ull : 2 * delay;
  s->retry_ns = shm_now() + s->retry_delay_ns;
  s->why_code = code;
  snprintf(s->why, sizeof s->why, "%s", why);
  shm_err(code, EPIPE, "%s; not replaced, next try in %.1f s (%llu tries so far)", why,
          (double)s->retry_delay_ns / 1e9, (unsigned long long)s->retries);
  return -1;
}

int shm_seg_retry(struct seg *s) {
  uint64_t now = shm_now();
  if (now < s->retry_ns) {
    shm_err(s->why_code, EPIPE, "%s; not replaced, next try in %.1f s (%llu tries so far)", s->why,
            (double)(s->retry_ns - now) / 1e9, (unsigned long long)s->retries);
    return -1;
  }
  return shm_seg_replace(s);
}

void shm_seg_move(struct seg *dst, struct seg *src) {
  int prot = PROT_READ | (src->writable ? PROT_WRITE : 0);
  shm_guard_unregister(src);
  uint32_t fault = atomic_load(&src->fault);
  *dst = *src;
  dst->guard_slot = 0;
  atomic_store(&dst->fault, fault); /* a fault taken before the move still counts */
  /* The slot src gave up is free: registering again cannot run out. */
  (void)shm_guard_register(dst, prot);
  src->base = NULL;
  src->fd = -1;
}

int shm_seg_rename(struct seg *s, const char *name) {
  if (check_name(name) < 0)
    return -1;
  /* POSIX names shm_open's files after the name; glibc keeps them in /dev/shm. */
  char from[300], to[300];
  snprintf(from, sizeof from, "/dev/shm%s", s->name);
  snprintf(to, sizeof to, "/dev/shm%s", name);
  if (rename(from, to) < 0) {
    int e = errno;
    shm_err(VLFF_SHM_ERR_SYS, e, "%s: cannot take the name %s: %s", VLFF_Q(s->name), VLFF_Q(name), strerror(e));
    return -1;
  }
  snprintf(s->name, sizeof s->name, "%s", name);
  return 0;
}

void shm_seg_ready(struct seg *s) { atomic_store_explicit(&s->h->state, SEG_READY, memory_order_release); }

API int vlff_shm_unlink(const char *name) {
  if (check_name(name) < 0)
    return -1;
  if (shm_unlink(name) < 0)
    return open_error(name, "unlink");
  return 0;
}
