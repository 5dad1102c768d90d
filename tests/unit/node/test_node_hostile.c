/*
 * The node against frames whose intrinsics or pose are physically absurd
 * (issue 29 H1): cx = -1e9 / cy = 1e9, fx = 0.001, fy = 1e30, a camera
 * 1e300 m away. Each is refused and counted, good frames around them are
 * still admitted, and the node stops when asked. Before the bounds, the
 * trainer marched hundreds of millions of steps per pixel for such a frame
 * and never came back: the status never counted the frame, and stopping
 * the node (what SIGTERM does) joined a thread that never finished, so
 * this test hung until ctest's timeout.
 */
#include <math.h>
#include <pthread.h>
#include <stdatomic.h>
#include <sys/stat.h>
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>
#include <cmocka.h>

#include "config.h"
#include "node.h"
#include "sim_source.h"
#include "sim.h"
#include "testkit.h"
#include "unit.h"
#include "vlff/shm.h"

static struct tk tk;

static int teardown(void **state) {
  (void)state;
  return tk_teardown(&tk);
}

enum hostile { GOOD, CXCY, FX_TINY, FY_HUGE, FAR_AWAY, NKINDS };

static void send(struct vlff_ring *ring, const struct vlff_sim_frame *f, long long id, enum hostile kind) {
  uint64_t len;
  struct vlff_frame_hdr *hd =
      tk_frame_reserve(ring, f, id, vlff_shm_now_ns(), f->width, f->height, VLFF_PIX_DEPTH_U16_MM, &len);
  memcpy((uint8_t *)hd + hd->plane[0].offset, f->rgb, (size_t)f->width * f->height * 3);
  memcpy((uint8_t *)hd + hd->plane[1].offset, f->depth_mm, (size_t)f->width * f->height * 2);
  switch (kind) {
  case CXCY: hd->cx = -1e9, hd->cy = 1e9; break;
  case FX_TINY: hd->fx = 0.001; break;
  case FY_HUGE: hd->fy = 1e30; break;
  case FAR_AWAY: hd->pose[3] = 1e300; break;
  default: break;
  }
  assert_int_equal(vlff_ring_commit(ring, len), 0);
}

/* The small node both cases run: a 64x48 simulated stream, a tiny field,
 * no checkpoints; extra is YAML appended. */
static void hostile_config(struct vlff_config *cfg, const char *extra) {
  tk_config(&tk, cfg,
            "node:\n  state_dir: %s\n  checkpoint_period_s: 0\n  threads: 2\n"
            "source:\n  kind: sim\n  features: sim\n"
            "sim:\n  seed: 3\n  width: 64\n  height: 48\n  frames: 100\n"
            "field:\n  feature_dim: 16\n  hash_log2_size: 14\n"
            "shm:\n%s"
            "  max_width: 64\n  max_height: 48\n  map_max_voxels: 100000\n"
            "%s",
            tk.dir, tk_shm_names(&tk), extra);
}

static void test_absurd_intrinsics(void **state) {
  (void)state;
  tk_setup(&tk, "hostile");
  struct vlff_config cfg;
  hostile_config(&cfg, "keyframes:\n  rate_hz: 100\n  start_after: 100\n");
  char err[512];
  struct tk_scene sc;
  struct vlff_sim_source *src;
  struct vlff_node *n = tk_scene_node(&sc, &cfg, 16, 64, 48, &src);
  int bad = 0, good = 0;
  for (long long id = 0; id < 3 * NKINDS; id++) {
    enum hostile kind = (enum hostile)(id % NKINDS);
    assert_int_equal(vlff_sim_render(sc.sim, id, VLFF_SIM_RGBD, sc.frame, err, sizeof err), 0);
    send(sc.ring, sc.frame, id, kind);
    kind == GOOD ? good++ : bad++;
    /* Slower than the trainer takes candidates: none is dropped. */
    tk_sleep_s(0.3);
  }
  struct vlff_node_status st;
  for (int i = 0; i < 600; i++) {
    vlff_node_status(n, &st);
    if (st.frames_invalid + st.keyframes >= bad + good) break;
    tk_sleep_s(0.1);
  }
  printf("sent %d absurd and %d good frames: invalid %lld, keyframes %d, dropped %lld, lost %lld\n", bad, good,
         st.frames_invalid, st.keyframes, st.candidates_dropped, st.frames_lost);
  assert_int_equal(st.frames_lost, 0);
  assert_int_equal(st.candidates_dropped, 0);
  assert_int_equal(st.frames_invalid, bad);
  assert_int_equal(st.keyframes, good);
  /* What SIGTERM does: stop and join the threads. */
  vlff_node_stop(n);
  tk_node_destroy(n, src);
  tk_scene_close(&sc);
}


/* A FIFO planted at the node's ring names (issue 51, item 1; anyone may mkfifo in
 * /dev/shm): the ingest thread opened the frame ring for reading and waited for
 * a writer for ever, so stopping the node (SIGTERM) hung in pthread_join. The
 * node refuses it, says why it waits, and stops when asked. Stopping runs in a
 * thread of its own so that a hang fails the test instead of stalling it. */
struct stopper {
  struct vlff_node *n;
  struct vlff_sim_source *src;
  atomic_int done;
};

static void *stop_node(void *arg) {
  struct stopper *s = arg;
  vlff_node_stop(s->n);
  tk_node_destroy(s->n, s->src);
  atomic_store(&s->done, 1);
  return NULL;
}

static void test_fifo_at_ring_names(void **state) {
  (void)state;
  tk_setup(&tk, "hfifo");
  struct vlff_config cfg;
  hostile_config(&cfg, "");
  const char *rings[] = {cfg.shm.ring, cfg.shm.pose_ring, cfg.shm.feature_ring};
  for (int i = 0; i < 3; i++) {
    char path[300];
    snprintf(path, sizeof path, "/dev/shm%s", rings[i]);
    assert_int_equal(mkfifo(path, 0644), 0);
  }
  char err[512];
  struct stopper s = {0};
  s.n = tk_node_create(&cfg, &s.src, err, sizeof err);
  if (!s.n) fail_msg("%s", err);
  tk_sleep_s(1.0); /* the ingest thread tries the frame ring several times */
  pthread_t t;
  assert_int_equal(pthread_create(&t, NULL, stop_node, &s), 0);
  for (int i = 0; i < 300 && !atomic_load(&s.done); i++) tk_sleep_s(0.1);
  if (!atomic_load(&s.done)) fail_msg("the node did not stop within 30 s with a FIFO at %s", cfg.shm.ring);
  pthread_join(t, NULL);
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test_teardown(test_absurd_intrinsics, teardown),
    cmocka_unit_test_teardown(test_fifo_at_ring_names, teardown))
