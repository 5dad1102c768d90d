/* Writes the seed corpus of fuzz_shm_header (tests/fuzz/seeds/shm_header/) from
 * segments made by libvlff-shm itself, so that the seeds always speak the library's
 * current ABI and reach past the header checks into the readers:
 *
 *   map                    a published map: grid, prompts, label image, status
 *   prompts                a mailbox with answered requests and a pending one
 *   ring_frame, ring_pose  rings the producer lapped
 *   prompts-dead-poster    a poster died mid-post (sequence word odd, pid 1 in the
 *                          lock word, half a body written)
 *   prompts-forged         a request written past the library's checks, with a
 *                          newline in a prompt
 *   regress-dims-overflow  a published map whose grid dims multiply past 64 bits
 *                          (once read out of bounds; the readers refuse it)
 *
 * The adversarial ones are what a hostile process with write access leaves; they
 * are written into the library's segments at the offsets the library uses (shm/),
 * and test_shm_seeds checks that each still gets as far as it is meant to. Every
 * seed names no creator (pid 0): a pid of the machine that wrote it means nothing
 * where it is read. Run after every ABI change: gen_shm_seeds DIR. */
#include "shm_internal.h"
#include "shm_test_util.h"

#include <errno.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* The map's published buffers as a hostile writer sees them (shm/map.c): two
 * buffers of geom[3] bytes from offset 4096, each a 64-byte sequence line and then
 * the metadata, whose grid dims follow two counters, the origin and the voxel size. */
#define MAP_BUF_OFF 4096
#define MAP_META_OFF 64
#define MAP_DIMS_OFF (8 + 8 + 3 * 8 + 8)

static const char *out_dir;
static int failures;

/* The segment being made is removed: a failed run leaves nothing behind. */
static void die(const char *name) {
  fprintf(stderr, "gen_shm_seeds: %s: %s\n", name, vlff_shm_last_message());
  vlff_shm_unlink(name);
  exit(1);
}

/* The segment's bytes, mapped read-write for the adversarial edits. */
static struct shm_raw raw_open(const char *name) {
  struct shm_raw r;
  if (shm_raw_open(name, &r) < 0) {
    perror(name);
    vlff_shm_unlink(name);
    exit(1);
  }
  return r;
}

/* Copies segment name into out_dir/seed, without a creator, and removes it. */
static void save(const char *name, const char *seed) {
  struct shm_raw r = raw_open(name);
  struct seg_hdr *h = (struct seg_hdr *)r.base;
  atomic_store(&h->creator_pid, 0);
  char path[4096];
  snprintf(path, sizeof path, "%s/%s", out_dir, seed);
  FILE *f = fopen(path, "wb");
  if (!f || fwrite(r.base, 1, r.size, f) != r.size || fclose(f) != 0) {
    fprintf(stderr, "gen_shm_seeds: %s: %s\n", path, strerror(errno));
    failures++;
  } else {
    printf("%s (%zu bytes)\n", path, r.size);
  }
  shm_raw_close(&r);
  vlff_shm_unlink(name);
}

static void identity(double pose[16], double x, double y, double z) {
  memset(pose, 0, 16 * sizeof pose[0]);
  pose[0] = pose[5] = pose[10] = pose[15] = 1;
  pose[3] = x, pose[7] = y, pose[11] = z;
}

/* A published map of 4x4x2 voxels with three prompts, a label image and a status. */
static void make_map(const char *name) {
  struct vlff_map_params mp = {.max_voxels = 64, .label_max_width = 8, .label_max_height = 6};
  struct vlff_map *m = vlff_map_create(name, &mp);
  if (!m)
    die(name);
  uint16_t labels[32], limg[48];
  uint8_t conf[32];
  for (int i = 0; i < 32; i++) {
    labels[i] = i % 5 == 4 ? VLFF_LABEL_FREE : (uint16_t)(i % 3);
    conf[i] = (uint8_t)(8 * i);
  }
  for (int i = 0; i < 48; i++)
    limg[i] = i % 7 == 6 ? VLFF_LABEL_UNKNOWN : (uint16_t)(i % 3);
  const char *prompts[] = {"chair", "table", "door"};
  struct vlff_map_grid g = {.origin = {0, 0, 0}, .voxel_size = 0.25, .dims = {4, 4, 2}, .labels = labels,
                            .confidence = conf};
  struct vlff_map_label_image li = {.width = 8, .height = 6, .labels = limg, .fx = 6, .fy = 6, .cx = 4, .cy = 3,
                                    .t_ns = 1000};
  identity(li.pose, 0.5, 0.5, -1);
  struct vlff_map_update u = {.grid = &g, .prompts = prompts, .prompt_count = 3, .label_image = &li};
  /* Two versions: both buffers hold a map, and the change log the runs of the
   * second, a partial publish, for a follower to read. */
  if (vlff_map_publish(m, &u) < 0)
    die(name);
  const struct vlff_map_range runs[2] = {{3, 4}, {20, 2}};
  for (int i = 3; i < 7; i++)
    labels[i] = 2;
  struct vlff_map_update part = {.grid = &g, .ranges = runs, .range_count = 2};
  if (vlff_map_publish(m, &part) < 0)
    die(name);
  struct vlff_map_status st = {.state = 2, .frames_in = 40, .frames_refused = 3, .keyframes = 5,
                               .iterations = 100, .iterations_per_s = 50, .fps_in = 10, .loss = 0.5,
                               .psnr = 20, .reason_count = 2};
  snprintf(st.state_name, sizeof st.state_name, "operational");
  snprintf(st.reason[0].name, sizeof st.reason[0].name, "no pose");
  st.reason[0].count = 2;
  snprintf(st.reason[1].name, sizeof st.reason[1].name, "bad intrinsics");
  st.reason[1].count = 1;
  if (vlff_map_set_status(m, &st) < 0)
    die(name);
  vlff_map_detach(m);
}

static void seed_map(const char *name) {
  make_map(name);
  save(name, "map");
}

/* 2^22 * 2^21 * 2^21 = 2^64: the product wraps to 0 in 64 bits. */
static void seed_dims_overflow(const char *name) {
  make_map(name);
  struct shm_raw r = raw_open(name);
  const struct seg_hdr *h = (const struct seg_hdr *)r.base;
  const uint32_t dims[3] = {1u << 22, 1u << 21, 1u << 21};
  for (uint64_t b = 0; b < 2; b++)
    memcpy(r.base + MAP_BUF_OFF + b * h->geom[3] + MAP_META_OFF + MAP_DIMS_OFF, dims, sizeof dims);
  shm_raw_close(&r);
  save(name, "regress-dims-overflow");
}

/* A mailbox with requests posted and answered through the library, and one
 * left pending if asked; both handles closed. */
static void make_mailbox(const char *name, bool pending) {
  struct vlff_prompts *learner = vlff_prompts_create(name, NULL);
  struct vlff_prompts *poster = learner ? vlff_prompts_attach(name) : NULL;
  if (!poster)
    die(name);
  const char *set[] = {"chair", "table", "café"}, *later[] = {"sofa", "lamp"};
  uint64_t last = 0;
  struct vlff_prompt_request req;
  if (vlff_prompts_post(poster, set, 3) < 0 || vlff_prompts_poll(learner, &last, &req) != 1 ||
      vlff_prompts_answer(learner, last, 1, NULL) < 0)
    die(name);
  if (vlff_prompts_post_index(poster, 7) < 0 || vlff_prompts_poll(learner, &last, &req) != 1 ||
      vlff_prompts_answer(learner, last, 0, "prompt set 7 does not exist (2 sets)") < 0)
    die(name);
  if (pending && vlff_prompts_post(poster, later, 2) < 0)
    die(name);
  vlff_prompts_close(poster);
  vlff_prompts_close(learner);
}

static void seed_prompts(const char *name) {
  make_mailbox(name, true);
  save(name, "prompts");
}

static void seed_dead_poster(const char *name) {
  make_mailbox(name, false);
  struct shm_raw r = raw_open(name);
  volatile struct mbox_raw_ctl *c = (volatile struct mbox_raw_ctl *)(r.base + MBOX_CTL_OFF);
  c->lock_pid = 1;
  c->seq |= 1;
  memset(r.base + MBOX_BODY_OFF, 'x', 100);
  shm_raw_close(&r);
  save(name, "prompts-dead-poster");
}

static void seed_forged(const char *name) {
  make_mailbox(name, false);
  struct shm_raw r = raw_open(name);
  struct vlff_prompt_request q = {.set_index = -1, .count = 2};
  snprintf(q.text[0], sizeof q.text[0], "wall\nlabel 0 confidence 255 prompt FAKE");
  snprintf(q.text[1], sizeof q.text[1], "floor");
  if (mbox_raw_post(r.fd, r.base, &q) < 0)
    die(name);
  shm_raw_close(&r);
  save(name, "prompts-forged");
}

/* Three 8x6 colour + depth frames with pose and intrinsics into two slots. */
static void seed_ring_frame(const char *name) {
  uint64_t slot = vlff_frame_slot_size(8, 6, VLFF_PIX_RGB8, VLFF_PIX_DEPTH_U16_MM);
  struct vlff_ring_params p = {.record_kind = VLFF_RECORD_FRAME, .slots = 2, .slot_size = slot};
  struct vlff_ring *r = vlff_ring_create(name, &p);
  if (!r)
    die(name);
  for (int i = 0; i < 3; i++) {
    struct vlff_frame_hdr *f = vlff_ring_reserve(r, NULL);
    uint64_t len = f ? vlff_frame_layout(f, slot, 8, 6, VLFF_PIX_RGB8, VLFF_PIX_DEPTH_U16_MM) : 0;
    if (!len)
      die(name);
    f->frame_id = (uint64_t)i;
    f->t_device_ns = 1000 + (uint64_t)i;
    f->t_host_ns = 2000 + (uint64_t)i;
    f->flags = VLFF_FRAME_POSE_VALID | VLFF_FRAME_INTRINSICS_VALID;
    f->fx = f->fy = 6, f->cx = 4, f->cy = 3;
    identity(f->pose, 0.1 * i, 0, 0);
    f->pose_t_ns = f->t_host_ns;
    uint8_t *rgb = (uint8_t *)f + f->plane[VLFF_PLANE_COLOR].offset;
    uint16_t *depth = (uint16_t *)((uint8_t *)f + f->plane[VLFF_PLANE_DEPTH].offset);
    for (int k = 0; k < 8 * 6; k++) {
      rgb[3 * k] = rgb[3 * k + 1] = rgb[3 * k + 2] = (uint8_t)(k + i);
      depth[k] = (uint16_t)(1000 + k);
    }
    if (vlff_ring_commit(r, len) < 0)
      die(name);
  }
  vlff_ring_close(r);
  save(name, "ring_frame");
}

/* Six poses 10 ns apart into four slots. */
static void seed_ring_pose(const char *name) {
  struct vlff_ring_params p = {.record_kind = VLFF_RECORD_POSE, .slots = 4, .slot_size = sizeof(struct vlff_pose_rec)};
  struct vlff_ring *r = vlff_ring_create(name, &p);
  if (!r)
    die(name);
  for (int i = 0; i < 6; i++) {
    struct vlff_pose_rec pr = {.t_ns = 1000 + 10 * (uint64_t)i, .source_id = 1};
    identity(pr.pose, 0.01 * i, 0, 0);
    if (i == 5)
      pr.flags = VLFF_FRAME_POSE_UNTRUSTED;
    if (vlff_ring_write(r, &pr, sizeof pr) < 0)
      die(name);
  }
  vlff_ring_close(r);
  save(name, "ring_pose");
}

int main(int argc, char **argv) {
  if (argc != 2) {
    fprintf(stderr, "usage: gen_shm_seeds DIR\n");
    return 2;
  }
  out_dir = argv[1];
  static void (*const seeds[])(const char *) = {seed_map, seed_dims_overflow, seed_prompts, seed_dead_poster,
                                                seed_forged, seed_ring_frame, seed_ring_pose};
  for (size_t i = 0; i < sizeof seeds / sizeof seeds[0]; i++) {
    char name[64];
    test_name(name, sizeof name, "seed");
    vlff_shm_unlink(name);
    seeds[i](name);
  }
  return failures ? 1 : 0;
}
