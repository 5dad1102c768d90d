/* Segments under attack by someone with write access, or by another uid: a file
 * truncated under a reader, a writer, a ring producer or consumer and a mailbox
 * must give an error, never a SIGBUS; the application's own SIGBUS handler keeps
 * working; another user's segment is never adopted or removed, and attachers refuse
 * files of the wrong owner or mode. (issue 29: C1, C2) */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <cmocka.h>

#include "shm_test_util.h"
#include "unit.h"

#include <errno.h>
#include <fcntl.h>
#include <pthread.h>
#include <stdatomic.h>
#include <signal.h>
#include <stdbool.h>
#include <stdlib.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#define NOBODY 65534

static void truncate_seg(const char *name, off_t size) {
  int fd = shm_open(name, O_RDWR, 0);
  assert_true(fd >= 0);
  assert_int_equal(ftruncate(fd, size), 0);
  close(fd);
}

/* A map for the tests' 64 x 64 x 16 grid, named after tag. */
static struct vlff_map *make_map(char name[64], const char *tag) {
  test_name(name, 64, tag);
  struct vlff_map_params mp = {.max_voxels = 64 * 64 * 16, .label_max_width = 64, .label_max_height = 48};
  struct vlff_map *w = vlff_map_create(name, &mp);
  assert_non_null(w);
  return w;
}

/* A raw ring of four 64 KiB slots, named after tag. */
static struct vlff_ring *make_raw_ring(char name[64], const char *tag) {
  test_name(name, 64, tag);
  struct vlff_ring_params p = {.record_kind = VLFF_RECORD_RAW, .slots = 4, .slot_size = 64 * 1024};
  struct vlff_ring *w = vlff_ring_create(name, &p);
  assert_non_null(w);
  return w;
}

static int publish(struct vlff_map *w, uint16_t label) {
  static uint16_t labels[64 * 64 * 16];
  for (size_t i = 0; i < sizeof labels / sizeof *labels; i++)
    labels[i] = label;
  struct vlff_map_grid g = {.voxel_size = 0.1, .dims = {64, 64, 16}, .labels = labels};
  const char *prompts[] = {"wall", "floor"};
  struct vlff_map_update u = {.grid = &g, .prompts = prompts, .prompt_count = 2};
  return vlff_map_publish(w, &u);
}

/* A controller reading the map: the reader library's calls fail, the process lives. */
static void test_truncate_under_map_reader(void **state) {
  (void)state;
  char name[64];
  struct vlff_map *w = make_map(name, "trmr");
  assert_int_equal(publish(w, 1), 0);
  struct vlff_map *r = vlff_map_attach(name);
  assert_non_null(r);
  uint16_t label;
  assert_int_equal(vlff_map_label_at(r, 6.35, 6.35, 1.55, &label, NULL), 0);
  assert_int_equal(label, 1);
  truncate_seg(name, 4096);
  struct vlff_map_snapshot *snap = vlff_map_snapshot_new(r);
  assert_non_null(snap);
  assert_int_equal(vlff_map_snapshot_take(r, snap), -1);
  assert_int_equal(errno, EPIPE);
  assert_int_equal(vlff_shm_last_error(), VLFF_SHM_ERR_TRUNCATED);
  assert_non_null(strstr(vlff_shm_last_message(), "shrank"));
  assert_int_equal(vlff_map_label_at(r, 6.35, 6.35, 1.55, &label, NULL), -1);
  assert_int_equal(errno, EPIPE);
  assert_int_equal(vlff_map_writer_alive(r, UINT64_MAX), 0);
  vlff_map_snapshot_free(snap);
  vlff_map_detach(r);
  /* Attaching to the shrunk file is refused up front. */
  assert_null(vlff_map_attach(name));
  assert_int_equal(vlff_shm_last_error(), VLFF_SHM_ERR_TRUNCATED);
  vlff_map_detach(w);
  vlff_shm_unlink(name);
}

/* The node's map writer: the publish that finds it is refused, the map is replaced by
 * a new segment and the versions go on from where they were. */
static void test_truncate_under_map_writer(void **state) {
  (void)state;
  char name[64];
  struct vlff_map *w = make_map(name, "trmw");
  for (int i = 0; i < 3; i++)
    assert_int_equal(publish(w, 2), 0);
  struct vlff_map *old = vlff_map_attach(name);
  assert_non_null(old);
  truncate_seg(name, 4096);
  assert_int_equal(publish(w, 3), -1);
  assert_int_equal(errno, EPIPE);
  assert_int_equal(vlff_shm_last_error(), VLFF_SHM_ERR_TRUNCATED);
  assert_non_null(strstr(vlff_shm_last_message(), "replacing it"));
  /* A reader of the old segment is told to attach again. */
  uint16_t label;
  assert_int_equal(vlff_map_label_at(old, 0.05, 0.05, 0.05, &label, NULL), -1);
  assert_int_equal(errno, EPIPE);
  vlff_map_detach(old);
  assert_int_equal(publish(w, 3), 0);
  struct vlff_map *r = vlff_map_attach(name);
  assert_non_null(r);
  assert_int_equal(vlff_map_version(r), 4);
  assert_int_equal(vlff_map_label_at(r, 0.05, 0.05, 0.05, &label, NULL), 0);
  assert_int_equal(label, 3);
  vlff_map_detach(r);
  /* Heartbeats find it too. */
  truncate_seg(name, 200);
  assert_int_equal(vlff_map_heartbeat(w), -1);
  assert_int_equal(errno, EPIPE);
  assert_int_equal(publish(w, 4), 0);
  assert_int_equal(vlff_map_version(w), 5);
  vlff_map_detach(w);
  vlff_shm_unlink(name);
}

/* A producer writing a record in place through the slot pointer when the file shrinks:
 * its stores land in private memory, the commit says so, the next record goes to a
 * new ring that numbers on. */
static void test_truncate_under_ring_writer(void **state) {
  (void)state;
  char name[64];
  struct vlff_ring *w = make_raw_ring(name, "trrw");
  for (int i = 0; i < 5; i++) {
    uint8_t b[128] = {(uint8_t)i};
    assert_int_equal(vlff_ring_write(w, b, sizeof b), 0);
  }
  uint64_t seq;
  uint8_t *slot = vlff_ring_reserve(w, &seq);
  assert_non_null(slot);
  assert_int_equal(seq, 5);
  truncate_seg(name, 4096);
  memset(slot, 0xAB, 64 * 1024); /* past the new end of file: SIGBUS without the guard */
  assert_int_equal(vlff_ring_commit(w, 64 * 1024), -1);
  assert_int_equal(errno, EPIPE);
  assert_int_equal(vlff_shm_last_error(), VLFF_SHM_ERR_TRUNCATED);
  uint8_t b[128] = {42};
  assert_int_equal(vlff_ring_write(w, b, sizeof b), 0);
  struct vlff_ring *r = vlff_ring_attach(name, VLFF_RECORD_RAW);
  assert_non_null(r);
  vlff_ring_seek_oldest(r);
  uint8_t got[128];
  struct vlff_ring_view v;
  assert_int_equal(vlff_ring_read_copy(r, got, sizeof got, &v, 0), 128);
  assert_int_equal(v.seq, 5); /* numbering went on; the lost record's number reused */
  assert_int_equal(got[0], 42);
  vlff_ring_close(r);
  /* Shrunk between records: reserve finds it before handing out a slot. */
  truncate_seg(name, 4096);
  assert_null(vlff_ring_reserve(w, NULL));
  assert_int_equal(errno, EPIPE);
  assert_non_null(vlff_ring_reserve(w, NULL));
  assert_int_equal(vlff_ring_commit(w, 8), 0);
  vlff_ring_close(w);
  vlff_shm_unlink(name);
}

/* A consumer: reading in place through the view, copying, and waiting. */
static void test_truncate_under_ring_reader(void **state) {
  (void)state;
  char name[64];
  struct vlff_ring *w = make_raw_ring(name, "trrr");
  struct vlff_ring *r = vlff_ring_attach(name, VLFF_RECORD_RAW);
  assert_non_null(r);
  static uint8_t rec[64 * 1024];
  memset(rec, 7, sizeof rec);
  for (int i = 0; i < 3; i++)
    assert_int_equal(vlff_ring_write(w, rec, sizeof rec), 0);
  struct vlff_ring_view v;
  assert_int_equal(vlff_ring_read_begin(r, &v, 0), 0);
  truncate_seg(name, 4096);
  volatile uint64_t sum = 0;
  for (size_t i = 0; i < v.len; i += 512)
    sum += ((const volatile uint8_t *)v.data)[i]; /* the application's own access */
  (void)sum;
  assert_int_equal(vlff_ring_read_end(r, &v), -1);
  assert_int_equal(errno, EPIPE);
  static uint8_t buf[64 * 1024];
  assert_int_equal(vlff_ring_read_copy(r, buf, sizeof buf, NULL, 0), -1);
  assert_int_equal(errno, EPIPE);
  vlff_ring_close(r);
  /* A consumer asleep waiting for the next record is not left asleep forever. */
  vlff_ring_close(w);
  vlff_shm_unlink(name);
  w = make_raw_ring(name, "trrr2");
  r = vlff_ring_attach(name, VLFF_RECORD_RAW);
  assert_non_null(r);
  truncate_seg(name, 8192);
  assert_int_equal(vlff_ring_read_copy(r, buf, sizeof buf, NULL, UINT64_MAX), -1);
  assert_int_equal(errno, EPIPE);
  assert_int_equal(vlff_shm_last_error(), VLFF_SHM_ERR_TRUNCATED);
  vlff_ring_close(r);
  vlff_ring_close(w);
  vlff_shm_unlink(name);
}

/* A ring removed from /dev/shm by hand while its creator is gone and a reader
 * waits (rm after a crash, then a restart): the new creator makes a new file
 * under the name, nobody marks the old one abandoned, and the reader used to
 * wait on it for ever. It is told to attach again, and then reads the new
 * creator's records. */
static void test_removed_under_ring_reader(void **state) {
  (void)state;
  char name[64];
  struct vlff_ring *old = make_raw_ring(name, "rmrr");
  struct vlff_ring *r = vlff_ring_attach(name, VLFF_RECORD_RAW);
  assert_non_null(r);
  static uint8_t buf[64 * 1024];
  assert_int_equal(vlff_ring_read_copy(r, buf, sizeof buf, NULL, 0), -1);
  assert_int_equal(errno, EAGAIN); /* attached, nothing yet */
  assert_int_equal(shm_unlink(name), 0);
  struct vlff_ring_params p = {.record_kind = VLFF_RECORD_RAW, .slots = 4, .slot_size = 64 * 1024};
  struct vlff_ring *w = vlff_ring_create(name, &p);
  assert_non_null(w);
  uint8_t rec[128] = {9};
  assert_int_equal(vlff_ring_write(w, rec, sizeof rec), 0);
  assert_int_equal(vlff_ring_read_copy(r, buf, sizeof buf, NULL, 2000ull * 1000 * 1000), -1);
  assert_int_equal(errno, EPIPE);
  assert_int_equal(vlff_shm_last_error(), VLFF_SHM_ERR_ABANDONED);
  assert_non_null(strstr(vlff_shm_last_message(), "removed"));
  assert_int_equal(vlff_ring_read_copy(r, buf, sizeof buf, NULL, 0), -1); /* a poller too */
  assert_int_equal(errno, EPIPE);
  vlff_ring_close(r);
  r = vlff_ring_attach(name, VLFF_RECORD_RAW);
  assert_non_null(r);
  vlff_ring_seek_oldest(r);
  assert_int_equal(vlff_ring_read_copy(r, buf, sizeof buf, NULL, 0), 128);
  assert_int_equal(buf[0], 9);
  vlff_ring_close(r);
  vlff_ring_close(w);
  vlff_ring_close(old);
  vlff_shm_unlink(name);
}

/* The mailbox: a poster's post fails, the learner's poll replaces it, posting works
 * again after attaching anew. */
static void test_truncate_under_mailbox(void **state) {
  (void)state;
  char name[64];
  test_name(name, sizeof name, "trmb");
  struct vlff_prompts *learner = vlff_prompts_create(name, NULL);
  assert_non_null(learner);
  struct vlff_prompts *poster = vlff_prompts_attach(name);
  assert_non_null(poster);
  const char *t[] = {"chair"};
  assert_int_equal(vlff_prompts_post(poster, t, 1), 0);
  uint64_t last = 0;
  struct vlff_prompt_request req;
  assert_int_equal(vlff_prompts_poll(learner, &last, &req), 1);
  assert_int_equal(vlff_prompts_answer(learner, req.seq, 1, NULL), 0);
  truncate_seg(name, 100);
  assert_int_equal(vlff_prompts_post(poster, t, 1), -1);
  assert_int_equal(errno, EPIPE);
  vlff_prompts_close(poster);
  assert_int_equal(vlff_prompts_poll(learner, &last, &req), -1);
  assert_int_equal(errno, EPIPE);
  assert_int_equal(vlff_shm_last_error(), VLFF_SHM_ERR_TRUNCATED);
  poster = vlff_prompts_attach(name);
  assert_non_null(poster);
  assert_int_equal(vlff_prompts_post(poster, t, 1), 0);
  assert_int_equal(vlff_prompts_last_post(poster), 2); /* numbering goes on */
  assert_int_equal(vlff_prompts_poll(learner, &last, &req), 1);
  assert_int_equal(req.seq, 2);
  vlff_prompts_close(poster);
  vlff_prompts_close(learner);
  vlff_shm_unlink(name);
}

/* Threads: readers of two maps in two threads while one map is truncated. The
 * reader of the truncated map gets EPIPE, the other one keeps reading. */
struct reader_arg {
  const char *name;
  atomic_int stop, reads;
  int epipe, other_errors;
};

static void *reader_thread(void *v) {
  struct reader_arg *a = v;
  struct vlff_map *r = vlff_map_attach(a->name);
  if (!r) {
    a->other_errors++;
    return NULL;
  }
  struct vlff_map_snapshot *snap = vlff_map_snapshot_new(r);
  while (!atomic_load(&a->stop)) {
    if (vlff_map_snapshot_take(r, snap) == 0) {
      atomic_fetch_add(&a->reads, 1);
    } else if (errno == EPIPE && vlff_shm_last_error() == VLFF_SHM_ERR_TRUNCATED) {
      a->epipe++;
      break;
    } else if (errno != EAGAIN) {
      a->other_errors++;
    }
  }
  vlff_map_snapshot_free(snap);
  vlff_map_detach(r);
  return NULL;
}

static void test_truncate_with_threads(void **state) {
  (void)state;
  char n1[64], n2[64];
  struct vlff_map *w1 = make_map(n1, "thr1"), *w2 = make_map(n2, "thr2");
  assert_int_equal(publish(w1, 1), 0);
  assert_int_equal(publish(w2, 2), 0);
  struct reader_arg a1 = {.name = n1}, a2 = {.name = n2};
  pthread_t t1, t2;
  assert_int_equal(pthread_create(&t1, NULL, reader_thread, &a1), 0);
  assert_int_equal(pthread_create(&t2, NULL, reader_thread, &a2), 0);
  while (atomic_load(&a1.reads) < 3 || atomic_load(&a2.reads) < 3)
    nanosleep(&(struct timespec){0, 1000000}, NULL);
  truncate_seg(n1, 4096);
  pthread_join(t1, NULL);
  int before = atomic_load(&a2.reads);
  while (atomic_load(&a2.reads) < before + 3)
    nanosleep(&(struct timespec){0, 1000000}, NULL);
  atomic_store(&a2.stop, 1);
  pthread_join(t2, NULL);
  assert_int_equal(a1.epipe, 1);
  assert_int_equal(a1.other_errors, 0);
  assert_int_equal(a2.epipe, 0);
  assert_int_equal(a2.other_errors, 0);
  vlff_map_detach(w1);
  vlff_map_detach(w2);
  vlff_shm_unlink(n1);
  vlff_shm_unlink(n2);
}

/* The application's SIGBUS handler still gets the faults that are not the library's. */
static sigjmp_buf app_jump;
static volatile sig_atomic_t app_hits;
static void app_sigbus(int sig, siginfo_t *si, void *uc) {
  (void)sig, (void)si, (void)uc;
  app_hits++;
  siglongjmp(app_jump, 1);
}

static void fault_outside_segments(void) {
  char path[] = "/tmp/vlff-sigbus-XXXXXX";
  int fd = mkstemp(path);
  assert_true(fd >= 0);
  unlink(path);
  assert_int_equal(ftruncate(fd, 4096), 0);
  volatile uint8_t *m = mmap(NULL, 4096, PROT_READ, MAP_SHARED, fd, 0);
  assert_true(m != MAP_FAILED);
  assert_int_equal(ftruncate(fd, 0), 0);
  (void)m[0];
  munmap((void *)m, 4096);
  close(fd);
}

static void test_application_sigbus_handler_kept(void **state) {
  (void)state;
  struct sigaction sa = {.sa_sigaction = app_sigbus, .sa_flags = SA_SIGINFO}, old;
  sigemptyset(&sa.sa_mask);
  sigaction(SIGBUS, &sa, &old);
  char name[64];
  struct vlff_map *w = make_map(name, "apph"); /* installs the library's guard over ours */
  app_hits = 0;
  if (sigsetjmp(app_jump, 1) == 0)
    fault_outside_segments();
  assert_int_equal(app_hits, 1);
  vlff_map_detach(w);
  vlff_shm_unlink(name);
  sigaction(SIGBUS, &old, NULL);
}

/* Without a handler of its own, a process still dies of a fault that is not in a
 * segment (the guard hides nothing else). */
static void test_foreign_fault_still_fatal(void **state) {
  (void)state;
  pid_t c = fork();
  assert_true(c >= 0);
  if (c == 0) {
    struct sigaction dfl = {.sa_handler = SIG_DFL};
    sigaction(SIGBUS, &dfl, NULL);
    char name[64];
    test_name(name, sizeof name, "fatal");
    struct vlff_map_params mp = {.max_voxels = 64};
    struct vlff_map *w = vlff_map_create(name, &mp);
    vlff_shm_unlink(name);
    if (!w)
      _exit(3);
    fault_outside_segments();
    _exit(0);
  }
  int st;
  assert_int_equal(waitpid(c, &st, 0), c);
  assert_true(WIFSIGNALED(st));
  assert_int_equal(WTERMSIG(st), SIGBUS);
}

/* --- C2: other uids -------------------------------------------------------- */

/* Runs fn(name) in a child as uid nobody; returns its exit status. */
static int as_nobody(void (*fn)(const char *), const char *name) {
  pid_t c = fork();
  assert_true(c >= 0);
  if (c == 0) {
    if (setgid(NOBODY) || setuid(NOBODY))
      _exit(99);
    fn(name);
    _exit(0);
  }
  int st;
  assert_int_equal(waitpid(c, &st, 0), c);
  return WIFEXITED(st) ? WEXITSTATUS(st) : 100;
}

static void nobody_leaves_stale_map(const char *name) {
  struct vlff_map_params mp = {.max_voxels = 64 * 64 * 16, .label_max_width = 64, .label_max_height = 48};
  struct vlff_map *w = vlff_map_create(name, &mp);
  if (!w)
    _exit(1);
  int fd = shm_open(name, O_RDWR, 0);
  if (fd < 0 || fchmod(fd, 0666))
    _exit(2);
  _exit(0); /* dies without detaching: a stale segment of another user */
}

static void test_other_users_stale_segment_refused(void **state) {
  (void)state;
  if (geteuid() != 0)
    skip();
  char name[64];
  test_name(name, sizeof name, "c2map");
  assert_int_equal(as_nobody(nobody_leaves_stale_map, name), 0);
  struct vlff_map_params mp = {.max_voxels = 64 * 64 * 16, .label_max_width = 64, .label_max_height = 48};
  assert_null(vlff_map_create(name, &mp));
  assert_int_equal(vlff_shm_last_error(), VLFF_SHM_ERR_PERM);
  assert_int_equal(errno, EACCES);
  assert_non_null(strstr(vlff_shm_last_message(), "uid 65534"));
  /* Neither adopted nor removed. */
  char path[128];
  snprintf(path, sizeof path, "/dev/shm%s", name);
  struct stat st;
  assert_int_equal(stat(path, &st), 0);
  assert_int_equal(st.st_uid, NOBODY);
  /* A reader refuses the world-writable file. */
  assert_null(vlff_map_attach(name));
  assert_int_equal(vlff_shm_last_error(), VLFF_SHM_ERR_PERM);
  assert_non_null(strstr(vlff_shm_last_message(), "0666"));
  vlff_shm_unlink(name);
}

static void nobody_makes_ring(const char *name) {
  struct vlff_ring_params p = {.record_kind = VLFF_RECORD_FRAME, .slots = 2, .slot_size = 4096};
  if (!vlff_ring_create(name, &p))
    _exit(1);
  _exit(0);
}

static void test_attach_owned_refuses(void **state) {
  (void)state;
  if (geteuid() != 0)
    skip();
  char name[64];
  test_name(name, sizeof name, "c2ring");
  assert_int_equal(as_nobody(nobody_makes_ring, name), 0);
  assert_null(vlff_ring_attach_owned(name, VLFF_RECORD_FRAME, 0, 0640));
  assert_int_equal(vlff_shm_last_error(), VLFF_SHM_ERR_PERM);
  assert_non_null(strstr(vlff_shm_last_message(), "owned by uid 65534"));
  struct vlff_ring *any = vlff_ring_attach(name, VLFF_RECORD_FRAME); /* a plain consumer may */
  assert_non_null(any);
  vlff_ring_close(any);
  vlff_shm_unlink(name);
  /* Our own ring, but group-writable where the configuration says 0640. */
  struct vlff_ring_params p = {.record_kind = VLFF_RECORD_FRAME, .slots = 2, .slot_size = 4096,
                               .perm = {.mode = 0660}};
  struct vlff_ring *w = vlff_ring_create(name, &p);
  assert_non_null(w);
  assert_null(vlff_ring_attach_owned(name, VLFF_RECORD_FRAME, 0, 0640));
  assert_int_equal(vlff_shm_last_error(), VLFF_SHM_ERR_PERM);
  assert_non_null(strstr(vlff_shm_last_message(), "mode 0660"));
  struct vlff_ring *ok = vlff_ring_attach_owned(name, VLFF_RECORD_FRAME, 0, 0660);
  assert_non_null(ok);
  vlff_ring_close(ok);
  vlff_ring_close(w);
  vlff_shm_unlink(name);
}

/* Process pid's start time, field 22 of its stat (after the last ')'), read
 * where the library reads it (qemu-user fakes a process's own /proc/PID/stat). */
static uint64_t start_time_of(int pid) {
  char path[64], buf[1024];
  snprintf(path, sizeof path, "/proc/%d/task/%d/stat", pid, pid);
  FILE *f = fopen(path, "r");
  assert_non_null(f);
  size_t n = fread(buf, 1, sizeof buf - 1, f);
  fclose(f);
  buf[n] = 0;
  unsigned long long t = 0;
  const char *p = strrchr(buf, ')');
  assert_non_null(p);
  assert_int_equal(sscanf(p + 2, "%*c %*d %*d %*d %*d %*d %*u %*u %*u %*u %*u %*u %*u %*d %*d %*d %*d %*d %*d %llu",
                          &t), 1);
  return t;
}

/* Writes a map segment's creator: its PID (header word at 84) and start
 * time (at 104). */
static void set_creator(const char *name, int32_t pid, uint64_t start) {
  int fd = shm_open(name, O_RDWR, 0);
  assert_true(fd >= 0);
  assert_int_equal(pwrite(fd, &pid, 4, 84), 4);
  assert_int_equal(pwrite(fd, &start, 8, 104), 8);
  close(fd);
}

/* A stale segment whose creator's PID a later process reuses: alive, but
 * started at another time. It is taken over; a creator that is the live
 * process (the same start time), or of a header without a start time, is
 * not. Before the start time was kept, a restarted simulator found its
 * dead predecessor's PID reused and refused to start. */
static void test_stale_creator_pid_reused(void **state) {
  (void)state;
  char name[64];
  struct vlff_map *w = make_map(name, "reuse");
  assert_int_equal(publish(w, 1), 0);
  vlff_map_detach(w);
  /* PID 1 is alive and started long before this test. */
  const uint64_t init_start = start_time_of(1), mine = start_time_of(getpid());
  assert_true(init_start != mine);
  set_creator(name, 1, mine);
  struct vlff_shm_info info;
  assert_int_equal(vlff_shm_stat(name, &info), 0);
  assert_int_equal(info.creator_pid, 1);
  assert_false(info.creator_alive);
  struct vlff_map_params mp = {.max_voxels = 64 * 64 * 16, .label_max_width = 64, .label_max_height = 48};
  w = vlff_map_create(name, &mp);
  assert_non_null(w);
  assert_int_equal(vlff_map_generation(w), 2); /* taken over in place */
  vlff_map_detach(w);
  /* The live process itself, and a PID without a start time: refused. */
  const uint64_t starts[] = {init_start, 0};
  for (int i = 0; i < 2; i++) {
    set_creator(name, 1, starts[i]);
    assert_int_equal(vlff_shm_stat(name, &info), 0);
    assert_true(info.creator_alive);
    assert_null(vlff_map_create(name, &mp));
    assert_int_equal(vlff_shm_last_error(), VLFF_SHM_ERR_EXISTS);
    assert_non_null(strstr(vlff_shm_last_message(), "owned by live process 1"));
  }
  vlff_shm_unlink(name);
}

/* Our own stale segment with a wider mode than configured is replaced, not taken over
 * in place: someone may hold a descriptor the wider mode let them open. */
static void test_own_stale_wider_mode_replaced(void **state) {
  (void)state;
  char name[64];
  struct vlff_map *w = make_map(name, "c2wide");
  assert_int_equal(publish(w, 1), 0);
  vlff_map_detach(w);
  set_creator(name, 0, 0); /* stale: its creator (us) is alive, so mark it dead */
  int fd = shm_open(name, O_RDWR, 0);
  assert_true(fd >= 0);
  assert_int_equal(fchmod(fd, 0660), 0);
  close(fd);
  struct vlff_map_params mp = {.max_voxels = 64 * 64 * 16, .label_max_width = 64, .label_max_height = 48,
                               .perm = {.mode = 0640}};
  w = vlff_map_create(name, &mp);
  assert_non_null(w);
  assert_int_equal(vlff_map_generation(w), 1); /* fresh, not generation 2 */
  char path[128];
  snprintf(path, sizeof path, "/dev/shm%s", name);
  struct stat st;
  assert_int_equal(stat(path, &st), 0);
  assert_int_equal(st.st_mode & 07777, 0640);
  vlff_map_detach(w);
  /* The same with the right mode is taken over in place. */
  set_creator(name, 0, 0);
  w = vlff_map_create(name, &mp);
  assert_non_null(w);
  assert_int_equal(vlff_map_generation(w), 2);
  vlff_map_detach(w);
  vlff_shm_unlink(name);
}

/* A writer killed between flipping the current buffer and storing the version left
 * the control word one behind what readers already see: the next writer must not
 * reuse the number for a different map. */
static void test_version_never_reused(void **state) {
  (void)state;
  char name[64];
  struct vlff_map *w = make_map(name, "vreuse");
  assert_int_equal(publish(w, 1), 0);
  assert_int_equal(publish(w, 2), 0);
  struct vlff_map *r = vlff_map_attach(name);
  assert_non_null(r);
  struct vlff_map_snapshot *snap = vlff_map_snapshot_new(r);
  assert_int_equal(vlff_map_snapshot_take(r, snap), 0);
  struct vlff_map_info in;
  vlff_map_snapshot_info(snap, &in);
  assert_int_equal(in.version, 2);
  int fd = shm_open(name, O_RDWR, 0);
  assert_true(fd >= 0);
  uint64_t one = 1;
  assert_int_equal(pwrite(fd, &one, 8, 136), 8); /* the control block's version word */
  close(fd);
  assert_int_equal(publish(w, 3), 0);
  assert_int_equal(vlff_map_snapshot_take(r, snap), 0);
  vlff_map_snapshot_info(snap, &in);
  assert_int_equal(in.version, 3);
  vlff_map_snapshot_free(snap);
  vlff_map_detach(r);
  vlff_map_detach(w);
  vlff_shm_unlink(name);
}

/* A 5-byte foreign file at our name is not deleted. */
static void test_small_foreign_file_untouched(void **state) {
  (void)state;
  char name[64];
  test_name(name, sizeof name, "c2small");
  int fd = shm_open(name, O_RDWR | O_CREAT | O_EXCL, 0640);
  assert_true(fd >= 0);
  assert_int_equal(write(fd, "hello", 5), 5);
  close(fd);
  struct vlff_map_params mp = {.max_voxels = 64};
  assert_null(vlff_map_create(name, &mp));
  assert_int_equal(vlff_shm_last_error(), VLFF_SHM_ERR_FOREIGN);
  fd = shm_open(name, O_RDONLY, 0);
  assert_true(fd >= 0);
  char b[8] = {0};
  assert_int_equal(read(fd, b, sizeof b), 5);
  assert_string_equal(b, "hello");
  close(fd);
  vlff_shm_unlink(name);
}


/* Anyone may mkfifo /dev/shm/<name> (issue 51, item 1): a plain open() of a FIFO for
 * reading waits for a writer, for ever, so every reader of that name hung (the
 * node's ingest thread, then its SIGTERM in pthread_join; vlff-view; vlff-shm).
 * Every attach, stat and create refuses it at once, naming the segment and what
 * is there. An alarm without SA_RESTART turns a hang into EINTR: a failed check,
 * not a test stuck until ctest's timeout. */
static void on_alarm(int sig) { (void)sig; }

static void expect_fifo_refused(const char *name, const char *what) {
  int err = vlff_shm_last_error();
  const char *msg = vlff_shm_last_message();
  if (err != VLFF_SHM_ERR_FOREIGN || !strstr(msg, name) || !strstr(msg, "is a FIFO"))
    fail_msg("%s: error %d (%s), errno %d", what, err, msg, errno);
}

static void test_fifo_at_segment_name(void **state) {
  (void)state;
  char name[64], path[128];
  test_name(name, sizeof name, "fifo");
  snprintf(path, sizeof path, "/dev/shm%s", name);
  assert_int_equal(mkfifo(path, 0644), 0);
  struct sigaction sa = {.sa_handler = on_alarm}, old;
  sigemptyset(&sa.sa_mask);
  assert_int_equal(sigaction(SIGALRM, &sa, &old), 0);
  alarm(10);
  assert_null(vlff_ring_attach(name, VLFF_RECORD_ANY));
  expect_fifo_refused(name, "ring attach");
  assert_null(vlff_ring_attach_owned(name, VLFF_RECORD_FRAME, geteuid(), 0));
  expect_fifo_refused(name, "ring attach_owned");
  assert_null(vlff_map_attach(name));
  expect_fifo_refused(name, "map attach");
  assert_null(vlff_prompts_attach(name));
  expect_fifo_refused(name, "prompts attach");
  struct vlff_shm_info in;
  assert_int_equal(vlff_shm_stat(name, &in), -1);
  expect_fifo_refused(name, "stat");
  /* Creators neither open it for reading nor remove it. */
  struct vlff_ring_params rp = {.record_kind = VLFF_RECORD_RAW, .slots = 2, .slot_size = 64};
  assert_null(vlff_ring_create(name, &rp));
  expect_fifo_refused(name, "ring create");
  assert_int_equal(errno, EEXIST); /* something else holds the name */
  struct vlff_map_params mp = {.max_voxels = 64};
  assert_null(vlff_map_create(name, &mp));
  expect_fifo_refused(name, "map create");
  assert_null(vlff_prompts_create(name, NULL));
  expect_fifo_refused(name, "prompts create");
  alarm(0);
  sigaction(SIGALRM, &old, NULL);
  struct stat st;
  assert_int_equal(lstat(path, &st), 0);
  assert_true(S_ISFIFO(st.st_mode));
  unlink(path);
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(test_truncate_under_map_reader),
    cmocka_unit_test(test_truncate_under_map_writer),
    cmocka_unit_test(test_truncate_under_ring_writer),
    cmocka_unit_test(test_truncate_under_ring_reader), cmocka_unit_test(test_removed_under_ring_reader),
    cmocka_unit_test(test_truncate_under_mailbox), cmocka_unit_test(test_truncate_with_threads),
    cmocka_unit_test(test_application_sigbus_handler_kept),
    cmocka_unit_test(test_foreign_fault_still_fatal),
    cmocka_unit_test(test_other_users_stale_segment_refused),
    cmocka_unit_test(test_attach_owned_refuses),
    cmocka_unit_test(test_own_stale_wider_mode_replaced), cmocka_unit_test(test_stale_creator_pid_reused),
    cmocka_unit_test(test_small_foreign_file_untouched),
    cmocka_unit_test(test_version_never_reused), cmocka_unit_test(test_fifo_at_segment_name))
