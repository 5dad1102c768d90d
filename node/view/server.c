/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * server.c - the foxglove.websocket.v1 server and the page's HTTP files, one port.
 *
 * libwebsockets runs one event loop; a timer on it polls the feed and fans each new
 * message out to the clients subscribed to its channel. A client owns a queue of
 * references to shared messages; the loop writes one message per writable event, so
 * a client that reads slowly only grows its own queue, and once that queue holds more
 * than max_queue_bytes the client is dropped: the node's map reaches every other
 * client on time and the viewer's memory stays bounded.
 *
 * Client requests are JSON texts (subscribe, unsubscribe, advertise, unadvertise) and
 * binary messages on a channel the client advertised (clientPublish, offered only
 * when a token is configured: a prompt set for the mailbox). A malformed request gets
 * a Foxglove status message naming what is wrong and is counted; the connection
 * stays. An oversized message, too many clients or a foreign subprotocol close the
 * connection with a WebSocket close reason or an HTTP error saying so.
 *
 * The viewer owns the listening socket (the loop watches it as a raw file): it
 * accepts each connection itself, pausing when out of descriptors, into the gate's
 * vhost as a raw socket. Two vhosts: the gate reads the request head and checks it
 * (page.h: syntax, file, Host and Origin against the allow-list) before
 * libwebsockets' HTTP parser sees a byte; a refused head gets its HTTP status and sentence from
 * the gate, a passed one is handed with its bytes to the second vhost, which serves
 * the page's files from memory (with the Content-Security-Policy) or upgrades to the
 * Foxglove WebSocket. A page request's descriptor itself is handed on; an upgrade
 * is relayed through a socket pair (libwebsockets serves one end), the gate passing
 * bytes both ways and reading the client's frame headers, since libwebsockets 4.1
 * accepts client frames that are not masked and does not show the mask bit. A page response closes its connection, so that every request
 * passes the gate. Refusals are counted per status (the status channel's viewer
 * object); their log lines are rate-limited, so that a flood cannot fill the journal,
 * and so are libwebsockets' own.
 *
 * Nothing here waits: a prompt set is posted with vlff_prompts_try_post ("busy" at
 * once when the mailbox holds an unanswered request) and the learner's answer is
 * looked for from a timer. A WebSocket client silent for a third of the idle timeout
 * is pinged and one silent for all of it closed, so that dead peers free their slot.
 */
#include "view.h"
#include "mcap.h"

#include <arpa/inet.h>
#include <errno.h>
#include <fcntl.h>
#include <ifaddrs.h>
#include <netinet/in.h>
#include <json-c/json.h>
#include <libwebsockets.h>
#include <stddef.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/socket.h>
#include <unistd.h>

#include "clock.h"
#include "log.h"
#include "page.h"
#include "vlff/escape.h" /* what a peer sent, quoted in messages */

#define FOX_PROTOCOL "foxglove.websocket.v1"
#define PROMPT_TOPIC "/vlff/prompts"
#define MAX_CLIENT_CHANNELS 8
#define GATE_PROTOCOL "vlff-gate"
#define HEAD_TIMEOUT_S 5       /* default for a whole request head */
#define IDLE_TIMEOUT_S 30      /* default: a WebSocket client silent this long is closed */
#define ANSWER_WAIT_S 30       /* how long a posted prompt set waits for the learner */
#define ANSWER_POLL_US 20000   /* how often the loop looks for the learner's answer */
#define DROP_GRACE_S 10         /* a dropped client's socket taking its close frame */
#define GATE_LINGER_S 2        /* reading what a refused client still sends */
#define GATE_DRAIN_MAX (1u << 20)
#define GATE_PENDING_MAX 64    /* connections that have not finished their head */
#define GATE_TOTAL_MAX 256     /* connections at the gate: reading, answering, lingering */
#define PAGE_CHUNK 16384
#define RELAY_CHUNK 65536      /* bytes a relay moves per read */
#define ACCEPT_BURST 64        /* connections accepted per wake-up of the listener */
#define ACCEPT_PAUSE_US 200000 /* out of descriptors: the listener rests this long */

/* A connection whose request head is being read and checked. */
struct gate {
  struct vlff_view *v;
  struct lws *wsi;
  struct gate *older, *newer; /* the list of heads being read, oldest first */
  int listed;
  lws_sorted_usec_list_t sul; /* the head's deadline */
  enum { GATE_READING, GATE_ANSWERING, GATE_FLUSHING, GATE_DRAINING, GATE_PASSED, GATE_RELAY } state;
  char peer[64];
  /* RELAY: a WebSocket's bytes pass between the client's socket and the viewer's end
   * of a socket pair whose other end libwebsockets serves; the client's frames are
   * read on the way (fh: a frame header so far, f_left: payload bytes to skip) */
  struct gate *pair;
  int inner, closing;
  unsigned char fh[14];
  size_t fh_len, fh_need;
  uint64_t f_left;
  size_t len, drained, resp_len;
  char resp[LWS_PRE + 768];
  char buf[VLFF_HTTP_HEAD_MAX + 1];
};

/* The client address of a relayed WebSocket, whose socket libwebsockets sees is
 * the socket pair's. */
struct peer_note {
  struct peer_note *next;
  int fd;
  char peer[64];
};

/* A passed head on its way to the HTTP vhost (outside the gate's callback). */
struct handoff {
  struct handoff *next;
  int fd;
  size_t len;
  char head[];
};

/* A page file being sent. */
struct http_session {
  const struct vlff_page_file *f;
  size_t off;
  int head_only;
};

struct qitem {
  struct vlff_view_msg *m;
  uint32_t sub_id;
  int text;
  struct qitem *next;
};

struct client {
  struct vlff_view *v;
  struct lws *wsi;
  struct client *next;
  char peer[64];
  int subscribed[VLFF_VIEW_CH_MAX + 1];
  uint32_t sub_id[VLFF_VIEW_CH_MAX + 1];
  uint32_t adv_id[MAX_CLIENT_CHANNELS]; /* client channels advertised for the prompt topic */
  int nadv;
  struct qitem *head, *tail;
  size_t queued;
  unsigned char *rx;
  size_t rx_len;
  int dropping;
  int close_code;      /* dropping: the close frame's code and reason */
  char close_why[124]; /* a close reason is at most 123 bytes */
  uint64_t last_rx_ns; /* the client's last frame, pong included */
  int want_ping, pinged;
};

struct vlff_view {
  struct vlff_view_params p;
  struct vlff_feed *feed;
  struct lws_context *ctx;
  struct lws_vhost *vh, *http_vh; /* the listening gate, the HTTP and WebSocket side */
  struct lws_protocols gate_protocols[2], protocols[3];
  struct vlff_page page;
  lws_sorted_usec_list_t sul, handoff_sul;
  struct handoff *handoffs;
  int gate_pending;                 /* connections at the gate */
  int gate_reading;                 /* of which reading their head, listed: */
  struct gate *adopting;            /* the client whose pair end is being adopted */
  unsigned char relay_buf[LWS_PRE + RELAY_CHUNK];
  struct peer_note *peer_notes;
  struct gate *oldest, *newest;
  uint64_t ws_refusals; /* WebSocket-level refusals, for their log's rate limit */
  int nch;              /* channels served: this build's, or a recording's */
  struct vlff_view_log *log; /* the /log channel's lines (live only) */
  int record_failed;    /* the recording stopped at its first write error */
  uint64_t rec_whole_ns, rec_whole_version; /* the whole map last recorded: when, which version */
  struct client *clients;
  struct vlff_view_counters c;
  struct vlff_prompts *mailbox;
  /* the prompt set posted and waiting for the learner's answer (seq 0: none); the
   * loop polls for the answer instead of waiting in a callback */
  struct {
    struct client *cl;
    uint64_t seq, t0_ns;
  } pending;
  lws_sorted_usec_list_t answer_sul;
  struct vlff_allow allow;
  int head_timeout_s, idle_timeout_s;
  /* the listening socket is the viewer's own, watched by the loop as a raw file:
   * accept() is called here, so that running out of descriptors pauses it instead
   * of spinning on a listener that stays readable */
  int listen_fd, port;
  struct lws *listen_wsi;
  lws_sorted_usec_list_t accept_sul;
  uint64_t accept_failures;
  volatile int stop;
};

/* The client's address for a connection of the HTTP side: noted for a relayed
 * WebSocket, else the socket's peer. */
static void peer_of(struct vlff_view *v, struct lws *wsi, char *out, size_t cap) {
  int fd = lws_get_socket_fd(wsi);
  for (struct peer_note *n = v->peer_notes; n; n = n->next)
    if (n->fd == fd) {
      snprintf(out, cap, "%s", n->peer);
      return;
    }
  lws_get_peer_simple(wsi, out, cap);
}

static void forget_peer(struct vlff_view *v, int fd) {
  for (struct peer_note **pp = &v->peer_notes; *pp; pp = &(*pp)->next)
    if ((*pp)->fd == fd) {
      struct peer_note *n = *pp;
      *pp = n->next;
      free(n);
      return;
    }
}

/* Counts a refusal with HTTP status (its own counter in the status channel) and
 * logs it: the first five of each status and every 1000th. */
static void count_refusal(struct vlff_view *v, const char *peer, int status, const char *why) {
  v->c.refused++;
  /* every status the gate answers with has a counter; were one added
   * without, it is counted as a bad request rather than lost */
  int i = vlff_view_http_index(status);
  if (i < 0) i = 0;
  vlff_warn_limited(&v->c.http_refused[i], "vlff-view", "refused %s: %s [HTTP %d %s, %llu so far]", peer, why, status,
                    vlff_http_reason(status), (unsigned long long)v->c.http_refused[i] + 1);
}

/* ----------------------------------------------------------------- queues */

static void free_queue(struct client *cl);

/* Drops a client with a close frame carrying code and why (a WebSocket close reason
 * is at most 123 bytes): what it had queued is discarded, so that the close frame is
 * the next thing written once its socket takes bytes again (the writeable callback
 * sends it); a client that takes none within DROP_GRACE_S is cut off without one.
 * The grace covers a client that reads again (its kernel buffers, megabytes,
 * drain before the close frame) on a loaded host: at 5 s a sanitized viewer
 * beside other tests cut a client off that had resumed (close 1006, no reason). */
static void drop_client(struct client *cl, int code, const char *why) {
  if (cl->dropping) return;
  cl->dropping = 1;
  vlff_log(VLFF_LOG_WARN, "vlff-view", "client %s dropped: %s", cl->peer, why);
  cl->close_code = code;
  snprintf(cl->close_why, sizeof cl->close_why, "%s", why);
  free_queue(cl);
  lws_set_timeout(cl->wsi, PENDING_TIMEOUT_USER_REASON_BASE, DROP_GRACE_S);
  lws_callback_on_writable(cl->wsi);
}

/* Unlinked item q leaves cl's queue: its bytes no longer count. */
static void qitem_free(struct client *cl, struct qitem *q) {
  cl->queued -= q->m->len;
  vlff_view_msg_unref(q->m);
  free(q);
}

static void enqueue(struct client *cl, struct vlff_view_msg *m, uint32_t sub_id, int text) {
  if (cl->dropping) return;
  struct qitem *q = malloc(sizeof *q);
  if (!q) {
    drop_client(cl, LWS_CLOSE_STATUS_UNEXPECTED_CONDITION, "out of memory for its queue");
    return;
  }
  q->m = vlff_view_msg_ref(m);
  q->sub_id = sub_id;
  q->text = text;
  q->next = NULL;
  if (cl->tail) cl->tail->next = q;
  else cl->head = q;
  cl->tail = q;
  cl->queued += m->len;
  if (cl->queued > cl->v->p.max_queue_bytes) {
    char why[120];
    snprintf(why, sizeof why, "too slow: %zu bytes unsent, above --max-queue-mb (%zu bytes)", cl->queued,
             cl->v->p.max_queue_bytes);
    cl->v->c.dropped_slow++;
    drop_client(cl, 1013 /* try again later */, why);
    return;
  }
  lws_callback_on_writable(cl->wsi);
}

static void free_queue(struct client *cl) {
  while (cl->head) {
    struct qitem *q = cl->head;
    cl->head = q->next;
    qitem_free(cl, q);
  }
  cl->tail = NULL;
}

/* A control message (JSON text) for one client, from a json-c object it consumes. */
static void send_json(struct client *cl, json_object *o) {
  size_t n;
  const char *s = json_object_to_json_string_length(o, JSON_C_TO_STRING_PLAIN, &n);
  struct vlff_view_msg *m = vlff_view_msg_new(0, n);
  if (m) {
    memcpy(vlff_view_msg_payload(m), s, n);
    m->len = n;
    enqueue(cl, m, 0, 1);
    vlff_view_msg_unref(m);
  }
  json_object_put(o);
}

/* Foxglove status op: 0 info, 1 warning, 2 error. */
static void send_status(struct client *cl, int level, const char *fmt, ...) __attribute__((format(printf, 3, 4)));
static void send_status(struct client *cl, int level, const char *fmt, ...) {
  char text[512];
  va_list ap;
  va_start(ap, fmt);
  vsnprintf(text, sizeof text, fmt, ap);
  va_end(ap);
  if (level == 2) vlff_warn_limited(&cl->v->c.bad_requests, "vlff-view", "client %s: %s", cl->peer, text);
  json_object *o = json_object_new_object();
  json_object_object_add(o, "op", json_object_new_string("status"));
  json_object_object_add(o, "level", json_object_new_int(level));
  json_object_object_add(o, "message", json_object_new_string(text));
  send_json(cl, o);
}

/* Channel ch as advertised: a recording's own when playing one, else this build's
 * (JSON messages with JSON Schemas). */
static struct vlff_view_chan chan_info(const struct vlff_view *v, int ch) {
  if (v->p.play) return *vlff_view_play_channel(v->p.play, ch);
  const struct vlff_view_channel_def *d = vlff_view_channel(ch);
  int pb = !strcmp(d->encoding, "protobuf");
  return (struct vlff_view_chan){d->topic, d->encoding, d->schema_name, pb ? "protobuf" : "jsonschema", d->schema};
}

/* The first message of a new subscription to ch. */
static struct vlff_view_msg *current(struct vlff_view *v, int ch) {
  if (v->p.play) return vlff_view_play_current(v->p.play, ch);
  if (ch == VLFF_VIEW_CH_LOG) return vlff_view_log_current(v->log);
  return vlff_feed_current(v->feed, ch, &v->c);
}

static void send_hello(struct client *cl) {
  struct vlff_view *v = cl->v;
  json_object *o = json_object_new_object();
  json_object_object_add(o, "op", json_object_new_string("serverInfo"));
  json_object_object_add(o, "name", json_object_new_string("vlff-view " VLFF_VERSION));
  json_object *caps = json_object_new_array();
  if (v->p.token) json_object_array_add(caps, json_object_new_string("clientPublish"));
  json_object_object_add(o, "capabilities", caps);
  json_object *enc = json_object_new_array();
  if (v->p.token) json_object_array_add(enc, json_object_new_string("json"));
  json_object_object_add(o, "supportedEncodings", enc);
  json_object *md = json_object_new_object();
  json_object_object_add(md, "prompt_topic", json_object_new_string(PROMPT_TOPIC));
  json_object_object_add(o, "metadata", md);
  char sid[32];
  snprintf(sid, sizeof sid, "%llu", (unsigned long long)vlff_now_ns());
  json_object_object_add(o, "sessionId", json_object_new_string(sid));
  send_json(cl, o);

  o = json_object_new_object();
  json_object_object_add(o, "op", json_object_new_string("advertise"));
  json_object *chans = json_object_new_array();
  for (int ch = 1; ch <= v->nch; ch++) {
    struct vlff_view_chan d = chan_info(v, ch);
    json_object *c = json_object_new_object();
    json_object_object_add(c, "id", json_object_new_int(ch));
    json_object_object_add(c, "topic", json_object_new_string(d.topic));
    json_object_object_add(c, "encoding", json_object_new_string(d.encoding));
    json_object_object_add(c, "schemaName", json_object_new_string(d.schema_name));
    json_object_object_add(c, "schema", json_object_new_string(d.schema));
    json_object_object_add(c, "schemaEncoding", json_object_new_string(d.schema_encoding));
    json_object_array_add(chans, c);
  }
  json_object_object_add(o, "channels", chans);
  send_json(cl, o);
}

/* --------------------------------------------------------------- requests */

/* An unsigned 32-bit integer member, or -1 with a status sent. */
static int64_t get_u32(struct client *cl, json_object *o, const char *key, const char *where) {
  json_object *x;
  if (!json_object_object_get_ex(o, key, &x) || !json_object_is_type(x, json_type_int)) {
    send_status(cl, 2, "%s: \"%s\" must be an integer", where, key);
    return -1;
  }
  int64_t n = json_object_get_int64(x);
  if (n < 0 || n > UINT32_MAX) {
    send_status(cl, 2, "%s: \"%s\" %lld is outside 0..4294967295", where, key, (long long)n);
    return -1;
  }
  return n;
}

static json_object *get_array(struct client *cl, json_object *o, const char *key, const char *where) {
  json_object *a;
  if (!json_object_object_get_ex(o, key, &a) || !json_object_is_type(a, json_type_array)) {
    send_status(cl, 2, "%s: \"%s\" must be an array", where, key);
    return NULL;
  }
  return a;
}

static void do_subscribe(struct client *cl, json_object *req) {
  json_object *subs = get_array(cl, req, "subscriptions", "subscribe");
  if (!subs) return;
  size_t n = json_object_array_length(subs);
  for (size_t i = 0; i < n; i++) {
    json_object *s = json_object_array_get_idx(subs, i);
    if (!json_object_is_type(s, json_type_object)) {
      send_status(cl, 2, "subscribe: subscriptions[%zu] is not an object", i);
      continue;
    }
    int64_t id = get_u32(cl, s, "id", "subscribe"), ch = get_u32(cl, s, "channelId", "subscribe");
    if (id < 0 || ch < 0) continue;
    if (ch < 1 || ch > cl->v->nch) {
      send_status(cl, 2, "subscribe: no channel %lld (channels are 1..%d)", (long long)ch, cl->v->nch);
      continue;
    }
    int dup = 0;
    for (int c = 1; c <= cl->v->nch; c++) dup |= cl->subscribed[c] && cl->sub_id[c] == (uint32_t)id;
    if (dup || cl->subscribed[ch]) {
      send_status(cl, 2, "subscribe: %s", dup ? "subscription id already in use" : "already subscribed to that channel");
      continue;
    }
    cl->subscribed[ch] = 1;
    cl->sub_id[ch] = (uint32_t)id;
    struct vlff_view_msg *m = current(cl->v, (int)ch);
    if (m) {
      enqueue(cl, m, (uint32_t)id, 0);
      vlff_view_msg_unref(m);
    }
  }
}

/* Drops the messages of subscription sub_id queued but not yet written: a
 * client that unsubscribed gets none of them (a slow reader would
 * otherwise keep receiving a channel it left for as long as its queue
 * lasts). */
static void forget_queued(struct client *cl, uint32_t sub_id) {
  struct qitem **pp = &cl->head;
  cl->tail = NULL;
  while (*pp) {
    struct qitem *q = *pp;
    if (!q->text && q->sub_id == sub_id) {
      *pp = q->next;
      qitem_free(cl, q);
    } else {
      cl->tail = q;
      pp = &q->next;
    }
  }
}

static void do_unsubscribe(struct client *cl, json_object *req) {
  json_object *ids = get_array(cl, req, "subscriptionIds", "unsubscribe");
  if (!ids) return;
  for (size_t i = 0; i < json_object_array_length(ids); i++) {
    json_object *x = json_object_array_get_idx(ids, i);
    int found = 0;
    if (json_object_is_type(x, json_type_int))
      for (int c = 1; c <= cl->v->nch; c++)
        if (cl->subscribed[c] && cl->sub_id[c] == json_object_get_int64(x)) {
          cl->subscribed[c] = 0;
          forget_queued(cl, cl->sub_id[c]);
          found = 1;
        }
    if (!found) send_status(cl, 2, "unsubscribe: subscriptionIds[%zu] is not a subscription of this client", i);
  }
}

static void do_advertise(struct client *cl, json_object *req) {
  if (!cl->v->p.token) {
    send_status(cl, 2, "advertise: this viewer does not accept client messages (no token configured)");
    return;
  }
  json_object *chans = get_array(cl, req, "channels", "advertise");
  if (!chans) return;
  for (size_t i = 0; i < json_object_array_length(chans); i++) {
    json_object *c = json_object_array_get_idx(chans, i), *topic, *enc;
    int64_t id = json_object_is_type(c, json_type_object) ? get_u32(cl, c, "id", "advertise") : -1;
    if (id < 0) continue;
    if (!json_object_object_get_ex(c, "topic", &topic) || !json_object_object_get_ex(c, "encoding", &enc) ||
        strcmp(json_object_get_string(topic), PROMPT_TOPIC) || strcmp(json_object_get_string(enc), "json")) {
      send_status(cl, 2, "advertise: channels[%zu]: only topic \"" PROMPT_TOPIC "\" with encoding \"json\" is accepted",
                  i);
      continue;
    }
    if (cl->nadv == MAX_CLIENT_CHANNELS) {
      send_status(cl, 2, "advertise: at most %d client channels", MAX_CLIENT_CHANNELS);
      return;
    }
    cl->adv_id[cl->nadv++] = (uint32_t)id;
  }
}

static void do_unadvertise(struct client *cl, json_object *req) {
  json_object *ids = get_array(cl, req, "channelIds", "unadvertise");
  if (!ids) return;
  for (size_t i = 0; i < json_object_array_length(ids); i++) {
    int64_t id = json_object_get_int64(json_object_array_get_idx(ids, i));
    for (int k = 0; k < cl->nadv; k++)
      if (cl->adv_id[k] == id) cl->adv_id[k--] = cl->adv_id[--cl->nadv];
  }
}

static int token_ok(const char *want, const char *got) {
  size_t a = strlen(want), b = strlen(got);
  unsigned diff = (unsigned)(a ^ b);
  /* compare every byte whatever the first mismatch, so timing says nothing */
  for (size_t i = 0; i < a; i++) diff |= (unsigned char)want[i] ^ (unsigned char)(i < b ? got[i] : 0);
  return diff == 0;
}

/* The loop's look for the learner's answer to the pending post: the client gets it
 * as a status (or hears that none came in ANSWER_WAIT_S); nothing here waits. */
static void poll_answer(lws_sorted_usec_list_t *sul) {
  struct vlff_view *v = lws_container_of(sul, struct vlff_view, answer_sul);
  if (!v->pending.seq) return;
  char reason[128] = "";
  int st = v->mailbox ? vlff_prompts_wait_answer(v->mailbox, v->pending.seq, 0, reason, sizeof reason) : -1;
  int e = errno;
  struct client *cl = v->pending.cl;
  if (st < 0 && e == ETIMEDOUT && vlff_now_ns() - v->pending.t0_ns < (uint64_t)ANSWER_WAIT_S * 1000000000ull) {
    lws_sul_schedule(v->ctx, 0, &v->answer_sul, poll_answer, ANSWER_POLL_US);
    return;
  }
  if (cl && st == VLFF_PROMPT_ACCEPTED)
    send_status(cl, 0, "prompt set (request %llu) accepted by the learner", (unsigned long long)v->pending.seq);
  else if (cl && st == VLFF_PROMPT_REFUSED)
    send_status(cl, 2, PROMPT_TOPIC ": the learner refused request %llu: %s", (unsigned long long)v->pending.seq,
                reason);
  else if (cl)
    send_status(cl, 2, PROMPT_TOPIC ": no answer to request %llu: %s", (unsigned long long)v->pending.seq,
                e == ETIMEDOUT ? "the learner did not answer in time" : vlff_shm_last_message());
  if (st < 0 && e == EPIPE) {
    vlff_prompts_close(v->mailbox);
    v->mailbox = NULL;
  }
  v->pending.seq = 0;
  v->pending.cl = NULL;
}

/* A client message on an advertised channel: {"token": "...", "prompts": [...]} or
 * {"token": "...", "set_index": n}, posted to the prompt mailbox. */
static void do_publish(struct client *cl, const unsigned char *d, size_t n) {
  struct vlff_view *v = cl->v;
  char why[160];
  uint32_t id;
  if (vlff_view_publish_header(d, n, &id, why, sizeof why)) {
    send_status(cl, 2, "%s", why);
    return;
  }
  int known = 0;
  for (int k = 0; k < cl->nadv; k++) known |= cl->adv_id[k] == id;
  if (!known) {
    send_status(cl, 2, "message data on channel %u, which this client has not advertised", id);
    return;
  }
  json_object *o = vlff_view_parse_json((const char *)d + 5, n - 5, why, sizeof why);
  json_object *t, *p, *si;
  if (!o) {
    send_status(cl, 2, PROMPT_TOPIC ": the message is not JSON: %s", why);
  } else if (!json_object_is_type(o, json_type_object)) {
    send_status(cl, 2, PROMPT_TOPIC ": the message is not a JSON object");
  } else if (!json_object_object_get_ex(o, "token", &t) || !json_object_is_type(t, json_type_string) ||
             !token_ok(v->p.token, json_object_get_string(t))) {
    send_status(cl, 2, PROMPT_TOPIC ": wrong or missing token");
  } else {
    /* validate the request whole before touching the mailbox */
    const char *texts[VLFF_SHM_MAX_PROMPTS];
    int np = -1;
    int64_t set = -1;
    if (json_object_object_get_ex(o, "set_index", &si)) {
      set = json_object_is_type(si, json_type_int) ? json_object_get_int64(si) : -1;
      if (set < 0 || set > 1000) {
        send_status(cl, 2, PROMPT_TOPIC ": set_index must be an integer 0..1000");
        goto out;
      }
    } else if (!json_object_object_get_ex(o, "prompts", &p) || !json_object_is_type(p, json_type_array)) {
      send_status(cl, 2, PROMPT_TOPIC ": \"prompts\" must be an array of strings");
      goto out;
    } else {
      size_t len = json_object_array_length(p);
      int ok = len >= 1 && len <= VLFF_SHM_MAX_PROMPTS;
      for (size_t i = 0; ok && i < len; i++) {
        json_object *x = json_object_array_get_idx(p, i);
        texts[i] = json_object_is_type(x, json_type_string) ? json_object_get_string(x) : NULL;
        ok = texts[i] && *texts[i] && strlen(texts[i]) < VLFF_SHM_PROMPT_LEN;
      }
      if (!ok) {
        send_status(cl, 2, PROMPT_TOPIC ": 1..%d prompts, each a non-empty string shorter than %d bytes",
                    VLFF_SHM_MAX_PROMPTS, VLFF_SHM_PROMPT_LEN);
        goto out;
      }
      np = (int)len;
    }
    if (!v->mailbox) v->mailbox = vlff_prompts_attach(v->p.prompts_name);
    if (!v->mailbox) {
      send_status(cl, 2, PROMPT_TOPIC ": mailbox %s: %s", v->p.prompts_name, vlff_shm_last_message());
    } else if (v->pending.seq) {
      /* the mailbox takes one request at a time: answer at once, never wait */
      send_status(cl, 2, PROMPT_TOPIC ": busy: request %llu is still waiting for the learner's answer; post again later",
                  (unsigned long long)v->pending.seq);
    } else if (vlff_prompts_try_post(v->mailbox, np > 0 ? texts : NULL, np > 0 ? np : 0, np > 0 ? -1 : (int)set) != 0) {
      int e = errno;
      send_status(cl, 2, PROMPT_TOPIC ": %sposting to %s: %s", e == EBUSY ? "busy: " : "", v->p.prompts_name,
                  vlff_shm_last_message());
      if (e == EPIPE) {
        vlff_prompts_close(v->mailbox); /* replaced by a restarted node: attach again next time */
        v->mailbox = NULL;
      }
    } else {
      v->c.prompts_posted++;
      v->pending.cl = cl;
      v->pending.seq = vlff_prompts_last_post(v->mailbox);
      v->pending.t0_ns = vlff_now_ns();
      send_status(cl, 0, "prompt set posted to %s as request %llu; waiting for the learner's answer",
                  v->p.prompts_name, (unsigned long long)v->pending.seq);
      vlff_log(VLFF_LOG_INFO, "vlff-view", "client %s posted a prompt set to %s (request %llu)", cl->peer, v->p.prompts_name,
              (unsigned long long)v->pending.seq);
      lws_sul_schedule(v->ctx, 0, &v->answer_sul, poll_answer, ANSWER_POLL_US);
    }
  }
out:
  json_object_put(o);
}

static void handle_text(struct client *cl, const char *s, size_t n) {
  char why[160];
  json_object *o = vlff_view_parse_json(s, n, why, sizeof why);
  json_object *op;
  if (!o) {
    send_status(cl, 2, "request is not JSON: %s", why);
  } else if (!json_object_is_type(o, json_type_object) || !json_object_object_get_ex(o, "op", &op) ||
             !json_object_is_type(op, json_type_string)) {
    send_status(cl, 2, "request has no \"op\" string");
  } else {
    const char *name = json_object_get_string(op);
    if (!strcmp(name, "subscribe")) do_subscribe(cl, o);
    else if (!strcmp(name, "unsubscribe")) do_unsubscribe(cl, o);
    else if (!strcmp(name, "advertise")) do_advertise(cl, o);
    else if (!strcmp(name, "unadvertise")) do_unadvertise(cl, o);
    else send_status(cl, 2, "op \"%.40s\" is not supported by this server", name);
  }
  json_object_put(o);
}

/* ---------------------------------------------------------------- the loop */

static int write_one(struct client *cl) {
  if (cl->want_ping) {
    /* with a payload: libwebsockets 4.1 passes an empty pong to no callback */
    unsigned char ping[LWS_PRE + 4];
    memcpy(ping + LWS_PRE, "vlff", 4);
    cl->want_ping = 0;
    if (lws_write(cl->wsi, ping + LWS_PRE, 4, LWS_WRITE_PING) < 4) return -1;
    if (cl->head) lws_callback_on_writable(cl->wsi);
    return 0;
  }
  struct qitem *q = cl->head;
  if (!q) return 0;
  unsigned char *p = vlff_view_msg_payload(q->m);
  size_t n = q->m->len;
  enum lws_write_protocol kind = LWS_WRITE_TEXT;
  if (!q->text) {
    p -= VLFF_VIEW_FOX_HDR;
    p[0] = 1; /* message data */
    for (int i = 0; i < 4; i++) p[1 + i] = (unsigned char)(q->sub_id >> (8 * i));
    for (int i = 0; i < 8; i++) p[5 + i] = (unsigned char)(q->m->t_ns >> (8 * i));
    n += VLFF_VIEW_FOX_HDR;
    kind = LWS_WRITE_BINARY;
  }
  int w = lws_write(cl->wsi, p, n, kind);
  if (w < (int)n) return -1;
  if (q->m->next) {
    /* the next piece of a message sent in pieces takes its place at the head: the
     * pieces go out in a row, ahead of what was queued after them, and only the
     * piece waiting counts against the queue limit, so that a whole map larger
     * than the limit reaches a client that reads */
    struct vlff_view_msg *next = vlff_view_msg_ref(q->m->next);
    cl->queued -= q->m->len;
    vlff_view_msg_unref(q->m);
    q->m = next;
    cl->queued += next->len;
  } else {
    cl->head = q->next;
    if (!cl->head) cl->tail = NULL;
    qitem_free(cl, q);
  }
  cl->v->c.messages_sent++;
  cl->v->c.bytes_sent += n;
  if (cl->head) lws_callback_on_writable(cl->wsi);
  return 0;
}

/* A client silent for a third of the idle timeout is pinged (a live one answers
 * with a pong, browsers and Foxglove on their own); one silent for the whole of it
 * is closed, so that idle or dead peers cannot hold the client slots. */
static void check_idle(struct vlff_view *v) {
  uint64_t now = vlff_now_ns(), limit = (uint64_t)v->idle_timeout_s * 1000000000ull;
  for (struct client *cl = v->clients; cl; cl = cl->next) {
    if (cl->dropping) continue;
    uint64_t quiet = now - cl->last_rx_ns;
    if (quiet >= limit) {
      char why[96];
      snprintf(why, sizeof why, "no answer to ping: silent for %d s", v->idle_timeout_s);
      drop_client(cl, LWS_CLOSE_STATUS_POLICY_VIOLATION, why);
    } else if (quiet >= limit / 3 && !cl->pinged) {
      cl->pinged = 1;
      cl->want_ping = 1;
      lws_callback_on_writable(cl->wsi);
    }
  }
}

/* Every message the feed made, into the recording (log time: now, on the wall
 * clock; publish time: the message's own). The whole map opens a chunk of its
 * own, so that the chunk indexes lead a seeking reader to it. A write error ends
 * the recording with one line; the viewer serves on. */
static void record(struct vlff_view *v, struct vlff_view_msg **out, int n) {
  struct vlff_mcap_writer *w = v->p.record;
  if (!w || v->record_failed) return;
  uint64_t now = vlff_wall_ns();
  int rc = 0;
  for (int i = 0; i < n && !rc; i++) {
    if (out[i]->whole && !(i && out[i - 1]->whole)) rc = vlff_mcap_writer_flush(w);
    for (struct vlff_view_msg *m = out[i]; m && !rc; m = m->next) /* every piece */
      rc = vlff_mcap_writer_message(w, (uint16_t)m->channel, now, m->t_ns, vlff_view_msg_payload(m), m->len);
    if (out[i]->whole && out[i]->channel == VLFF_VIEW_CH_SCENE) {
      v->rec_whole_ns = vlff_now_ns();
      v->rec_whole_version = out[i]->version;
    }
  }
  if (!rc) rc = vlff_mcap_writer_tick(w, vlff_now_ns());
  if (rc) {
    v->record_failed = 1;
    vlff_log(VLFF_LOG_WARN, "vlff-view", "recording stopped: %s", vlff_mcap_writer_error(w));
  }
}

/* The map's channels carry changes, and a reader that seeks (Foxglove after a
 * jump, a script starting mid-file) holds only what came after the point it
 * started from: so while the map changes, the whole map (voxels, point cloud and
 * scene, the ones a new subscriber gets, each in its pieces) goes into the
 * recording every record_map_s, and the latest whole map before any point, with
 * the changes after it, is the map at that point. Live clients get none of these. */
static void record_whole_map(struct vlff_view *v) {
  if (!v->p.record || v->record_failed || !v->feed) return;
  uint64_t version = vlff_feed_version(v->feed), now = vlff_now_ns();
  double every = v->p.record_map_s > 0 ? v->p.record_map_s : 10;
  if (!version || version == v->rec_whole_version || now - v->rec_whole_ns < (uint64_t)(every * 1e9)) return;
  /* in the order the feed sends a whole map */
  const int chans[3] = {VLFF_VIEW_CH_VOXELS, VLFF_VIEW_CH_CLOUD, VLFF_VIEW_CH_SCENE};
  struct vlff_view_msg *out[3];
  int n = 0;
  for (int i = 0; i < 3; i++) {
    struct vlff_view_msg *m = vlff_feed_current(v->feed, chans[i], NULL);
    if (m) out[n++] = m;
  }
  record(v, out, n);
  for (int i = 0; i < n; i++) vlff_view_msg_unref(out[i]);
}

/* The channels, declared in the recording before any message. */
static int declare_channels(struct vlff_view *v) {
  for (int ch = 1; ch <= v->nch; ch++) {
    struct vlff_view_chan d = chan_info(v, ch);
    /* MCAP holds a protobuf schema as the FileDescriptorSet's bytes, not base64 */
    const void *schema = d.schema;
    size_t len = strlen(d.schema);
    if (!strcmp(d.encoding, "protobuf")) schema = vlff_view_descriptor(ch, &len);
    if (vlff_mcap_writer_channel(v->p.record, (uint16_t)ch, d.topic, d.encoding, d.schema_name, d.schema_encoding,
                                 schema, len)) {
      vlff_log(VLFF_LOG_WARN, "vlff-view", "--record: %s", vlff_mcap_writer_error(v->p.record));
      return -1;
    }
  }
  return 0;
}

static void tick(lws_sorted_usec_list_t *sul) {
  struct vlff_view *v = lws_container_of(sul, struct vlff_view, sul);
  struct vlff_view_msg *out[32];
  unsigned wanted = 0;
  check_idle(v);
  for (struct client *cl = v->clients; cl; cl = cl->next)
    for (int ch = 1; ch <= v->nch; ch++)
      if (cl->subscribed[ch]) wanted |= 1u << ch;
  int n;
  if (v->p.play) {
    n = vlff_view_play_poll(v->p.play, wanted, vlff_now_ns(), out, 16);
  } else {
    if (v->p.record && !v->record_failed) wanted = ~0u; /* a recording wants every channel */
    /* the log follows the status whether or not /log has subscribers, so that its
     * latest line is there for the first one */
    wanted |= 1u << VLFF_VIEW_CH_STATUS;
    n = vlff_feed_poll(v->feed, &v->c, wanted, out, 16);
    for (int i = 0, k = n; i < k && n < 32; i++)
      if (out[i]->channel == VLFF_VIEW_CH_STATUS) n += vlff_view_log_status(v->log, out[i], out + n, 32 - n);
    record(v, out, n);
    record_whole_map(v);
  }
  for (int i = 0; i < n; i++) {
    for (struct client *cl = v->clients; cl; cl = cl->next)
      if (cl->subscribed[out[i]->channel]) enqueue(cl, out[i], cl->sub_id[out[i]->channel], 0);
    vlff_view_msg_unref(out[i]);
  }
  lws_sul_schedule(v->ctx, 0, &v->sul, tick, (lws_usec_t)(1e6 / v->p.poll_hz));
}

static int refuse(struct vlff_view *v, struct lws *wsi, enum lws_close_status code, const char *why) {
  char peer[64] = "?";
  peer_of(v, wsi, peer, sizeof peer);
  v->c.refused++;
  vlff_warn_limited(&v->ws_refusals, "vlff-view", "refused %s: %s", peer, why);
  lws_close_reason(wsi, code, (unsigned char *)why, strlen(why));
  return -1;
}

static int fox_cb(struct lws *wsi, enum lws_callback_reasons reason, void *user, void *in, size_t len) {
  struct vlff_view *v = lws_context_user(lws_get_context(wsi));
  struct client *cl = user;
  switch (reason) {
  case LWS_CALLBACK_ESTABLISHED: {
    if (v->c.clients >= v->p.max_clients) {
      char why[64];
      snprintf(why, sizeof why, "too many clients (%d)", v->p.max_clients);
      return refuse(v, wsi, (enum lws_close_status)1013 /* try again later */, why);
    }
    memset(cl, 0, sizeof *cl);
    cl->v = v;
    cl->wsi = wsi;
    peer_of(v, wsi, cl->peer, sizeof cl->peer);
    size_t pl = strlen(cl->peer);
    snprintf(cl->peer + pl, sizeof cl->peer - pl, "#%llu", (unsigned long long)v->c.connections + 1);
    cl->last_rx_ns = vlff_now_ns();
    cl->next = v->clients;
    v->clients = cl;
    v->c.clients++;
    v->c.connections++;
    if (v->p.verbose) vlff_log(VLFF_LOG_INFO, "vlff-view", "client %s connected", cl->peer);
    send_hello(cl);
    return 0;
  }
  case LWS_CALLBACK_RECEIVE_PONG:
    if (cl->v) cl->last_rx_ns = vlff_now_ns(), cl->pinged = 0;
    return 0;
  case LWS_CALLBACK_RECEIVE: {
    if (!cl->v || cl->dropping) return 0;
    cl->last_rx_ns = vlff_now_ns();
    cl->pinged = 0;
    if (cl->rx_len + len > v->p.max_request_bytes) {
      char why[96];
      snprintf(why, sizeof why, "message larger than %zu bytes", v->p.max_request_bytes);
      v->c.bad_requests++;
      return refuse(v, wsi, LWS_CLOSE_STATUS_MESSAGE_TOO_LARGE, why);
    }
    unsigned char *b = realloc(cl->rx, cl->rx_len + len + 1);
    if (!b) return refuse(v, wsi, LWS_CLOSE_STATUS_UNEXPECTED_CONDITION, "out of memory");
    cl->rx = b;
    memcpy(cl->rx + cl->rx_len, in, len);
    cl->rx_len += len;
    if (!lws_is_final_fragment(wsi) || lws_remaining_packet_payload(wsi)) return 0;
    cl->rx[cl->rx_len] = 0;
    if (lws_frame_is_binary(wsi)) do_publish(cl, cl->rx, cl->rx_len);
    else handle_text(cl, (const char *)cl->rx, cl->rx_len);
    cl->rx_len = 0;
    return 0;
  }
  case LWS_CALLBACK_SERVER_WRITEABLE:
    if (!cl->v) return -1;
    if (cl->dropping) {
      lws_close_reason(wsi, (enum lws_close_status)cl->close_code, (unsigned char *)cl->close_why,
                       strlen(cl->close_why));
      return -1;
    }
    return write_one(cl);
  case LWS_CALLBACK_CLOSED:
    if (!cl->v) return 0;
    for (struct client **pp = &v->clients; *pp; pp = &(*pp)->next)
      if (*pp == cl) {
        *pp = cl->next;
        break;
      }
    v->c.clients--;
    forget_peer(v, lws_get_socket_fd(wsi));
    if (v->pending.cl == cl) v->pending.cl = NULL; /* its answer has nobody to go to */
    if (v->p.verbose) vlff_log(VLFF_LOG_INFO, "vlff-view", "client %s left", cl->peer);
    free_queue(cl);
    free(cl->rx);
    cl->v = NULL;
    return 0;
  default:
    return 0;
  }
}

/* Lists the Foxglove subprotocol among the comma-separated ones offered. */
static int offers_foxglove(const char *list) {
  size_t n = strlen(FOX_PROTOCOL);
  for (const char *p = list; p && *p;) {
    p += strspn(p, " ,");
    size_t len = strcspn(p, " ,");
    if (len == n && !strncmp(p, FOX_PROTOCOL, n)) return 1;
    p += len;
  }
  return 0;
}

/* ------------------------------------------------------------------ gate */

static void reading_add(struct vlff_view *v, struct gate *g) {
  g->older = v->newest;
  g->newer = NULL;
  if (v->newest) v->newest->newer = g;
  else v->oldest = g;
  v->newest = g;
  g->listed = 1;
  v->gate_reading++;
}

static void reading_remove(struct vlff_view *v, struct gate *g) {
  if (!g->listed) return;
  if (g->older) g->older->newer = g->newer;
  else v->oldest = g->newer;
  if (g->newer) g->newer->older = g->older;
  else v->newest = g->older;
  g->listed = 0;
  v->gate_reading--;
}

static void gate_answer(struct gate *g, int status, const char *why, int is_head) {
  reading_remove(g->v, g);
  count_refusal(g->v, g->peer, status, why);
  g->resp_len = vlff_http_refusal(g->resp + LWS_PRE, sizeof g->resp - LWS_PRE, status, why, is_head);
  g->state = GATE_ANSWERING;
  lws_sul_cancel(&g->sul);
  lws_callback_on_writable(g->wsi);
}

static void gate_deadline(lws_sorted_usec_list_t *sul) {
  struct gate *g = lws_container_of(sul, struct gate, sul);
  if (g->state != GATE_READING) return;
  if (g->len) {
    char why[96];
    snprintf(why, sizeof why, "no complete request head within %d s", g->v->head_timeout_s);
    gate_answer(g, 408, why, 0);
  } else {
    /* a connection that never sent a byte (a browser's spare one) just closes */
    lws_set_timeout(g->wsi, PENDING_TIMEOUT_USER_REASON_BASE, LWS_TO_KILL_ASYNC);
  }
}

static void run_handoffs(lws_sorted_usec_list_t *sul) {
  struct vlff_view *v = lws_container_of(sul, struct vlff_view, handoff_sul);
  while (v->handoffs) {
    struct handoff *h = v->handoffs;
    v->handoffs = h->next;
    /* on failure libwebsockets closes the descriptor itself */
    if (!lws_adopt_socket_vhost_readbuf(v->http_vh, h->fd, h->head, h->len))
      vlff_log(VLFF_LOG_WARN, "vlff-view", "a checked request could not be handed to the HTTP side");
    free(h);
  }
}

/* Queues descriptor fd with the head the gate read for the HTTP vhost, which
 * adopts it from the loop (run_handoffs), and leaves the gate's reading list in
 * state (passed, or relaying a WebSocket). */
static void gate_hand_over(struct gate *g, struct handoff *h, int fd, size_t head_len, int state) {
  struct vlff_view *v = g->v;
  h->fd = fd;
  h->len = head_len;
  memcpy(h->head, g->buf, head_len);
  h->next = v->handoffs;
  v->handoffs = h;
  lws_sul_schedule(v->ctx, 0, &v->handoff_sul, run_handoffs, 1);
  g->state = state;
  reading_remove(v, g);
  lws_sul_cancel(&g->sul);
}

/* Hands the connection on: a copy of its descriptor, with the head it sent, goes to
 * the HTTP vhost from the loop (not from inside this connection's callback); this
 * raw connection then closes its own descriptor only (a raw socket is not shut
 * down on close). Returns the callback's answer. */
static int gate_pass(struct gate *g, size_t head_len) {
  int fd = fcntl(lws_get_socket_fd(g->wsi), F_DUPFD_CLOEXEC, 0);
  struct handoff *h = fd >= 0 ? malloc(sizeof *h + head_len) : NULL;
  if (!h) {
    if (fd >= 0) close(fd);
    gate_answer(g, 503, "out of descriptors or memory", 0);
    return 0;
  }
  gate_hand_over(g, h, fd, head_len, GATE_PASSED);
  return -1;
}

/* Bytes to the other end of a relay; when that end's socket is full, this end stops
 * being read until it drains (its RAW_WRITEABLE), so that libwebsockets' writes to a
 * client that reads slowly back up to its own queue, which drops the client. */
static int relay_send(struct gate *from, struct gate *to, const void *data, size_t n) {
  unsigned char *buf = n <= RELAY_CHUNK ? from->v->relay_buf : malloc(LWS_PRE + n);
  if (!buf) return -1;
  memcpy(buf + LWS_PRE, data, n);
  int w = lws_write(to->wsi, buf + LWS_PRE, n, LWS_WRITE_RAW);
  if (buf != from->v->relay_buf) free(buf);
  if (w < (int)n) return -1;
  if (lws_send_pipe_choked(to->wsi)) {
    lws_rx_flow_control(from->wsi, 0);
    lws_callback_on_writable(to->wsi);
  }
  return 0;
}

/* The relay's end of its socket pair closes: what libwebsockets wrote into the
 * pair and the relay has not read yet (it stops reading while the client's
 * socket is full: a slow client's close frame, 1013) goes to the client before
 * its end closes too. Without this, a client dropped as too slow now and then
 * got no close frame at all (1006). */
static void relay_forward_rest(struct gate *g, struct gate *o) {
  int fd = lws_get_socket_fd(g->wsi);
  if (fd < 0) return;
  unsigned char b[16384];
  for (ssize_t n; (n = recv(fd, b, sizeof b, MSG_DONTWAIT)) > 0;)
    if (relay_send(g, o, b, (size_t)n)) break;
}

/* Reads the client's frame headers in data[n]: the offset of the first frame that
 * is not masked (RFC 6455 5.1: a server must close the connection), or n. */
static size_t relay_scan(struct gate *g, const unsigned char *d, size_t n) {
  size_t i = 0;
  while (i < n) {
    if (g->f_left) {
      size_t take = g->f_left < n - i ? (size_t)g->f_left : n - i;
      g->f_left -= take;
      i += take;
      continue;
    }
    size_t start = i - g->fh_len; /* where this frame began, when within data */
    g->fh[g->fh_len++] = d[i++];
    if (g->fh_len == 2) {
      if (!(g->fh[1] & 0x80)) return g->fh_len <= i ? start : 0;
      unsigned l7 = g->fh[1] & 0x7f;
      g->fh_need = 2 + (l7 == 126 ? 2 : l7 == 127 ? 8 : 0) + 4;
    }
    if (g->fh_len >= 2 && g->fh_len == g->fh_need) {
      unsigned l7 = g->fh[1] & 0x7f;
      uint64_t len = l7;
      if (l7 >= 126) {
        len = 0;
        for (size_t k = 0; k < (l7 == 126 ? 2u : 8u); k++) len = len << 8 | g->fh[2 + k];
      }
      g->f_left = len;
      g->fh_len = g->fh_need = 0;
    }
  }
  return n;
}

/* The Sec-WebSocket-Protocol lines of the canonical head buf[n] (vlff_head_canon),
 * joined with commas into out[cap]. */
static void head_protocols(const char *buf, size_t n, char *out, size_t cap) {
  static const char name[] = "Sec-WebSocket-Protocol:";
  size_t o = 0;
  out[0] = 0;
  for (const char *q = buf, *e = buf + n; q < e;) {
    const char *le = memchr(q, '\n', (size_t)(e - q));
    if (!le) break;
    if ((size_t)(le - q) > sizeof name - 1 && !strncasecmp(q, name, sizeof name - 1)) {
      const char *v = q + sizeof name - 1, *ve = le > v && le[-1] == '\r' ? le - 1 : le;
      while (v < ve && (*v == ' ' || *v == '\t')) v++;
      while (ve > v && (ve[-1] == ' ' || ve[-1] == '\t')) ve--;
      int w = snprintf(out + o, cap - o, "%s%.*s", o ? "," : "", (int)(ve - v), v);
      if (w < 0 || (size_t)w >= cap - o) break;
      o += (size_t)w;
    }
    q = le + 1;
  }
}

/* Whether a checked WebSocket upgrade (its canonical head buf[n]) is served: 0, or
 * the HTTP status that refuses it with the sentence in why[len]: 400 when it does not
 * offer the Foxglove subprotocol, 503 when all client slots are taken. */
static int upgrade_refusal(struct vlff_view *v, const char *buf, size_t n, char *why, size_t len) {
  char offered[256];
  head_protocols(buf, n, offered, sizeof offered);
  if (!offers_foxglove(offered)) {
    snprintf(why, len, "unknown or missing WebSocket subprotocol \"%s\"; this server speaks " FOX_PROTOCOL,
             VLFF_QMAX(offered, 60));
    return 400;
  }
  if (v->c.clients >= v->p.max_clients) {
    snprintf(why, len, "too many clients (%d); try again later", v->p.max_clients);
    return 503;
  }
  return 0;
}

/* Hands a WebSocket upgrade on through a socket pair: libwebsockets serves one end
 * (with the head, from the loop), the gate relays between the client and the other
 * end, reading the client's frame headers on the way. */
static int relay_start(struct gate *g, size_t head_len) {
  struct vlff_view *v = g->v;
  int sp[2] = {-1, -1};
  struct handoff *h = NULL;
  struct peer_note *pn = NULL;
  if (socketpair(AF_UNIX, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0, sp) == 0) {
    h = malloc(sizeof *h + head_len);
    pn = malloc(sizeof *pn);
  }
  if (!h || !pn) {
    if (sp[0] >= 0) close(sp[0]), close(sp[1]);
    free(h);
    free(pn);
    gate_answer(g, 503, "out of descriptors or memory", 0);
    return 0;
  }
  lws_sock_file_fd_type u;
  u.sockfd = sp[0];
  v->adopting = g;
  struct lws *in = lws_adopt_descriptor_vhost(v->vh, LWS_ADOPT_SOCKET, u, GATE_PROTOCOL, NULL);
  v->adopting = NULL;
  if (!in || !g->pair) { /* libwebsockets closed sp[0] */
    close(sp[1]);
    free(h);
    free(pn);
    gate_answer(g, 503, "out of descriptors or memory", 0);
    return 0;
  }
  forget_peer(v, sp[1]);
  pn->fd = sp[1];
  snprintf(pn->peer, sizeof pn->peer, "%s", g->peer);
  pn->next = v->peer_notes;
  v->peer_notes = pn;
  gate_hand_over(g, h, sp[1], head_len, GATE_RELAY);
  v->gate_pending--; /* a WebSocket now: its client slot is counted on the other side */
  lws_set_timeout(g->wsi, NO_PENDING_TIMEOUT, 0);
  return 0;
}

/* The relayed client sent a frame that is not masked: a close frame 1002 goes to it
 * straight away, libwebsockets' end is dropped, the client's socket closes once the
 * close frame is out. */
static void relay_refuse_unmasked(struct gate *g) {
  struct vlff_view *v = g->v;
  static const char why[] = "client frames must be masked (RFC 6455 5.1)";
  unsigned char f[2 + 2 + sizeof why - 1];
  f[0] = 0x88;
  f[1] = (unsigned char)(2 + sizeof why - 1);
  f[2] = 1002 >> 8;
  f[3] = 1002 & 0xff;
  memcpy(f + 4, why, sizeof why - 1);
  v->c.refused++;
  v->c.bad_requests++;
  vlff_warn_limited(&v->ws_refusals, "vlff-view", "refused %s: %s [WebSocket close 1002]", g->peer, why);
  if (g->pair) {
    g->pair->pair = NULL;
    lws_set_timeout(g->pair->wsi, PENDING_TIMEOUT_USER_REASON_BASE, LWS_TO_KILL_ASYNC);
    g->pair = NULL;
  }
  unsigned char buf[LWS_PRE + sizeof f];
  memcpy(buf + LWS_PRE, f, sizeof f);
  lws_write(g->wsi, buf + LWS_PRE, sizeof f, LWS_WRITE_RAW);
  g->closing = 1;
  lws_set_timeout(g->wsi, PENDING_TIMEOUT_USER_REASON_BASE, 2 * GATE_LINGER_S);
  lws_callback_on_writable(g->wsi);
}

static void accept_resume(lws_sorted_usec_list_t *sul) {
  struct vlff_view *v = lws_container_of(sul, struct vlff_view, accept_sul);
  if (v->listen_wsi) lws_rx_flow_control(v->listen_wsi, 1);
}

/* The listener is readable: accept what waits (a bounded burst, so that the loop
 * goes on serving) and hand each connection to the gate. Out of descriptors (or
 * memory), the listener stops being watched for ACCEPT_PAUSE_US: the connections
 * wait in the kernel's backlog, and the log says so at the rate limit. */
static void accept_some(struct vlff_view *v, struct lws *wsi) {
  for (int i = 0; i < ACCEPT_BURST; i++) {
    int fd = accept4(v->listen_fd, NULL, NULL, SOCK_NONBLOCK | SOCK_CLOEXEC);
    if (fd < 0) {
      if (errno == EAGAIN || errno == EWOULDBLOCK) return;
      if (errno == EINTR || errno == ECONNABORTED || errno == EPROTO) continue;
      int e = errno;
      vlff_warn_limited(&v->accept_failures, "vlff-view",
                        "cannot accept a connection: %s; not accepting for %d ms [%llu so far]", strerror(e),
                        ACCEPT_PAUSE_US / 1000, (unsigned long long)v->accept_failures + 1);
      lws_rx_flow_control(wsi, 0);
      lws_sul_schedule(v->ctx, 0, &v->accept_sul, accept_resume, ACCEPT_PAUSE_US);
      return;
    }
    lws_sock_file_fd_type u;
    u.sockfd = fd;
    /* on failure libwebsockets closes the descriptor itself */
    lws_adopt_descriptor_vhost(v->vh, LWS_ADOPT_SOCKET, u, GATE_PROTOCOL, NULL);
  }
}

static int gate_cb(struct lws *wsi, enum lws_callback_reasons reason, void *user, void *in, size_t len) {
  struct vlff_view *v = lws_context_user(lws_get_context(wsi));
  struct gate *g = user;
  switch (reason) {
  case LWS_CALLBACK_RAW_ADOPT_FILE: return 0; /* the listener */
  case LWS_CALLBACK_RAW_RX_FILE:
    if (wsi == v->listen_wsi) accept_some(v, wsi);
    return 0;
  case LWS_CALLBACK_RAW_CLOSE_FILE:
    if (wsi == v->listen_wsi) v->listen_wsi = NULL;
    return 0;
  case LWS_CALLBACK_RAW_ADOPT:
    memset(g, 0, offsetof(struct gate, resp));
    g->v = v;
    g->wsi = wsi;
    if (v->adopting) { /* the viewer's end of a relay's socket pair */
      g->inner = 1;
      g->state = GATE_RELAY;
      g->pair = v->adopting;
      v->adopting->pair = g;
      snprintf(g->peer, sizeof g->peer, "%s", g->pair->peer);
      return 0;
    }
    lws_get_peer_simple(wsi, g->peer, sizeof g->peer);
    v->gate_pending++;
    /* the last word on how long a connection may stay here, whatever happens */
    lws_set_timeout(wsi, PENDING_TIMEOUT_USER_REASON_BASE, v->head_timeout_s + 2 * GATE_LINGER_S);
    if (v->gate_pending > GATE_TOTAL_MAX) {
      char why[96];
      snprintf(why, sizeof why, "more than %d connections are at the gate", GATE_TOTAL_MAX);
      gate_answer(g, 503, why, 0);
    } else {
      /* full of unfinished heads: the oldest makes room, so that connections that
       * stall cannot lock out those that send their head at once */
      if (v->gate_reading >= GATE_PENDING_MAX && v->oldest) {
        char why[120];
        snprintf(why, sizeof why, "%d request heads were unfinished: the oldest is closed to make room",
                 GATE_PENDING_MAX);
        gate_answer(v->oldest, 408, why, 0);
      }
      reading_add(v, g);
      lws_sul_schedule(lws_get_context(wsi), 0, &g->sul, gate_deadline, (lws_usec_t)v->head_timeout_s * LWS_US_PER_SEC);
    }
    return 0;
  case LWS_CALLBACK_RAW_RX: {
    if (!g->v) return -1;
    if (g->state == GATE_RELAY) {
      if (!g->pair || g->closing) return 0; /* the other end is gone: drop */
      if (g->inner) return relay_send(g, g->pair, in, len);
      size_t ok = relay_scan(g, in, len);
      if (ok && relay_send(g, g->pair, in, ok)) {
        /* The viewer's end is gone (it has just closed this client): the
         * client's bytes have nowhere to go. Closing here reset the
         * connection with them unread, and the reset destroyed what the
         * viewer sent last, its close frame, before the client read it
         * (1006 rather than 1013 for a client dropped as too slow). This end
         * is ended in order instead: flushed, shut, lingering. */
        g->closing = 1;
        lws_set_timeout(wsi, PENDING_TIMEOUT_USER_REASON_BASE, 2 * GATE_LINGER_S);
        lws_callback_on_writable(wsi);
        return 0;
      }
      if (ok < len) relay_refuse_unmasked(g);
      return 0;
    }
    if (g->state != GATE_READING) {
      g->drained += len; /* a refused client still sending: read and drop, up to a bound */
      return g->drained > GATE_DRAIN_MAX ? -1 : 0;
    }
    size_t take = len < sizeof g->buf - g->len ? len : sizeof g->buf - g->len;
    memcpy(g->buf + g->len, in, take);
    g->len += take;
    struct vlff_head h;
    switch (vlff_head_check(g->buf, g->len, &v->page, &v->allow, &h)) {
    case VLFF_HEAD_MORE: return 0;
    case VLFF_HEAD_REFUSE: gate_answer(g, h.status, h.why, h.is_head); return 0;
    case VLFF_HEAD_PASS: {
      /* only the header lines the server uses reach libwebsockets' parser */
      char canon[VLFF_HTTP_HEAD_MAX + 1];
      size_t n = vlff_head_canon(g->buf, &h, canon, sizeof canon);
      if (!n) {
        gate_answer(g, 400, "the request head could not be rewritten", 0);
        return 0;
      }
      memcpy(g->buf, canon, n);
      if (h.upgrade) {
        /* refused here, before the relay, so that the answer is the viewer's own
         * plain sentence rather than libwebsockets' error page */
        char why[160];
        int code = upgrade_refusal(v, g->buf, n, why, sizeof why);
        if (code) {
          gate_answer(g, code, why, 0);
          return 0;
        }
        return relay_start(g, n);
      }
      return gate_pass(g, n);
    }
    }
    return -1;
  }
  case LWS_CALLBACK_RAW_WRITEABLE:
    if (!g->v) return -1;
    if (g->state == GATE_RELAY) {
      if (lws_send_pipe_choked(wsi)) {
        lws_callback_on_writable(wsi);
      } else if (g->closing) {
        /* what was queued for the client is out: end our side, linger for its close */
        shutdown(lws_get_socket_fd(wsi), SHUT_WR);
        g->state = GATE_DRAINING;
        lws_set_timeout(wsi, PENDING_TIMEOUT_USER_REASON_BASE, GATE_LINGER_S);
      } else if (g->pair) {
        lws_rx_flow_control(g->pair->wsi, 1); /* drained: read the other end again */
      }
      return 0;
    }
    if (g->state == GATE_ANSWERING) {
      if (lws_write(wsi, (unsigned char *)g->resp + LWS_PRE, g->resp_len, LWS_WRITE_RAW) < 0) return -1;
      g->state = GATE_FLUSHING; /* called again once libwebsockets has sent it all */
      lws_callback_on_writable(wsi);
    } else if (g->state == GATE_FLUSHING) {
      /* the client may still be sending: a close with its bytes unread would reset
       * the connection, and the reset can destroy the answer before the client
       * reads it. End our side and read until it closes or the linger ends. */
      shutdown(lws_get_socket_fd(wsi), SHUT_WR);
      g->state = GATE_DRAINING;
      lws_set_timeout(wsi, PENDING_TIMEOUT_USER_REASON_BASE, GATE_LINGER_S);
    }
    return 0;
  case LWS_CALLBACK_RAW_CLOSE:
    if (g->v) {
      lws_sul_cancel(&g->sul);
      reading_remove(v, g);
      if (g->pair) { /* the relay's other end follows */
        struct gate *o = g->pair;
        o->pair = NULL;
        if (o->inner) {
          lws_set_timeout(o->wsi, PENDING_TIMEOUT_USER_REASON_BASE, LWS_TO_KILL_ASYNC);
        } else { /* the client gets what libwebsockets sent (its close frame) first */
          relay_forward_rest(g, o);
          o->closing = 1;
          lws_set_timeout(o->wsi, PENDING_TIMEOUT_USER_REASON_BASE, 2 * GATE_LINGER_S);
          lws_callback_on_writable(o->wsi);
        }
      }
      if (!g->inner && g->state != GATE_RELAY && !(g->state == GATE_DRAINING && g->closing)) v->gate_pending--;
      g->v = NULL;
    }
    return 0;
  default:
    return 0;
  }
}

/* ------------------------------------------------------------- HTTP side */

static int add_header(struct lws *wsi, const char *name, const char *value, unsigned char **p, unsigned char *end) {
  return lws_add_http_header_by_name(wsi, (const unsigned char *)name, (const unsigned char *)value,
                                     (int)strlen(value), p, end);
}

/* A passed head: a page file (GET or HEAD) or an upgrade. A refusal here closes
 * the connection, so that no further request on it skips the gate. */
static int http_cb(struct lws *wsi, enum lws_callback_reasons reason, void *user, void *in, size_t len) {
  struct vlff_view *v = lws_context_user(lws_get_context(wsi));
  struct http_session *s = user;
  char peer[64] = "?", why[160];
  switch (reason) {
  case LWS_CALLBACK_HTTP_CONFIRM_UPGRADE: {
    if (!in || strcmp(in, "websocket")) break;
    char offered[256] = "";
    lws_hdr_copy(wsi, offered, sizeof offered, WSI_TOKEN_PROTOCOL);
    int code = 0;
    if (!offers_foxglove(offered)) {
      snprintf(why, sizeof why, "unknown or missing WebSocket subprotocol \"%s\"; this server speaks " FOX_PROTOCOL,
               VLFF_QMAX(offered, 60));
      code = HTTP_STATUS_BAD_REQUEST;
    } else if (v->c.clients >= v->p.max_clients) {
      snprintf(why, sizeof why, "too many clients (%d); try again later", v->p.max_clients);
      code = HTTP_STATUS_SERVICE_UNAVAILABLE;
    }
    if (!code) return 0;
    peer_of(v, wsi, peer, sizeof peer);
    count_refusal(v, peer, code, why);
    lws_return_http_status(wsi, (unsigned)code, why);
    return -1;
  }
  case LWS_CALLBACK_HTTP: {
    const char *uri = in ? in : "";
    const struct vlff_page_file *f = vlff_page_find(&v->page, uri, strlen(uri));
    if (!f) { /* the gate passes listed files only; this is the second line */
      lws_get_peer_simple(wsi, peer, sizeof peer);
      snprintf(why, sizeof why, "%s is not a file of this page", VLFF_QMAX(uri, 60));
      count_refusal(v, peer, HTTP_STATUS_NOT_FOUND, why);
      lws_return_http_status(wsi, HTTP_STATUS_NOT_FOUND, why);
      return -1;
    }
    s->f = f;
    s->off = 0;
    s->head_only = lws_hdr_total_length(wsi, WSI_TOKEN_HEAD_URI) > 0;
    unsigned char hdr[LWS_PRE + 1024], *start = hdr + LWS_PRE, *p = start, *end = hdr + sizeof hdr - 1;
    if (lws_add_http_common_headers(wsi, HTTP_STATUS_OK, f->mime, f->len, &p, end) ||
        add_header(wsi, "content-security-policy:", VLFF_PAGE_CSP, &p, end) ||
        add_header(wsi, "x-content-type-options:", "nosniff", &p, end) ||
        add_header(wsi, "referrer-policy:", "no-referrer", &p, end) ||
        add_header(wsi, "cache-control:", "no-cache", &p, end) ||
        lws_add_http_header_by_token(wsi, WSI_TOKEN_CONNECTION, (const unsigned char *)"close", 5, &p, end) ||
        lws_finalize_write_http_header(wsi, start, &p, end))
      return -1;
    lws_callback_on_writable(wsi);
    return 0;
  }
  case LWS_CALLBACK_HTTP_WRITEABLE: {
    /* called again only once everything written before has gone out: with the
     * whole file sent, the connection closes (one request per connection) */
    if (!s->f || s->head_only || s->off == s->f->len) return -1;
    size_t n = s->f->len - s->off < PAGE_CHUNK ? s->f->len - s->off : PAGE_CHUNK;
    unsigned char buf[LWS_PRE + PAGE_CHUNK];
    memcpy(buf + LWS_PRE, s->f->data + s->off, n);
    int last = s->off + n == s->f->len;
    if (lws_write(wsi, buf + LWS_PRE, n, last ? LWS_WRITE_HTTP_FINAL : LWS_WRITE_HTTP) < (int)n) return -1;
    s->off += n;
    lws_callback_on_writable(wsi);
    return 0;
  }
  default:
    break;
  }
  return lws_callback_http_dummy(wsi, reason, user, in, len);
}

/* libwebsockets' own lines go through the viewer's rate limit: one counter per kind
 * of line (its text without digits, so "accept: errno 24" is one kind however often
 * it comes), the first five of each and every 1000th logged. */
#define LWS_LOG_KINDS 16
static struct {
  char key[48];
  uint64_t count;
} lws_log_kinds[LWS_LOG_KINDS];

static void log_lws(int level, const char *line) {
  /* lws_adopt_socket_vhost_readbuf reports its ordinary path at error level: every
   * passed request would log it */
  if (strstr(line, "adopt_socket_readbuf")) return;
  if (!(level & (LLL_ERR | LLL_WARN))) return;
  const char *msg = strstr(line, "] ");
  msg = msg ? msg + 2 : line; /* after lws' own time stamp */
  int n = (int)strcspn(msg, "\r\n");
  char key[48];
  size_t k = 0;
  for (const char *p = msg; p < msg + n && k < sizeof key - 1; p++)
    if (*p < '0' || *p > '9') key[k++] = *p;
  key[k] = 0;
  int slot = LWS_LOG_KINDS - 1; /* the last kind is shared by all the others */
  for (int i = 0; i < LWS_LOG_KINDS - 1; i++)
    if (!lws_log_kinds[i].key[0] || !strcmp(lws_log_kinds[i].key, key)) {
      if (!lws_log_kinds[i].key[0]) memcpy(lws_log_kinds[i].key, key, k + 1);
      slot = i;
      break;
    }
  vlff_warn_limited(&lws_log_kinds[slot].count, "vlff-view", "libwebsockets: %.*s [%llu so far]", n, msg,
                    (unsigned long long)lws_log_kinds[slot].count + 1);
}

static int is_loopback(const struct sockaddr *sa) {
  if (sa->sa_family == AF_INET) return (ntohl(((const struct sockaddr_in *)sa)->sin_addr.s_addr) >> 24) == 127;
  if (sa->sa_family == AF_INET6) return IN6_IS_ADDR_LOOPBACK(&((const struct sockaddr_in6 *)sa)->sin6_addr);
  return 0;
}

/* An address as a Host names it: IPv4 dotted, IPv6 in brackets. */
static void add_addr(struct vlff_allow *a, const struct sockaddr *sa) {
  char s[INET6_ADDRSTRLEN + 2] = "[";
  if (sa->sa_family == AF_INET && inet_ntop(AF_INET, &((const struct sockaddr_in *)sa)->sin_addr, s, sizeof s))
    vlff_allow_name(a, s);
  else if (sa->sa_family == AF_INET6 &&
           inet_ntop(AF_INET6, &((const struct sockaddr_in6 *)sa)->sin6_addr, s + 1, sizeof s - 2)) {
    if (strchr(s, '%')) return; /* link-local with a zone: not a Host a browser sends */
    strcat(s, "]");
    vlff_allow_name(a, s);
  }
}

/* The viewer's own names, which a Host (and an Origin's authority) may carry: its
 * listening address; every address of the machine (and its host name) when it
 * listens on all of them or on an interface; "localhost", "127.0.0.1" and "[::1]"
 * when one of them is a loopback address. Then the configured origins. */
static int build_allow(struct vlff_view *v) {
  struct vlff_allow *a = &v->allow;
  a->port = v->port;
  const char *addr = v->p.address ? v->p.address : "";
  struct in_addr in4;
  int any = !*addr || !strcmp(addr, "0.0.0.0"), loop = !strcmp(addr, "localhost");
  if (!any && !loop && inet_pton(AF_INET, addr, &in4) == 1) {
    /* In storage of any family's size: is_loopback reads the address by its family. */
    struct sockaddr_storage ss = {0};
    struct sockaddr_in *sin = (struct sockaddr_in *)&ss;
    sin->sin_family = AF_INET;
    sin->sin_addr = in4;
    add_addr(a, (struct sockaddr *)&ss);
    loop = is_loopback((struct sockaddr *)&ss);
  } else if (!loop) {
    /* all addresses, or those of the interface named */
    struct ifaddrs *ifs = NULL;
    if (getifaddrs(&ifs) == 0) {
      for (struct ifaddrs *i = ifs; i; i = i->ifa_next) {
        if (!i->ifa_addr || (!any && strcmp(i->ifa_name, addr))) continue;
        add_addr(a, i->ifa_addr);
        loop |= is_loopback(i->ifa_addr);
      }
      freeifaddrs(ifs);
    }
    char host[256];
    if (any && gethostname(host, sizeof host) == 0) {
      host[sizeof host - 1] = 0;
      vlff_allow_name(a, host);
    }
  }
  if (loop) {
    vlff_allow_name(a, "localhost");
    vlff_allow_name(a, "127.0.0.1");
    vlff_allow_name(a, "[::1]");
  }
  for (int i = 0; i < v->p.n_allow_origins; i++) {
    char why[200];
    if (vlff_allow_origin(a, v->p.allow_origins[i], why, sizeof why)) {
      vlff_log(VLFF_LOG_INFO, "vlff-view", "--allow-origin %s", why);
      return -1;
    }
  }
  return 0;
}

/* The listening socket on the address (an IPv4 address, or an interface's first
 * one; "0.0.0.0" all) and port, watched by the loop as a raw file of the gate. */
static int open_listener(struct vlff_view *v) {
  const char *addr = v->p.address ? v->p.address : "0.0.0.0";
  struct sockaddr_in sin = {.sin_family = AF_INET, .sin_port = htons((uint16_t)v->p.port)};
  if (!strcmp(addr, "localhost")) addr = "127.0.0.1";
  if (inet_pton(AF_INET, addr, &sin.sin_addr) != 1) {
    int found = 0;
    struct ifaddrs *ifs = NULL;
    if (getifaddrs(&ifs) == 0) {
      for (struct ifaddrs *i = ifs; i && !found; i = i->ifa_next)
        if (i->ifa_addr && i->ifa_addr->sa_family == AF_INET && !strcmp(i->ifa_name, addr)) {
          sin.sin_addr = ((struct sockaddr_in *)i->ifa_addr)->sin_addr;
          found = 1;
        }
      freeifaddrs(ifs);
    }
    if (!found) {
      vlff_log(VLFF_LOG_INFO, "vlff-view", "--listen %s is neither an IPv4 address nor an interface with one", addr);
      return -1;
    }
  }
  int one = 1;
  socklen_t sl = sizeof sin;
  v->listen_fd = socket(AF_INET, SOCK_STREAM | SOCK_NONBLOCK | SOCK_CLOEXEC, 0);
  if (v->listen_fd < 0 || setsockopt(v->listen_fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one) != 0 ||
      bind(v->listen_fd, (struct sockaddr *)&sin, sizeof sin) != 0 || listen(v->listen_fd, SOMAXCONN) != 0 ||
      getsockname(v->listen_fd, (struct sockaddr *)&sin, &sl) != 0) {
    vlff_log(VLFF_LOG_WARN, "vlff-view", "cannot listen on %s:%d: %s", addr, v->p.port, strerror(errno));
    if (v->listen_fd >= 0) close(v->listen_fd);
    v->listen_fd = -1;
    return -1;
  }
  v->port = ntohs(sin.sin_port);
  lws_sock_file_fd_type u;
  u.filefd = v->listen_fd;
  v->listen_wsi = lws_adopt_descriptor_vhost(v->vh, LWS_ADOPT_RAW_FILE_DESC, u, GATE_PROTOCOL, NULL);
  if (!v->listen_wsi) {
    v->listen_fd = -1; /* closed by libwebsockets */
    vlff_log(VLFF_LOG_WARN, "vlff-view", "cannot watch the listening socket");
    return -1;
  }
  return 0;
}

struct vlff_view *vlff_view_new(const struct vlff_view_params *p, struct vlff_feed *feed) {
  struct vlff_view *v = calloc(1, sizeof *v);
  if (!v) return NULL;
  v->p = *p;
  v->feed = feed;
  v->nch = p->play ? vlff_view_play_channels(p->play) : VLFF_VIEW_CH_COUNT;
  if (!p->play && !(v->log = vlff_view_log_new())) {
    free(v);
    return NULL;
  }
  if (p->record && (p->play || declare_channels(v))) {
    if (p->play) vlff_log(VLFF_LOG_WARN, "vlff-view", "--record and --play together: a recording is not re-recorded");
    vlff_view_log_free(v->log);
    free(v);
    return NULL;
  }
  v->listen_fd = -1;
  if (vlff_page_load(&v->page, p->www_dir) != 0) {
    vlff_view_log_free(v->log);
    free(v);
    return NULL;
  }
  lws_set_log_level(LLL_ERR | LLL_WARN | (p->verbose > 1 ? LLL_NOTICE | LLL_INFO : 0), log_lws);
  v->head_timeout_s = p->head_timeout_s > 0 ? (int)(p->head_timeout_s + 0.5) : HEAD_TIMEOUT_S;
  v->idle_timeout_s = p->idle_timeout_s > 0 ? (int)(p->idle_timeout_s + 0.5) : IDLE_TIMEOUT_S;
  if (v->head_timeout_s < 1) v->head_timeout_s = 1;
  if (v->idle_timeout_s < 3) v->idle_timeout_s = 3;

  v->gate_protocols[0] = (struct lws_protocols){GATE_PROTOCOL, gate_cb, sizeof(struct gate), RELAY_CHUNK, 0, NULL, 0};
  v->protocols[0] = (struct lws_protocols){"http", http_cb, sizeof(struct http_session), 0, 0, NULL, 0};
  v->protocols[1] = (struct lws_protocols){FOX_PROTOCOL, fox_cb, sizeof(struct client), 65536, 0, NULL, 0};

  struct lws_context_creation_info info;
  memset(&info, 0, sizeof info);
  /* libwebsockets reads this option from the context's options, not the vhost's: a
   * text frame that is not UTF-8 is closed with 1007 */
  info.options = LWS_SERVER_OPTION_EXPLICIT_VHOSTS | LWS_SERVER_OPTION_VALIDATE_UTF8;
  info.user = v;
  /* room for any head the gate passes */
  info.max_http_header_data = VLFF_HTTP_HEAD_MAX + 1024;
  /* raw reads (the gate's relays) take at most this much at a time */
  info.pt_serv_buf_size = RELAY_CHUNK;
  v->ctx = lws_create_context(&info);
  if (!v->ctx) {
    vlff_log(VLFF_LOG_WARN, "vlff-view", "cannot start libwebsockets");
    vlff_page_free(&v->page);
    free(v);
    return NULL;
  }
  /* the gate's vhost: every connection, accepted by the viewer, a raw socket of it */
  /* "no listener" in the client sense: libwebsockets picks the vhost of a request
   * handed on by its port, and that must be the HTTP side's (NO_LISTEN_SERVER) */
  info.port = CONTEXT_PORT_NO_LISTEN;
  info.protocols = v->gate_protocols;
  info.options = LWS_SERVER_OPTION_DISABLE_IPV6;
  info.vhost_name = "vlff-view";
  v->vh = lws_create_vhost(v->ctx, &info);
  if (!v->vh) {
    vlff_log(VLFF_LOG_WARN, "vlff-view", "cannot create the gate");
    vlff_view_free(v);
    return NULL;
  }
  if (open_listener(v) != 0) {
    vlff_view_free(v);
    return NULL;
  }
  if (build_allow(v) != 0) {
    vlff_view_free(v);
    return NULL;
  }
  /* the HTTP and WebSocket side: no socket of its own, it takes passed heads */
  memset(&info, 0, sizeof info);
  info.port = CONTEXT_PORT_NO_LISTEN_SERVER;
  info.protocols = v->protocols;
  info.options = LWS_SERVER_OPTION_VALIDATE_UTF8 | LWS_SERVER_OPTION_DISABLE_IPV6;
  info.vhost_name = "vlff-view-http";
  v->http_vh = lws_create_vhost(v->ctx, &info);
  if (!v->http_vh) {
    vlff_log(VLFF_LOG_WARN, "vlff-view", "cannot create the HTTP side");
    vlff_view_free(v);
    return NULL;
  }
  lws_sul_schedule(v->ctx, 0, &v->sul, tick, 1);
  return v;
}

int vlff_view_port(const struct vlff_view *v) { return v->port; }

int vlff_view_run(struct vlff_view *v) {
  while (!v->stop)
    if (lws_service(v->ctx, 0) < 0) return -1;
  return 0;
}

void vlff_view_stop(struct vlff_view *v) {
  v->stop = 1;
  lws_cancel_service(v->ctx);
}

void vlff_view_free(struct vlff_view *v) {
  if (!v) return;
  lws_sul_cancel(&v->sul);
  lws_sul_cancel(&v->handoff_sul);
  lws_sul_cancel(&v->answer_sul);
  lws_sul_cancel(&v->accept_sul);
  while (v->handoffs) {
    struct handoff *h = v->handoffs;
    v->handoffs = h->next;
    close(h->fd);
    free(h);
  }
  lws_context_destroy(v->ctx);
  while (v->peer_notes) {
    struct peer_note *n = v->peer_notes;
    v->peer_notes = n->next;
    free(n);
  }
  vlff_prompts_close(v->mailbox);
  vlff_page_free(&v->page);
  vlff_view_log_free(v->log);
  free(v);
}
