/*
 * The simulator behind the node's source hooks (sim_source.h).
 */
#include "sim_source.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "metrics.h"
#include "palette.h"
#include "sim.h"

struct vlff_sim_source {
  struct vlff_sim *sim;
  int frames;                       /* sim.frames: the loop the ring's ids run through */
  struct vlff_sim_frame *feat;      /* the features caller's (ingest thread) */
  struct vlff_sim_frame *truth;     /* the other hooks' (trainer thread) */
  struct vlff_sim_points points;    /* labelled surface points for the 3D score */
  struct vlff_confusion conf;
};

static long long scene_frame(const struct vlff_sim_source *s, long long id) {
  return vlff_sim_stream_frame(s->sim, id);
}

static int features(void *ctx, long long frame_id, uint16_t *out, char *err, size_t errlen) {
  struct vlff_sim_source *s = ctx;
  if (vlff_sim_render(s->sim, scene_frame(s, frame_id), VLFF_SIM_FEATURES, s->feat, err, errlen)) return -1;
  const struct vlff_sim_frame *f = s->feat;
  memcpy(out, f->features, (size_t)f->feat_width * f->feat_height * f->feature_dim * sizeof *out);
  return 0;
}

static int embed(void *ctx, const char *text, float *out, char *err, size_t errlen) {
  (void)err, (void)errlen;
  struct vlff_sim_source *s = ctx;
  /* The simulated encoder knows class names, not templated sentences. */
  vlff_sim_text_embedding(s->sim, text, out);
  return 0;
}

/* Prompt index -> the scene's class, so a prompt set in any order (or with
 * texts the scene does not know) is scored against the ground truth. */
static int class_of_prompt(const struct vlff_map_seen *m, int label) {
  return label >= 0 && label < m->prompt_count ? vlff_sim_class_of(m->prompts[label]) : -1;
}

static double miou_of(const struct vlff_confusion *c) {
  struct vlff_summary sum;
  vlff_confusion_summary(c, &sum);
  return sum.present ? sum.miou * 100.0 : -1;
}

static int grid_label(const struct vlff_map_grid *g, const float x[3]) {
  long idx[3];
  for (int i = 0; i < 3; i++) {
    double f = (x[i] - g->origin[i]) / g->voxel_size;
    if (!(f >= 0) || f >= g->dims[i]) return -1;
    idx[i] = (long)f;
  }
  uint16_t l = g->labels[idx[0] + (long)g->dims[0] * (idx[1] + (long)g->dims[1] * idx[2])];
  return l <= VLFF_LABEL_MAX ? l : -1;
}

static void observe(void *ctx, const struct vlff_map_seen *m, double *miou2d, double *miou3d) {
  struct vlff_sim_source *s = ctx;
  char err[128];
  *miou2d = *miou3d = -1;
  if (m->image_labels && vlff_sim_render(s->sim, scene_frame(s, m->frame_id), 0, s->truth, err, sizeof err) == 0) {
    const struct vlff_sim_frame *g = s->truth;
    vlff_confusion_reset(&s->conf);
    for (int y = 0; y < m->height; y++)
      for (int x = 0; x < m->width; x++) {
        int gy = y * g->height / m->height, gx = x * g->width / m->width;
        vlff_confusion_add_one(&s->conf, g->label[(size_t)gy * g->width + gx],
                               class_of_prompt(m, m->image_labels[(size_t)y * m->width + x]));
      }
    *miou2d = miou_of(&s->conf);
  }
  if (s->points.n) {
    vlff_confusion_reset(&s->conf);
    for (size_t i = 0; i < s->points.n; i++)
      vlff_confusion_add_one(&s->conf, s->points.label[i], class_of_prompt(m, grid_label(m->grid, s->points.xyz + i * 3)));
    *miou3d = miou_of(&s->conf);
  }
}

static int panels(void *ctx, long long frame_id, int w, int h, uint8_t *image, uint8_t *truth) {
  struct vlff_sim_source *s = ctx;
  char err[128];
  if (vlff_sim_render(s->sim, scene_frame(s, frame_id), VLFF_SIM_RGBD, s->truth, err, sizeof err)) return -1;
  const struct vlff_sim_frame *g = s->truth;
  for (int y = 0; y < h; y++)
    for (int x = 0; x < w; x++) {
      size_t gi = (size_t)(y * g->height / h) * g->width + (size_t)(x * g->width / w), i = (size_t)y * w + x;
      int gl = g->label[gi];
      memcpy(image + i * 3, g->rgb + gi * 3, 3);
      memcpy(truth + i * 3, vlff_label_color(gl < VLFF_SIM_CLASSES ? gl : -1), 3);
    }
  return 0;
}

static const uint8_t *color(void *ctx, const char *prompt) {
  (void)ctx;
  int c = vlff_sim_class_of(prompt);
  return c >= 0 ? vlff_label_color(c) : NULL;
}

void vlff_sim_source_destroy(struct vlff_sim_source *s) {
  if (!s) return;
  vlff_sim_frame_free(s->feat);
  vlff_sim_frame_free(s->truth);
  vlff_sim_points_free(&s->points);
  vlff_confusion_free(&s->conf);
  vlff_sim_destroy(s->sim);
  free(s);
}

struct vlff_sim_source *vlff_sim_source_create(const struct vlff_config *cfg, struct vlff_source_hooks *hooks,
                                               char *err, size_t errlen) {
  memset(hooks, 0, sizeof *hooks);
  struct vlff_sim_source *s = calloc(1, sizeof *s);
  if (!s) return snprintf(err, errlen, "out of memory"), NULL;
  bool feats = cfg->source.features == VLFF_FEAT_SIM, truth = cfg->source.kind == VLFF_SOURCE_SIM;
  if (!feats && !truth) return s;
  s->frames = cfg->sim.frames;
  s->sim = vlff_sim_create(&cfg->sim, &cfg->field, err, errlen);
  if (!s->sim) goto fail;
  s->feat = vlff_sim_frame_new(s->sim);
  s->truth = vlff_sim_frame_new(s->sim);
  if (!s->feat || !s->truth) {
    snprintf(err, errlen, "out of memory");
    goto fail;
  }
  if (vlff_confusion_init(&s->conf, VLFF_SIM_CLASSES, err, errlen)) goto fail;
  hooks->ctx = s;
  hooks->embed = embed; /* features and prompts come from the same simulated encoder */
  if (feats) {
    int w, h, fw, fh, d;
    vlff_sim_size(s->sim, &w, &h, &fw, &fh, &d);
    hooks->features = features;
    hooks->feat_width = fw;
    hooks->feat_height = fh;
  }
  if (truth) {
    if (vlff_sim_points_budget(s->sim, cfg->sim.frames, 5, 0.05, VLFF_SIM_POINTS_RAYS, &s->points, err, errlen))
      goto fail;
    hooks->observe = observe;
    hooks->panels = panels;
    hooks->color = color;
  }
  return s;
fail:
  memset(hooks, 0, sizeof *hooks);
  vlff_sim_source_destroy(s);
  return NULL;
}
