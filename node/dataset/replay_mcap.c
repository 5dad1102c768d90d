/*
 * replay_mcap.c - MCAP recordings of the node's inputs played into the rings
 * (replay_mcap.h).
 */
#include "replay_mcap.h"

#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include "cli.h"
#include "clock.h"
#include "files.h"
#include "inputs.h"
#include "replay_rings.h"
#include "vlff/escape.h"
#include "vlff/shm.h"

int vlff_replay_is_mcap(const char *path) {
  char err[256];
  int fd = vlff_open_regular(path, err, sizeof err);
  if (fd < 0) return 0;
  uint8_t magic[8];
  int is = vlff_read_at(fd, 0, magic, sizeof magic) == 0 && !memcmp(magic, "\x89MCAP0\r\n", 8);
  close(fd);
  return is;
}

/* What the validating pass found. */
struct scan {
  long long frames, poses, maps;
  uint64_t *stamp; /* [frames] */
  uint32_t width, height, color_format, depth_format, dim, fh, fw;
};

/* The frames played lately: a feature map finds its frame's new id and time by
 * the frame's recorded stamp. Maps come after their frame; the recorder keeps
 * them within a ring's length of it. */
#define RECENT 1024
struct recent {
  uint64_t rec_t, id, t, pass;
};

struct player {
  const char *path;
  const struct vlff_replay_opts *o;
  const uint8_t *file; /* the recording, mapped */
  size_t n, given_back;  /* its size; the prefix whose pages went back */
  struct vlff_in_reader *in;
  struct scan s;
  struct vlff_ring *frames, *poses, *feats;
  struct recent recent[RECENT];
  long long published, poses_out, maps_out, orphans, late;
};

/* The pages of what was read go back as it is read: a recording larger than
 * memory plays (and is checked) through a bounded resident set. */
static void give_back(struct player *p) { vlff_unread_mapped_paced(p->file, &p->given_back, vlff_in_consumed(p->in)); }

static int scan(struct player *p) {
  char why[1024];
  struct vlff_in_event ev;
  int rc;
  size_t cap = 0;
  while ((rc = vlff_in_next(p->in, &ev, why, sizeof why)) == 1) {
    give_back(p);
    if (ev.kind == VLFF_IN_EV_FRAME) {
      if ((size_t)p->s.frames == cap) {
        cap = cap ? cap * 2 : 1024;
        uint64_t *s = realloc(p->s.stamp, cap * sizeof *s);
        if (!s) {
          fprintf(stderr, "vlff-replay: out of memory\n");
          return -1;
        }
        p->s.stamp = s;
      }
      if (!p->s.frames)
        p->s.width = ev.width, p->s.height = ev.height, p->s.color_format = ev.color_format,
        p->s.depth_format = ev.depth_format;
      p->s.stamp[p->s.frames++] = ev.t_ns;
    } else if (ev.kind == VLFF_IN_EV_POSE) {
      p->s.poses++;
    } else {
      if (!p->s.maps) p->s.dim = ev.dim, p->s.fh = ev.feat_height, p->s.fw = ev.feat_width;
      p->s.maps++;
    }
  }
  if (rc < 0) {
    fprintf(stderr, "vlff-replay: %s: %s\n", VLFF_Q(p->path), why);
    return -1;
  }
  if (!p->s.frames) {
    fprintf(stderr, "vlff-replay: %s: no frames on %s (%llu messages on other channels: a vlff-view recording "
                    "holds no inputs; vlff-record records them)\n",
            VLFF_Q(p->path), vlff_in_topic(VLFF_IN_COLOR), (unsigned long long)vlff_in_other_messages(p->in));
    return -1;
  }
  return 0;
}

static int open_rings(struct player *p, const struct vlff_config *cfg) {
  struct vlff_replay_rings r = {0};
  int rc = vlff_replay_rings_open(&r, cfg, p->s.width, p->s.height, p->s.color_format, p->s.depth_format,
                                  (uint32_t)p->o->pose_slots, p->o->features ? p->s.dim : 0, p->s.fh, p->s.fw);
  p->frames = r.frames, p->poses = r.poses, p->feats = r.feats;
  return rc;
}

static int put_frame(struct player *p, const struct vlff_in_event *ev, uint64_t id, uint64_t t, uint64_t t_dev,
                     double rate) {
  struct vlff_frame_hdr *h = vlff_ring_reserve(p->frames, NULL);
  uint64_t len = h ? vlff_frame_layout(h, vlff_ring_slot_size(p->frames), ev->width, ev->height, ev->color_format,
                                       ev->depth_format)
                   : 0;
  if (!len) return vlff_replay_ring_error("frame", "layout");
  h->frame_id = id;
  h->t_host_ns = t;
  h->t_device_ns = t_dev;
  h->flags = VLFF_FRAME_INTRINSICS_VALID;
  h->fx = ev->fx, h->fy = ev->fy, h->cx = ev->cx, h->cy = ev->cy;
  if (ev->has_pose) {
    /* the frame's own pose, as far from the frame's new time as it was recorded */
    h->flags |= VLFF_FRAME_POSE_VALID;
    memcpy(h->pose, ev->pose, sizeof h->pose);
    int64_t d = (int64_t)(ev->pose_t_ns - ev->t_ns);
    if (d == INT64_MIN) d++;
    if (rate != 1) d = (int64_t)llround((double)d / rate);
    h->pose_t_ns = d < 0 && (uint64_t)-d > t ? 0 : t + (uint64_t)d;
  }
  for (unsigned i = 0; i < 2; i++) {
    const uint8_t *src = i ? ev->depth : ev->color;
    if (!src) continue;
    const struct vlff_plane *pl = &h->plane[i];
    size_t step = (size_t)pl->width * vlff_pixfmt_bpp(pl->format);
    uint8_t *dst = (uint8_t *)h + pl->offset;
    for (uint32_t v = 0; v < pl->height; v++) memcpy(dst + (size_t)v * pl->stride, src + (size_t)v * step, step);
  }
  if (vlff_ring_commit(p->frames, len) < 0) return vlff_replay_ring_error("frame", "commit");
  return 0;
}

static int put_features(struct player *p, const struct vlff_in_event *ev, uint64_t id, uint64_t t) {
  struct vlff_feature_hdr *f = vlff_ring_reserve(p->feats, NULL);
  uint64_t len = f ? vlff_feature_layout(f, vlff_ring_slot_size(p->feats), ev->dim, ev->feat_height, ev->feat_width)
                   : 0;
  if (!len) return vlff_replay_ring_error("feature", "layout");
  f->frame_id = id;
  f->t_host_ns = t;
  memcpy((uint8_t *)f + f->data_offset, ev->features, (size_t)2 * ev->dim * ev->feat_height * ev->feat_width);
  if (vlff_ring_commit(p->feats, len) < 0) return vlff_replay_ring_error("feature", "commit");
  return 0;
}

static int play(struct player *p) {
  const struct vlff_replay_opts *o = p->o;
  const uint64_t first = p->s.stamp[0], last = p->s.stamp[p->s.frames - 1];
  /* one loop's length: the recording's plus one mean frame interval */
  uint64_t mean = p->s.frames > 1 ? (last - first) / (uint64_t)(p->s.frames - 1) : 33333333u;
  if (!mean) mean = 1;
  const uint64_t span = last - first + mean;
  double rate = o->rate;
  if (o->fps > 0) rate *= o->fps * (double)mean * 1e-9;
  const uint64_t t0 = p->s.stamp[o->start];
  if (o->wait_reader && !o->backpressure) vlff_replay_wait_reader(p->frames, o->quiet);
  uint64_t base = vlff_now_ns(), newest = 0;
  int have_newest = 0;
  uint64_t id = 0;
  char why[1024];
  for (uint64_t pass = 0; !vlff_cli_stop; pass++) {
    vlff_in_rewind(p->in);
    struct vlff_in_event ev;
    int rc = 0;
    int done = 0;
    while (!vlff_cli_stop && (rc = vlff_in_next(p->in, &ev, why, sizeof why)) == 1) {
      give_back(p);
      /* Records before the first played frame (--start's, or a pose ring's
       * history the recorder found when it attached) have no place in the
       * schedule, which starts at that frame: passed over. */
      if (ev.t_ns < (pass ? first : t0)) continue;
      uint64_t rec = pass * span + ev.t_ns; /* the record's place in the playback */
      uint64_t off = rate == 1 ? rec - t0 : (uint64_t)llround((double)(rec - t0) / rate);
      if (ev.kind == VLFF_IN_EV_FRAME) {
        if (o->count > 0 && (long long)id >= o->count) {
          done = 1;
          break;
        }
        if (o->backpressure) {
          /* No reader yet (or a node restarting) holds the replay: frames
           * nobody reads would be lost, which is what this mode exists to prevent. */
          vlff_replay_wait_reader(p->frames, o->quiet);
          if (vlff_cli_stop) break;
        }
      }
      /* The schedule moves at a new stamp only: records of one stamp (a frame and
       * its pose) keep one time, and a late replay restarts its schedule from now
       * rather than bursting to catch up. */
      if (!have_newest || rec > newest) {
        uint64_t now = vlff_now_ns(), due = base + off;
        if (o->backpressure) {
          /* Paced by the reader, not the schedule: a stamp is when its
           * records go out. One kept from the schedule was ahead of the
           * clock whenever the reader ran faster than the recording, and the
           * node refuses a pose from the future. */
          base = now - off;
        } else if (now > due + 1000000ull) {
          /* a late pose restarts the schedule as a late frame does, and the
           * frames after it go out at the new times: counted alike */
          p->late++;
          base = now - off;
        } else {
          vlff_replay_sleep_until(due);
          if (vlff_cli_stop) break; /* cut short: this record's time has not come */
        }
        newest = rec, have_newest = 1;
      }
      uint64_t t = base + off;
      if (ev.kind == VLFF_IN_EV_POSE) {
        struct vlff_pose_rec pr = {.t_ns = t, .flags = 0, .source_id = 0};
        memcpy(pr.pose, ev.pose, sizeof pr.pose);
        if (vlff_ring_write(p->poses, &pr, sizeof pr) < 0) return vlff_replay_ring_error("pose", "commit");
        p->poses_out++;
      } else if (ev.kind == VLFF_IN_EV_FRAME) {
        if (put_frame(p, &ev, id, t, rec - first, rate) < 0) return -1;
        p->recent[id % RECENT] = (struct recent){ev.t_ns, id, t, pass};
        id++;
        p->published++;
        if (!o->quiet && p->published % 100 == 0)
          fprintf(stderr, "vlff-replay: %lld frames published (pass %llu)\n", p->published,
                  (unsigned long long)pass + 1);
      } else if (p->feats) {
        /* its frame: the newest played with the map's stamp, in this pass */
        const struct recent *hit = NULL;
        for (uint64_t k = 0; k < RECENT && k < id; k++) {
          const struct recent *r = &p->recent[(id - 1 - k) % RECENT];
          if (r->pass != pass || r->rec_t < ev.t_ns) break;
          if (r->rec_t == ev.t_ns) {
            hit = r;
            break;
          }
        }
        if (!hit) {
          p->orphans++; /* its frame was not recorded (the recorder missed it) or not played */
        } else {
          if (put_features(p, &ev, hit->id, hit->t) < 0) return -1;
          p->maps_out++;
        }
      }
    }
    if (!vlff_cli_stop && !done && rc < 0) {
      /* the file was checked whole before: it changed under the replay */
      fprintf(stderr, "vlff-replay: %s: %s\n", VLFF_Q(p->path), why);
      return -1;
    }
    if (done || !o->loop) break;
  }
  return 0;
}

int vlff_replay_mcap(const char *path, const struct vlff_config *cfg, const struct vlff_replay_opts *o) {
  struct player p;
  memset(&p, 0, sizeof p);
  p.path = path;
  p.o = o;
  char err[1024];
  int status = 1;
  if (vlff_map_file(path, VLFF_MCAP_MAX_FILE, &p.file, &p.n, err, sizeof err) != 0) {
    fprintf(stderr, "vlff-replay: %s\n", err);
    return 1;
  }
  vlff_map_exit_on_sigbus("vlff-replay", path);
  p.in = vlff_in_reader_new(p.file, p.n, err, sizeof err);
  if (!p.in) {
    fprintf(stderr, "vlff-replay: %s: %s\n", VLFF_Q(path), err);
    goto out;
  }
  if (scan(&p) < 0) goto out;
  if (o->start >= p.s.frames) {
    fprintf(stderr, "vlff-replay: --start %d: the recording has %lld frames\n", o->start, p.s.frames);
    goto out;
  }
  struct vlff_replay_opts opts = *o;
  if (opts.features && !p.s.maps) {
    fprintf(stderr, "vlff-replay: %s has no feature maps (%s): playing without features, as --no-features\n",
            VLFF_Q(path), vlff_in_topic(VLFF_IN_FEATURES));
    opts.features = 0;
  }
  p.o = &opts;
  if (open_rings(&p, cfg) < 0) goto out;
  vlff_cli_catch_stop();
  char pace[96];
  if (opts.backpressure) snprintf(pace, sizeof pace, "paced by the reader");
  else if (opts.fps > 0)
    snprintf(pace, sizeof pace, "at the recording's stamps scaled to %g Hz on average (--fps)", opts.fps * opts.rate);
  else if (opts.rate != 1) snprintf(pace, sizeof pace, "at %g times the recording's stamps", opts.rate);
  else snprintf(pace, sizeof pace, "at the recording's stamps");
  if (!opts.quiet)
    fprintf(stderr, "vlff-replay: %s: %lld frames %ux%u, %lld poses, %lld feature maps%s, %s\n", VLFF_Q(path),
            p.s.frames, p.s.width, p.s.height, p.s.poses, p.s.maps, opts.features ? "" : " (not played)", pace);
  if (play(&p) == 0) status = 0;
  if (!opts.quiet || status)
    fprintf(stderr, "vlff-replay: %lld frames, %lld poses, %lld feature maps published; %lld maps without their "
                    "frame passed over, %lld late\n",
            p.published, p.poses_out, p.maps_out, p.orphans, p.late);
out:
  vlff_ring_close(p.frames);
  vlff_ring_close(p.poses);
  vlff_ring_close(p.feats);
  vlff_in_reader_free(p.in);
  free(p.s.stamp);
  vlff_unmap_file(p.file, p.n);
  return status;
}
