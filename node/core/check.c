/*
 * What vlff-node's start-up refuses before it touches shared memory, as one
 * function: vlff_node_create runs it first, and --check-config runs it with
 * the files loaded too (node.h).
 */
#include "node.h"

#include <stdio.h>

#include "embeddings.h"
#include "field.h"
#include "files.h"
#include "vlff/escape.h"
#ifdef VLFF_HAVE_VLM
#include "image_encoder.h"
#include "text_encoder.h"
#endif

/* Every prompt of every set is in the embeddings file: a set a controller
 * selects later is embedded from it as the active one is at start-up.
 * Without prompts.sets the file defines the prompts (adopt_embeddings_prompts):
 * then only its size matters, as at start-up. */
static int check_embeddings(const struct vlff_config *cfg, char *err, size_t errlen) {
  char e[512];
  struct vlff_embeddings *emb = vlff_embeddings_load(cfg->prompts.embeddings, cfg->field.feature_dim, e, sizeof e);
  if (!emb) return snprintf(err, errlen, "key 'prompts.embeddings': %s", e), -1;
  int rc = 0;
  if (!cfg->prompts.sets_named) {
    int k = vlff_embeddings_count(emb);
    if (k < 1 || k > VLFF_MAX_PROMPTS) {
      snprintf(err, errlen, "key 'prompts.embeddings': %s holds %d prompts; without prompts.sets it defines the "
               "prompts, 1 to %d of them: name the ones to use in prompts.sets", VLFF_Q(cfg->prompts.embeddings), k,
               VLFF_MAX_PROMPTS);
      rc = -1;
    }
    vlff_embeddings_free(emb);
    return rc;
  }
  for (int s = 0; s < cfg->prompts.set_count && !rc; s++)
    for (int i = 0; i < cfg->prompts.sets[s].count && !rc; i++)
      if (!vlff_embeddings_lookup(emb, cfg->prompts.sets[s].text[i])) {
        snprintf(err, errlen, "key 'prompts.embeddings': prompt '%s' of set '%s' is not in %s",
                 VLFF_Q(cfg->prompts.sets[s].text[i]), VLFF_Q(cfg->prompts.sets[s].name),
                 VLFF_Q(cfg->prompts.embeddings));
        rc = -1;
      }
  vlff_embeddings_free(emb);
  return rc;
}

#ifdef VLFF_HAVE_VLM
/* key's file is a readable regular file: the files the user supplies are
 * named by their key before the encoders say more of them. */
static int check_file(const char *key, const char *path, char *err, size_t errlen) {
  char e[512];
  if (!path[0] || vlff_check_regular(path, e, sizeof e) == 0) return 0; /* none: the encoder says so */
  snprintf(err, errlen, "key '%s': %s", key, e);
  return -1;
}
#endif

/* The models and the vocabulary load as start-up loads them. */
static int check_models(const struct vlff_config *cfg, char *err, size_t errlen) {
#ifdef VLFF_HAVE_VLM
  bool text = !cfg->prompts.embeddings[0] && cfg->vlm.text_model[0], image = cfg->source.features == VLFF_FEAT_MODEL;
  if ((text && check_file("vlm.text_model", cfg->vlm.text_model, err, errlen)) ||
      (image && check_file("vlm.image_model", cfg->vlm.image_model, err, errlen)) ||
      (text && check_file("vlm.bpe_vocab", cfg->vlm.bpe_vocab, err, errlen)))
    return -1;
  if (text) {
    struct vlff_text_encoder *t = vlff_text_encoder_open(&cfg->vlm, cfg->prompts.templ, cfg->field.feature_dim, err,
                                                         errlen);
    if (!t) return -1;
    vlff_text_encoder_close(t);
  }
  if (image) {
    struct vlff_image_encoder *m = vlff_image_encoder_open(&cfg->vlm, cfg->field.feature_dim, err, errlen);
    if (!m) return -1;
    vlff_image_encoder_close(m);
  }
#else
  (void)cfg, (void)err, (void)errlen;
#endif
  return 0;
}

int vlff_node_check(const struct vlff_config *cfg, const struct vlff_source_hooks *hooks, bool load_files, char *err,
                    size_t errlen) {
  static const struct vlff_source_hooks none;
  if (!hooks) hooks = &none;
#ifndef VLFF_HAVE_VLM
  if (cfg->source.features == VLFF_FEAT_MODEL || cfg->vlm.text_model[0]) {
    snprintf(err, errlen, "%s: this vlff-node was built without OpenCV (VLFF_WITH_OPENCV=OFF)",
             cfg->source.features == VLFF_FEAT_MODEL ? "source.features: model" : "vlm.text_model");
    return -1;
  }
#endif
  if (vlff_field_check_memory(&cfg->field, &cfg->train, err, errlen)) return -1;
  if (!cfg->prompts.embeddings[0] && !cfg->vlm.text_model[0] && !hooks->embed) {
    /* Checked before any segment is made: without a text encoder no prompt
     * can be embedded, and the node would stop at the first one. */
    snprintf(err, errlen, "no text encoder for the prompts: set prompts.embeddings (a precomputed file) or "
             "vlm.text_model (the CLIP text encoder, ONNX)");
    return -1;
  }
  if (vlff_config_sim_features_misused(cfg)) {
    snprintf(err, errlen, "source.features: sim with source.kind: ring pairs the simulator's features with a "
             "camera's images; use ring or model, or set source.allow_sim_features: true to force it");
    return -1;
  }
  if (cfg->source.features == VLFF_FEAT_SIM && !hooks->features) {
    snprintf(err, errlen, "source.features: sim, but the source gives no features (vlff-node makes the simulator's "
             "hooks; a program embedding the node passes them to vlff_node_create)");
    return -1;
  }
  if (!load_files) return 0;
  if (cfg->prompts.embeddings[0] && check_embeddings(cfg, err, errlen)) return -1;
  return check_models(cfg, err, errlen);
}
