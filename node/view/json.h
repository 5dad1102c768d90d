/* SPDX-License-Identifier: BSD-3-Clause */
/* json.h - the viewer's append-only JSON writer into a shared message (msg.c). */
#ifndef VLFF_VIEW_JSON_H
#define VLFF_VIEW_JSON_H

#include "view.h"

struct jw {
  struct vlff_view_msg *m;
  int failed;
};

void jw_raw(struct jw *w, const char *s, size_t n);
void jw_s(struct jw *w, const char *s);                              /* verbatim */
void jw_f(struct jw *w, const char *fmt, ...) __attribute__((format(printf, 2, 3)));
void jw_str(struct jw *w, const char *s);                            /* quoted, escaped */
void jw_b64(struct jw *w, const uint8_t *d, size_t n);               /* quoted base64 */
void jw_time(struct jw *w, uint64_t t_ns);                           /* foxglove Time */
/* The message, or NULL (and the message freed) if an allocation failed. */
struct vlff_view_msg *jw_finish(struct jw *w);

#endif
