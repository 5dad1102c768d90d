/* Frame ring producer behind the sink interface; pose ring lookups. */
#include "ringsink.h"

#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <vlff/shm.h>

#include "clock.h"
#include "log.h"
#include "vlff/escape.h"

#define TAG "ring"

struct vlff_ringsink {
  struct vlff_sink sink;
  struct vlff_pose_source poses;
  struct vlff_ring *ring;
  uint64_t slot_size;
  struct vlff_frame_hdr *hdr;   /* reserved record */
  uint64_t len;
  char pose_name[VLFF_CFG_STR];
  struct vlff_ring *pose_ring;
  uint64_t pose_retry_ns;
  uint64_t pose_warned; /* vlff_warn_limited's */
};

static int reserve(struct vlff_sink *s, struct vlff_sink_frame *f, char *err, size_t errlen) {
  struct vlff_ringsink *r = s->ctx;
  uint32_t dfmt = f->depth_format == VLFF_DEPTH_FMT_U16_MM ? VLFF_PIX_DEPTH_U16_MM
                  : f->depth_format == VLFF_DEPTH_FMT_F32_M ? VLFF_PIX_DEPTH_F32_M
                                                            : VLFF_PIX_NONE;
  uint64_t need = vlff_frame_slot_size((uint32_t)f->width, (uint32_t)f->height, (uint32_t)f->color_format, dfmt);
  if (!need || need > r->slot_size) {
    snprintf(err, errlen, "frame %dx%d needs %llu bytes, ring slots hold %llu (raise shm.max_width/max_height)",
             f->width, f->height, (unsigned long long)need, (unsigned long long)r->slot_size);
    return -1;
  }
  void *rec = vlff_ring_reserve(r->ring, NULL);
  if (!rec) {
    snprintf(err, errlen, "ring reserve: %s", vlff_shm_last_message());
    return -1;
  }
  struct vlff_frame_hdr *h = rec;
  r->len = vlff_frame_layout(h, r->slot_size, (uint32_t)f->width, (uint32_t)f->height, (uint32_t)f->color_format,
                             dfmt);
  r->hdr = h;
  f->color = (uint8_t *)rec + h->plane[VLFF_PLANE_COLOR].offset;
  f->color_stride = h->plane[VLFF_PLANE_COLOR].stride;
  f->depth = dfmt ? (uint8_t *)rec + h->plane[VLFF_PLANE_DEPTH].offset : NULL;
  f->depth_stride = dfmt ? h->plane[VLFF_PLANE_DEPTH].stride : 0;
  return 0;
}

static int commit(struct vlff_sink *s, struct vlff_sink_frame *f) {
  struct vlff_ringsink *r = s->ctx;
  struct vlff_frame_hdr *h = r->hdr;
  h->frame_id = f->device_frame_id;
  h->t_device_ns = f->device_ns;
  h->t_host_ns = f->host_ns;
  h->sensor_id = f->sensor_id;
  h->flags = 0;
  if (f->intrinsics[0] > 0 && f->intrinsics[1] > 0) {
    /* The drivers, camera.intrinsics and calibration files count pixels as
     * OpenCV does (pixel (0,0) centred at (0,0)); the record, like the
     * field, centres it at (0.5,0.5). */
    h->fx = f->intrinsics[0], h->fy = f->intrinsics[1];
    h->cx = f->intrinsics[2] + 0.5, h->cy = f->intrinsics[3] + 0.5;
    h->flags |= VLFF_FRAME_INTRINSICS_VALID;
  }
  if (f->pose_valid) {
    memcpy(h->pose, f->pose, sizeof h->pose);
    h->pose_t_ns = f->pose_ns;
    h->flags |= VLFF_FRAME_POSE_VALID;
    if (f->pose_untrusted) h->flags |= VLFF_FRAME_POSE_UNTRUSTED;
  }
  r->hdr = NULL;
  return vlff_ring_commit(r->ring, r->len);
}

/* A reserved slot cannot be un-reserved; committing it as a zero-length
 * record would hand consumers garbage, so the next reserve simply reuses
 * it (vlff_ring_reserve returns the same slot until a commit). */
static void abort_frame(struct vlff_sink *s, struct vlff_sink_frame *f) {
  (void)f;
  ((struct vlff_ringsink *)s->ctx)->hdr = NULL;
}

static int pose_lookup(void *ctx, uint64_t t_ns, double tol_s, double pose[16], uint64_t *pose_ns, bool *untrusted) {
  struct vlff_ringsink *r = ctx;
  if (!r->pose_ring) {
    if (vlff_now_ns() < r->pose_retry_ns) return -1;
    r->pose_retry_ns = vlff_now_ns() + 1000000000u;
    r->pose_ring = vlff_ring_attach(r->pose_name, VLFF_RECORD_POSE);
    if (!r->pose_ring) {
      if (errno != ENOENT) vlff_warn_limited(&r->pose_warned, TAG, "pose ring: %s", vlff_shm_last_message());
      return -1;
    }
    VLFF_INFO(TAG, "poses from %s", VLFF_Q(r->pose_name));
  }
  struct vlff_pose_rec rec;
  if (vlff_pose_lookup(r->pose_ring, t_ns, (uint64_t)llround(tol_s * 1e9), &rec)) {
    if (errno == EPIPE) { /* SLAM restarted on a new segment: re-attach next time */
      vlff_ring_close(r->pose_ring);
      r->pose_ring = NULL;
    }
    return -1;
  }
  memcpy(pose, rec.pose, sizeof rec.pose);
  *pose_ns = rec.t_ns;
  *untrusted = rec.flags & VLFF_FRAME_POSE_UNTRUSTED;
  return 0;
}

struct vlff_ringsink *vlff_ringsink_new(const struct vlff_cfg_shm *shm, const struct vlff_cfg_camera *camera, char *err,
                                        size_t errlen) {
  struct vlff_ringsink *r = calloc(1, sizeof *r);
  if (!r) return snprintf(err, errlen, "out of memory"), NULL;
  uint32_t dfmt = camera->depth == VLFF_DEPTH_NONE       ? VLFF_PIX_NONE
                  : camera->depth_unit == VLFF_DEPTH_UNIT_MM ? VLFF_PIX_DEPTH_U16_MM
                                                             : VLFF_PIX_DEPTH_F32_M;
  r->slot_size = vlff_frame_slot_size((uint32_t)shm->max_width, (uint32_t)shm->max_height, VLFF_PIX_RGB8, dfmt);
  struct vlff_ring_params p = {
      .record_kind = VLFF_RECORD_FRAME,
      .slots = (uint32_t)shm->ring_slots,
      .slot_size = r->slot_size,
      .perm = {.mode = (mode_t)shm->mode, .group = shm->group},
  };
  r->ring = vlff_ring_create(shm->ring, &p);
  if (!r->ring) {
    snprintf(err, errlen, "key 'shm.ring': cannot create frame ring %s: %s", shm->ring, vlff_shm_last_message());
    free(r);
    return NULL;
  }
  snprintf(r->pose_name, sizeof r->pose_name, "%s", shm->pose_ring);
  r->sink = (struct vlff_sink){reserve, commit, abort_frame, r};
  r->poses = (struct vlff_pose_source){pose_lookup, r};
  VLFF_INFO(TAG, "frame ring %s: %d slots of %llu bytes (generation %u)", shm->ring, shm->ring_slots,
            (unsigned long long)r->slot_size, vlff_ring_generation(r->ring));
  return r;
}

void vlff_ringsink_free(struct vlff_ringsink *r) {
  if (!r) return;
  vlff_ring_close(r->ring);
  vlff_ring_close(r->pose_ring);
  free(r);
}

struct vlff_sink *vlff_ringsink_sink(struct vlff_ringsink *r) { return &r->sink; }
struct vlff_pose_source *vlff_ringsink_poses(struct vlff_ringsink *r) { return &r->poses; }
