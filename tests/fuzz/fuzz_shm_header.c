/* Attach-validation on arbitrary bytes: the fuzzed input becomes the content of a
 * shared-memory segment, which is then attached as every kind of segment and, when
 * attach succeeds, read through the reader calls. Nothing may crash or read out of
 * bounds; failures must come with an error code. */
#include "vlff/shm.h"

#include <errno.h>
#include <fcntl.h>
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/mman.h>
#include <unistd.h>

/* shm/map.c: the map's `current` buffer word follows the 128-byte segment header. */
#define MAP_CURRENT_OFF 128

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size) {
  static char name[64];
  if (!name[0])
    snprintf(name, sizeof name, "/vlff-fuzz-hdr-%d", (int)getpid());
  if (size > (1u << 20))
    return 0;
  int fd = shm_open(name, O_RDWR | O_CREAT | O_TRUNC, 0600);
  if (fd < 0)
    abort();
  if (size && write(fd, data, size) != (ssize_t)size)
    abort();
  close(fd);
  struct vlff_shm_info info;
  if (vlff_shm_stat(name, &info) < 0 && vlff_shm_last_error() == VLFF_SHM_OK)
    abort();
  struct vlff_ring *r = vlff_ring_attach(name, VLFF_RECORD_ANY);
  if (r) {
    static uint8_t buf[1 << 16];
    struct vlff_ring_view v;
    vlff_ring_seek_oldest(r);
    for (int i = 0; i < 4 && vlff_ring_read_begin(r, &v, 0) == 0; i++) {
      memcpy(buf, v.data, v.len < sizeof buf ? v.len : sizeof buf);
      if (vlff_ring_read_end(r, &v) == 0 && v.len <= sizeof buf)
        (void)vlff_frame_validate(buf, v.len);
    }
    (void)vlff_ring_read_latest(r, buf, sizeof buf, &v);
    struct vlff_pose_rec pr;
    (void)vlff_pose_lookup(r, 1000, 100, &pr);
    vlff_ring_close(r);
  } else if (vlff_shm_last_error() == VLFF_SHM_OK) {
    abort();
  }
  struct vlff_map *m = vlff_map_attach(name);
  if (m) {
    uint16_t l;
    uint8_t c;
    char text[64];
    (void)vlff_map_label_at(m, 0.5, 0.5, 0.5, &l, &c);
    /* A non-finite point is refused whatever the segment holds. */
    if (vlff_map_label_at(m, 0.5, NAN, 0.5, &l, &c) != -1 || errno != EINVAL)
      abort();
    (void)vlff_map_prompt(m, 0, text, sizeof text);
    struct vlff_map_snapshot *s = vlff_map_snapshot_new(m);
    if (s && vlff_map_snapshot_take(m, s) == 0)
      (void)vlff_map_snapshot_label_at(s, 0.1, 0.2, 0.3, &c);
    /* The change log: the other buffer made current (an older version, or
     * anything) is followed, then the current one again, from the log. */
    int mfd = shm_open(name, O_RDWR, 0);
    void *base = mfd >= 0 ? mmap(NULL, 4096, PROT_READ | PROT_WRITE, MAP_SHARED, mfd, 0) : MAP_FAILED;
    if (s && base != MAP_FAILED && size >= MAP_CURRENT_OFF + 4) {
      volatile uint32_t *current = (volatile uint32_t *)((uint8_t *)base + MAP_CURRENT_OFF);
      const struct vlff_map_range *runs;
      *current ^= 1;
      (void)vlff_map_snapshot_follow(m, s);
      *current ^= 1;
      if (vlff_map_snapshot_follow(m, s) >= 0) {
        (void)vlff_map_snapshot_changes(s, &runs, NULL);
        (void)vlff_map_snapshot_label_at(s, 0.1, 0.2, 0.3, &c);
      }
    }
    if (base != MAP_FAILED)
      munmap(base, 4096);
    if (mfd >= 0)
      close(mfd);
    vlff_map_snapshot_free(s);
    vlff_map_detach(m);
  }
  struct vlff_prompts *p = vlff_prompts_attach(name);
  if (p) {
    uint64_t last = 0;
    struct vlff_prompt_request *req = malloc(sizeof *req);
    (void)vlff_prompts_poll(p, &last, req);
    free(req);
    vlff_prompts_close(p);
  }
  shm_unlink(name);
  return 0;
}
