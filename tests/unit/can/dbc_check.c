#include "dbc_check.h"

#include "can_proto.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

int dbc_load_vlff(struct dbc *db) {
  const char *root = getenv("VLFF_SOURCE_DIR");
  if (!root) root = getenv("VLFF_SRC");
  if (!root) root = ".";
  char path[512], err[256];
  snprintf(path, sizeof path, "%s/configs/vlff.dbc", root);
  if (dbc_load(path, db, err, sizeof err) < 0) {
    fprintf(stderr, "%s\n", err);
    return -1;
  }
  return 0;
}

/* What a receiver should read for a value sent as u16 with this scale. */
static double expect_scaled(double v, double scale) {
  if (!isfinite(v)) return 65535 * scale;
  if (v <= 0) return 0;
  double raw = floor(v / scale + 0.5);
  return (raw > 65535 ? 65535 : raw) * scale;
}

/* What a receiver should read for MiB sent in a bits-wide field of this
 * scale: all ones (unknown, above range) reads as its raw value times scale. */
static double expect_mib(double v, double scale, int bits) {
  const double all = (double)((1u << bits) - 1);
  if (!(v >= 0)) return all * scale;
  double raw = floor(v / scale + 0.5);
  return (raw > all ? all : raw) * scale;
}

static int near(const char *sig, double got, double want, double tol, char *why, size_t n) {
  if (fabs(got - want) <= tol) return 0;
  snprintf(why, n, "signal %s: decoded %.6f, expected %.6f", sig, got, want);
  return -1;
}

int dbc_check_status(const struct dbc_message *m, int part, const uint8_t *data, int len,
                     const struct vlff_can_status *st, int nmt_state, char *why, size_t n) {
  const char *prefix_names[VLFF_CANP_STATUS_FRAMES] = {"VLFF_TRAIN",  "VLFF_LOSS",   "VLFF_MAP",   "VLFF_HEALTH",
                                                       "VLFF_INGEST", "VLFF_MEMORY", "VLFF_PAGING"};
  const char *kind = m->name;
  if (!strcmp(m->name, "VLFF_STATUS_FD")) {
    if (part < 0 || part >= VLFF_CANP_STATUS_FRAMES) { snprintf(why, n, "bad FD part %d", part); return -1; }
    kind = prefix_names[part];
  }
  if (len != m->dlc) {
    snprintf(why, n, "%s: frame length %d, DBC says %d", m->name, len, m->dlc);
    return -1;
  }
  struct want { const char *sig; double want, tol; } c[8];
  int k = 0;
  if (!strcmp(kind, "VLFF_TRAIN")) {
    c[k++] = (struct want){"Iteration", st->iteration, 0};
    c[k++] = (struct want){"Keyframes", st->keyframes > 65535 ? 65535 : st->keyframes, 0};
    c[k++] = (struct want){"PromptSet", st->prompt_set > 255 ? 255 : st->prompt_set, 0};
    c[k++] = (struct want){"NmtState", nmt_state, 0};
  } else if (!strcmp(kind, "VLFF_LOSS")) {
    c[k++] = (struct want){"LossTotal", expect_scaled(st->loss_total, 0.001), 1e-9};
    c[k++] = (struct want){"LossColor", expect_scaled(st->loss_color, 0.0001), 1e-9};
    c[k++] = (struct want){"LossDepth", expect_scaled(st->loss_depth, 0.0001), 1e-9};
    c[k++] = (struct want){"LossFeature", expect_scaled(st->loss_feature, 0.0001), 1e-9};
  } else if (!strcmp(kind, "VLFF_MAP")) {
    c[k++] = (struct want){"MapVersion", st->map_version, 0};
    c[k++] = (struct want){"FpsIn", expect_scaled(st->fps_in, 0.01), 1e-9};
  } else if (!strcmp(kind, "VLFF_HEALTH")) {
    c[k++] = (struct want){"ErrCameraLost", (st->error_flags & VLFF_CAN_ERRF_CAMERA_LOST) ? 1 : 0, 0};
    c[k++] = (struct want){"ErrPoseStale", (st->error_flags & VLFF_CAN_ERRF_POSE_STALE) ? 1 : 0, 0};
    c[k++] = (struct want){"ErrShmLapped", (st->error_flags & VLFF_CAN_ERRF_SHM_LAPPED) ? 1 : 0, 0};
    c[k++] = (struct want){"ErrCheckpointFailed", (st->error_flags & VLFF_CAN_ERRF_CHECKPOINT_FAILED) ? 1 : 0, 0};
    c[k++] = (struct want){"FpsDropped", expect_scaled(st->fps_dropped, 0.01), 1e-9};
  } else if (!strcmp(kind, "VLFF_INGEST")) {
    c[k++] = (struct want){"FramesRefused", st->frames_refused, 0};
    c[k++] = (struct want){"LastRefusal", st->last_refusal > 255 ? 255 : st->last_refusal, 0};
  } else if (!strcmp(kind, "VLFF_MEMORY")) {
    c[k++] = (struct want){"MemRss", expect_mib(st->mem_rss_mb, 1, 16), 0};
    c[k++] = (struct want){"MemKeyframes", expect_mib(st->mem_keyframes_mb, 4, 12), 0};
    c[k++] = (struct want){"MemKeyframesLimit", expect_mib(st->mem_keyframes_limit_mb, 4, 12), 0};
    c[k++] = (struct want){"MemEvidence", expect_mib(st->mem_evidence_mb, 1, 12), 0};
    c[k++] = (struct want){"MemEvidenceLimit", expect_mib(st->mem_evidence_limit_mb, 1, 12), 0};
  } else if (!strcmp(kind, "VLFF_PAGING")) {
    c[k++] = (struct want){"KeyframesPaged", st->keyframes_paged > 65535 ? 65535 : st->keyframes_paged, 0};
    c[k++] = (struct want){"KeyframesDropped", st->keyframes_dropped > 65535 ? 65535 : st->keyframes_dropped, 0};
    c[k++] = (struct want){"EvidenceDropped", st->evidence_dropped > 65535 ? 65535 : st->evidence_dropped, 0};
    c[k++] = (struct want){"BoxGrowths", st->box_growths > 255 ? 255 : st->box_growths, 0};
    c[k++] = (struct want){"BoxRefused", st->box_refused > 255 ? 255 : st->box_refused, 0};
  } else {
    snprintf(why, n, "%s is not a status message", m->name);
    return -1;
  }
  int base = strcmp(m->name, "VLFF_STATUS_FD") ? 0 : 8 * part;
  for (int i = 0; i < k; i++) {
    /* In the FD message the signals sit at +64 bits per part but keep their names. */
    const struct dbc_signal *s = NULL;
    for (int j = 0; j < m->nsig; j++)
      if (!strcmp(m->sig[j].name, c[i].sig) && m->sig[j].start / 64 == base / 8) s = &m->sig[j];
    if (!s) { snprintf(why, n, "%s has no signal %s", m->name, c[i].sig); return -1; }
    int64_t raw;
    if (dbc_raw(s, data, len, &raw) < 0) { snprintf(why, n, "%s.%s does not fit", m->name, c[i].sig); return -1; }
    double got = (double)(uint64_t)raw * s->scale + s->offset;
    if (near(c[i].sig, got, c[i].want, c[i].tol, why, n) < 0) return -1;
    if (got < s->min - 1e-9 || got > s->max + 1e-9) {
      snprintf(why, n, "%s.%s = %f outside the DBC range [%f, %f]", m->name, c[i].sig, got, s->min, s->max);
      return -1;
    }
  }
  return 0;
}
