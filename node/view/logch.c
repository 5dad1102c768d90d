/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * logch.c - the /log channel (foxglove.Log): what the node's status block and the
 * segments report, as the lines an operator reads in Foxglove's Log panel.
 *
 * It reads the status messages the feed makes (the /vlff/status JSON) rather than
 * the segments, so that it sees exactly what clients see and the feed stays the one
 * reader of the segments. A line is made when something changes between two
 * statuses: the map or frame segment attached or gone, the map's writer alive or
 * silent, the learner's state, its error flags, and frames refused (per reason) or
 * lost. Refusals and losses, which can come with every frame, are summed: one line
 * per reason at most every REPEAT_S seconds, with the count since the last line.
 */
#include <json-c/json.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "json.h"
#include "view.h"

#define REPEAT_S 10
#define MAX_REASONS 32

/* foxglove.LogLevel */
enum { L_INFO = 2, L_WARNING = 3, L_ERROR = 4 };

struct counted {
  char name[64];
  uint64_t count, reported; /* the status' count, the count the last line gave */
  uint64_t t_ns;            /* when that line was made */
};

struct vlff_view_log {
  int seen;
  int map_attached, frames_attached, writer_alive, has_learner;
  char state[64];
  unsigned flags;
  struct counted reasons[MAX_REASONS + 1]; /* the last: frames lost */
  int nreasons;
  struct vlff_view_msg *latest;
};

struct vlff_view_log *vlff_view_log_new(void) { return calloc(1, sizeof(struct vlff_view_log)); }

void vlff_view_log_free(struct vlff_view_log *l) {
  if (!l) return;
  vlff_view_msg_unref(l->latest);
  free(l);
}

struct vlff_view_msg *vlff_view_log_current(struct vlff_view_log *l) { return vlff_view_msg_ref(l->latest); }

static void line(struct vlff_view_log *l, uint64_t t_ns, int level, const char *name, const char *text,
                 struct vlff_view_msg **out, int cap, int *n) {
  if (*n >= cap) return;
  struct jw w = {vlff_view_msg_new(VLFF_VIEW_CH_LOG, 256 + strlen(text)), 0};
  if (!w.m) return;
  w.m->t_ns = t_ns;
  jw_s(&w, "{\"timestamp\":");
  jw_time(&w, t_ns);
  jw_f(&w, ",\"level\":%d,\"message\":", level);
  jw_str(&w, text);
  jw_s(&w, ",\"name\":");
  jw_str(&w, name);
  jw_s(&w, ",\"file\":\"\",\"line\":0}");
  struct vlff_view_msg *m = jw_finish(&w);
  if (!m) return;
  vlff_view_msg_unref(l->latest);
  l->latest = vlff_view_msg_ref(m);
  out[(*n)++] = m;
}

static json_object *member(json_object *o, const char *k) {
  json_object *x = NULL;
  return o && json_object_object_get_ex(o, k, &x) ? x : NULL;
}

static int flag(json_object *o, const char *k) { return json_object_get_boolean(member(o, k)); }

/* A refusal reason's (or the losses') count: a line when it rose and the last
 * line for it is REPEAT_S old (or there was none). */
static void counted(struct vlff_view_log *l, struct counted *c, uint64_t count, uint64_t t_ns, const char *what,
                    struct vlff_view_msg **out, int cap, int *n) {
  c->count = count;
  if (count <= c->reported) {
    c->reported = count; /* a counter that went back: a restarted node */
    return;
  }
  if (c->t_ns && t_ns - c->t_ns < (uint64_t)REPEAT_S * 1000000000u) return;
  char text[200];
  snprintf(text, sizeof text, "%llu frame%s %.16s: %.63s (%llu in all)", (unsigned long long)(count - c->reported),
           count - c->reported == 1 ? "" : "s", what, c->name, (unsigned long long)count);
  line(l, t_ns, L_WARNING, "vlff-node", text, out, cap, n);
  c->reported = count;
  c->t_ns = t_ns;
}

int vlff_view_log_status(struct vlff_view_log *l, const struct vlff_view_msg *status, struct vlff_view_msg **out,
                         int cap) {
  char why[128];
  json_object *s = vlff_view_parse_json((const char *)status->buf + vlff_view_headroom(), status->len, why,
                                        sizeof why);
  if (!s) return 0;
  uint64_t t = status->t_ns;
  int n = 0;
  char text[256];
  json_object *map = member(s, "map"), *frames = member(s, "frames"), *learner = member(s, "learner");
  const char *map_name = json_object_get_string(member(map, "segment"));
  const char *frames_name = json_object_get_string(member(frames, "segment"));
  int map_attached = flag(map, "attached"), writer = flag(map, "writer_alive"), frames_attached = flag(frames, "attached");
  if (map_attached != l->map_attached || !l->seen) {
    snprintf(text, sizeof text, "map segment %.100s %s", map_name ? map_name : "?",
             map_attached ? "attached" : l->seen ? "gone (its writer removed or replaced it)" : "not there yet");
    line(l, t, map_attached ? L_INFO : L_WARNING, "vlff-view", text, out, cap, &n);
  }
  if (map_attached && (l->seen ? l->map_attached && writer != l->writer_alive : !writer)) {
    line(l, t, writer ? L_INFO : L_ERROR, "vlff-view",
         writer ? "the map's writer is alive again" : "the map's writer stopped (vlff-node gone or hung for 2 s)", out,
         cap, &n);
  }
  if (frames_name && *frames_name && (frames_attached != l->frames_attached || !l->seen) &&
      (frames_attached || l->seen)) {
    snprintf(text, sizeof text, "frame ring %.100s %s", frames_name, frames_attached ? "attached" : "gone");
    line(l, t, frames_attached ? L_INFO : L_WARNING, "vlff-view", text, out, cap, &n);
  }
  l->map_attached = map_attached;
  l->writer_alive = writer;
  l->frames_attached = frames_attached;

  if (learner && json_object_is_type(learner, json_type_object)) {
    const char *state = json_object_get_string(member(learner, "state"));
    unsigned flags = (unsigned)json_object_get_int64(member(learner, "error_flags"));
    if (state && (!l->has_learner || strcmp(state, l->state))) {
      if (l->has_learner) snprintf(text, sizeof text, "learner state %.63s (was %.63s)", state, l->state);
      else snprintf(text, sizeof text, "learner state %.63s", state);
      line(l, t, L_INFO, "vlff-node", text, out, cap, &n);
      snprintf(l->state, sizeof l->state, "%.63s", state);
    }
    if (flags != l->flags && (l->has_learner || flags)) {
      unsigned set = flags & ~l->flags, cleared = l->flags & ~flags;
      if (set) snprintf(text, sizeof text, "error flags 0x%x: 0x%x set (vlff-node's enum vlff_node_error_flags)", flags, set);
      else snprintf(text, sizeof text, "error flags 0x%x: 0x%x cleared", flags, cleared);
      line(l, t, set ? L_WARNING : L_INFO, "vlff-node", text, out, cap, &n);
    }
    l->flags = flags;
    l->has_learner = 1;
    json_object *refused = member(learner, "refused");
    size_t nr = json_object_is_type(refused, json_type_array) ? json_object_array_length(refused) : 0;
    for (size_t i = 0; i < nr; i++) {
      json_object *r = json_object_array_get_idx(refused, i);
      const char *reason = json_object_get_string(member(r, "reason"));
      uint64_t count = (uint64_t)json_object_get_int64(member(r, "count"));
      if (!reason) continue;
      struct counted *c = NULL;
      for (int k = 0; k < l->nreasons && !c; k++)
        if (!strncmp(l->reasons[k].name, reason, sizeof l->reasons[k].name - 1)) c = &l->reasons[k];
      if (!c && l->nreasons < MAX_REASONS) {
        c = &l->reasons[l->nreasons++];
        snprintf(c->name, sizeof c->name, "%.63s", reason);
      }
      if (c) counted(l, c, count, t, "refused", out, cap, &n);
    }
    struct counted *lost = &l->reasons[MAX_REASONS];
    snprintf(lost->name, sizeof lost->name, "%s", "before the node could read them");
    counted(l, lost, (uint64_t)json_object_get_int64(member(learner, "frames_lost")), t, "lost", out, cap, &n);
  }
  l->seen = 1;
  json_object_put(s);
  return n;
}
