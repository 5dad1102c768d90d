/*
 * Why O_NONBLOCK then fstat: stat() then open() races with a rename, and a
 * plain open() of a FIFO blocks until a writer appears (forever, for a node
 * starting alone). Opening non-blocking never waits; fstat on the
 * descriptor then judges exactly the file that was opened.
 */
#include "files.h"

#include <dirent.h>
#include <errno.h>
#include <fcntl.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
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
    if (err && errlen) snprintf(err, errlen, "%s: cannot open: %s", path, strerror(errno));
    return -1;
  }
  struct stat st;
  if (fstat(fd, &st) < 0) {
    if (err && errlen) snprintf(err, errlen, "%s: cannot stat: %s", path, strerror(errno));
    close(fd);
    return -1;
  }
  if (!S_ISREG(st.st_mode)) {
    if (err && errlen) snprintf(err, errlen, "%s: is %s, expected a regular file", path, kind_of(st.st_mode));
    close(fd);
    return -1;
  }
  int fl = fcntl(fd, F_GETFL);
  if (fl < 0 || fcntl(fd, F_SETFL, fl & ~O_NONBLOCK) < 0) {
    if (err && errlen) snprintf(err, errlen, "%s: fcntl: %s", path, strerror(errno));
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

int vlff_create_temp(const char *tmp, unsigned mode, char *err, size_t errlen) {
  if (unlink(tmp) < 0 && errno != ENOENT) {
    if (err && errlen) snprintf(err, errlen, "%s: cannot remove the old temporary: %s", tmp, strerror(errno));
    return -1;
  }
  int fd = open(tmp, O_WRONLY | O_CREAT | O_EXCL | O_NOFOLLOW | O_CLOEXEC, (mode_t)mode);
  if (fd < 0 && err && errlen) snprintf(err, errlen, "%s: cannot create: %s", tmp, strerror(errno));
  return fd;
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
