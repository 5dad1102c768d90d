/* External extractor: the Python client (ctypes over libvlff-shm) reads
 * frames from a frame ring and writes features into a feature ring; the C
 * join pairs them with keyframes by id and expires the ones never served.
 * An extractor slower than the frames serves the newest frame and counts
 * the ones it passed over; against vlff-node, the keyframes whose features
 * come too late are a refusal reason with its count on --status. Also the
 * join's own rules without Python. */
#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <setjmp.h>
#include <signal.h>
#include <spawn.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include <cmocka.h>
#include <vlff/shm.h>

#include "field.h"
#include "clock.h"
#include "feature_join.h"
#include "node.h"
#include "testkit.h"
#include "unit.h"

extern char **environ;

static struct tk tk;

/* The extractor needs python3 and numpy (python3-numpy) only. */
static bool have_numpy(void) {
  if (system("/usr/bin/python3 -c 'import numpy' >/dev/null 2>&1") == 0) return true;
  print_message("\n*** SKIPPED: /usr/bin/python3 cannot import numpy (apt install python3-numpy): the extractor "
                "checks did NOT run ***\n\n");
  return false;
}

#define FW 24
#define FH 16
#define D 16
#define HH 8
#define WW 12

static uint8_t pix(uint64_t id, int x, int y, int c) { return (uint8_t)((id * 13 + (uint64_t)x * 7 + (uint64_t)y * 3 + (uint64_t)c * 5) & 255); }

static float expected(uint64_t id, int d, int y, int x) {
  double m = (pix(id, 2 * x, 2 * y, 0) + pix(id, 2 * x, 2 * y, 1) + pix(id, 2 * x, 2 * y, 2)) / 3.0 / 255.0;
  return (float)(m * (d + 1) / D);
}

static void write_frame(struct vlff_ring *ring, uint64_t id) {
  uint64_t seq;
  uint8_t *rec = vlff_ring_reserve(ring, &seq);
  assert_non_null(rec);
  struct vlff_frame_hdr *h = (struct vlff_frame_hdr *)rec;
  uint64_t len = vlff_frame_layout(h, vlff_ring_slot_size(ring), FW, FH, VLFF_PIX_RGB8, VLFF_PIX_NONE);
  assert_true(len > 0);
  h->frame_id = id;
  h->t_host_ns = vlff_shm_now_ns();
  uint8_t *px = rec + h->plane[0].offset;
  for (int y = 0; y < FH; y++)
    for (int x = 0; x < FW; x++)
      for (int c = 0; c < 3; c++) px[(size_t)y * h->plane[0].stride + (size_t)x * 3 + (size_t)c] = pix(id, x, y, c);
  assert_int_equal(vlff_ring_commit(ring, len), 0);
}

/* The frame ring the extractor reads: 8 slots of FW x FH RGB8 frames. */
static struct vlff_ring *create_frame_ring(const char *name) {
  struct vlff_ring_params p = {.record_kind = VLFF_RECORD_FRAME, .slots = 8,
                               .slot_size = vlff_frame_slot_size(FW, FH, VLFF_PIX_RGB8, VLFF_PIX_NONE)};
  struct vlff_ring *fr = vlff_ring_create(name, &p);
  if (!fr) fail_msg("%s", vlff_shm_last_message());
  return fr;
}

/* The feature ring the extractor pid creates, attached (python and numpy
 * start up first); fails the test, stopping pid, when it never comes. out:
 * the extractor's output file, shown then, or NULL. */
static struct vlff_ring *attach_features(const char *feats, pid_t pid, const char *out) {
  struct vlff_ring *ft = NULL;
  for (int i = 0; i < 400 && !ft; i++) {
    ft = vlff_ring_attach(feats, VLFF_RECORD_FEATURE);
    if (!ft) usleep(50000);
  }
  if (!ft) {
    kill(pid, SIGTERM);
    waitpid(pid, NULL, 0);
    fail_msg("extractor never created %s: %s\n%s", feats, vlff_shm_last_message(), out ? tk_slurp(out) : "");
  }
  return ft;
}

static void test_python_extractor_round_trip(void **state) {
  if (!have_numpy()) skip();
  char frames[64], feats[64];
  snprintf(frames, sizeof frames, "/vlff-test-frames-%d", (int)getpid());
  snprintf(feats, sizeof feats, "/vlff-test-features-%d", (int)getpid());
  vlff_shm_unlink(frames);
  vlff_shm_unlink(feats);
  struct vlff_ring *fr = create_frame_ring(frames);

  char script[512], fn[512], dim[8], hh[8], ww[8];
  snprintf(script, sizeof script, "%s/node/vlm/extractor/vlff_extractor.py", getenv("VLFF_SOURCE_DIR"));
  snprintf(fn, sizeof fn, "%s/tests/unit/vlm/fake_features.py:features", getenv("VLFF_SOURCE_DIR"));
  snprintf(dim, sizeof dim, "%d", D), snprintf(hh, sizeof hh, "%d", HH), snprintf(ww, sizeof ww, "%d", WW);
  char *argv[] = {"/usr/bin/python3", script, "--lib", VLFF_SHM_SO, "--frames", frames, "--features", feats,
                  "--dim", dim, "--height", hh, "--width", ww, "--fn", fn, "--max-frames", "5",
                  "--idle-exit", "20", NULL};
  pid_t pid;
  assert_int_equal(posix_spawn(&pid, argv[0], NULL, NULL, argv, environ), 0);

  struct vlff_ring *ft = attach_features(feats, pid, NULL);
  char err[256];
  struct vlff_feature_join *j = vlff_feature_join_create(8, 10.0, D, HH, WW, err, sizeof err);
  assert_non_null(j);
  /* Frame 1000 is a keyframe that never reaches the extractor; registered
   * 9.5 s in the past it expires soon, while the served frames have 10 s. */
  assert_int_equal(vlff_feature_join_add_frame(j, 1000, vlff_shm_now_ns() - 9500000000ull, err, sizeof err), 0);
  /* One frame at a time, each once the previous one's features came: the
   * extractor serves every one (frames that came while it was busy would
   * be passed over for the newest). */
  uint64_t written = 1;
  write_frame(fr, 11);
  assert_int_equal(vlff_feature_join_add_frame(j, 11, vlff_shm_now_ns(), err, sizeof err), 0);
  uint16_t *out = malloc((size_t)D * HH * WW * sizeof *out);
  int joined = 0, expired = 0;
  bool seen[6] = {false};
  uint64_t t0 = vlff_shm_now_ns();
  while ((joined < 5 || expired < 1) && vlff_shm_now_ns() - t0 < 30ull * 1000000000ull) {
    vlff_feature_join_pump(j, ft);
    uint64_t id;
    int h, w;
    int r = vlff_feature_join_poll(j, vlff_shm_now_ns(), &id, out, &h, &w);
    if (r == VLFF_JOIN_NONE) {
      usleep(10000);
      continue;
    }
    if (r == VLFF_JOIN_EXPIRED) {
      assert_int_equal(id, 1000);
      expired++;
      continue;
    }
    assert_int_equal(r, VLFF_JOIN_READY);
    assert_int_equal(h, HH);
    assert_int_equal(w, WW);
    assert_int_equal(id % 11, 0);
    seen[id / 11] = true;
    double worst = 0;
    for (int y = 0; y < HH; y++)
      for (int x = 0; x < WW; x++)
        for (int d = 0; d < D; d++) {
          double e = fabs(vlff_f16_to_f32(out[((size_t)y * WW + x) * D + d]) - expected(id, d, y, x));
          if (e > worst) worst = e;
        }
    if (worst > 1e-3) fail_msg("frame %llu: features differ by %g", (unsigned long long)id, worst);
    joined++;
    if (written < 5) {
      written++;
      write_frame(fr, written * 11);
      assert_int_equal(vlff_feature_join_add_frame(j, written * 11, vlff_shm_now_ns(), err, sizeof err), 0);
    }
  }
  struct vlff_feature_join_stats st;
  vlff_feature_join_stats(j, &st);
  assert_int_equal(joined, 5);
  for (int k = 1; k <= 5; k++) assert_true(seen[k]);
  assert_int_equal(expired, 1);
  assert_int_equal(st.joined, 5);
  assert_int_equal(st.expired, 1);
  assert_int_equal(st.bad_records, 0);
  int status = 0;
  assert_int_equal(waitpid(pid, &status, 0), pid);
  assert_true(WIFEXITED(status) && WEXITSTATUS(status) == 0);
  free(out);
  vlff_feature_join_destroy(j);
  vlff_ring_close(ft);
  vlff_ring_close(fr);
  vlff_shm_unlink(frames);
  vlff_shm_unlink(feats);
}

/* Starts the extractor (python3, this tree's script, the build's library)
 * on the named rings with fake_features.py's function fn, stdout and stderr
 * into out; extra: more arguments, NULL-terminated. */
static pid_t spawn_extractor(const char *frames, const char *feats, int dim, int h, int w, const char *fn,
                             const char *out, const char *const *extra) {
  char script[512], fnspec[512], sd[8], sh[8], sw[8];
  snprintf(script, sizeof script, "%s/node/vlm/extractor/vlff_extractor.py", getenv("VLFF_SOURCE_DIR"));
  snprintf(fnspec, sizeof fnspec, "%s/tests/unit/vlm/fake_features.py:%s", getenv("VLFF_SOURCE_DIR"), fn);
  snprintf(sd, sizeof sd, "%d", dim), snprintf(sh, sizeof sh, "%d", h), snprintf(sw, sizeof sw, "%d", w);
  char *argv[32] = {"/usr/bin/python3", script, "--lib", VLFF_SHM_SO, "--frames", (char *)frames, "--features",
                    (char *)feats, "--dim", sd, "--height", sh, "--width", sw, "--fn", fnspec};
  int k = 16;
  for (; extra && *extra && k < 31; extra++) argv[k++] = (char *)*extra;
  argv[k] = NULL;
  posix_spawn_file_actions_t fa;
  posix_spawn_file_actions_init(&fa);
  posix_spawn_file_actions_addopen(&fa, 1, out, O_WRONLY | O_CREAT | O_TRUNC, 0644);
  posix_spawn_file_actions_adddup2(&fa, 1, 2);
  pid_t pid;
  assert_int_equal(posix_spawn(&pid, argv[0], &fa, NULL, argv, environ), 0);
  posix_spawn_file_actions_destroy(&fa);
  return pid;
}

static long file_size(const char *path) {
  struct stat sb;
  return stat(path, &sb) == 0 ? (long)sb.st_size : -1;
}

/* Frames come while the extractor is busy with one (its function takes a
 * second): the next frame it serves is the newest, and the ones in between
 * are counted as skipped. Before it skipped, it served them in order (the
 * second record was frame 22) and fell ever further behind. */
static void test_python_extractor_skips_to_newest(void **state) {
  (void)state;
  if (!have_numpy()) skip();
  char frames[64], feats[64], mark[192], out[192];
  snprintf(frames, sizeof frames, "/%s-sf", tk.tag);
  snprintf(feats, sizeof feats, "/%s-sx", tk.tag);
  snprintf(mark, sizeof mark, "%s/mark", tk.dir);
  snprintf(out, sizeof out, "%s/extractor.out", tk.dir);
  struct vlff_ring *fr = create_frame_ring(frames);
  setenv("VLFF_TEST_MARK", mark, 1);
  setenv("VLFF_TEST_DELAY_S", "1", 1);
  const char *extra[] = {"--max-frames", "2", "--idle-exit", "20", NULL};
  pid_t pid = spawn_extractor(frames, feats, D, HH, WW, "slow_features", out, extra);
  unsetenv("VLFF_TEST_MARK");
  unsetenv("VLFF_TEST_DELAY_S");
  struct vlff_ring *ft = attach_features(feats, pid, out);
  write_frame(fr, 11);
  /* Frame 11 is being served (its function was called): five more come. */
  for (int i = 0; i < 400 && file_size(mark) <= 0; i++) usleep(50000);
  assert_true(file_size(mark) > 0);
  for (uint64_t id = 22; id <= 66; id += 11) write_frame(fr, id);
  size_t cap = vlff_ring_slot_size(ft);
  void *rec = malloc(cap);
  uint64_t got[4];
  int n = 0;
  uint64_t t0 = vlff_shm_now_ns();
  while (n < 2 && vlff_shm_now_ns() - t0 < 30ull * 1000000000ull) {
    struct vlff_ring_view v;
    ssize_t len = vlff_ring_read_copy(ft, rec, cap, &v, 1000000000ull);
    if (len > 0) got[n++] = ((const struct vlff_feature_hdr *)rec)->frame_id;
  }
  free(rec);
  int status = 0;
  assert_int_equal(waitpid(pid, &status, 0), pid);
  char *text = strdup(tk_slurp(out));
  if (!WIFEXITED(status) || WEXITSTATUS(status) != 0) fail_msg("extractor failed:\n%s", text);
  assert_int_equal(n, 2);
  assert_int_equal(got[0], 11);
  assert_int_equal(got[1], 66);
  /* Its function saw exactly those two frames (their first red byte). */
  char want[32];
  snprintf(want, sizeof want, "%u\n%u\n", pix(11, 0, 0, 0), pix(66, 0, 0, 0));
  assert_string_equal(tk_slurp(mark), want);
  if (!strstr(text, "vlff_extractor: 2 frames, 0 failed, 4 skipped\n")) fail_msg("extractor said:\n%s", text);
  assert_non_null(strstr(text, "4 skipped for newer ones (4 in all)"));
  free(text);
  vlff_ring_close(ft);
  vlff_ring_close(fr);
}

/* Features beyond float16's range are refused by the extractor (they would
 * be infinite in the record) and not published; the next frame's features
 * take the slot and arrive whole. */
static void test_python_extractor_refuses_out_of_range(void **state) {
  (void)state;
  if (!have_numpy()) skip();
  char frames[64], feats[64], out[192];
  snprintf(frames, sizeof frames, "/%s-of", tk.tag);
  snprintf(feats, sizeof feats, "/%s-ox", tk.tag);
  snprintf(out, sizeof out, "%s/extractor-range.out", tk.dir);
  struct vlff_ring *fr = create_frame_ring(frames);
  const char *extra[] = {"--max-frames", "2", "--idle-exit", "20", NULL};
  pid_t pid = spawn_extractor(frames, feats, D, HH, WW, "odd_huge_features", out, extra);
  struct vlff_ring *ft = attach_features(feats, pid, out);
  assert_true(pix(11, 0, 0, 0) % 2 == 1 && pix(22, 0, 0, 0) % 2 == 0);
  write_frame(fr, 11);
  assert_true(tk_wait_for_text(out, "vlff_extractor: frame 11: non-finite features", 20));
  write_frame(fr, 22);
  size_t cap = vlff_ring_slot_size(ft);
  uint8_t *rec = malloc(cap);
  struct vlff_ring_view v;
  ssize_t len = vlff_ring_read_copy(ft, rec, cap, &v, 20000000000ull);
  assert_true(len > 0);
  int status = 0;
  assert_int_equal(waitpid(pid, &status, 0), pid);
  assert_true(WIFEXITED(status) && WEXITSTATUS(status) == 0);
  assert_non_null(strstr(tk_slurp(out), "vlff_extractor: 1 frames, 1 failed, 0 skipped\n"));
  const struct vlff_feature_hdr *h = (const struct vlff_feature_hdr *)rec;
  assert_int_equal(h->frame_id, 22);
  assert_int_equal(vlff_feature_validate(rec, (size_t)len), 0);
  const uint16_t *data = (const uint16_t *)(rec + h->data_offset);
  for (int d = 0; d < D; d++)
    for (int y = 0; y < HH; y++)
      for (int x = 0; x < WW; x++)
        assert_true(fabs(vlff_f16_to_f32(data[((size_t)d * HH + y) * WW + x]) - expected(22, d, y, x)) < 1e-3);
  /* Nothing else was published. */
  assert_int_equal(vlff_ring_read_copy(ft, rec, cap, &v, 0), -1);
  free(rec);
  vlff_ring_close(ft);
  vlff_ring_close(fr);
}

/* Renders scene frame index into the ring as a camera driver would (RGB8,
 * depth, the pose and intrinsics flagged valid), stamped now. */
static void put_scene_frame(struct tk_scene *sc, long long index) {
  char err[256];
  struct vlff_sim_frame *f = sc->frame;
  assert_int_equal(vlff_sim_render(sc->sim, index, VLFF_SIM_RGBD, f, err, sizeof err), 0);
  uint64_t len;
  struct vlff_frame_hdr *h =
      tk_frame_reserve(sc->ring, f, index, vlff_shm_now_ns(), f->width, f->height, VLFF_PIX_DEPTH_U16_MM, &len);
  memcpy((uint8_t *)h + h->plane[0].offset, f->rgb, (size_t)f->width * f->height * 3);
  memcpy((uint8_t *)h + h->plane[1].offset, f->depth_mm, (size_t)f->width * f->height * 2);
  assert_int_equal(vlff_ring_commit(sc->ring, len), 0);
}

/* The count after "(features late " on the last --status line that has one. */
static long long features_late_count(const char *text) {
  long long k = -1;
  for (const char *s = text; (s = strstr(s, "(features late ")) != NULL; s++) k = atoll(s + 15);
  return k;
}

/* Vectors for the prompts "wall" and "floor" in dir/prompts.embeddings
 * (its path into emb). */
static void write_embeddings(char *emb, size_t cap) {
  snprintf(emb, cap, "%s/prompts.embeddings", tk.dir);
  FILE *ef = fopen(emb, "w");
  assert_non_null(ef);
  fprintf(ef, "vlff-embeddings 1\ndim %d\n", D);
  for (int k = 0; k < 2; k++) {
    fprintf(ef, "%s\t", k ? "floor" : "wall");
    for (int d = 0; d < D; d++) fprintf(ef, "%s%g", d ? " " : "", d == k ? 1.0 : 0.1);
    fprintf(ef, "\n");
  }
  assert_int_equal(fclose(ef), 0);
}

/* vlff-node fed from a ring at 10 frames/s with the real extractor, whose
 * features take 1.5 s a frame against vlm.feature_timeout_s 0.5: every
 * keyframe's features come too late. The node refuses those keyframes
 * under "features late", counted on --status and in its log (once with the
 * detail, then the 5 s summaries); the extractor serves the newest frames
 * and says how many it skipped. Before, the status said "refused 0" and the
 * log had a warning per keyframe. */
static void test_slow_feature_source_refused(void **state) {
  (void)state;
  if (!have_numpy()) skip();
  char emb[192];
  write_embeddings(emb, sizeof emb);
  struct vlff_config cfg;
  const char *cfg_path = tk_config(&tk, &cfg,
      "node:\n  state_dir: %s/state\n  checkpoint_period_s: 0\n  log_level: info\n"
      "prompts:\n  embeddings: %s\n  sets:\n    - name: two\n      prompts: [wall, floor]\n"
      "source:\n  kind: ring\n  features: ring\n"
      "field:\n  feature_dim: %d\n"
      "vlm:\n  feature_timeout_s: 0.5\n  input_width: 80\n  input_height: 60\n"
      "sim:\n  seed: 3\n  width: 160\n  height: 120\n  frames: 150\n"
      "shm:\n%s  max_width: 320\n  max_height: 240\n"
      "train:\n  image_scale: 0.5\n"
      "keyframes:\n  start_after: 3\n",
      tk.dir, emb, D, tk_shm_names(&tk));
  struct tk_scene sc;
  tk_scene_open(&sc, &cfg, 16, 160, 120);
  char log[256], out[256];
  snprintf(log, sizeof log, "%s/node.log", tk.dir);
  snprintf(out, sizeof out, "%s/extractor.out", tk.dir);
  const char *args[] = {"--config", cfg_path, "--status", NULL};
  pid_t node = tk_spawn(&tk, "node/vlff-node", args, log);
  assert_true(node > 0);
  if (!tk_wait_for_text(log, "attached to ring", 30 * tk.scale)) fail_msg("node log:\n%s", tk_slurp(log));
  setenv("VLFF_TEST_DELAY_S", "1.5", 1);
  const char *extra[] = {"--idle-exit", "2", NULL};
  pid_t ex = spawn_extractor(cfg.shm.ring, cfg.shm.feature_ring, D, 60, 80, "slow_features", out, extra);
  unsetenv("VLFF_TEST_DELAY_S");
  /* Its first line comes once it created the feature ring. */
  char started[160];
  snprintf(started, sizeof started, "-> %s [%d,60,80]", cfg.shm.feature_ring, D);
  bool up = tk_wait_for_text(out, started, 30 * tk.scale);
  if (!up) kill(ex, SIGTERM);
  if (!up) fail_msg("extractor did not start:\n%s", tk_slurp(out));
  /* 6.5 s of frames: more than one summary period. */
  for (long long i = 0; i < 65; i++) {
    put_scene_frame(&sc, i);
    tk_sleep_s(0.1);
  }
  int status = 0;
  assert_int_equal(waitpid(ex, &status, 0), ex); /* --idle-exit: 2 s after the last frame */
  const char *etext = tk_slurp(out);
  char *extext = strdup(etext);
  bool ok = WIFEXITED(status) && WEXITSTATUS(status) == 0;
  tk_sleep_s(1.0); /* a --status line after the last expiry */
  kill(node, SIGTERM);
  assert_int_equal(tk_wait_child(&tk, node), 0);
  const char *text = tk_slurp(log);
  if (!ok) fail_msg("extractor failed:\n%s", extext);
  /* The extractor kept up by skipping: 65 frames at 1.5 s each would take
   * 97 s in order. */
  int served = -1, failed = -1, skipped = -1;
  const char *fin = strstr(extext, "vlff_extractor: ");
  const char *last = NULL;
  for (const char *s = extext; (s = strstr(s, " frames, ")) != NULL; s++) last = s;
  if (last) {
    while (last > extext && last[-1] != ' ') last--;
    sscanf(last, "%d frames, %d failed, %d skipped", &served, &failed, &skipped);
  }
  if (!fin || served < 1 || served > 12 || skipped < 40 || failed != 0)
    fail_msg("extractor: %d served, %d skipped:\n%s", served, skipped, extext);
  free(extext);
  long long late = features_late_count(text);
  if (late < 5) fail_msg("no --status count of features late keyframes (%lld) in:\n%s", late, text);
  /* Every refusal is a late keyframe here: the total is its count. */
  char want[64];
  snprintf(want, sizeof want, "refused %lld (features late %lld)", late, late);
  assert_non_null(strstr(text, want));
  /* Once with the detail, then counts every 5 s, not a line per keyframe. */
  const char *first = strstr(text, " refused, features late: its features did not arrive within "
                                   "vlm.feature_timeout_s (0.5 s): the feature source lags or stopped");
  assert_non_null(first);
  assert_null(strstr(first + 1, " refused, features late: "));
  assert_non_null(strstr(text, " I node: frames refused in the last"));
  assert_null(strstr(text, "features did not arrive within 0.5 s"));
  tk_scene_close(&sc);
}

/* A [D][h][w] record built in memory. */
static size_t make_record(uint8_t *buf, size_t cap, uint64_t id, uint32_t dim, uint32_t h, uint32_t w, float v) {
  struct vlff_feature_hdr *hdr = (struct vlff_feature_hdr *)buf;
  uint64_t len = vlff_feature_layout(hdr, cap, dim, h, w);
  assert_true(len > 0);
  hdr->frame_id = id;
  uint16_t *data = (uint16_t *)(buf + hdr->data_offset);
  for (size_t i = 0; i < (size_t)dim * h * w; i++) data[i] = vlff_f32_to_f16(v + (float)i * 1e-3f);
  return (size_t)(hdr->data_offset + hdr->data_size);
}

/* Sizes that cross the transpose's 16-pixel, 64-channel tiles in both directions: every
 * element lands where [d][y][x] says, bit for bit. */
static void test_join_transpose(void **state) {
  (void)state;
  enum { TD = 70, TH = 9, TW = 11 };
  char err[256];
  struct vlff_feature_join *j = vlff_feature_join_create(2, 1.0, TD, TH, TW, err, sizeof err);
  assert_non_null(j);
  size_t cap = vlff_feature_slot_size(TD, TH, TW);
  uint8_t *buf = aligned_alloc(64, (cap + 63) / 64 * 64);
  struct vlff_feature_hdr *hdr = (struct vlff_feature_hdr *)buf;
  assert_true(vlff_feature_layout(hdr, cap, TD, TH, TW) > 0);
  hdr->frame_id = 3;
  uint16_t *data = (uint16_t *)(buf + hdr->data_offset);
  for (size_t i = 0; i < (size_t)TD * TH * TW; i++) data[i] = (uint16_t)(i * 7 % 0x6000); /* halves within +-512 */
  assert_int_equal(vlff_feature_join_add_record(j, buf, (size_t)(hdr->data_offset + hdr->data_size), err, sizeof err), 0);
  assert_int_equal(vlff_feature_join_add_frame(j, 3, 1, err, sizeof err), 0);
  uint16_t *out = malloc((size_t)TD * TH * TW * sizeof *out);
  uint64_t id;
  int h, w;
  assert_int_equal(vlff_feature_join_poll(j, 1, &id, out, &h, &w), VLFF_JOIN_READY);
  assert_int_equal(h, TH);
  assert_int_equal(w, TW);
  for (int y = 0; y < TH; y++)
    for (int x = 0; x < TW; x++)
      for (int d = 0; d < TD; d++) {
        size_t src = ((size_t)d * TH + y) * TW + x, dst = ((size_t)y * TW + x) * TD + d;
        if (out[dst] != data[src]) fail_msg("(y=%d, x=%d, d=%d): %u, expected %u", y, x, d, out[dst], data[src]);
      }
  free(out);
  free(buf);
  vlff_feature_join_destroy(j);
}

static void test_join_rules(void **state) {
  char err[256];
  assert_null(vlff_feature_join_create(0, 1, 8, 2, 2, err, sizeof err));
  struct vlff_feature_join *j = vlff_feature_join_create(2, 1.0, 8, 4, 4, err, sizeof err);
  assert_non_null(j);
  size_t cap = vlff_feature_slot_size(16, 8, 8);
  uint8_t *buf = aligned_alloc(64, cap);
  uint16_t out[4 * 4 * 8];
  uint64_t id;
  int h, w;
  const uint64_t s = 1000000000ull;

  /* Features first, keyframe later: still joined, transposed to [h][w][D]. */
  size_t len = make_record(buf, cap, 7, 8, 2, 3, 0.5f);
  assert_int_equal(vlff_feature_join_add_record(j, buf, len, err, sizeof err), 0);
  assert_int_equal(vlff_feature_join_poll(j, 10 * s, &id, out, &h, &w), VLFF_JOIN_NONE);
  assert_int_equal(vlff_feature_join_add_frame(j, 7, 10 * s, err, sizeof err), 0);
  assert_int_equal(vlff_feature_join_poll(j, 10 * s, &id, out, &h, &w), VLFF_JOIN_READY);
  assert_int_equal(id, 7);
  assert_int_equal(h, 2);
  assert_int_equal(w, 3);
  /* element (y=1, x=2, d=5) came from [d][y][x] index 5*6 + 1*3 + 2 = 35 */
  assert_true(fabsf(vlff_f16_to_f32(out[(1 * 3 + 2) * 8 + 5]) - (0.5f + 35e-3f)) < 1e-3f);

  /* Expiry exactly after the timeout, once. */
  assert_int_equal(vlff_feature_join_add_frame(j, 8, 20 * s, err, sizeof err), 0);
  assert_int_equal(vlff_feature_join_add_frame(j, 8, 20 * s, err, sizeof err), -1); /* duplicate */
  assert_int_equal(vlff_feature_join_poll(j, 21 * s, &id, out, &h, &w), VLFF_JOIN_NONE);
  assert_int_equal(vlff_feature_join_poll(j, 21 * s + 1, &id, out, &h, &w), VLFF_JOIN_EXPIRED);
  assert_int_equal(id, 8);
  assert_int_equal(vlff_feature_join_poll(j, 30 * s, &id, out, &h, &w), VLFF_JOIN_NONE);

  /* Full: a third waiting keyframe is refused. */
  assert_int_equal(vlff_feature_join_add_frame(j, 1, 40 * s, err, sizeof err), 0);
  assert_int_equal(vlff_feature_join_add_frame(j, 2, 40 * s, err, sizeof err), 0);
  assert_int_equal(vlff_feature_join_add_frame(j, 3, 40 * s, err, sizeof err), -1);

  /* Bad records: wrong D, too large, non-finite, corrupt header, truncated. */
  len = make_record(buf, cap, 1, 16, 2, 2, 0.f);
  assert_int_equal(vlff_feature_join_add_record(j, buf, len, err, sizeof err), -1);
  assert_non_null(strstr(err, "D=8"));
  len = make_record(buf, cap, 1, 8, 8, 8, 0.f);
  assert_int_equal(vlff_feature_join_add_record(j, buf, len, err, sizeof err), -1);
  len = make_record(buf, cap, 1, 8, 2, 2, 0.f);
  ((uint16_t *)(buf + ((struct vlff_feature_hdr *)buf)->data_offset))[3] = 0x7E00; /* NaN */
  assert_int_equal(vlff_feature_join_add_record(j, buf, len, err, sizeof err), -1);
  assert_non_null(strstr(err, "non-finite"));
  len = make_record(buf, cap, 1, 8, 2, 2, 0.f);
  ((struct vlff_feature_hdr *)buf)->data_size += 2;
  assert_int_equal(vlff_feature_join_add_record(j, buf, len, err, sizeof err), -1);
  len = make_record(buf, cap, 1, 8, 2, 2, 0.f);
  assert_int_equal(vlff_feature_join_add_record(j, buf, len - 2, err, sizeof err), -1);
  /* finite but beyond any model's features: 65504 (float16's largest)
   * drove the feature loss from 0.05 to 1800; 1000 itself is taken */
  len = make_record(buf, cap, 1, 8, 2, 2, 0.f);
  ((uint16_t *)(buf + ((struct vlff_feature_hdr *)buf)->data_offset))[5] = 0xFBFF; /* -65504 */
  assert_int_equal(vlff_feature_join_add_record(j, buf, len, err, sizeof err), -1);
  if (!strstr(err, "out-of-range value at 5 (1 outside [-1000, 1000] in all)")) fail_msg("%s", err);
  assert_string_equal(vlff_feature_join_last_bad(j), err);
  len = make_record(buf, cap, 99, 8, 2, 2, 0.f);
  ((uint16_t *)(buf + ((struct vlff_feature_hdr *)buf)->data_offset))[5] = 0x63D0; /* 1000 */
  assert_int_equal(vlff_feature_join_add_record(j, buf, len, err, sizeof err), 0);
  struct vlff_feature_join_stats st;
  vlff_feature_join_stats(j, &st);
  assert_int_equal(st.bad_records, 6);
  /* None of them reached keyframe 1. */
  assert_int_equal(vlff_feature_join_poll(j, 40 * s, &id, out, &h, &w), VLFF_JOIN_NONE);

  /* Orphans beyond capacity: the oldest goes. */
  for (uint64_t k = 100; k < 103; k++) {
    len = make_record(buf, cap, k, 8, 2, 2, 0.f);
    assert_int_equal(vlff_feature_join_add_record(j, buf, len, err, sizeof err), 0);
  }
  vlff_feature_join_stats(j, &st);
  assert_int_equal(st.orphans_evicted, 2); /* 99 (the 1000 above) and 100 */

  /* Read from a ring's oldest record: a map of a frame stamped before the
   * join's time is passed over and counted, and joins nothing; one stamped
   * at it joins. */
  assert_int_equal(vlff_feature_join_poll(j, 60 * s, &id, out, &h, &w), VLFF_JOIN_EXPIRED); /* frames 1, 2 */
  assert_int_equal(vlff_feature_join_poll(j, 60 * s, &id, out, &h, &w), VLFF_JOIN_EXPIRED);
  vlff_feature_join_not_before(j, 50 * s);
  assert_int_equal(vlff_feature_join_add_frame(j, 200, 60 * s, err, sizeof err), 0);
  len = make_record(buf, cap, 200, 8, 2, 2, 0.f);
  ((struct vlff_feature_hdr *)buf)->t_host_ns = 50 * s - 1;
  assert_int_equal(vlff_feature_join_add_record(j, buf, len, err, sizeof err), 1);
  assert_int_equal(vlff_feature_join_poll(j, 60 * s, &id, out, &h, &w), VLFF_JOIN_NONE);
  vlff_feature_join_stats(j, &st);
  assert_int_equal(st.stale, 1);
  ((struct vlff_feature_hdr *)buf)->t_host_ns = 50 * s;
  assert_int_equal(vlff_feature_join_add_record(j, buf, len, err, sizeof err), 0);
  assert_int_equal(vlff_feature_join_poll(j, 60 * s, &id, out, &h, &w), VLFF_JOIN_READY);
  assert_int_equal(id, 200);
  free(buf);
  vlff_feature_join_destroy(j);
}

/* An extractor that starts with its camera can commit a frame's features
 * before the node, which attached the frame ring first, attaches the feature
 * ring: the node must still take them. Here the feature ring holds the maps
 * of frames 0-5 while the node refuses it (mode 0644 is wider than its
 * 0640), and is then narrowed: the node attaches and joins every one; at the
 * newest record it would have waited for them until vlm.feature_timeout_s
 * and refused each frame as "features late". */
static void test_features_before_attach(void **state) {
  (void)state;
  char emb[192];
  write_embeddings(emb, sizeof emb);
  struct vlff_config cfg;
  tk_config(&tk, &cfg,
            "node:\n  state_dir: %s/state\n  checkpoint_period_s: 0\n"
            "prompts:\n  embeddings: %s\n  sets:\n    - name: two\n      prompts: [wall, floor]\n"
            "source:\n  kind: ring\n  features: ring\n"
            "field:\n  feature_dim: %d\n"
            "vlm:\n  feature_timeout_s: 3\n  input_width: 80\n  input_height: 60\n"
            "sim:\n  seed: 3\n  width: 160\n  height: 120\n  frames: 150\n"
            "shm:\n%s  max_width: 320\n  max_height: 240\n"
            "train:\n  image_scale: 0.5\n"
            "keyframes:\n  start_after: 1\n",
            tk.dir, emb, D, tk_shm_names(&tk));
  vlff_shm_unlink(cfg.shm.feature_ring); /* an earlier test's extractor's */
  struct tk_scene sc;
  struct vlff_sim_source *src;
  struct vlff_node *n = tk_scene_node(&sc, &cfg, 16, 160, 120, &src);
  struct vlff_ring_params p = {.record_kind = VLFF_RECORD_FEATURE, .slots = 8,
                               .slot_size = vlff_feature_slot_size(D, 60, 80), .perm = {.mode = 0644}};
  struct vlff_ring *fr = vlff_ring_create(cfg.shm.feature_ring, &p);
  if (!fr) fail_msg("%s", vlff_shm_last_message());
  char path[300];
  snprintf(path, sizeof path, "/dev/shm%s", cfg.shm.feature_ring);
  assert_int_equal(chmod(path, 0644), 0); /* whatever the umask made of it */
  size_t cap = vlff_ring_slot_size(fr);
  for (long long i = 0; i < 6; i++) {
    put_scene_frame(&sc, i);
    uint8_t *rec = vlff_ring_reserve(fr, NULL);
    assert_non_null(rec);
    size_t len = make_record(rec, cap, (uint64_t)i, D, 60, 80, 0.1f);
    ((struct vlff_feature_hdr *)rec)->t_host_ns = vlff_shm_now_ns();
    assert_int_equal(vlff_ring_commit(fr, len), 0);
    tk_sleep_s(0.1);
  }
  struct vlff_node_status st;
  vlff_node_status(n, &st);
  assert_int_equal(st.features_timeout, 0); /* nothing expired yet: 3 s */
  assert_int_equal(chmod(path, 0640), 0);
  double t0 = vlff_seconds();
  do {
    tk_sleep_s(0.2);
    vlff_node_status(n, &st);
  } while (st.keyframes < 6 && st.features_timeout == 0 && vlff_seconds() - t0 < 10 * tk.scale);
  tk_sleep_s(3.5); /* past the timeout: a frame still waiting would have expired */
  vlff_node_status(n, &st);
  printf("%lld frames in, %d keyframes, %lld features late, %lld refused\n", st.frames_in, st.keyframes,
         st.features_timeout, st.frames_invalid);
  assert_int_equal(st.frames_in, 6);
  assert_int_equal(st.features_timeout, 0);
  assert_int_equal(st.refused[VLFF_REFUSED_FEATURES_LATE], 0);
  assert_true(st.keyframes >= 1);
  tk_node_destroy(n, src);
  vlff_ring_close(fr);
  tk_scene_close(&sc);
}

static int setup(void **state) {
  (void)state;
  tk_setup(&tk, "ext");
  return 0;
}

static int teardown(void **state) {
  (void)state;
  return tk_teardown(&tk);
}

VLFF_UNIT_MAIN(setup, teardown,
    cmocka_unit_test(test_join_rules), cmocka_unit_test(test_join_transpose),
    cmocka_unit_test(test_python_extractor_round_trip), cmocka_unit_test(test_python_extractor_skips_to_newest),
    cmocka_unit_test(test_python_extractor_refuses_out_of_range),
    cmocka_unit_test(test_slow_feature_source_refused), cmocka_unit_test(test_features_before_attach))
