/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * msg.c - the viewer's shared messages and the JSON writer that fills them.
 *
 * A message is written once and sent to every subscriber: its buffer starts with
 * headroom for libwebsockets' frame header and the Foxglove binary header, which the
 * server overwrites per client just before each write, so that ten clients cost ten
 * writes and no copies. Large payloads (a whole map, a camera image) are appended by
 * hand rather than as a json-c tree: a tree would hold several objects per cube.
 */
#include "json.h"

#include <libwebsockets.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

size_t vlff_view_headroom(void) { return LWS_PRE + VLFF_VIEW_FOX_HDR; }

struct vlff_view_msg *vlff_view_msg_new(int channel, size_t cap) {
  struct vlff_view_msg *m = calloc(1, sizeof *m);
  if (!m) return NULL;
  if (cap < 256) cap = 256;
  m->buf = malloc(vlff_view_headroom() + cap);
  if (!m->buf) {
    free(m);
    return NULL;
  }
  m->refs = 1;
  m->channel = channel;
  m->cap = cap;
  return m;
}

unsigned char *vlff_view_msg_payload(struct vlff_view_msg *m) { return m->buf + vlff_view_headroom(); }

struct vlff_view_msg *vlff_view_msg_ref(struct vlff_view_msg *m) {
  if (m) m->refs++;
  return m;
}

void vlff_view_msg_unref(struct vlff_view_msg *m) {
  while (m && --m->refs == 0) {
    struct vlff_view_msg *next = m->next;
    free(m->buf);
    free(m);
    m = next; /* the pieces after it go with it, unless shared */
  }
}

/* The writer remembers a failed allocation and refuses the message at the end
 * (jw_ok), so call sites stay one line each. */
static int reserve(struct jw *w, size_t more) {
  struct vlff_view_msg *m = w->m;
  if (w->failed) return -1;
  if (m->len + more <= m->cap) return 0;
  size_t cap = m->cap * 2;
  while (cap < m->len + more) cap *= 2;
  unsigned char *b = realloc(m->buf, vlff_view_headroom() + cap);
  if (!b) {
    w->failed = 1;
    return -1;
  }
  m->buf = b;
  m->cap = cap;
  return 0;
}

void jw_raw(struct jw *w, const char *s, size_t n) {
  if (reserve(w, n)) return;
  memcpy(vlff_view_msg_payload(w->m) + w->m->len, s, n);
  w->m->len += n;
}

void jw_s(struct jw *w, const char *s) { jw_raw(w, s, strlen(s)); }

void jw_f(struct jw *w, const char *fmt, ...) {
  char tmp[256];
  va_list ap;
  va_start(ap, fmt);
  int n = vsnprintf(tmp, sizeof tmp, fmt, ap);
  va_end(ap);
  if (n < 0) {
    w->failed = 1;
  } else if ((size_t)n < sizeof tmp) {
    jw_raw(w, tmp, (size_t)n);
  } else if (!reserve(w, (size_t)n + 1)) {
    /* a long line (a huge coordinate printed in full): straight into the message */
    va_start(ap, fmt);
    vsnprintf((char *)vlff_view_msg_payload(w->m) + w->m->len, (size_t)n + 1, fmt, ap);
    va_end(ap);
    w->m->len += (size_t)n;
  }
}

void jw_str(struct jw *w, const char *s) {
  jw_raw(w, "\"", 1);
  for (const unsigned char *p = (const unsigned char *)s; *p; p++) {
    if (*p == '"' || *p == '\\') {
      char e[2] = {'\\', (char)*p};
      jw_raw(w, e, 2);
    } else if (*p < 0x20) {
      jw_f(w, "\\u%04x", *p);
    } else {
      jw_raw(w, (const char *)p, 1);
    }
  }
  jw_raw(w, "\"", 1);
}

void jw_b64(struct jw *w, const uint8_t *d, size_t n) {
  static const char tab[] = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
  if (reserve(w, (n + 2) / 3 * 4 + 2)) return;
  char *o = (char *)vlff_view_msg_payload(w->m) + w->m->len;
  char *start = o;
  *o++ = '"';
  size_t i = 0;
  for (; i + 3 <= n; i += 3) {
    uint32_t v = (uint32_t)d[i] << 16 | (uint32_t)d[i + 1] << 8 | d[i + 2];
    *o++ = tab[v >> 18];
    *o++ = tab[(v >> 12) & 63];
    *o++ = tab[(v >> 6) & 63];
    *o++ = tab[v & 63];
  }
  if (i < n) {
    uint32_t v = (uint32_t)d[i] << 16 | (i + 1 < n ? (uint32_t)d[i + 1] << 8 : 0);
    *o++ = tab[v >> 18];
    *o++ = tab[(v >> 12) & 63];
    *o++ = i + 1 < n ? tab[(v >> 6) & 63] : '=';
    *o++ = '=';
  }
  *o++ = '"';
  w->m->len += (size_t)(o - start);
}

void jw_time(struct jw *w, uint64_t t_ns) {
  jw_f(w, "{\"sec\":%llu,\"nsec\":%u}", (unsigned long long)(t_ns / 1000000000u), (unsigned)(t_ns % 1000000000u));
}

struct vlff_view_msg *jw_finish(struct jw *w) {
  if (w->failed) {
    vlff_view_msg_unref(w->m);
    w->m = NULL;
    fprintf(stderr, "vlff-view: out of memory building a message\n");
  }
  return w->m;
}
