/*
 * Files the node reads: only regular files, and what a dead writer left.
 *
 * Every file vlff reads (configs, checkpoints, observation grids, dataset
 * files, embeddings, models, vocabularies) is opened through
 * vlff_open_regular(): a FIFO, device, socket or directory at that name is
 * refused at once instead of blocking start-up on open() or read().
 *
 * Atomic writers in vlff write "<path>.tmp.<pid>" and rename it over path.
 * A writer killed before the rename leaves that temporary behind;
 * vlff_remove_dead_temps() removes such files whose writer is gone.
 *
 * Contract
 *  - Functions returning int give 0 (or a descriptor), or -1 with one line
 *    in err (when err is not NULL) naming the path and what was wrong.
 *  - No global state; thread-safe.
 */
#ifndef VLFF_FILES_H
#define VLFF_FILES_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* Open path read-only (O_CLOEXEC) without blocking on a FIFO or device,
 * and refuse anything but a regular file. Returns the descriptor in
 * blocking mode (the caller closes it), or -1. */
int vlff_open_regular(const char *path, char *err, size_t errlen);

/* The same check without keeping the file open, for readers that take a
 * path (libhdf5, OpenCV): 0 when path is a readable regular file. */
int vlff_check_regular(const char *path, char *err, size_t errlen);

/* Remove the regular files in dir named "<prefix>...tmp.<pid>" for one of
 * the NULL-terminated prefixes, whose writer pid is no longer alive (or is
 * this very process, which has not written yet when this is called at
 * start). Returns how many were removed; names of other shapes, live
 * writers' files and non-regular files are left alone. */
int vlff_remove_dead_temps(const char *dir, const char *const *prefixes);

/* The directory the running executable lies in (/proc/self/exe without its
 * last component; "" for one at the root), for programs that find their
 * install from where they run. 0, or -1 when it cannot be read or does not
 * fit out. */
int vlff_exe_dir(char *out, size_t len);

/* An output path a user named (vlff-shm dump-map FILE): 0 when nothing is
 * there yet or a regular file is (following links), which an atomic writer
 * then replaces; -1 with err naming what else is there. Renaming a file over
 * /dev/sda or a FIFO replaces the device node or the pipe, and opening a FIFO
 * to write waits for a reader: neither is what the user meant. */
int vlff_check_output(const char *path, char *err, size_t errlen);

/* Create an atomic writer's temporary "tmp" for writing (mode before the
 * umask): whatever sat at that name is removed first and the file is
 * created exclusively without following links, so a FIFO or a symbolic
 * link planted at the name can neither block the writer nor redirect what
 * it writes. Returns the descriptor, or -1 with err. */
int vlff_create_temp(const char *tmp, unsigned mode, char *err, size_t errlen);

/* Atomic replacement of a file: begin creates "<path>.tmp.<pid>"
 * (vlff_create_temp) and gives its descriptor in a->fd; commit fsyncs and
 * closes it, renames it over path and fsyncs the directory, so after a
 * crash path holds the old or the new content, never a mix; abort closes
 * and removes the temporary. Commit and abort free what begin took. */
struct vlff_atomic {
  int fd;
  char *tmp;
  const char *path;
};
int vlff_atomic_begin(struct vlff_atomic *a, const char *path, unsigned mode, char *err, size_t errlen);
int vlff_atomic_commit(struct vlff_atomic *a, char *err, size_t errlen);
void vlff_atomic_abort(struct vlff_atomic *a);
/* write(2) of all n bytes, retried on EINTR and short writes: 0 or -1. */
int vlff_write_all(int fd, const void *p, size_t n);
/* pread(2) of all n bytes at offset off, retried on EINTR and short reads:
 * 0, or -1 with errno set (EIO where the file ends first). */
int vlff_read_at(int fd, uint64_t off, void *p, size_t n);
/* pwrite(2) of all n bytes at offset off, retried on EINTR and short
 * writes: 0, or -1 with errno set (EIO where the kernel wrote nothing and
 * gave no reason). */
int vlff_write_at(int fd, uint64_t off, const void *p, size_t n);
/* A whole regular file of at most max bytes (opened with vlff_open_regular);
 * *buf is NUL-terminated (not counted in *len), the caller frees it. */
int vlff_read_file(const char *path, size_t max, uint8_t **buf, size_t *len, char *err, size_t errlen);
/* A whole regular file of at most max bytes, mapped read-only (opened with
 * vlff_open_regular): the kernel reads it in as it is touched, and
 * vlff_unread_mapped gives pages back, so a file larger than memory can be
 * read through. A file cut short while mapped makes a read past its new end
 * raise SIGBUS: callers that read files others may write catch it
 * (vlff-replay says so and exits 1). An empty file maps to a valid empty
 * buffer. Unmapped with vlff_unmap_file. */
int vlff_map_file(const char *path, size_t max, const uint8_t **buf, size_t *len, char *err, size_t errlen);
void vlff_unmap_file(const uint8_t *buf, size_t len);
/* The pages of buf[0, upto) given back (read from the file again if
 * touched again); upto is rounded down to a page. */
void vlff_unread_mapped(const uint8_t *buf, size_t upto);
/* For a reader going through a mapped file: gives back buf[0, consumed)
 * once 4 MiB more than at the last give-back (*given, 0 at the start) were
 * consumed; a consumed below *given (a rewind) starts the count again. */
void vlff_unread_mapped_paced(const uint8_t *buf, size_t *given, size_t consumed);
/* From now on a SIGBUS (a mapped file cut short under its reader: the file
 * was checked whole before, so nothing more of it can be trusted) writes
 * "PROG: PATH: the file was cut short while it was played" to stderr and
 * exits with status 1. One file per process. */
void vlff_map_exit_on_sigbus(const char *prog, const char *path);
/* The whole of data as path's new content, atomically (0644). */
int vlff_write_file_atomic(const char *path, const void *data, size_t len, char *err, size_t errlen);

/* True when "<anything>.tmp.<pid>" names pid's temporary (pid > 0). */
bool vlff_temp_name_pid(const char *name, long *pid);

#ifdef __cplusplus
}
#endif

#endif
