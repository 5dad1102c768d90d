/* The simulator behind the node's source hooks: which hooks a config gets,
 * features by ring frame id, and the observer's scores against the scene's
 * ground truth (a map labelled from that truth scores high, one label for
 * everything scores low, and the prompts' order does not matter). */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#include <cmocka.h>

#include "config.h"
#include "palette.h"
#include "sim.h"
#include "sim_source.h"
#include "unit.h"

static void small_cfg(struct vlff_config *c) {
  vlff_config_defaults(c);
  c->sim.seed = 5;
  c->sim.width = 80, c->sim.height = 60, c->sim.frames = 40;
  c->field.feature_dim = 16;
  c->source.kind = VLFF_SOURCE_SIM;
  c->source.features = VLFF_FEAT_SIM;
}

static struct vlff_sim_source *make(const struct vlff_config *c, struct vlff_source_hooks *h) {
  char err[256] = "";
  struct vlff_sim_source *s = vlff_sim_source_create(c, h, err, sizeof err);
  if (!s) fail_msg("%s", err);
  return s;
}

static void test_hooks_follow_the_config(void **state) {
  (void)state;
  struct vlff_config c;
  small_cfg(&c);
  struct vlff_source_hooks h;
  struct vlff_sim_source *s = make(&c, &h);
  assert_non_null(h.features), assert_non_null(h.embed), assert_non_null(h.observe), assert_non_null(h.panels);
  vlff_sim_source_destroy(s);

  c.source.kind = VLFF_SOURCE_RING; /* a camera's frames: no ground truth to score against */
  c.source.allow_sim_features = true;
  s = make(&c, &h);
  assert_non_null(h.features), assert_null(h.observe), assert_null(h.panels), assert_null(h.color);
  vlff_sim_source_destroy(s);

  c.source.features = VLFF_FEAT_RING;
  s = make(&c, &h);
  assert_null(h.features), assert_null(h.embed), assert_null(h.observe), assert_null(h.ctx);
  vlff_sim_source_destroy(s);

}

/* Ring ids run on past the scene's loop: id and id + sim.frames are one frame. */
static void test_features_by_ring_id(void **state) {
  (void)state;
  struct vlff_config c;
  small_cfg(&c);
  struct vlff_source_hooks h;
  struct vlff_sim_source *s = make(&c, &h);
  size_t n = (size_t)h.feat_width * h.feat_height * c.field.feature_dim;
  assert_true(n > 0);
  uint16_t *a = malloc(n * 2), *b = malloc(n * 2), *d = malloc(n * 2);
  char err[256] = "";
  assert_int_equal(h.features(h.ctx, 3, a, err, sizeof err), 0);
  assert_int_equal(h.features(h.ctx, 3 + c.sim.frames, b, err, sizeof err), 0);
  assert_int_equal(h.features(h.ctx, 20, d, err, sizeof err), 0);
  assert_memory_equal(a, b, n * 2);
  assert_memory_not_equal(a, d, n * 2);
  free(a), free(b), free(d);
  vlff_sim_source_destroy(s);
}

/* A grid labelled with the truth of its points (by prompt index, in the
 * given prompt order), or with one label everywhere. */
struct grid {
  struct vlff_map_grid g;
  uint16_t *labels;
};

static void grid_of_truth(struct grid *gr, const struct vlff_config *c, const char *const *prompts, int k,
                          int one_label) {
  struct vlff_sim *sim = vlff_sim_create(&c->sim, &c->field, (char[128]){0}, 128);
  assert_non_null(sim);
  struct vlff_sim_points pts;
  assert_int_equal(vlff_sim_points(sim, c->sim.frames, 5, 0.05, &pts, (char[128]){0}, 128), 0);
  gr->g.voxel_size = 0.05;
  for (int a = 0; a < 3; a++) {
    gr->g.origin[a] = c->field.scene_min[a];
    gr->g.dims[a] = (uint32_t)((c->field.scene_max[a] - c->field.scene_min[a]) / 0.05) + 1;
  }
  size_t nv = (size_t)gr->g.dims[0] * gr->g.dims[1] * gr->g.dims[2];
  gr->labels = malloc(nv * sizeof *gr->labels);
  for (size_t i = 0; i < nv; i++) gr->labels[i] = VLFF_LABEL_UNKNOWN;
  for (size_t i = 0; i < pts.n; i++) {
    const float *x = pts.xyz + i * 3;
    size_t idx[3];
    for (int a = 0; a < 3; a++) idx[a] = (size_t)((x[a] - gr->g.origin[a]) / 0.05);
    int label = 0;
    for (int j = 0; j < k; j++)
      if (vlff_sim_class_of(prompts[j]) == pts.label[i]) label = j;
    gr->labels[idx[0] + gr->g.dims[0] * (idx[1] + (size_t)gr->g.dims[1] * idx[2])] =
        (uint16_t)(one_label >= 0 ? one_label : label);
  }
  gr->g.labels = gr->labels;
  vlff_sim_points_free(&pts);
  vlff_sim_destroy(sim);
}

static void test_observer_scores_against_truth(void **state) {
  (void)state;
  struct vlff_config c;
  small_cfg(&c);
  struct vlff_source_hooks h;
  struct vlff_sim_source *s = make(&c, &h);
  const char *names[VLFF_SIM_CLASSES], *reversed[VLFF_SIM_CLASSES];
  for (int i = 0; i < VLFF_SIM_CLASSES; i++)
    names[i] = vlff_sim_class_name(i), reversed[VLFF_SIM_CLASSES - 1 - i] = vlff_sim_class_name(i);
  double m2, m3, m3_reversed, m3_one;
  struct grid g;
  grid_of_truth(&g, &c, names, VLFF_SIM_CLASSES, -1);
  struct vlff_map_seen seen = {.grid = &g.g, .prompts = names, .prompt_count = VLFF_SIM_CLASSES};
  h.observe(h.ctx, &seen, &m2, &m3);
  assert_true(m2 == -1); /* no label image */
  free(g.labels);
  grid_of_truth(&g, &c, reversed, VLFF_SIM_CLASSES, -1);
  seen = (struct vlff_map_seen){.grid = &g.g, .prompts = reversed, .prompt_count = VLFF_SIM_CLASSES};
  h.observe(h.ctx, &seen, &m2, &m3_reversed);
  free(g.labels);
  grid_of_truth(&g, &c, names, VLFF_SIM_CLASSES, 0);
  seen = (struct vlff_map_seen){.grid = &g.g, .prompts = names, .prompt_count = VLFF_SIM_CLASSES};
  h.observe(h.ctx, &seen, &m2, &m3_one);
  free(g.labels);
  print_message("3D mIoU: truth %.1f, truth with the prompts reversed %.1f, one label %.1f\n", m3, m3_reversed, m3_one);
  assert_true(m3 > 90); /* a voxel holding two classes' points keeps one of them */
  assert_true(m3_reversed > m3 - 0.5 && m3_reversed < m3 + 0.5);
  assert_true(m3_one >= 0 && m3_one < 25);

  /* A label image equal to the truth of frame 7, seen as ring id 7 + frames. */
  struct vlff_sim *sim = vlff_sim_create(&c.sim, &c.field, (char[128]){0}, 128);
  struct vlff_sim_frame *f = vlff_sim_frame_new(sim);
  assert_int_equal(vlff_sim_render(sim, 7, 0, f, (char[128]){0}, 128), 0);
  int *img = malloc((size_t)f->width * f->height * sizeof *img);
  for (int i = 0; i < f->width * f->height; i++) img[i] = f->label[i] < VLFF_SIM_CLASSES ? f->label[i] : -1;
  grid_of_truth(&g, &c, names, VLFF_SIM_CLASSES, -1);
  seen = (struct vlff_map_seen){.grid = &g.g, .image_labels = img, .width = f->width, .height = f->height,
                                .frame_id = 7 + c.sim.frames, .prompts = names, .prompt_count = VLFF_SIM_CLASSES};
  h.observe(h.ctx, &seen, &m2, &m3);
  assert_true(m2 > 99.9);
  /* Snapshot panels of that frame: the truth in the palette's colours. */
  uint8_t *image = malloc((size_t)f->width * f->height * 3), *truth = malloc((size_t)f->width * f->height * 3);
  assert_int_equal(h.panels(h.ctx, 7, f->width, f->height, image, truth), 0);
  for (int i = 0; i < f->width * f->height; i += 97)
    assert_memory_equal(truth + i * 3, vlff_label_color(img[i]), 3);
  assert_memory_equal(h.color(h.ctx, "chair"), vlff_label_color(vlff_sim_class_of("chair")), 3);
  assert_null(h.color(h.ctx, "a thing no scene has"));
  free(image), free(truth), free(img), free(g.labels);
  vlff_sim_frame_free(f);
  vlff_sim_destroy(sim);
  vlff_sim_source_destroy(s);
}

VLFF_UNIT_MAIN(NULL, NULL,
    cmocka_unit_test(test_hooks_follow_the_config), cmocka_unit_test(test_features_by_ring_id),
    cmocka_unit_test(test_observer_scores_against_truth))
