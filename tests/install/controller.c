/* A controller built against an installed vlff-shm with pkg-config alone:
 * the same file compiles as C and as C++ (the header's promise to C++
 * controllers). It writes a record into a ring it creates, reads it back as
 * a consumer, checks the segment's header through vlff_shm_stat, removes it. */
#include <vlff/shm.h>

#include <stdio.h>
#include <string.h>
#include <unistd.h>

int main(int argc, char **argv) {
  if (argc != 2) {
    fprintf(stderr, "usage: controller /SEGMENT\n");
    return 2;
  }
  const char *name = argv[1];
  struct vlff_ring_params p;
  memset(&p, 0, sizeof p);
  p.record_kind = VLFF_RECORD_RAW;
  p.slots = 4;
  p.slot_size = 256;
  struct vlff_ring *w = vlff_ring_create(name, &p);
  if (!w) {
    fprintf(stderr, "controller: create %s: %s\n", name, vlff_shm_last_message());
    return 1;
  }
  struct vlff_ring *r = vlff_ring_attach(name, VLFF_RECORD_RAW);
  if (!r) {
    fprintf(stderr, "controller: attach %s: %s\n", name, vlff_shm_last_message());
    return 1;
  }
  const char msg[] = "hello from an installed vlff-shm";
  char buf[256];
  struct vlff_ring_view v;
  if (vlff_ring_write(w, msg, sizeof msg) < 0 ||
      vlff_ring_read_copy(r, buf, sizeof buf, &v, 1000000000ull) != (ssize_t)sizeof msg || memcmp(buf, msg, sizeof msg)) {
    fprintf(stderr, "controller: record did not come back: %s\n", vlff_shm_last_message());
    return 1;
  }
  struct vlff_shm_info in;
  if (vlff_shm_stat(name, &in) < 0 || in.kind != VLFF_SHM_KIND_RING || in.head != 1 || in.creator_pid != getpid()) {
    fprintf(stderr, "controller: stat %s disagrees\n", name);
    return 1;
  }
  vlff_ring_close(r);
  vlff_ring_close(w);
  vlff_shm_unlink(name);
  printf("ok %s seq %llu\n", name, (unsigned long long)v.seq);
  return 0;
}
