/*
 * The CAN thread: heartbeat, status, commands and error frames on one raw
 * SocketCAN socket.
 *
 * Timing idea: the thread waits for commands with ppoll() only until a guard
 * interval before the next deadline, then sleeps the rest with
 * clock_nanosleep(TIMER_ABSTIME). Deadlines advance by whole periods from
 * the first one, so scheduling delays never accumulate into drift, and the
 * last wake is always an absolute timer (with timer slack at 1 ns) rather
 * than a relative timeout computed some microseconds earlier. Before a
 * heartbeat that timer fires early by a margin learnt from recent wake-up
 * lateness (capped by can.heartbeat_spin_max_us) and the thread spins the
 * rest: on a loaded machine a timer alone is late by scheduler and timer
 * emulation delays that no priority removes.
 *
 * The learner hands its status over through a seqlock whose payload is
 * atomics: it never waits for this thread, and ThreadSanitizer sees no race.
 * The socket is non-blocking: a frame the kernel will not queue is dropped
 * and counted. ENETDOWN/ENODEV close the socket; reopening is retried with
 * exponential backoff until the interface is up again.
 */
#include "vlff_can.h"

#include <errno.h>
#include <fcntl.h>
#include <inttypes.h>
#include <linux/can.h>
#include <linux/can/raw.h>
#include <net/if.h>
#include <poll.h>
#include <pthread.h>
#include <sched.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/eventfd.h>
#include <sys/ioctl.h>
#include <sys/prctl.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#include "can_proto.h"
#include "clock.h"
#include "config.h"
#include "log.h"
#include "vlff/escape.h"

#define TAG "can"
#define NS 1000000000LL
#define GUARD_NS 2000000LL      /* last stretch before a deadline: absolute sleep */
#define SPIN_MIN_NS 100000LL    /* smallest early wake before a heartbeat */
#define BACKOFF_MIN_NS 50000000LL
#define BACKOFF_MAX_NS 2000000000LL

#define STATUS_WORDS (sizeof(struct vlff_can_status) / sizeof(uint32_t))
_Static_assert(sizeof(struct vlff_can_status) % sizeof(uint32_t) == 0, "status is copied as 32-bit words");

struct vlff_can {
  /* Settings copied from the config at open. */
  char iface[IFNAMSIZ];
  int node_id;
  int64_t hb_ns, status_ns;
  uint32_t status_base, cmd_id, ack_id;
  bool want_fd;
  int prompt_sets;
  int rt_priority;
  int64_t spin_max_ns;       /* cap on the early-wake margin; 0 = plain sleep */
  vlff_can_command_fn fn;
  void *ctx;

  pthread_t thread;
  int wake_fd;               /* eventfd: close() wakes the thread */
  atomic_bool stop;

  /* Seqlock: odd while the writer is inside. */
  atomic_uint seq;
  _Atomic uint32_t words[STATUS_WORDS];
  atomic_int nmt_state;

  /* Counters, written by the CAN thread, read by anyone. */
  atomic_bool connected;
  _Atomic uint64_t hb_sent, status_sent, acks_sent, tx_dropped, tx_late, hb_spin_ns, hb_timer_late;
  _Atomic uint64_t cmd_ok, cmd_malformed, cmd_unknown, cmd_range, cmd_other_node;
  _Atomic uint64_t err_frames, bus_off, err_passive, err_warning, ctrl_problems, tx_timeouts, prot_errors;
  _Atomic uint64_t reopens;
  _Atomic uint32_t can_errors;

  /* Owned by the CAN thread. */
  int sock;
  bool fd_frames;            /* the socket sends CAN FD */
  bool ever_opened;
  uint8_t period_errors;     /* VLFF_CAN_BUS_* since the last HEALTH frame */
  uint64_t period_drops_at, period_rejects_at;
  uint32_t period_refused_at[VLFF_CAN_REFUSAL_CODES], period_refused_total_at;
  int64_t last_log_ns;
};

static struct timespec to_ts(int64_t ns) {
  struct timespec ts = {.tv_sec = ns / NS, .tv_nsec = ns % NS};
  return ts;
}

static void inc(_Atomic uint64_t *c) { atomic_fetch_add_explicit(c, 1, memory_order_relaxed); }
static uint64_t ld(const _Atomic uint64_t *c) { return atomic_load_explicit(c, memory_order_relaxed); }

/* ------------------------------------------------------------ names */

const char *vlff_can_nmt_name(int s) {
  switch (s) {
    case VLFF_NMT_BOOTUP: return "boot-up";
    case VLFF_NMT_STOPPED: return "stopped";
    case VLFF_NMT_OPERATIONAL: return "operational";
    case VLFF_NMT_PREOPERATIONAL: return "pre-operational";
    case VLFF_NMT_ERROR: return "error";
    default: return "unknown-state";
  }
}

const char *vlff_can_cmd_name(int c) {
  switch (c) {
    case VLFF_CAN_CMD_START: return "start";
    case VLFF_CAN_CMD_STOP: return "stop";
    case VLFF_CAN_CMD_RESET: return "reset";
    case VLFF_CAN_CMD_SAVE: return "save";
    case VLFF_CAN_CMD_PROMPT_SET: return "prompt-set";
    case VLFF_CAN_CMD_PUBLISH: return "publish";
    default: return "unknown-command";
  }
}

const char *vlff_can_result_name(int r) {
  switch (r) {
    case VLFF_CAN_RES_OK: return "ok";
    case VLFF_CAN_RES_UNKNOWN: return "unknown-command";
    case VLFF_CAN_RES_RANGE: return "out-of-range";
    case VLFF_CAN_RES_REFUSED: return "refused";
    case VLFF_CAN_RES_FAILED: return "failed";
    case VLFF_CAN_RES_BUSY: return "busy";
    default: return "unknown-result";
  }
}

/* ------------------------------------------------------------ config */

int vlff_can_check_config(const struct vlff_cfg_can *cfg, char *err, size_t errlen) {
  const int node = cfg->node_id, base = cfg->status_base_id;
  const int hb = VLFF_CANP_HEARTBEAT_BASE + node;
  const int last = base + (cfg->fd ? VLFF_CANP_STATUS_FD_OFFSET : vlff_canp_status_offset(VLFF_CANP_PAGING));
  if (cfg->interface[0] == 0 || strlen(cfg->interface) >= IFNAMSIZ) {
    snprintf(err, errlen, "key 'can.interface': expected an interface name of 1..%d characters, got '%s'",
             IFNAMSIZ - 1, VLFF_Q(cfg->interface));
    return -1;
  }
  if (node < 1 || node > 127) {
    snprintf(err, errlen, "key 'can.node_id': expected integer in [1, 127], got %d", node);
    return -1;
  }
  if (last > 0x7ff) {
    snprintf(err, errlen, "key 'can.status_base_id': status frames 0x%x..0x%x run past 0x7ff", base, last);
    return -1;
  }
  const struct { const char *key; int id; } one[] = {
      {"can.command_id", cfg->command_id}, {"can.ack_id", cfg->ack_id}};
  for (int i = 0; i < 2; i++) {
    if (one[i].id == hb) {
      snprintf(err, errlen, "key '%s': 0x%x is the heartbeat id (0x700 + can.node_id)", one[i].key, one[i].id);
      return -1;
    }
    if (one[i].id >= base && one[i].id <= last) {
      snprintf(err, errlen, "key '%s': 0x%x overlaps the status frames 0x%x..0x%x", one[i].key, one[i].id, base,
               last);
      return -1;
    }
  }
  if (hb >= base && hb <= last) {
    snprintf(err, errlen, "key 'can.status_base_id': status frames 0x%x..0x%x include the heartbeat id 0x%x", base,
             last, hb);
    return -1;
  }
  if (cfg->command_id == cfg->ack_id) {
    snprintf(err, errlen, "key 'can.ack_id': same id as can.command_id (0x%x)", cfg->ack_id);
    return -1;
  }
  return 0;
}

/* ------------------------------------------------------------ status seqlock */

void vlff_can_set_status(struct vlff_can *can, const struct vlff_can_status *st) {
  uint32_t w[STATUS_WORDS];
  memcpy(w, st, sizeof w);
  /* No fences (ThreadSanitizer does not model them): each word is a release
   * store, so a reader that sees any new word also sees the odd sequence. */
  unsigned s = atomic_load_explicit(&can->seq, memory_order_relaxed);
  atomic_store_explicit(&can->seq, s + 1, memory_order_relaxed);
  for (size_t i = 0; i < STATUS_WORDS; i++) atomic_store_explicit(&can->words[i], w[i], memory_order_release);
  atomic_store_explicit(&can->seq, s + 2, memory_order_release);
}

static void read_status(struct vlff_can *can, struct vlff_can_status *st) {
  uint32_t w[STATUS_WORDS];
  for (;;) {
    unsigned s1 = atomic_load_explicit(&can->seq, memory_order_acquire);
    if (s1 & 1) continue;
    for (size_t i = 0; i < STATUS_WORDS; i++) w[i] = atomic_load_explicit(&can->words[i], memory_order_acquire);
    if (atomic_load_explicit(&can->seq, memory_order_relaxed) == s1) break;
  }
  memcpy(st, w, sizeof w);
}

void vlff_can_set_state(struct vlff_can *can, enum vlff_can_nmt state) {
  atomic_store_explicit(&can->nmt_state, (int)state, memory_order_relaxed);
}

void vlff_can_get_stats(const struct vlff_can *can, struct vlff_can_stats *st) {
  memset(st, 0, sizeof *st);
  st->connected = atomic_load_explicit(&can->connected, memory_order_relaxed);
  st->heartbeats_sent = ld(&can->hb_sent);
  st->status_sent = ld(&can->status_sent);
  st->acks_sent = ld(&can->acks_sent);
  st->tx_dropped = ld(&can->tx_dropped);
  st->tx_late = ld(&can->tx_late);
  st->hb_spin_ns = ld(&can->hb_spin_ns);
  st->hb_timer_late = ld(&can->hb_timer_late);
  st->cmd_ok = ld(&can->cmd_ok);
  st->cmd_malformed = ld(&can->cmd_malformed);
  st->cmd_unknown = ld(&can->cmd_unknown);
  st->cmd_range = ld(&can->cmd_range);
  st->cmd_other_node = ld(&can->cmd_other_node);
  st->err_frames = ld(&can->err_frames);
  st->bus_off = ld(&can->bus_off);
  st->err_passive = ld(&can->err_passive);
  st->err_warning = ld(&can->err_warning);
  st->ctrl_problems = ld(&can->ctrl_problems);
  st->tx_timeouts = ld(&can->tx_timeouts);
  st->prot_errors = ld(&can->prot_errors);
  st->reopens = ld(&can->reopens);
  st->can_errors = atomic_load_explicit(&can->can_errors, memory_order_relaxed);
}

/* ------------------------------------------------------------ socket */

/* Rate limit for repeated warnings: one a second. */
static bool may_log(struct vlff_can *can) {
  int64_t now = (int64_t)vlff_now_ns();
  if (now - can->last_log_ns < NS) return false;
  can->last_log_ns = now;
  return true;
}

static void close_sock(struct vlff_can *can, const char *why) {
  if (can->sock < 0) return;
  close(can->sock);
  can->sock = -1;
  atomic_store_explicit(&can->connected, false, memory_order_relaxed);
  VLFF_WARN(TAG, "%s: %s; reopening with backoff", can->iface, why);
}

static int open_sock(struct vlff_can *can) {
  int s = socket(PF_CAN, SOCK_RAW | SOCK_NONBLOCK | SOCK_CLOEXEC, CAN_RAW);
  if (s < 0) return -1;
  struct ifreq ifr;
  memset(&ifr, 0, sizeof ifr);
  snprintf(ifr.ifr_name, sizeof ifr.ifr_name, "%s", can->iface);
  if (ioctl(s, SIOCGIFINDEX, &ifr) < 0) goto fail;
  int ifindex = ifr.ifr_ifindex;
  if (ioctl(s, SIOCGIFFLAGS, &ifr) < 0) goto fail;
  if (!(ifr.ifr_flags & IFF_UP)) {
    errno = ENETDOWN;
    goto fail;
  }
  /* Only our command id (standard frames; RTR ones too, to count them as
   * malformed) and every error class. */
  struct can_filter f = {.can_id = can->cmd_id, .can_mask = CAN_SFF_MASK | CAN_EFF_FLAG};
  can_err_mask_t em = CAN_ERR_MASK;
  if (setsockopt(s, SOL_CAN_RAW, CAN_RAW_FILTER, &f, sizeof f) < 0) goto fail;
  if (setsockopt(s, SOL_CAN_RAW, CAN_RAW_ERR_FILTER, &em, sizeof em) < 0) goto fail;
  can->fd_frames = false;
  if (can->want_fd) {
    int on = 1;
    if (ioctl(s, SIOCGIFMTU, &ifr) == 0 && ifr.ifr_mtu == (int)CANFD_MTU &&
        setsockopt(s, SOL_CAN_RAW, CAN_RAW_FD_FRAMES, &on, sizeof on) == 0) {
      can->fd_frames = true;
    } else if (may_log(can)) {
      VLFF_WARN(TAG, "%s: can.fd is set but the interface is not CAN FD (MTU %d); sending classic frames",
                can->iface, ifr.ifr_mtu);
    }
  }
  struct sockaddr_can addr = {.can_family = AF_CAN, .can_ifindex = ifindex};
  if (bind(s, (struct sockaddr *)&addr, sizeof addr) < 0) goto fail;
  can->sock = s;
  return 0;
fail:;
  int e = errno;
  close(s);
  errno = e;
  return -1;
}

/* Send one frame without ever blocking. Returns 0 sent, -1 dropped. */
static int send_frame(struct vlff_can *can, uint32_t id, const uint8_t *data, int len, bool fd) {
  if (can->sock < 0) {
    inc(&can->tx_dropped);
    return -1;
  }
  struct canfd_frame f;
  memset(&f, 0, sizeof f);
  f.can_id = id;
  f.len = (uint8_t)len;
  memcpy(f.data, data, (size_t)len);
  size_t size = fd ? CANFD_MTU : CAN_MTU;
  ssize_t n = send(can->sock, &f, size, MSG_DONTWAIT);
  if (n == (ssize_t)size) return 0;
  int e = n < 0 ? errno : EIO;
  inc(&can->tx_dropped);
  if (e == ENETDOWN || e == ENODEV || e == ENXIO) {
    close_sock(can, strerror(e));
  } else if (e != ENOBUFS && e != EAGAIN && may_log(can)) {
    VLFF_WARN(TAG, "%s: send 0x%03x: %s (frame dropped)", can->iface, id, strerror(e));
  }
  return -1;
}

static void send_heartbeat(struct vlff_can *can, bool *bootup_pending) {
  uint8_t state = *bootup_pending ? (uint8_t)VLFF_NMT_BOOTUP
                                  : (uint8_t)atomic_load_explicit(&can->nmt_state, memory_order_relaxed);
  if (send_frame(can, VLFF_CANP_HEARTBEAT_BASE + (uint32_t)can->node_id, &state, 1, false) == 0) {
    inc(&can->hb_sent);
    *bootup_pending = false;
  }
}

static void send_status(struct vlff_can *can) {
  struct vlff_can_status st;
  read_status(can, &st);
  uint64_t drops = ld(&can->tx_dropped);
  uint64_t rejects = ld(&can->cmd_malformed) + ld(&can->cmd_unknown) + ld(&can->cmd_range);
  struct vlff_canp_link link = {
      .nmt_state = (uint8_t)atomic_load_explicit(&can->nmt_state, memory_order_relaxed),
      .can_errors = can->period_errors,
      .cmd_rejected = rejects,
      .tx_dropped = drops,
      .map_age_ms = st.map_published_ns > 0 ? ((int64_t)vlff_now_ns() - st.map_published_ns) / 1000000 : -1,
  };
  if (link.map_age_ms < -1) link.map_age_ms = 0;
  if (can->period_errors & (VLFF_CAN_BUS_OFF | VLFF_CAN_BUS_PASSIVE | VLFF_CAN_BUS_CONTROLLER))
    link.extra_flags |= VLFF_CAN_ERRF_BUS_ERROR;
  if (drops != can->period_drops_at) link.extra_flags |= VLFF_CAN_ERRF_TX_DROPPED;
  if (rejects != can->period_rejects_at) link.extra_flags |= VLFF_CAN_ERRF_CMD_REJECTED;
  /* Refusals are cumulative from the node; the frame says which reasons
   * and how many in the period just ended. */
  for (int r = 1; r < VLFF_CAN_REFUSAL_CODES; r++)
    if (st.refused[r] != can->period_refused_at[r]) link.refused_active |= (uint16_t)(1u << (r - 1));
  link.refused_period = st.frames_refused - can->period_refused_total_at;
  memcpy(can->period_refused_at, st.refused, sizeof can->period_refused_at);
  can->period_refused_total_at = st.frames_refused;
  can->period_errors = 0;
  can->period_drops_at = drops;
  can->period_rejects_at = rejects;

  uint8_t frames[VLFF_CANP_STATUS_FD_LEN / 8][8];
  memset(frames, 0, sizeof frames);
  for (int i = 0; i < VLFF_CANP_STATUS_FRAMES; i++) vlff_canp_encode_status(i, &st, &link, frames[i]);
  if (can->fd_frames) {
    if (send_frame(can, can->status_base + VLFF_CANP_STATUS_FD_OFFSET, &frames[0][0], sizeof frames, true) == 0)
      inc(&can->status_sent);
    return;
  }
  for (int i = 0; i < VLFF_CANP_STATUS_FRAMES; i++)
    if (send_frame(can, can->status_base + (uint32_t)vlff_canp_status_offset(i), frames[i], 8, false) == 0)
      inc(&can->status_sent);
}

static void handle_error_frame(struct vlff_can *can, const struct canfd_frame *f) {
  char desc[160];
  uint32_t bits = vlff_canp_decode_error(f->can_id, f->data, desc, sizeof desc);
  inc(&can->err_frames);
  if (bits & VLFF_CAN_BUS_OFF) inc(&can->bus_off);
  if (bits & VLFF_CAN_BUS_PASSIVE) inc(&can->err_passive);
  if (bits & VLFF_CAN_BUS_WARNING) inc(&can->err_warning);
  if (bits & VLFF_CAN_BUS_CONTROLLER) inc(&can->ctrl_problems);
  if (bits & VLFF_CAN_BUS_TX_TIMEOUT) inc(&can->tx_timeouts);
  if (bits & (VLFF_CAN_BUS_PROTOCOL | VLFF_CAN_BUS_NO_ACK)) inc(&can->prot_errors);
  can->period_errors |= (uint8_t)bits;
  atomic_fetch_or_explicit(&can->can_errors, bits, memory_order_relaxed);
  if (may_log(can)) VLFF_WARN(TAG, "%s: error frame: %s", can->iface, desc);
}

static void handle_command(struct vlff_can *can, const struct canfd_frame *f, int len) {
  struct vlff_can_command cmd = {0};
  int check = (f->can_id & CAN_RTR_FLAG) ? VLFF_CANP_CMD_MALFORMED
                                         : vlff_canp_check_command(f->data, len, can->node_id, can->prompt_sets, &cmd);
  int result;
  switch (check) {
    case VLFF_CANP_CMD_VALID:
      inc(&can->cmd_ok);
      result = can->fn ? can->fn(can->ctx, &cmd) : VLFF_CAN_RES_REFUSED;
      break;
    case VLFF_CANP_CMD_OTHER_NODE:
      inc(&can->cmd_other_node);
      return;
    case VLFF_CANP_CMD_UNKNOWN:
      inc(&can->cmd_unknown);
      result = VLFF_CAN_RES_UNKNOWN;
      if (may_log(can)) VLFF_WARN(TAG, "%s: unknown command code 0x%02x ignored", can->iface, cmd.code);
      break;
    case VLFF_CANP_CMD_RANGE:
      inc(&can->cmd_range);
      result = VLFF_CAN_RES_RANGE;
      if (may_log(can))
        VLFF_WARN(TAG, "%s: command %s argument %u out of range, ignored", can->iface, vlff_can_cmd_name(cmd.code),
                  cmd.arg);
      break;
    default:
      inc(&can->cmd_malformed);
      if (may_log(can))
        VLFF_WARN(TAG, "%s: malformed command frame (len %d, expected %d) ignored", can->iface, len,
                  VLFF_CANP_CMD_LEN);
      return;
  }
  uint8_t ack[VLFF_CANP_ACK_LEN];
  vlff_canp_encode_ack(can->node_id, &cmd, result, ack);
  if (send_frame(can, can->ack_id, ack, sizeof ack, false) == 0) inc(&can->acks_sent);
}

static void drain_rx(struct vlff_can *can) {
  for (int budget = 64; budget > 0 && can->sock >= 0; budget--) {
    struct canfd_frame f;
    ssize_t n = recv(can->sock, &f, sizeof f, MSG_DONTWAIT);
    if (n < 0) {
      if (errno == EAGAIN || errno == EINTR) return;
      /* The socket reports the link's state as a pending error (ENETDOWN). */
      close_sock(can, strerror(errno));
      return;
    }
    if (n != (ssize_t)CAN_MTU && n != (ssize_t)CANFD_MTU) continue;
    if (f.can_id & CAN_ERR_FLAG) {
      handle_error_frame(can, &f);
      continue;
    }
    if ((f.can_id & CAN_EFF_FLAG) || (f.can_id & CAN_SFF_MASK) != can->cmd_id) continue;
    handle_command(can, &f, f.len);
  }
}

/* ------------------------------------------------------------ thread */

static void *can_thread(void *arg) {
  struct vlff_can *can = arg;
  /* Default timer slack (50 us) would be jitter on every heartbeat. */
  prctl(PR_SET_TIMERSLACK, 1UL, 0, 0, 0);
  /* A learner saturating every core would otherwise delay each wake by up to
   * a scheduler slice; the thread sleeps almost all the time, so a real-time
   * priority costs the learner nothing measurable. */
  if (can->rt_priority > 0) {
    struct sched_param sp = {.sched_priority = can->rt_priority};
    int e = pthread_setschedparam(pthread_self(), SCHED_FIFO, &sp);
    if (e)
      VLFF_WARN(TAG, "%s: SCHED_FIFO %d refused (%s): heartbeat jitter follows the load (raise "
                "RLIMIT_RTPRIO, the unit's LimitRTPRIO=, grant CAP_SYS_NICE, or set can.rt_priority: 0)", can->iface, can->rt_priority, strerror(e));
  }
  bool bootup_pending = true;
  int64_t now = (int64_t)vlff_now_ns();
  int64_t next_hb = now, next_status = now + can->status_ns, next_retry = now;
  int64_t backoff = BACKOFF_MIN_NS;
  int64_t peak = 0, margin = SPIN_MIN_NS < can->spin_max_ns ? SPIN_MIN_NS : can->spin_max_ns;

  while (!atomic_load_explicit(&can->stop, memory_order_relaxed)) {
    now = (int64_t)vlff_now_ns();
    if (can->sock < 0 && now >= next_retry) {
      if (open_sock(can) == 0) {
        atomic_store_explicit(&can->connected, true, memory_order_relaxed);
        if (can->ever_opened) {
          inc(&can->reopens);
          VLFF_INFO(TAG, "%s: reopened", can->iface);
        } else {
          /* The grid starts with the boot-up message, not with the thread. */
          next_hb = (int64_t)vlff_now_ns();
          next_status = next_hb + can->status_ns;
        }
        can->ever_opened = true;
        backoff = BACKOFF_MIN_NS;
      } else {
        if (may_log(can)) VLFF_WARN(TAG, "%s: cannot open: %s (retry in %lld ms)", can->iface, strerror(errno),
                                    (long long)(backoff / 1000000));
        next_retry = now + backoff;
        backoff = backoff * 2 > BACKOFF_MAX_NS ? BACKOFF_MAX_NS : backoff * 2;
      }
    }
    int64_t due = next_hb < next_status ? next_hb : next_status;
    if (can->sock < 0 && next_retry < due) due = next_retry;

    int spin = can->spin_max_ns > 0 && due == next_hb;
    int64_t wake = spin ? due - margin : due;
    /* ppoll's own timeout is as late as any timer: it stops a margin
     * before the absolute sleep, so a late ppoll still leaves that sleep
     * (or at least the spin) ahead of the deadline. */
    int64_t guard = GUARD_NS + (spin ? margin : 0);
    if (wake - now > guard) {
      struct pollfd p[2] = {{.fd = can->wake_fd, .events = POLLIN}, {.fd = can->sock, .events = POLLIN}};
      struct timespec to = to_ts(wake - now - guard);
      int r = ppoll(p, can->sock >= 0 ? 2 : 1, &to, NULL);
      if (r > 0 && (p[1].revents & (POLLIN | POLLERR))) drain_rx(can);
      continue;
    }
    /* A heartbeat is not left to the timer alone: the thread wakes `margin`
     * early and spins to the deadline, and the margin follows the wake-up
     * lateness this machine has shown lately (a decaying peak). Where
     * timers are punctual the spin is ~0.1 ms a period; where they are not
     * (a loaded VM) it is what keeps the heartbeat on its grid. */
    struct timespec ts = to_ts(wake);
    int slept = wake > now;
    while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL) == EINTR) {}
    now = (int64_t)vlff_now_ns();
    if (spin) {
      if (slept) {
        int64_t late = now - wake;
        peak = late > peak ? late : peak - peak / 64;
      }
      margin = peak + peak / 4 + SPIN_MIN_NS;
      if (margin > can->spin_max_ns) margin = can->spin_max_ns;
      if (now > due) inc(&can->hb_timer_late);
      int64_t s0 = now;
      while (now < due) now = (int64_t)vlff_now_ns();
      atomic_fetch_add_explicit(&can->hb_spin_ns, (uint64_t)(now - s0), memory_order_relaxed);
    }
    if (now >= next_hb) {
      send_heartbeat(can, &bootup_pending);
      next_hb += can->hb_ns;
      /* Keep the phase; a deadline missed by a whole period is skipped. */
      while (next_hb <= now) {
        next_hb += can->hb_ns;
        inc(&can->tx_late);
      }
    }
    /* Status waits for the boot-up message: a listener sees boot-up first. */
    if (now >= next_status) {
      if (!bootup_pending) send_status(can);
      while (next_status <= now) next_status += can->status_ns;
    }
    if (can->sock >= 0) drain_rx(can);
  }
  if (can->sock >= 0) close(can->sock);
  can->sock = -1;
  atomic_store_explicit(&can->connected, false, memory_order_relaxed);
  return NULL;
}

struct vlff_can *vlff_can_open(const struct vlff_cfg_can *cfg, int prompt_sets, vlff_can_command_fn fn, void *ctx) {
  char err[256];
  if (vlff_can_check_config(cfg, err, sizeof err) < 0) {
    VLFF_ERROR(TAG, "%s", err);
    errno = EINVAL;
    return NULL;
  }
  struct vlff_can *can = calloc(1, sizeof *can);
  if (!can) return NULL;
  memcpy(can->iface, cfg->interface, strlen(cfg->interface) + 1); /* length checked above */
  can->node_id = cfg->node_id;
  can->hb_ns = (int64_t)cfg->heartbeat_ms * 1000000;
  can->status_ns = (int64_t)cfg->status_ms * 1000000;
  can->status_base = (uint32_t)cfg->status_base_id;
  can->cmd_id = (uint32_t)cfg->command_id;
  can->ack_id = (uint32_t)cfg->ack_id;
  can->want_fd = cfg->fd;
  can->prompt_sets = prompt_sets;
  can->rt_priority = cfg->rt_priority;
  can->spin_max_ns = (int64_t)cfg->heartbeat_spin_max_us * 1000;
  can->fn = fn;
  can->ctx = ctx;
  can->sock = -1;
  can->last_log_ns = -NS;
  atomic_init(&can->nmt_state, VLFF_NMT_PREOPERATIONAL);
  can->wake_fd = eventfd(0, EFD_CLOEXEC | EFD_NONBLOCK);
  if (can->wake_fd < 0) {
    free(can);
    return NULL;
  }
  int e = pthread_create(&can->thread, NULL, can_thread, can);
  if (e) {
    close(can->wake_fd);
    free(can);
    errno = e;
    return NULL;
  }
  return can;
}

void vlff_can_close(struct vlff_can *can) {
  if (!can) return;
  atomic_store_explicit(&can->stop, true, memory_order_relaxed);
  uint64_t one = 1;
  if (write(can->wake_fd, &one, sizeof one) < 0) { /* the thread also wakes at its next deadline */ }
  pthread_join(can->thread, NULL);
  close(can->wake_fd);
  free(can);
}
