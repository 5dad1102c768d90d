#include "stamps.h"

void vlff_stamps_init(struct vlff_stamps *q) {
  atomic_init(&q->head, 0);
  atomic_init(&q->tail, 0);
  for (int i = 0; i < VLFF_STAMPS_CAP; i++) atomic_init(&q->t[i], 0);
}

void vlff_stamps_push(struct vlff_stamps *q, uint64_t t_ns) {
  uint64_t h = atomic_load_explicit(&q->head, memory_order_relaxed);
  atomic_store_explicit(&q->t[h % VLFF_STAMPS_CAP], t_ns, memory_order_relaxed);
  atomic_store_explicit(&q->head, h + 1, memory_order_release);
}

uint64_t vlff_stamps_match(struct vlff_stamps *q, uint64_t arrival_ns, uint64_t window_ns) {
  uint64_t h = atomic_load_explicit(&q->head, memory_order_acquire);
  uint64_t t = atomic_load_explicit(&q->tail, memory_order_relaxed);
  /* Lapped: the oldest entries were overwritten; they are lost anyway. */
  if (h - t > VLFF_STAMPS_CAP / 2) t = h - VLFF_STAMPS_CAP / 2;
  uint64_t best = 0;
  while (t < h) {
    uint64_t s = atomic_load_explicit(&q->t[t % VLFF_STAMPS_CAP], memory_order_relaxed);
    if (s > arrival_ns) break;
    best = s;
    t++;
  }
  atomic_store_explicit(&q->tail, t, memory_order_relaxed);
  return best && arrival_ns - best <= window_ns ? best : 0;
}
