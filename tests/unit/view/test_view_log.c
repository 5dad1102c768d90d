/*
 * The /log channel (logch.c), in-process: a sequence of status messages as the feed
 * makes them, and the foxglove.Log lines each gives: segments attached and gone, the
 * writer silent and back, the learner's state and error flags, refusals per reason
 * and losses summed to one line per 10 s, a counter that goes back (a restarted
 * node), and the cap on lines per status.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <json-c/json.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "unit.h"
#include "view.h"

#define S 1000000000ull
#define T0 (1700000000ull * S)

struct st {
  int map, writer, frames;
  const char *state; /* NULL: no learner block */
  unsigned flags;
  unsigned long long no_pose, blurry, lost;
};

static struct vlff_view_msg *status(uint64_t t, const struct st *s) {
  char text[1024];
  int n;
  if (s->state)
    n = snprintf(text, sizeof text,
                 "{\"map\":{\"segment\":\"/m\",\"attached\":%s,\"version\":3,\"writer_alive\":%s},"
                 "\"learner\":{\"state\":\"%s\",\"state_code\":1,\"error_flags\":%u,\"frames_lost\":%llu,"
                 "\"refused\":[{\"reason\":\"no pose\",\"count\":%llu},{\"reason\":\"blurry\",\"count\":%llu}]},"
                 "\"frames\":{\"segment\":\"/f\",\"attached\":%s},\"viewer\":{}}",
                 s->map ? "true" : "false", s->writer ? "true" : "false", s->state, s->flags, s->lost, s->no_pose,
                 s->blurry, s->frames ? "true" : "false");
  else
    n = snprintf(text, sizeof text,
                 "{\"map\":{\"segment\":\"/m\",\"attached\":%s,\"version\":0,\"writer_alive\":%s},\"learner\":null,"
                 "\"frames\":{\"segment\":\"/f\",\"attached\":%s},\"viewer\":{}}",
                 s->map ? "true" : "false", s->writer ? "true" : "false", s->frames ? "true" : "false");
  struct vlff_view_msg *m = vlff_view_msg_new(VLFF_VIEW_CH_STATUS, (size_t)n);
  memcpy(vlff_view_msg_payload(m), text, (size_t)n);
  m->len = (size_t)n;
  m->t_ns = t;
  return m;
}

/* The lines one status gives, as "LEVEL name: message" joined by '|'. */
static const char *lines(struct vlff_view_log *l, uint64_t t, const struct st *s, int cap) {
  static char out[2048];
  struct vlff_view_msg *st = status(t, s), *msgs[16];
  int n = vlff_view_log_status(l, st, msgs, cap);
  out[0] = 0;
  for (int i = 0; i < n; i++) {
    assert_int_equal(msgs[i]->channel, VLFF_VIEW_CH_LOG);
    assert_true(msgs[i]->t_ns == t);
    char why[128];
    json_object *o = vlff_view_parse_json((const char *)vlff_view_msg_payload(msgs[i]), msgs[i]->len, why, sizeof why);
    assert_non_null(o);
    json_object *ts = NULL, *sec = NULL, *lv = NULL, *msg = NULL, *name = NULL, *file = NULL, *line = NULL;
    assert_true(json_object_object_get_ex(o, "timestamp", &ts) && json_object_object_get_ex(ts, "sec", &sec));
    assert_true((uint64_t)json_object_get_int64(sec) == t / S);
    assert_true(json_object_object_get_ex(o, "level", &lv) && json_object_object_get_ex(o, "message", &msg) &&
                json_object_object_get_ex(o, "name", &name) && json_object_object_get_ex(o, "file", &file) &&
                json_object_object_get_ex(o, "line", &line));
    static const char *lvl[] = {"?", "DEBUG", "INFO", "WARNING", "ERROR", "FATAL"};
    int level = json_object_get_int(lv);
    assert_true(level >= 2 && level <= 4);
    size_t k = strlen(out);
    snprintf(out + k, sizeof out - k, "%s%s %s: %s", k ? "|" : "", lvl[level], json_object_get_string(name),
             json_object_get_string(msg));
    json_object_put(o);
    if (i == n - 1) {
      struct vlff_view_msg *cur = vlff_view_log_current(l);
      assert_ptr_equal(cur, msgs[i]);
      vlff_view_msg_unref(cur);
    }
    vlff_view_msg_unref(msgs[i]);
  }
  vlff_view_msg_unref(st);
  return out;
}

static void test_lines(void **state) {
  (void)state;
  struct vlff_view_log *l = vlff_view_log_new();
  assert_null(vlff_view_log_current(l));
  struct st s = {0};
  assert_string_equal(lines(l, T0, &s, 16), "WARNING vlff-view: map segment /m not there yet");
  assert_string_equal(lines(l, T0 + S, &s, 16), "");
  s.map = s.writer = s.frames = 1;
  assert_string_equal(lines(l, T0 + 2 * S, &s, 16),
                      "INFO vlff-view: map segment /m attached|INFO vlff-view: frame ring /f attached");
  s.state = "starting";
  assert_string_equal(lines(l, T0 + 3 * S, &s, 16), "INFO vlff-node: learner state starting");
  s.state = "operational";
  s.no_pose = 3;
  assert_string_equal(lines(l, T0 + 4 * S, &s, 16),
                      "INFO vlff-node: learner state operational (was starting)|"
                      "WARNING vlff-node: 3 frames refused: no pose (3 in all)");
  /* within 10 s of that line: summed, not repeated */
  s.no_pose = 10;
  s.blurry = 1;
  assert_string_equal(lines(l, T0 + 5 * S, &s, 16), "WARNING vlff-node: 1 frame refused: blurry (1 in all)");
  s.no_pose = 25;
  assert_string_equal(lines(l, T0 + 9 * S, &s, 16), "");
  assert_string_equal(lines(l, T0 + 14 * S, &s, 16), "WARNING vlff-node: 22 frames refused: no pose (25 in all)");
  s.lost = 7;
  assert_string_equal(lines(l, T0 + 15 * S, &s, 16),
                      "WARNING vlff-node: 7 frames lost: before the node could read them (7 in all)");
  s.flags = 0x5;
  assert_string_equal(lines(l, T0 + 16 * S, &s, 16),
                      "WARNING vlff-node: error flags 0x5: 0x5 set (vlff-node's enum vlff_node_error_flags)");
  s.flags = 0x4;
  assert_string_equal(lines(l, T0 + 17 * S, &s, 16), "INFO vlff-node: error flags 0x4: 0x1 cleared");
  s.writer = 0;
  assert_string_equal(lines(l, T0 + 18 * S, &s, 16),
                      "ERROR vlff-view: the map's writer stopped (vlff-node gone or hung for 2 s)");
  s.writer = 1;
  s.no_pose = 2; /* a restarted node counts from zero: no line, and its new refusals count from there */
  assert_string_equal(lines(l, T0 + 30 * S, &s, 16), "INFO vlff-view: the map's writer is alive again");
  s.no_pose = 6;
  assert_string_equal(lines(l, T0 + 31 * S, &s, 16), "WARNING vlff-node: 4 frames refused: no pose (6 in all)");
  s.map = s.frames = 0;
  /* the cap: one line of the two */
  assert_string_equal(lines(l, T0 + 32 * S, &s, 1),
                      "WARNING vlff-view: map segment /m gone (its writer removed or replaced it)");
  vlff_view_log_free(l);
}

VLFF_UNIT_MAIN(NULL, NULL, cmocka_unit_test(test_lines))
