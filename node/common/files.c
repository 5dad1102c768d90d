/*
 * Why O_NONBLOCK then fstat: stat() then open() races with a rename, and a
 * plain open() of a FIFO blocks until a writer appears (forever, for a node
 * starting alone). Opening non-blocking never waits; fstat on the
 * descriptor then judges exactly the file that was opened.
 */
#include "files.h"
#include "log.h" /* vlff_errf */
#include "vlff/escape.h" /* VLFF_Q: paths quoted in messages */

#include <dirent.h>
#include <errno.h>
#include <fcntl.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

static const char *kind_of(mode_t m) {
  if (S_ISDIR(m)) return "a directory";
  if (S_ISFIFO(m)) return "a FIFO";
  if (S_ISCHR(m)) return "a character device";
  if (S_ISBLK(m)) return "a block device";
  if (S_ISSOCK(m)) return "a socket";
  return "not a regular file";
}

int vlff_open_regular(const char *path, char *err, size_t errlen) {
  int fd = open(path, O_RDONLY | O_CLOEXEC | O_NONBLOCK | O_NOCTTY);
  if (fd < 0) {
    if (err && errlen) snprintf(err, errlen, "%s: cannot open: %s", VLFF_Q(path), strerror(errno));
    return -1;
  }
  struct stat st;
  if (fstat(fd, &st) < 0) {
    if (err && errlen) snprintf(err, errlen, "%s: cannot stat: %s", VLFF_Q(path), strerror(errno));
    close(fd);
    return -1;
  }
  if (!S_ISREG(st.st_mode)) {
    if (err && errlen) snprintf(err, errlen, "%s: is %s, expected a regular file", VLFF_Q(path), kind_of(st.st_mode));
    close(fd);
    return -1;
  }
  int fl = fcntl(fd, F_GETFL);
  if (fl < 0 || fcntl(fd, F_SETFL, fl & ~O_NONBLOCK) < 0) {
    if (err && errlen) snprintf(err, errlen, "%s: fcntl: %s", VLFF_Q(path), strerror(errno));
    close(fd);
    return -1;
  }
  return fd;
}

int vlff_check_regular(const char *path, char *err, size_t errlen) {
  int fd = vlff_open_regular(path, err, errlen);
  if (fd < 0) return -1;
  close(fd);
  return 0;
}

int vlff_check_output(const char *path, char *err, size_t errlen) {
  struct stat st;
  if (stat(path, &st) < 0) {
    if (errno == ENOENT) return 0;
    if (err && errlen) snprintf(err, errlen, "%s: cannot stat: %s", VLFF_Q(path), strerror(errno));
    return -1;
  }
  if (S_ISREG(st.st_mode)) return 0;
  if (err && errlen)
    snprintf(err, errlen, "%s: is %s, expected a regular file or a new name to write", VLFF_Q(path), kind_of(st.st_mode));
  return -1;
}

int vlff_create_temp(const char *tmp, unsigned mode, char *err, size_t errlen) {
  if (unlink(tmp) < 0 && errno != ENOENT) {
    if (err && errlen) snprintf(err, errlen, "%s: cannot remove the old temporary: %s", VLFF_Q(tmp), strerror(errno));
    return -1;
  }
  int fd = open(tmp, O_WRONLY | O_CREAT | O_EXCL | O_NOFOLLOW | O_CLOEXEC, (mode_t)mode);
  if (fd < 0 && err && errlen) snprintf(err, errlen, "%s: cannot create: %s", VLFF_Q(tmp), strerror(errno));
  return fd;
}

int vlff_atomic_begin(struct vlff_atomic *a, const char *path, unsigned mode, char *err, size_t errlen) {
  size_t n = strlen(path) + 32;
  a->path = path, a->fd = -1, a->tmp = malloc(n);
  if (!a->tmp) {
    if (err && errlen) snprintf(err, errlen, "%s: out of memory", VLFF_Q(path));
    return -1;
  }
  snprintf(a->tmp, n, "%s.tmp.%ld", path, (long)getpid());
  a->fd = vlff_create_temp(a->tmp, mode, err, errlen);
  if (a->fd < 0) {
    free(a->tmp), a->tmp = NULL;
    return -1;
  }
  return 0;
}

void vlff_atomic_abort(struct vlff_atomic *a) {
  if (a->fd >= 0) close(a->fd);
  if (a->tmp) unlink(a->tmp);
  free(a->tmp);
  a->fd = -1, a->tmp = NULL;
}

int vlff_atomic_commit(struct vlff_atomic *a, char *err, size_t errlen) {
  int rc = fsync(a->fd);
  if (close(a->fd) < 0) rc = -1;
  a->fd = -1;
  if (rc == 0) rc = rename(a->tmp, a->path);
  if (rc < 0) {
    if (err && errlen) snprintf(err, errlen, "%s: write failed: %s", VLFF_Q(a->path), strerror(errno));
    vlff_atomic_abort(a);
    return -1;
  }
  free(a->tmp), a->tmp = NULL;
  /* the rename itself made durable */
  char *dir = strdup(a->path);
  if (dir) {
    char *slash = strrchr(dir, '/');
    const char *d = slash ? (slash == dir ? "/" : (*slash = 0, dir)) : ".";
    int dfd = open(d, O_RDONLY | O_DIRECTORY | O_CLOEXEC);
    if (dfd >= 0) fsync(dfd), close(dfd);
    free(dir);
  }
  return 0;
}

int vlff_write_all(int fd, const void *p, size_t n) {
  const unsigned char *b = p;
  while (n) {
    ssize_t w = write(fd, b, n);
    if (w < 0 && errno == EINTR) continue;
    if (w <= 0) return -1;
    b += w, n -= (size_t)w;
  }
  return 0;
}

int vlff_read_at(int fd, uint64_t off, void *p, size_t n) {
  unsigned char *b = p;
  while (n) {
    ssize_t r = pread(fd, b, n, (off_t)off);
    if (r < 0 && errno == EINTR) continue;
    if (r < 0) return -1;
    if (r == 0) return errno = EIO, -1; /* the file ended early */
    b += r, n -= (size_t)r, off += (uint64_t)r;
  }
  return 0;
}

int vlff_write_at(int fd, uint64_t off, const void *p, size_t n) {
  const unsigned char *b = p;
  while (n) {
    ssize_t w = pwrite(fd, b, n, (off_t)off);
    if (w < 0 && errno == EINTR) continue;
    if (w < 0) return -1;
    if (w == 0) return errno = EIO, -1;
    b += w, n -= (size_t)w, off += (uint64_t)w;
  }
  return 0;
}

int vlff_write_file_atomic(const char *path, const void *data, size_t len, char *err, size_t errlen) {
  struct vlff_atomic a;
  if (vlff_atomic_begin(&a, path, 0644, err, errlen) < 0) return -1;
  if (vlff_write_all(a.fd, data, len) < 0) {
    if (err && errlen) snprintf(err, errlen, "%s: write failed: %s", VLFF_Q(a.tmp), strerror(errno));
    vlff_atomic_abort(&a);
    return -1;
  }
  return vlff_atomic_commit(&a, err, errlen);
}

bool vlff_temp_name_pid(const char *name, long *pid) {
  const char *t = strstr(name, ".tmp.");
  if (!t) return false;
  /* The last ".tmp." counts: a stem may itself contain one. */
  for (const char *n; (n = strstr(t + 1, ".tmp."));) t = n;
  const char *d = t + 5;
  if (!*d || strlen(d) > 10) return false;
  long v = 0;
  for (; *d; d++) {
    if (*d < '0' || *d > '9') return false;
    v = v * 10 + (*d - '0');
  }
  if (v <= 0) return false;
  *pid = v;
  return true;
}

static bool pid_alive(long pid) {
  if (pid == (long)getpid()) return false;
  /* EPERM: a process of another user holds that pid, so it is alive. */
  return kill((pid_t)pid, 0) == 0 || errno == EPERM;
}

int vlff_remove_dead_temps(const char *dir, const char *const *prefixes) {
  DIR *d = opendir(dir);
  if (!d) return 0;
  int removed = 0;
  struct dirent *e;
  while ((e = readdir(d))) {
    bool match = false;
    for (int i = 0; prefixes[i] && !match; i++) match = !strncmp(e->d_name, prefixes[i], strlen(prefixes[i]));
    long pid;
    if (!match || !vlff_temp_name_pid(e->d_name, &pid) || pid_alive(pid)) continue;
    struct stat st;
    if (fstatat(dirfd(d), e->d_name, &st, AT_SYMLINK_NOFOLLOW) < 0 || !S_ISREG(st.st_mode)) continue;
    if (unlinkat(dirfd(d), e->d_name, 0) == 0) removed++;
  }
  closedir(d);
  return removed;
}

/* path opened as vlff_open_regular does, with its size, refused above max
 * bytes: the fd, or -1 with err. */
static int open_sized(const char *path, size_t max, size_t *size, char *err, size_t errlen) {
  int fd = vlff_open_regular(path, err, errlen);
  if (fd < 0) return -1;
  struct stat st;
  if (fstat(fd, &st) < 0) {
    vlff_errf(err, errlen, "%s: cannot stat: %s", VLFF_Q(path), strerror(errno));
    close(fd);
    return -1;
  }
  if ((uint64_t)st.st_size > max) {
    vlff_errf(err, errlen, "%s: %lld bytes, more than the %zu this file may have", VLFF_Q(path),
              (long long)st.st_size, max);
    close(fd);
    return -1;
  }
  *size = (size_t)st.st_size;
  return fd;
}

int vlff_read_file(const char *path, size_t max, uint8_t **buf, size_t *len, char *err, size_t errlen) {
  *buf = NULL, *len = 0;
  size_t size;
  int fd = open_sized(path, max, &size, err, errlen);
  if (fd < 0) return -1;
  FILE *f = fdopen(fd, "rb");
  if (!f) {
    close(fd);
    vlff_errf(err, errlen, "%s: cannot open: %s", VLFF_Q(path), strerror(errno));
    return -1;
  }
  uint8_t *b = malloc(size + 1);
  if (!b) {
    fclose(f);
    vlff_errf(err, errlen, "%s: out of memory", VLFF_Q(path));
    return -1;
  }
  size_t n = fread(b, 1, size, f);
  int bad = ferror(f);
  fclose(f);
  if (bad || n != size) {
    free(b);
    vlff_errf(err, errlen, "%s: read error", VLFF_Q(path));
    return -1;
  }
  b[n] = 0;
  *buf = b, *len = n;
  return 0;
}

int vlff_map_file(const char *path, size_t max, const uint8_t **buf, size_t *len, char *err, size_t errlen) {
  static const uint8_t empty[1];
  *buf = NULL, *len = 0;
  size_t size;
  int fd = open_sized(path, max, &size, err, errlen);
  if (fd < 0) return -1;
  if (size == 0) {
    close(fd);
    *buf = empty;
    return 0;
  }
  void *m = mmap(NULL, size, PROT_READ, MAP_PRIVATE, fd, 0);
  int e = errno;
  close(fd); /* the mapping keeps the file */
  if (m == MAP_FAILED) {
    vlff_errf(err, errlen, "%s: cannot map: %s", VLFF_Q(path), strerror(e));
    return -1;
  }
  /* read ahead further, and dropped behind sooner */
  (void)madvise(m, size, MADV_SEQUENTIAL);
  *buf = m, *len = size;
  return 0;
}

void vlff_unmap_file(const uint8_t *buf, size_t len) {
  if (buf && len) munmap((void *)buf, len);
}

void vlff_unread_mapped(const uint8_t *buf, size_t upto) {
  size_t page = (size_t)sysconf(_SC_PAGESIZE);
  upto -= upto % page;
  /* a private mapping never written: its pages come back from the file */
  if (buf && upto) (void)madvise((void *)buf, upto, MADV_DONTNEED);
}

/* Every 4 MiB read: a reader's resident share of the file stays small
 * beside its own buffers, and madvise is called a few times a second at most. */
#define GIVE_BACK_BYTES (4u << 20)
void vlff_unread_mapped_paced(const uint8_t *buf, size_t *given, size_t consumed) {
  if (consumed < *given) *given = 0; /* rewound */
  if (consumed - *given < GIVE_BACK_BYTES) return;
  vlff_unread_mapped(buf, consumed);
  *given = consumed;
}

static char bus_msg[600];
static size_t bus_len;
static void on_sigbus(int sig) {
  (void)sig;
  if (bus_len) (void)!write(2, bus_msg, bus_len);
  _exit(1);
}

void vlff_map_exit_on_sigbus(const char *prog, const char *path) {
  int m = snprintf(bus_msg, sizeof bus_msg, "%s: %s: the file was cut short while it was played\n", prog,
                   VLFF_Q(path));
  bus_len = m < 0 ? 0 : (size_t)m < sizeof bus_msg ? (size_t)m : sizeof bus_msg - 1;
  struct sigaction sa;
  memset(&sa, 0, sizeof sa);
  sa.sa_handler = on_sigbus;
  sigaction(SIGBUS, &sa, NULL);
}

int vlff_exe_dir(char *out, size_t len) {
  ssize_t n = readlink("/proc/self/exe", out, len);
  if (n <= 0 || (size_t)n >= len) return -1;
  out[n] = 0;
  char *slash = strrchr(out, '/');
  if (!slash) return -1;
  *slash = 0;
  return 0;
}
