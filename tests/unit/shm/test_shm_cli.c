/* The vlff-shm tool against real segments: list, stat, dump-frame, label,
 * set-prompts, and a clear error for a missing segment. */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <cmocka.h>

#include "shm_test_util.h"
#include "unit.h"

#include <errno.h>
#include <signal.h>
#include <stdbool.h>
#include <stdlib.h>
#include <sys/wait.h>
#include <unistd.h>

static int run(const char *args, char *out, size_t cap) {
  char cmd[1024];
  const char *emu = getenv("VLFF_EMULATOR"); /* qemu-user in a cross-built tree */
  snprintf(cmd, sizeof cmd, "timeout 30 %s %s %s 2>&1", emu ? emu : "", VLFF_SHM_CLI, args);
  FILE *f = popen(cmd, "r");
  assert_non_null(f);
  size_t n = fread(out, 1, cap - 1, f);
  out[n] = 0;
  /* The rest is read and dropped: a machine with many segments makes `list`
   * longer than out, and a reader that stops would kill it with SIGPIPE. */
  char sink[4096];
  while (fread(sink, 1, sizeof sink, f) > 0) {
  }
  int st = pclose(f);
  return WIFEXITED(st) ? WEXITSTATUS(st) : -1;
}

/* watch on a ring whose writer died waits for a new one, as it should, but
 * says so: it printed nothing and looked hung. Its output is read as it
 * comes (up to 30 s on a loaded or emulated host), then it is stopped. */
static void cli_watch_dead_writer(void **state) {
  (void)state;
  char name[64], cmd[1024], path[128], out[8192] = "";
  test_name(name, sizeof name, "cliwd");
  pid_t pid = fork();
  assert_true(pid >= 0);
  if (pid == 0) {
    struct vlff_ring_params rc = {.record_kind = VLFF_RECORD_FRAME, .slots = 4, .slot_size = 4096};
    _exit(vlff_ring_create(name, &rc) ? 0 : 1); /* exits without closing: a dead writer's ring */
  }
  int st;
  assert_int_equal(waitpid(pid, &st, 0), pid);
  assert_true(WIFEXITED(st) && WEXITSTATUS(st) == 0);
  snprintf(path, sizeof path, "/tmp/vlff-test-cliwd-%d.txt", (int)getpid());
  const char *emu = getenv("VLFF_EMULATOR");
  snprintf(cmd, sizeof cmd, "exec %s %s watch %s 1 >%s 2>&1", emu ? emu : "", VLFF_SHM_CLI, name, path);
  pid_t w = fork();
  assert_true(w >= 0);
  if (w == 0) {
    execl("/bin/sh", "sh", "-c", cmd, (char *)NULL);
    _exit(127);
  }
  bool said = false;
  for (int i = 0; i < 300 && !said; i++) {
    usleep(100000);
    FILE *f = fopen(path, "r");
    if (!f) continue;
    size_t n = fread(out, 1, sizeof out - 1, f);
    out[n] = 0;
    fclose(f);
    said = strstr(out, ") is not running; waiting for a new one") != NULL;
  }
  assert_int_equal(waitpid(w, &st, WNOHANG), 0); /* still waiting, as it should */
  kill(w, SIGTERM);
  assert_int_equal(waitpid(w, &st, 0), w);
  unlink(path);
  vlff_shm_unlink(name);
  if (!said || !strstr(out, "its writer (pid ")) fail_msg("watch: %s", out);
}

/* A FIFO at a name under /dev/shm (issue 51, item 1): list, stat and label
 * opened it for reading and waited for a writer for ever. `timeout` turns a hang
 * into status 124. */
static void cli_fifo_refused(void **state) {
  (void)state;
  char name[64], path[128], args[512], out[8192];
  test_name(name, sizeof name, "clififo");
  snprintf(path, sizeof path, "/dev/shm%s", name);
  assert_int_equal(mkfifo(path, 0644), 0);
  assert_int_equal(run("list", out, sizeof out), 0);
  assert_null(strstr(out, name)); /* not a vlff segment: not listed */
  snprintf(args, sizeof args, "stat %s", name);
  assert_int_equal(run(args, out, sizeof out), 1);
  if (!strstr(out, "is a FIFO, expected a regular file"))
    fail_msg("stat: %s", out);
  snprintf(args, sizeof args, "label %s 0 0 0", name);
  assert_int_equal(run(args, out, sizeof out), 1);
  assert_non_null(strstr(out, "is a FIFO"));
  snprintf(args, sizeof args, "watch %s 1", name);
  assert_int_equal(run(args, out, sizeof out), 1);
  assert_non_null(strstr(out, "is a FIFO"));
  unlink(path);
}

/* What the learner repaired in its mailbox (issue 51, items 3 and 15) is shown by
 * vlff-shm stat, for the chaos bench and for whoever wonders about log lines. */
static void cli_mailbox_repairs_shown(void **state) {
  (void)state;
  char mbox[64], args[256], out[8192];
  test_name(mbox, sizeof mbox, "clirep");
  struct vlff_prompts *pb = vlff_prompts_create(mbox, NULL);
  assert_non_null(pb);
  struct shm_raw r = {.fd = -1};
  assert_int_equal(shm_raw_open(mbox, &r), 0);
  __atomic_store_n((uint32_t *)(r.base + 80), 2u, __ATOMIC_RELEASE); /* the state word: "abandoned" */
  struct vlff_prompt_request *req = malloc(sizeof *req);
  uint64_t last = 0;
  assert_int_equal(vlff_prompts_poll(pb, &last, req), -1);
  __atomic_store_n((uint64_t *)(r.base + MBOX_CTL_OFF + 16), 5u, __ATOMIC_RELEASE); /* answered, nothing posted */
  assert_int_equal(vlff_prompts_poll(pb, &last, req), -1);
  free(req);
  snprintf(args, sizeof args, "stat %s", mbox);
  assert_int_equal(run(args, out, sizeof out), 0);
  if (!strstr(out, "posts 0\nstate_repairs 1\nresyncs 1\n"))
    fail_msg("stat: %s", out);
  shm_raw_close(&r);
  vlff_prompts_close(pb);
  vlff_shm_unlink(mbox);
}

/* A frame ring at name holding one 4x2 RGB frame numbered frame_id, its
 * colour bytes 0, 10, 20, ... (copied to rgb[24] when given). */
static struct vlff_ring *frame_ring(const char *name, uint64_t frame_id, uint8_t *rgb) {
  uint64_t slot = vlff_frame_slot_size(4, 2, VLFF_PIX_RGB8, VLFF_PIX_DEPTH_U16_MM);
  struct vlff_ring_params rp = {.record_kind = VLFF_RECORD_FRAME, .slots = 2, .slot_size = slot};
  struct vlff_ring *w = vlff_ring_create(name, &rp);
  assert_non_null(w);
  struct vlff_frame_hdr *h = vlff_ring_reserve(w, NULL);
  uint64_t len = vlff_frame_layout(h, slot, 4, 2, VLFF_PIX_RGB8, VLFF_PIX_DEPTH_U16_MM);
  h->frame_id = frame_id;
  uint8_t *px = (uint8_t *)h + h->plane[0].offset;
  for (int i = 0; i < 24; i++)
    px[i] = (uint8_t)(i * 10);
  if (rgb)
    memcpy(rgb, px, 24);
  assert_int_equal(vlff_ring_commit(w, len), 0);
  return w;
}

/* A map at name of 2x2x2 voxels of 1 m, published once. */
static struct vlff_map *small_map(const char *name, uint16_t labels[8], const char **prompts, int n) {
  struct vlff_map_params mp = {.max_voxels = 8};
  struct vlff_map *m = vlff_map_create(name, &mp);
  assert_non_null(m);
  struct vlff_map_grid g = {.voxel_size = 1, .dims = {2, 2, 2}, .labels = labels};
  struct vlff_map_update u = {.grid = &g, .prompts = prompts, .prompt_count = n};
  assert_int_equal(vlff_map_publish(m, &u), 0);
  return m;
}

/* The writer's paging counters and box (ABI 8; issue 48: memory bounded and
 * visible) are printed by vlff-shm stat, one "key value" line each, every
 * field its own value so that a field printed in another's place shows. */
static void cli_status_paging_shown(void **state) {
  (void)state;
  char map[64], args[256], out[8192];
  test_name(map, sizeof map, "clipage");
  uint16_t labels[8] = {0};
  const char *prompts[] = {"floor"};
  struct vlff_map *m = small_map(map, labels, prompts, 1);
  struct vlff_map_status st = {.keyframes_paged = 11, .keyframes_paged_out = 12, .keyframes_paged_in = 13,
                               .keyframes_dropped = 14, .keyframes_page_mb = 15.375, .keyframes_page_limit_mb = 128,
                               .evidence_paged = 21, .evidence_paged_out = 22, .evidence_paged_in = 23,
                               .evidence_dropped = 24, .box_lo = {-2.5, -3.25, -1.5}, .box_hi = {7.5, 4.125, 1.5},
                               .box_growths = 31, .box_refused = 32};
  snprintf(st.state_name, sizeof st.state_name, "operational");
  assert_int_equal(vlff_map_set_status(m, &st), 0);
  snprintf(args, sizeof args, "stat %s", map);
  assert_int_equal(run(args, out, sizeof out), 0);
  const char *want = "\nkeyframes_paged 11\nkeyframes_paged_out 12\nkeyframes_paged_in 13\nkeyframes_dropped 14\n"
                     "keyframes_page_mb 15.4\nkeyframes_page_limit_mb 128.0\nevidence_paged 21\n"
                     "evidence_paged_out 22\nevidence_paged_in 23\nevidence_dropped 24\n"
                     "box_lo -2.500 -3.250 -1.500\nbox_hi 7.500 4.125 1.500\nbox_growths 31\nbox_refused 32\n";
  if (!strstr(out, want)) fail_msg("stat '%s' lacks '%s'", out, want);
  vlff_map_detach(m);
  vlff_shm_unlink(map);
}

/* A segment whose published geometry was forged finite but absurd (a
 * 1e300 m voxel; the header's checksum does not cover the map's meta):
 * readers refuse it as corrupt; dump-map wrote infinite coordinates and
 * label answered a class. The voxel size is found by its bytes, 0.375 m,
 * which nothing else in the segment holds, and every copy replaced. */
static void cli_forged_geometry_refused(void **state) {
  (void)state;
  char map[64], args[512], out[8192];
  test_name(map, sizeof map, "cligeo");
  struct vlff_map_params mp = {.max_voxels = 8};
  struct vlff_map *m = vlff_map_create(map, &mp);
  assert_non_null(m);
  uint16_t labels[8] = {0, 1, 1, 0, 0, 1, 1, 0};
  const char *prompts[] = {"floor", "door"};
  struct vlff_map_grid g = {.voxel_size = 0.375, .dims = {2, 2, 2}, .labels = labels};
  struct vlff_map_update u = {.grid = &g, .prompts = prompts, .prompt_count = 2};
  assert_int_equal(vlff_map_publish(m, &u), 0);
  assert_int_equal(vlff_map_publish(m, &u), 0); /* both buffers hold the geometry */
  struct shm_raw r = {.fd = -1};
  assert_int_equal(shm_raw_open(map, &r), 0);
  const double was = 0.375, forged = 1e300;
  int copies = 0;
  for (size_t o = 0; o + 8 <= r.size; o += 8)
    if (!memcmp(r.base + o, &was, 8)) memcpy(r.base + o, &forged, 8), copies++;
  shm_raw_close(&r);
  assert_true(copies >= 1);
  struct vlff_map *rd = vlff_map_attach(map);
  assert_non_null(rd);
  uint16_t label;
  uint8_t conf;
  assert_int_equal(vlff_map_label_at(rd, 0.1, 0.1, 0.1, &label, &conf), -1);
  assert_int_equal(errno, EBADMSG);
  vlff_map_detach(rd);
  snprintf(args, sizeof args, "label %s 0.1 0.1 0.1", map);
  assert_int_equal(run(args, out, sizeof out), 1);
  if (!strstr(out, "published map metadata is inconsistent")) fail_msg("label: %s", out);
  snprintf(args, sizeof args, "dump-map %s /tmp/vlff-test-cligeo-%d.ply", map, (int)getpid());
  assert_int_equal(run(args, out, sizeof out), 1);
  if (!strstr(out, "published map metadata is inconsistent")) fail_msg("dump-map: %s", out);
  vlff_map_detach(m);
  vlff_shm_unlink(map);
}

/* A far map forged after it was published (a block's runs pointed past
 * the far area): the reader's lookup there and dump-map refuse it as
 * corrupt instead of reading past their copies (dump-map walked the runs it
 * was given and overflowed its snapshot). The block record is found by its
 * key, (7, 7, 7), in both buffers. */
static void cli_forged_far_refused(void **state) {
  (void)state;
  char map[64], args[512], out[8192];
  test_name(map, sizeof map, "clifar");
  struct vlff_map_params mp = {.max_voxels = 8};
  struct vlff_map *m = vlff_map_create_far(map, &mp, 4096);
  assert_non_null(m);
  uint16_t labels[8] = {0};
  const char *prompts[] = {"floor"};
  struct vlff_map_grid g = {.voxel_size = 0.5, .dims = {2, 2, 2}, .labels = labels};
  const struct vlff_map_far_block blk = {{7, 7, 7}, 0};
  const struct vlff_map_far_run runs[2] = {{.label = 0, .count = 100, .conf = 9},
                                           {.label = VLFF_LABEL_UNKNOWN, .count = 3996}};
  const struct vlff_map_far far = {.voxel_size = 0.5, .nblocks = 1, .nruns = 2, .blocks = &blk, .runs = runs};
  assert_int_equal(vlff_map_set_far(m, &far), 0);
  struct vlff_map_update u = {.grid = &g, .prompts = prompts, .prompt_count = 1};
  assert_int_equal(vlff_map_publish(m, &u), 0);
  assert_int_equal(vlff_map_publish(m, &u), 0); /* both buffers hold it */
  snprintf(args, sizeof args, "label %s 56.1 56.1 56.1", map);
  assert_int_equal(run(args, out, sizeof out), 0);
  if (!strstr(out, "label 0 confidence 9 prompt floor")) fail_msg("label: %s", out);
  /* first a run's count one short (the block covers 4095 voxels): the
   * lookup reads the whole block, not only up to the voxel it answers */
  struct shm_raw r = {.fd = -1};
  assert_int_equal(shm_raw_open(map, &r), 0);
  const struct vlff_map_far_run short_run = {.label = 0, .count = 99, .conf = 9};
  int shorts = 0;
  for (size_t o = 0; o + 6 <= r.size; o += 2)
    if (!memcmp(r.base + o, &runs[0], 6)) memcpy(r.base + o, &short_run, 6), shorts++;
  assert_int_equal(shorts, 2);
  shm_raw_close(&r);
  uint16_t label;
  uint8_t conf;
  struct vlff_map *rd0 = vlff_map_attach(map);
  assert_non_null(rd0);
  assert_int_equal(vlff_map_label_at(rd0, 56.1, 56.1, 56.1, &label, &conf), -1);
  assert_int_equal(errno, EBADMSG);
  vlff_map_detach(rd0);
  assert_int_equal(shm_raw_open(map, &r), 0);
  const uint32_t forged = 0x40000000;
  int copies = 0;
  for (size_t o = 0; o + 16 <= r.size; o += 4)
    if (!memcmp(r.base + o, &blk, 16)) memcpy(r.base + o + 12, &forged, 4), copies++;
  shm_raw_close(&r);
  assert_int_equal(copies, 2);
  struct vlff_map *rd = vlff_map_attach(map);
  assert_non_null(rd);
  assert_int_equal(vlff_map_label_at(rd, 56.1, 56.1, 56.1, &label, &conf), -1);
  assert_int_equal(errno, EBADMSG);
  assert_int_equal(vlff_map_label_at(rd, 0.1, 0.1, 0.1, &label, &conf), 0); /* the grid's own voxel */
  struct vlff_map_snapshot *s = vlff_map_snapshot_new(rd);
  assert_non_null(s);
  assert_int_equal(vlff_map_snapshot_take(rd, s), -1);
  assert_int_equal(errno, EBADMSG);
  vlff_map_snapshot_free(s);
  vlff_map_detach(rd);
  snprintf(args, sizeof args, "dump-map %s /tmp/vlff-test-clifar-%d.ply", map, (int)getpid());
  assert_int_equal(run(args, out, sizeof out), 1);
  if (!strstr(out, "published map metadata is inconsistent")) fail_msg("dump-map: %s", out);
  vlff_map_detach(m);
  vlff_shm_unlink(map);
}

static void cli_commands(void **state) {
  (void)state;
  char ring[64], map[64], mbox[64], args[512], out[8192];
  test_name(ring, sizeof ring, "cliring");
  test_name(map, sizeof map, "climap");
  test_name(mbox, sizeof mbox, "clibox");
  uint8_t rgb[24];
  struct vlff_ring *w = frame_ring(ring, 77, rgb);
  uint16_t labels[8] = {0, 1, 1, 0, 0, 1, 1, 0};
  const char *prompts[] = {"floor", "door"};
  struct vlff_map *m = small_map(map, labels, prompts, 2);
  struct vlff_shm_perm perm = {.mode = 0660};
  struct vlff_prompts *pb = vlff_prompts_create(mbox, &perm);
  assert_non_null(pb);

  assert_int_equal(run("list", out, sizeof out), 0);
  assert_non_null(strstr(out, ring));
  assert_non_null(strstr(out, "frame"));
  snprintf(args, sizeof args, "stat %s", map);
  assert_int_equal(run(args, out, sizeof out), 0);
  assert_non_null(strstr(out, "kind map\n"));
  assert_non_null(strstr(out, "prompt 1 door\n"));
  snprintf(args, sizeof args, "label %s 1.5 0.5 0.5", map);
  assert_int_equal(run(args, out, sizeof out), 0);
  assert_string_equal(out, "label 1 confidence 255 prompt door version 1\n");
  /* A coordinate that is no number of metres is a usage error naming it. */
  static const char *const not_metres[][2] = {{"1.5 nan 0.5", "Y 'nan'"}, {"1.5 0.5 -inf", "Z '-inf'"}};
  for (int i = 0; i < 2; i++) {
    snprintf(args, sizeof args, "label %s %s", map, not_metres[i][0]);
    assert_int_equal(run(args, out, sizeof out), 2);
    assert_non_null(strstr(out, not_metres[i][1]));
    assert_non_null(strstr(out, "expected a finite number of metres"));
  }
  char ppm[128];
  snprintf(ppm, sizeof ppm, "/tmp/vlff-cli-%d.ppm", (int)getpid());
  snprintf(args, sizeof args, "dump-frame %s %s", ring, ppm);
  assert_int_equal(run(args, out, sizeof out), 0);
  assert_non_null(strstr(out, "frame_id 77"));
  FILE *f = fopen(ppm, "rb");
  assert_non_null(f);
  uint8_t img[64];
  size_t n = fread(img, 1, sizeof img, f);
  fclose(f);
  unlink(ppm);
  assert_int_equal(n, 11 + 24);
  assert_memory_equal(img, "P6\n4 2\n255\n", 11);
  assert_memory_equal(img + 11, rgb, 24);
  /* A learner answering: the CLI waits for its answer and prints it. */
  pid_t learner = fork();
  assert_true(learner >= 0);
  if (learner == 0) {
    uint64_t seen = 0;
    struct vlff_prompt_request rq;
    for (int i = 0; i < 5000; i++) {
      if (vlff_prompts_poll(pb, &seen, &rq) == 1)
        _exit(vlff_prompts_answer(pb, rq.seq, 1, NULL) == 0 ? 0 : 2);
      usleep(1000);
    }
    _exit(1);
  }
  snprintf(args, sizeof args, "set-prompts %s \"red cup\" chair", mbox);
  assert_int_equal(run(args, out, sizeof out), 0);
  assert_string_equal(out, "accepted 1\n");
  int lst;
  assert_int_equal(waitpid(learner, &lst, 0), learner);
  assert_true(WIFEXITED(lst) && WEXITSTATUS(lst) == 0);
  uint64_t last = 0;
  struct vlff_prompt_request *req = malloc(sizeof *req);
  assert_int_equal(vlff_prompts_poll(pb, &last, req), 1);
  assert_string_equal(req->text[0], "red cup");
  assert_string_equal(req->text[1], "chair");
  free(req);
  /* Refused before posting: a newline would forge a line of the CLI's output. */
  snprintf(args, sizeof args, "set-prompts %s \"$(printf 'wall\\nlabel 0 confidence 255 prompt FAKE')\" floor", mbox);
  assert_int_equal(run(args, out, sizeof out), 1);
  assert_non_null(strstr(out, "control characters"));
  /* Nobody answers: the CLI says so and fails. */
  snprintf(args, sizeof args, "set-prompts -t 0.2 %s door", mbox);
  assert_int_equal(run(args, out, sizeof out), 1);
  assert_non_null(strstr(out, "no answer to request 2"));
  assert_int_equal(run("stat /vlff-test-cli-missing", out, sizeof out), 1);
  assert_non_null(strstr(out, "no such segment"));
  assert_int_equal(run("frobnicate", out, sizeof out), 2);
  assert_non_null(strstr(out, "Examples:"));
  vlff_prompts_close(pb);
  vlff_map_detach(m);
  vlff_ring_close(w);
  vlff_shm_unlink(ring);
  vlff_shm_unlink(map);
  vlff_shm_unlink(mbox);
}

/* What a new user gets wrong: a segment of the wrong kind is named as such
 * (it said "segment kind 1, expected 2"), each message names the segment
 * once, and an output FILE that is a FIFO or a directory is refused and left
 * as it was: dump-frame opened a FIFO to write and waited for a reader for
 * ever, dump-map renamed its file over it (over a device node too, as root).
 * `timeout` in run() turns a hang into status 124. */
static void cli_wrong_targets(void **state) {
  (void)state;
  char ring[64], map[64], args[512], out[8192], fifo[128], dir[128], fresh[128];
  test_name(ring, sizeof ring, "cliwr");
  test_name(map, sizeof map, "cliwm");
  struct vlff_ring *w = frame_ring(ring, 1, NULL);
  uint16_t labels[8] = {0};
  const char *prompts[] = {"floor"};
  struct vlff_map *m = small_map(map, labels, prompts, 1);

  static const struct {
    const char *cmd, *says;
  } kinds[] = {
      {"label %s 0 0 0", "(a ring where a map is expected)"},
      {"dump-map %s /tmp/vlff-cli-never.bin", "(a ring where a map is expected)"},
      {"set-prompts -t 0.2 %s door", "(a ring where a prompt mailbox is expected)"},
  };
  for (size_t i = 0; i < sizeof kinds / sizeof kinds[0]; i++) {
    snprintf(args, sizeof args, kinds[i].cmd, ring);
    assert_int_equal(run(args, out, sizeof out), 1);
    char once[128];
    snprintf(once, sizeof once, "vlff-shm: %s: segment kind 1, expected", ring);
    if (strncmp(out, once, strlen(once)) || !strstr(out, kinds[i].says)) fail_msg("%s: %s", args, out);
  }
  snprintf(args, sizeof args, "dump-frame %s /tmp/vlff-cli-never.ppm", map);
  assert_int_equal(run(args, out, sizeof out), 1);
  assert_non_null(strstr(out, "(a map where a ring is expected)"));

  snprintf(fifo, sizeof fifo, "/tmp/vlff-cli-fifo-%d", (int)getpid());
  snprintf(dir, sizeof dir, "/tmp/vlff-cli-dir-%d", (int)getpid());
  snprintf(fresh, sizeof fresh, "/tmp/vlff-cli-fresh-%d.bin", (int)getpid());
  assert_int_equal(mkfifo(fifo, 0644), 0);
  assert_int_equal(mkdir(dir, 0755), 0);
  const char *const targets[][2] = {{fifo, "is a FIFO"}, {dir, "is a directory"}};
  for (int t = 0; t < 2; t++)
    for (int c = 0; c < 2; c++) {
      snprintf(args, sizeof args, c ? "dump-map %s %s" : "dump-frame %s %s", c ? map : ring, targets[t][0]);
      assert_int_equal(run(args, out, sizeof out), 1);
      if (!strstr(out, targets[t][1]) || !strstr(out, "expected a regular file or a new name")) fail_msg("%s: %s", args, out);
      struct stat st;
      assert_int_equal(lstat(targets[t][0], &st), 0);
      assert_true(t ? S_ISDIR(st.st_mode) : S_ISFIFO(st.st_mode));
    }
  /* a new name and a regular file are written (replaced whole) */
  for (int k = 0; k < 2; k++) {
    snprintf(args, sizeof args, "dump-map %s %s", map, fresh);
    assert_int_equal(run(args, out, sizeof out), 0);
  }
  unlink(fresh);
  unlink(fifo);
  rmdir(dir);
  vlff_map_detach(m);
  vlff_ring_close(w);
  vlff_shm_unlink(ring);
  vlff_shm_unlink(map);
}

/* Segment names are outside data: a name holding ESC and a newline, given on
 * the command line or found in /dev/shm, reaches the terminal escaped
 * (vlff/escape.h), in the library's messages and in `list`. */
static void assert_no_raw_control(const char *out) {
  for (const unsigned char *c = (const unsigned char *)out; *c; c++)
    if ((*c < 0x20 && *c != '\n') || *c == 0x7f) fail_msg("raw byte 0x%02x in output '%s'", *c, out);
}

static void cli_escapes_names(void **state) {
  (void)state;
  char args[512], out[8192], want[256];
  snprintf(args, sizeof args, "stat \"/vlff-test-cli-esc-%d$(printf '\\033[2J\\nx')\"", (int)getpid());
  assert_int_equal(run(args, out, sizeof out), 1);
  print_message("  %s", out);
  assert_no_raw_control(out);
  snprintf(want, sizeof want, "/vlff-test-cli-esc-%d\\x1b[2J\\x0ax: no such segment", (int)getpid());
  if (!strstr(out, want)) fail_msg("output '%s' lacks '%s'", out, want);
  /* a broken vlff segment (the magic, then nothing) is listed with its error */
  char path[256];
  snprintf(path, sizeof path, "/dev/shm/vlff-test-cli-esc-%d\x1b]0;owned\x07\n", (int)getpid());
  FILE *f = fopen(path, "wb");
  assert_non_null(f);
  assert_int_equal(fwrite("VLFFSHM\0", 1, 8, f), 8);
  fclose(f);
  int rc = run("list", out, sizeof out);
  unlink(path);
  assert_int_equal(rc, 0);
  assert_no_raw_control(out);
  snprintf(want, sizeof want, "/vlff-test-cli-esc-%d\\x1b]0;owned\\x07\\x0a", (int)getpid());
  if (!strstr(out, want)) fail_msg("list '%s' lacks '%s'", out, want);
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(cli_commands), cmocka_unit_test(cli_status_paging_shown), cmocka_unit_test(cli_fifo_refused), cmocka_unit_test(cli_mailbox_repairs_shown),
    cmocka_unit_test(cli_watch_dead_writer), cmocka_unit_test(cli_forged_geometry_refused),
    cmocka_unit_test(cli_forged_far_refused),
    cmocka_unit_test(cli_escapes_names), cmocka_unit_test(cli_wrong_targets))
