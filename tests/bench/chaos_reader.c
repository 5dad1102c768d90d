/* chaos_reader - a controller reading the map while everything around it is killed
 * (tests/bench/chaos.sh). It takes snapshots as fast as the map changes and counts
 * two kinds of wrong result:
 *   torn       two snapshots of the same map version whose contents differ (one of
 *              them mixed two versions: a version number names exactly one map);
 *   backwards  a version lower than the highest one any incarnation of this reader
 *              has seen (kept in STATE, so a reader killed and restarted checks
 *              across node restarts too).
 * Each event is appended to STATE.events as one line the moment it is seen, since
 * this process may be killed at any instant. Usage: chaos_reader MAP STATE */
#include "vlff/shm.h"

#include <errno.h>
#include <fcntl.h>
#include <inttypes.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

static void event(const char *state, const char *fmt, uint64_t a, uint64_t b) {
  char path[512], line[128];
  snprintf(path, sizeof path, "%s.events", state);
  int fd = open(path, O_WRONLY | O_CREAT | O_APPEND, 0644);
  if (fd < 0)
    return;
  int n = snprintf(line, sizeof line, fmt, a, b);
  if (write(fd, line, (size_t)n) != n)
    perror("chaos_reader: events");
  close(fd);
}

static uint64_t load_max(const char *state) {
  FILE *f = fopen(state, "r");
  uint64_t v = 0;
  if (f) {
    if (fscanf(f, "%" SCNu64, &v) != 1)
      v = 0;
    fclose(f);
  }
  return v;
}

/* Written in place with a fixed width, so a kill mid-write leaves a number. */
static void store_max(const char *state, uint64_t v) {
  int fd = open(state, O_WRONLY | O_CREAT, 0644);
  if (fd < 0)
    return;
  char b[24];
  int n = snprintf(b, sizeof b, "%020" PRIu64 "\n", v);
  if (pwrite(fd, b, (size_t)n, 0) != n)
    perror("chaos_reader: state");
  close(fd);
}

static int same_content(const struct vlff_map_info *a, const struct vlff_map_info *b) {
  if (a->prompt_count != b->prompt_count || memcmp(a->grid.dims, b->grid.dims, sizeof a->grid.dims) ||
      a->has_label_image != b->has_label_image)
    return 0;
  size_t n = (size_t)a->grid.dims[0] * a->grid.dims[1] * a->grid.dims[2];
  if (n && (memcmp(a->grid.labels, b->grid.labels, 2 * n) || memcmp(a->grid.confidence, b->grid.confidence, n)))
    return 0;
  if (a->has_label_image) {
    size_t m = (size_t)a->label_image.width * a->label_image.height;
    if (a->label_image.width != b->label_image.width || a->label_image.height != b->label_image.height ||
        memcmp(a->label_image.labels, b->label_image.labels, 2 * m))
      return 0;
  }
  return 1;
}

int main(int argc, char **argv) {
  if (argc != 3) {
    fprintf(stderr, "usage: chaos_reader MAP STATE\n");
    return 2;
  }
  const char *name = argv[1], *state = argv[2];
  uint64_t maxv = load_max(state);
  for (;;) {
    struct vlff_map *m = vlff_map_attach(name);
    if (!m) {
      nanosleep(&(struct timespec){0, 10000000}, NULL);
      continue;
    }
    struct vlff_map_snapshot *s[2] = {vlff_map_snapshot_new(m), vlff_map_snapshot_new(m)};
    if (!s[0] || !s[1])
      return 1;
    int cur = 0;
    uint64_t prev = 0;
    for (;;) {
      if (vlff_map_snapshot_take(m, s[cur]) < 0) {
        if (errno == EAGAIN)
          continue;
        break; /* abandoned or truncated: attach again */
      }
      struct vlff_map_info in, pin;
      vlff_map_snapshot_info(s[cur], &in);
      if (in.version) {
        if (in.version < maxv)
          event(state, "backwards %" PRIu64 " after %" PRIu64 "\n", in.version, maxv);
        if (in.version == prev) {
          vlff_map_snapshot_info(s[cur ^ 1], &pin);
          if (!same_content(&in, &pin))
            event(state, "torn %" PRIu64 " %" PRIu64 "\n", in.version, 0);
        }
        if (in.version > maxv) {
          maxv = in.version;
          store_max(state, maxv);
        }
        if (in.version != prev) {
          prev = in.version;
          cur ^= 1;
        }
      }
      nanosleep(&(struct timespec){0, 5000000}, NULL);
    }
    vlff_map_snapshot_free(s[0]);
    vlff_map_snapshot_free(s[1]);
    vlff_map_detach(m);
  }
}
