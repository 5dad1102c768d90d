/* In-memory sink: a plain array of slots standing in for the shm ring. */
#include "sink.h"
#include "mem.h"

#include <vlff/shm.h>

#include <stdlib.h>
#include <stdio.h>

struct vlff_memsink {
  struct vlff_sink sink;
  int slots, max_w, max_h;
  uint64_t committed;
  struct vlff_sink_frame *frames;
  uint8_t **color;
  float **depth;
};

static int reserve(struct vlff_sink *s, struct vlff_sink_frame *f, char *err, size_t errlen) {
  struct vlff_memsink *m = s->ctx;
  if (f->width <= 0 || f->height <= 0 || f->width > m->max_w || f->height > m->max_h) {
    snprintf(err, errlen, "frame %dx%d does not fit a %dx%d slot", f->width, f->height, m->max_w, m->max_h);
    return -1;
  }
  int i = (int)(m->committed % (uint64_t)m->slots);
  f->slot = (void *)(intptr_t)i;
  f->color = f->color_format != VLFF_PIX_NONE ? m->color[i] : NULL; /* a range camera's frame: depth only */
  f->color_stride = (size_t)m->max_w * (f->color_format == VLFF_PIX_MONO16 ? 2 : 3);
  f->depth = f->depth_format ? (void *)m->depth[i] : NULL;
  f->depth_stride = f->depth_format == VLFF_DEPTH_FMT_U16_MM ? (size_t)m->max_w * 2 : (size_t)m->max_w * 4;
  return 0;
}

static int commit(struct vlff_sink *s, struct vlff_sink_frame *f) {
  struct vlff_memsink *m = s->ctx;
  m->frames[(intptr_t)f->slot] = *f;
  m->committed++;
  return 0;
}

static void abort_frame(struct vlff_sink *s, struct vlff_sink_frame *f) { (void)s, (void)f; }

struct vlff_memsink *vlff_memsink_new(int slots, int max_w, int max_h) {
  struct vlff_memsink *m = calloc(1, sizeof *m);
  if (!m) return NULL;
  m->slots = slots;
  m->max_w = max_w;
  m->max_h = max_h;
  m->frames = calloc((size_t)slots, sizeof *m->frames);
  m->color = calloc((size_t)slots, sizeof *m->color);
  m->depth = calloc((size_t)slots, sizeof *m->depth);
  if (!m->frames || !m->color || !m->depth) goto fail;
  for (int i = 0; i < slots; i++) {
    m->color[i] = malloc((size_t)max_w * max_h * 3);
    m->depth[i] = malloc((size_t)max_w * max_h * 4);
    if (!m->color[i] || !m->depth[i]) goto fail;
  }
  m->sink = (struct vlff_sink){reserve, commit, abort_frame, m};
  return m;
fail:
  vlff_memsink_free(m);
  return NULL;
}

void vlff_memsink_free(struct vlff_memsink *m) {
  if (!m) return;
  for (int i = 0; i < m->slots; i++) {
    if (m->color) free(m->color[i]);
    if (m->depth) free(m->depth[i]);
  }
  VLFF_FREE_ALL(m->color, m->depth, m->frames, m);
}

struct vlff_sink *vlff_memsink_sink(struct vlff_memsink *m) { return &m->sink; }

uint64_t vlff_memsink_committed(const struct vlff_memsink *m) { return m->committed; }

const struct vlff_sink_frame *vlff_memsink_get(const struct vlff_memsink *m, int i) {
  if (i < 0 || (uint64_t)i >= m->committed || i >= m->slots) return NULL;
  uint64_t n = m->committed - 1 - (uint64_t)i;
  return &m->frames[n % (uint64_t)m->slots];
}
