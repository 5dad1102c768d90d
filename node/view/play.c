/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * play.c - an MCAP recording served as if live (vlff-view --play; view.h).
 *
 * The file is mapped and walked once when opened, so that every error it holds
 * (mcap.h's checks) is found before a client connects rather than in the middle
 * of a playback; playing then walks it again, one message ahead. The pages
 * walked go back as the walks pass them (vlff_unread_mapped_paced), so a
 * recording larger than memory plays through a bounded resident set; one cut
 * short while it is played ends vlff-view with status 1 and says so
 * (vlff_map_exit_on_sigbus).
 */
#include <libwebsockets.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "files.h"
#include "log.h"
#include "mcap.h"
#include "view.h"
#include "vlff/escape.h"

struct vlff_view_play {
  const uint8_t *file; /* mapped */
  size_t len, given_back;
  struct vlff_mcap_reader *r;
  int nch;
  uint16_t mcap_id[VLFF_VIEW_CH_MAX + 1];
  struct vlff_view_chan ch[VLFF_VIEW_CH_MAX + 1];
  char *b64[VLFF_VIEW_CH_MAX + 1]; /* binary schemas (protobuf) as advertised: base64 */
  struct vlff_view_msg *latest[VLFF_VIEW_CH_MAX + 1];
  uint64_t total, sent;
  int started, done, have_next;
  uint64_t t0_log, t0_now, prev_log;
  double rate;
  struct vlff_mcap_message next;
};

/* Text advertised to clients as JSON strings: UTF-8 without NUL. */
static int utf8_ok(const char *s, size_t n) {
  for (size_t i = 0; i < n;) {
    unsigned long cp;
    size_t k = (unsigned char)s[i] < 0x80 ? (s[i] != 0) : vlff_utf8_len((const unsigned char *)s + i, n - i, &cp);
    if (!k) return 0;
    i += k;
  }
  return 1;
}

/* Log times are the recorder's wall clock: a clock stepped while recording (NTP
 * setting a robot's clock that started at 1970) leaves a jump of years between two
 * messages. A forward jump longer than this is played without waiting, as a step
 * back is (the writer records a time before the previous as the previous). */
#define PLAY_MAX_GAP_NS (60ull * 1000000000ull)

static int view_channel(const struct vlff_view_play *p, uint16_t id) {
  for (int i = 1; i <= p->nch; i++)
    if (p->mcap_id[i] == id) return i;
  return 0;
}

struct vlff_view_play *vlff_view_play_open(const char *path) {
  char why[512];
  struct vlff_view_play *p = calloc(1, sizeof *p);
  if (!p) return NULL;
  if (vlff_map_file(path, VLFF_MCAP_MAX_FILE, &p->file, &p->len, why, sizeof why) != 0) {
    fprintf(stderr, "vlff-view: --play %s\n", why);
    free(p);
    return NULL;
  }
  vlff_map_exit_on_sigbus("vlff-view: --play", path);
  p->r = vlff_mcap_reader_new(p->file, p->len, why, sizeof why);
  struct vlff_mcap_message m;
  int rc = p->r ? 1 : -1;
  uint64_t prev = 0, jumps = 0, largest = 0, largest_at = 0;
  while (rc == 1 && (rc = vlff_mcap_next(p->r, &m, why, sizeof why)) == 1) {
    vlff_unread_mapped_paced(p->file, &p->given_back, vlff_mcap_consumed(p->r));
    if (p->total && m.log_ns > prev && m.log_ns - prev > PLAY_MAX_GAP_NS) {
      jumps++;
      if (m.log_ns - prev > largest) largest = m.log_ns - prev, largest_at = p->total;
    }
    if (!p->total || m.log_ns > prev) prev = m.log_ns;
    p->total++;
  }
  if (rc < 0) {
    fprintf(stderr, "vlff-view: --play %s: %s\n", VLFF_Q(path), why);
    vlff_view_play_free(p);
    return NULL;
  }
  if (jumps)
    vlff_log(VLFF_LOG_WARN, "vlff-view",
             "--play %s: %llu jump%s of more than %llu s between messages' log times (the largest %.0f s, before "
             "message %llu: the recorder's clock stepped?): played without waiting",
             VLFF_Q(path), (unsigned long long)jumps, jumps == 1 ? "" : "s", PLAY_MAX_GAP_NS / 1000000000ull,
             (double)largest * 1e-9, (unsigned long long)largest_at + 1);
  uint64_t at;
  if (vlff_mcap_truncated(p->r, &at))
    vlff_log(VLFF_LOG_WARN, "vlff-view",
             "--play %s: the file ends at byte %llu without its summary (a recorder stopped before closing it): "
             "playing the %llu messages of its whole chunks",
             VLFF_Q(path), (unsigned long long)at, (unsigned long long)p->total);
  int n = vlff_mcap_channel_count(p->r);
  if (n > VLFF_VIEW_CH_MAX) {
    fprintf(stderr, "vlff-view: --play %s: %d channels, more than the %d vlff-view serves\n", VLFF_Q(path), n,
            VLFF_VIEW_CH_MAX);
    vlff_view_play_free(p);
    return NULL;
  }
  for (int i = 0; i < n; i++) {
    const struct vlff_mcap_channel *c = vlff_mcap_channel_at(p->r, i);
    /* a protobuf schema is a FileDescriptorSet's bytes, which the WebSocket
     * protocol advertises in base64; every other schema is text */
    int binary = !strcmp(c->schema_encoding, "protobuf");
    if (!utf8_ok(c->topic, strlen(c->topic)) || !utf8_ok(c->message_encoding, strlen(c->message_encoding)) ||
        !utf8_ok(c->schema_name, strlen(c->schema_name)) || !utf8_ok(c->schema_encoding, strlen(c->schema_encoding)) ||
        (!binary && !utf8_ok(c->schema, c->schema_len))) {
      fprintf(stderr, "vlff-view: --play %s: channel %u (%s): its topic, encodings or schema are not UTF-8 text\n",
              VLFF_Q(path), c->id, VLFF_Q(c->topic));
      vlff_view_play_free(p);
      return NULL;
    }
    p->nch++;
    p->mcap_id[p->nch] = c->id;
    const char *schema = c->schema;
    if (binary) {
      size_t cap = (c->schema_len + 2) / 3 * 4 + 8; /* libwebsockets wants room past the end */
      char *b = malloc(cap);
      if (!b || lws_b64_encode_string(c->schema, (int)c->schema_len, b, (int)cap) < 0) {
        free(b);
        fprintf(stderr, "vlff-view: --play %s: no memory for channel %u's schema\n", VLFF_Q(path), c->id);
        vlff_view_play_free(p);
        return NULL;
      }
      schema = p->b64[p->nch] = b;
    }
    p->ch[p->nch] = (struct vlff_view_chan){c->topic, c->message_encoding, c->schema_name, c->schema_encoding, schema};
  }
  if (!p->total) {
    fprintf(stderr, "vlff-view: --play %s: the recording holds no message\n", VLFF_Q(path));
    vlff_view_play_free(p);
    return NULL;
  }
  vlff_mcap_rewind(p->r);
  p->rate = 1;
  return p;
}

void vlff_view_play_free(struct vlff_view_play *p) {
  if (!p) return;
  for (int i = 0; i <= VLFF_VIEW_CH_MAX; i++) vlff_view_msg_unref(p->latest[i]), free(p->b64[i]);
  vlff_mcap_reader_free(p->r);
  if (p->file) vlff_unmap_file(p->file, p->len);
  free(p);
}

void vlff_view_play_rate(struct vlff_view_play *p, double rate) { p->rate = rate > 0 ? rate : 1; }

int vlff_view_play_channels(const struct vlff_view_play *p) { return p->nch; }

const struct vlff_view_chan *vlff_view_play_channel(const struct vlff_view_play *p, int ch) {
  return ch >= 1 && ch <= p->nch ? &p->ch[ch] : NULL;
}

/* The next message of the file into p->next; 0 at the end. The file was read
 * whole when opened, so an error here would be a changed file: it ends playback.
 * The message's bytes stay mapped: they are copied out before the next call. */
static int advance(struct vlff_view_play *p) {
  char why[256];
  int rc = vlff_mcap_next(p->r, &p->next, why, sizeof why);
  vlff_unread_mapped_paced(p->file, &p->given_back, vlff_mcap_consumed(p->r));
  if (rc < 0) vlff_log(VLFF_LOG_WARN, "vlff-view", "--play: %s", why);
  p->have_next = rc == 1;
  if (!p->have_next && !p->done) {
    p->done = 1;
    vlff_log(VLFF_LOG_INFO, "vlff-view", "--play: all %llu messages played", (unsigned long long)p->sent);
  }
  return p->have_next;
}

int vlff_view_play_poll(struct vlff_view_play *p, unsigned wanted, uint64_t now_ns, struct vlff_view_msg **out,
                        int out_cap) {
  if (!p->started) {
    if (!wanted) return 0;
    p->started = 1;
    if (!advance(p)) return 0;
    p->t0_log = p->prev_log = p->next.log_ns;
    p->t0_now = now_ns;
  }
  int n = 0;
  while (n < out_cap && p->have_next) {
    if (p->next.log_ns > p->prev_log) {
      /* a jump past the bound starts the clock again where the last message was due */
      if (p->next.log_ns - p->prev_log > PLAY_MAX_GAP_NS) p->t0_log += p->next.log_ns - p->prev_log;
      p->prev_log = p->next.log_ns;
    }
    uint64_t due = p->next.log_ns > p->t0_log ? (uint64_t)((double)(p->next.log_ns - p->t0_log) / p->rate) : 0;
    if (now_ns - p->t0_now < due) break;
    int ch = view_channel(p, p->next.channel);
    struct vlff_view_msg *m = ch ? vlff_view_msg_new(ch, p->next.len) : NULL;
    if (m) {
      memcpy(vlff_view_msg_payload(m), p->next.data, p->next.len);
      m->len = p->next.len;
      m->t_ns = p->next.publish_ns;
      vlff_view_msg_unref(p->latest[ch]);
      p->latest[ch] = vlff_view_msg_ref(m);
      out[n++] = m;
    }
    p->sent++;
    advance(p);
  }
  return n;
}

struct vlff_view_msg *vlff_view_play_current(struct vlff_view_play *p, int ch) {
  return ch >= 1 && ch <= p->nch ? vlff_view_msg_ref(p->latest[ch]) : NULL;
}

uint64_t vlff_view_play_sent(const struct vlff_view_play *p) { return p->sent; }
uint64_t vlff_view_play_total(const struct vlff_view_play *p) { return p->total; }
int vlff_view_play_done(const struct vlff_view_play *p) { return p->done; }
