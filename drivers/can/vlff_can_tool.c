/*
 * vlff-can: watch a vlff node on a CAN bus, or send it a command.
 * In the spirit of can-utils' candump/cansend: one line per frame, stable
 * enough to grep, and a usage text with real examples.
 */
#include <errno.h>
#include <limits.h>
#include <getopt.h>
#include <linux/can.h>
#include <linux/can/raw.h>
#include <net/if.h>
#include <poll.h>
#include <stdbool.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#include "can_proto.h"
#include "clock.h"
#include "cli.h"
#include "config.h"
#include "vlff/escape.h"

static const struct vlff_cli cli = {
    "vlff-can",
    "Usage: vlff-can [OPTIONS] IFACE dump\n"
    "       vlff-can [OPTIONS] IFACE send start|stop|reset|save|publish|prompt-set N\n"
    "       vlff-can [OPTIONS] dbc\n"
    "\n"
    "  dump   decode heartbeat, status, command and ack frames of a vlff node\n"
    "  send   send one command and wait for its ack (exit 0 ok ack, 1 nak or no ack)\n"
    "  dbc    write the DBC of the configured node (ids, cycle times) to stdout\n"
    "\n"
    "Options, before or after the command (the can.* ids come from the config:\n"
    "--config, else $VLFF_CONFIG, else the installed vlff.yaml; dump and send fall\n"
    "back to the default ids, saying so):\n"
    "  -c, --config FILE        read can.* from a vlff config file (-f as well)\n"
    "  -n, --node-id ID         node id, 1..127 (can.node_id)\n"
    "  -b, --status-base-id ID  status base id, 0..0x7FF (can.status_base_id)\n"
    "  -C, --command-id ID      command id, 0..0x7FF (can.command_id)\n"
    "  -a, --ack-id ID          ack id, 0..0x7FF (can.ack_id)\n"
    "  -t, --seconds SEC        dump: stop after SEC seconds; send: ack timeout (default 1)\n"
    "  -N, --count COUNT        dump: stop after COUNT frames\n"
    "  -s, --seq SEQ            send: sequence number 0..255 echoed in the ack (default: pid)\n"
    "  -V, --version            print the version and exit\n"
    "  -h, --help               print this help and exit\n"
    "\n"
    "Examples:\n"
    "  vlff-can can0 dump\n"
    "    0.100213 72A heartbeat node=42 state=operational\n"
    "    0.200118 180 TRAIN iteration=1532 keyframes=41 prompt_set=0 state=operational\n"
    "  vlff-can -n 42 can0 send prompt-set 2\n"
    "    580 ACK node=42 cmd=prompt-set seq=17 result=ok\n"
    "  vlff-can dbc --config /etc/vlff/vlff.yaml > vlff.dbc\n"
    "Exit status: 0 ok, 1 error (no interface, a nak, no ack in time; message on stderr),\n"
    "2 usage.\n",
};

/* An integer in [lo, hi] (decimal, 0x hex or 0 octal), else a usage error. */
static long num(const char *s, const char *what, long lo, long hi) {
  char *end;
  errno = 0;
  long v = strtol(s, &end, 0);
  if (errno || *end || end == s || v < lo || v > hi)
    exit(vlff_cli_usage_error(&cli, "%s: expected an integer in %ld..%ld (0x for hex), got '%s'", what, lo, hi,
                              VLFF_Q(s)));
  return v;
}

static int open_iface(const char *iface, bool fd) {
  int s = socket(PF_CAN, SOCK_RAW | SOCK_CLOEXEC, CAN_RAW);
  if (s < 0) {
    fprintf(stderr, "vlff-can: socket(PF_CAN): %s\n", strerror(errno));
    return -1;
  }
  struct sockaddr_can a = {.can_family = AF_CAN, .can_ifindex = (int)if_nametoindex(iface)};
  if (a.can_ifindex == 0) {
    fprintf(stderr, "vlff-can: %s: no such interface\n", iface);
    close(s);
    return -1;
  }
  int on = 1;
  can_err_mask_t em = CAN_ERR_MASK;
  if (fd) setsockopt(s, SOL_CAN_RAW, CAN_RAW_FD_FRAMES, &on, sizeof on); /* classic-only links refuse: fine */
  setsockopt(s, SOL_CAN_RAW, CAN_RAW_ERR_FILTER, &em, sizeof em);
  if (bind(s, (struct sockaddr *)&a, sizeof a) < 0) {
    fprintf(stderr, "vlff-can: bind %s: %s\n", iface, strerror(errno));
    close(s);
    return -1;
  }
  return s;
}

static const char *const flag_names[8] = {"camera-lost", "pose-stale", "shm-lapped", "checkpoint-failed",
                                          "bus-error", "tx-dropped", "cmd-rejected", "bit7"};
static const char *const bus_names[8] = {"bus-off", "error-passive", "error-warning", "controller",
                                         "tx-timeout", "protocol", "no-ack", "restarted"};

/* The set bits of an 8-bit field as comma-separated names. */
static void bits_text(unsigned f, const char *const names[8], char *out, size_t n) {
  size_t k = 0;
  out[0] = 0;
  for (int i = 0; i < 8; i++)
    if (f & (1u << i)) k += (size_t)snprintf(out + k, n - k, "%s%s", k ? "," : "", names[i]);
}

static void print_loss(const char *name, double v) {
  if (v < 0) printf(" %s=invalid", name);
  else printf(" %s=%.4f", name, v);
}

/* " name=USE/LIMITMiB" (limit -2: none), "?" for unknown or above range. */
static void print_mib(const char *name, double use, double limit) {
  printf(" %s=", name);
  if (use < 0) printf("?");
  else printf("%.0f", use);
  if (limit >= 0) printf("/%.0f", limit);
  else if (limit > -2) printf("/?");
  printf("MiB");
}

static void print_status(int index, const uint8_t *d) {
  struct vlff_canp_status_view v;
  char a[96], b[96];
  vlff_canp_decode_status(index, d, 8, &v);
  switch (index) {
    case VLFF_CANP_TRAIN:
      printf("TRAIN iteration=%u keyframes=%u prompt_set=%u state=%s", v.iteration, v.keyframes, v.prompt_set,
             vlff_can_nmt_name(v.nmt_state));
      break;
    case VLFF_CANP_LOSS:
      printf("LOSS");
      print_loss("total", v.loss_total);
      print_loss("color", v.loss_color);
      print_loss("depth", v.loss_depth);
      print_loss("feature", v.loss_feature);
      break;
    case VLFF_CANP_MAP:
      printf("MAP version=%u", v.map_version);
      if (v.map_age_ms == 0xffff) printf(" age_ms=never");
      else printf(" age_ms=%u", v.map_age_ms);
      if (v.fps_in < 0) printf(" fps_in=invalid");
      else printf(" fps_in=%.2f", v.fps_in);
      break;
    case VLFF_CANP_HEALTH:
      bits_text(v.error_flags, flag_names, a, sizeof a);
      bits_text(v.can_errors, bus_names, b, sizeof b);
      printf("HEALTH flags=0x%02x[%s] fps_dropped=%.2f cmd_rejected=%u tx_dropped=%u can_errors=0x%02x[%s]",
             v.error_flags, a, v.fps_dropped < 0 ? -1.0 : v.fps_dropped, v.cmd_rejected, v.tx_dropped,
             v.can_errors, b);
      break;
    case VLFF_CANP_INGEST:
      printf("INGEST refused=%u last_reason=%u refused_period=%u active=0x%04x", v.frames_refused, v.last_refusal,
             v.refused_period, v.refused_active);
      break;
    case VLFF_CANP_MEMORY:
      printf("MEMORY");
      print_mib("rss", v.mem_rss_mb, -2);
      print_mib("keyframes", v.mem_keyframes_mb, v.mem_keyframes_limit_mb);
      print_mib("evidence", v.mem_evidence_mb, v.mem_evidence_limit_mb);
      break;
    case VLFF_CANP_PAGING:
      printf("PAGING keyframes_paged=%u keyframes_dropped=%u evidence_dropped=%u box_growths=%u box_refused=%u",
             v.keyframes_paged, v.keyframes_dropped, v.evidence_dropped, v.box_growths, v.box_refused);
      break;
  }
}

static void print_frame(const struct vlff_config *c, const struct canfd_frame *f, double t) {
  uint32_t id = f->can_id & CAN_SFF_MASK;
  if (f->can_id & CAN_ERR_FLAG) {
    char desc[160];
    vlff_canp_decode_error(f->can_id, f->data, desc, sizeof desc);
    printf("%.6f ERR %s\n", t, desc);
    return;
  }
  if (f->can_id & CAN_EFF_FLAG) return;
  uint32_t base = (uint32_t)c->can.status_base_id;
  if (id == VLFF_CANP_HEARTBEAT_BASE + (uint32_t)c->can.node_id && f->len == 1) {
    printf("%.6f %03X heartbeat node=%d state=%s\n", t, id, c->can.node_id, vlff_can_nmt_name(f->data[0]));
  } else if (id >= base && vlff_canp_status_index((int)(id - base)) >= 0 && f->len == 8) {
    printf("%.6f %03X ", t, id);
    print_status(vlff_canp_status_index((int)(id - base)), f->data);
    printf("\n");
  } else if (id == base + VLFF_CANP_STATUS_FD_OFFSET && f->len == VLFF_CANP_STATUS_FD_LEN) {
    for (int i = 0; i < VLFF_CANP_STATUS_FRAMES; i++) {
      printf("%.6f %03X FD ", t, id);
      print_status(i, f->data + 8 * i);
      printf("\n");
    }
  } else if (id == (uint32_t)c->can.ack_id && f->len == VLFF_CANP_ACK_LEN) {
    printf("%.6f %03X ACK node=%u cmd=%s seq=%u result=%s\n", t, id, f->data[0], vlff_can_cmd_name(f->data[1]),
           f->data[3], vlff_can_result_name(f->data[2]));
  } else if (id == (uint32_t)c->can.command_id) {
    if (f->len == VLFF_CANP_CMD_LEN)
      printf("%.6f %03X CMD target=%u cmd=%s arg=%u seq=%u\n", t, id, f->data[0], vlff_can_cmd_name(f->data[1]),
             f->data[2], f->data[3]);
    else
      printf("%.6f %03X CMD malformed len=%u\n", t, id, f->len);
  } else {
    return;
  }
  fflush(stdout);
}

static int dump(const struct vlff_config *c, const char *iface, double seconds, long count) {
  int s = open_iface(iface, true);
  if (s < 0) return 1;
  double t0 = vlff_seconds();
  long n = 0;
  for (;;) {
    double left = seconds > 0 ? seconds - (vlff_seconds() - t0) : 1e9;
    if (left <= 0 || (count > 0 && n >= count)) break;
    struct pollfd p = {.fd = s, .events = POLLIN};
    int r = poll(&p, 1, left > 1e6 ? -1 : (int)(left * 1000) + 1);
    if (r < 0 && errno != EINTR) break;
    if (r <= 0) continue;
    struct canfd_frame f;
    ssize_t got = read(s, &f, sizeof f);
    if (got < 0) {
      fprintf(stderr, "vlff-can: read %s: %s\n", iface, strerror(errno));
      if (errno == ENETDOWN) continue;
      break;
    }
    if (got != CAN_MTU && got != CANFD_MTU) continue;
    print_frame(c, &f, vlff_seconds() - t0);
    n++;
  }
  close(s);
  return 0;
}

/* send's operands into cmd: 0, or the usage error's exit status (2). */
static int send_parse(int argc, char **argv, struct vlff_can_command *cmd) {
  static const struct { const char *name; int code; } cmds[] = {
      {"start", VLFF_CAN_CMD_START}, {"stop", VLFF_CAN_CMD_STOP},       {"reset", VLFF_CAN_CMD_RESET},
      {"save", VLFF_CAN_CMD_SAVE},   {"prompt-set", VLFF_CAN_CMD_PROMPT_SET}, {"publish", VLFF_CAN_CMD_PUBLISH}};
  if (argc < 1) return vlff_cli_usage_error(&cli, "send needs a command (start|stop|reset|save|publish|prompt-set N)");
  int code = -1;
  for (size_t i = 0; i < sizeof cmds / sizeof cmds[0]; i++)
    if (!strcmp(argv[0], cmds[i].name)) code = cmds[i].code;
  if (code < 0)
    return vlff_cli_usage_error(&cli, "send: unknown command '%s' (start|stop|reset|save|publish|prompt-set N)",
                                VLFF_Q(argv[0]));
  cmd->code = (uint8_t)code;
  int nargs = code == VLFF_CAN_CMD_PROMPT_SET ? 2 : 1;
  if (argc < nargs) return vlff_cli_usage_error(&cli, "send prompt-set needs an index");
  if (argc > nargs)
    return vlff_cli_usage_error(&cli, "send %s: unexpected argument '%s'", VLFF_Q(argv[0]), VLFF_Q(argv[nargs]));
  if (code == VLFF_CAN_CMD_PROMPT_SET) cmd->arg = (uint8_t)num(argv[1], "prompt set index", 0, 255);
  return 0;
}

static int send_cmd(const struct vlff_config *c, const char *iface, struct vlff_can_command cmd, double timeout) {
  int s = open_iface(iface, false);
  if (s < 0) return 1;
  struct can_filter flt = {.can_id = (canid_t)c->can.ack_id, .can_mask = CAN_SFF_MASK | CAN_EFF_FLAG};
  setsockopt(s, SOL_CAN_RAW, CAN_RAW_FILTER, &flt, sizeof flt);
  struct can_frame f = {.can_id = (canid_t)c->can.command_id, .len = VLFF_CANP_CMD_LEN};
  vlff_canp_encode_command(c->can.node_id, &cmd, f.data);
  if (write(s, &f, sizeof f) != (ssize_t)sizeof f) {
    fprintf(stderr, "vlff-can: send on %s: %s\n", iface, strerror(errno));
    close(s);
    return 1;
  }
  double t0 = vlff_seconds();
  for (;;) {
    double left = timeout - (vlff_seconds() - t0);
    if (left <= 0) break;
    struct pollfd p = {.fd = s, .events = POLLIN};
    if (poll(&p, 1, (int)(left * 1000) + 1) <= 0) continue;
    struct can_frame a;
    if (read(s, &a, sizeof a) != (ssize_t)sizeof a) continue;
    if (a.len != VLFF_CANP_ACK_LEN || a.data[0] != c->can.node_id || a.data[1] != cmd.code || a.data[3] != cmd.seq)
      continue;
    printf("%03X ACK node=%u cmd=%s seq=%u result=%s\n", c->can.ack_id, a.data[0], vlff_can_cmd_name(a.data[1]),
           a.data[3], vlff_can_result_name(a.data[2]));
    close(s);
    return a.data[2] == VLFF_CAN_RES_OK ? 0 : 1;
  }
  fprintf(stderr, "vlff-can: no ack from node %d within %.1f s\n", c->can.node_id, timeout);
  close(s);
  return 1;
}

int main(int argc, char **argv) {
  static const struct option opts[] = {
      {"config", required_argument, NULL, 'c'},  {"node-id", required_argument, NULL, 'n'},
      {"status-base-id", required_argument, NULL, 'b'}, {"command-id", required_argument, NULL, 'C'},
      {"ack-id", required_argument, NULL, 'a'},  {"seconds", required_argument, NULL, 't'},
      {"count", required_argument, NULL, 'N'},   {"seq", required_argument, NULL, 's'},
      VLFF_CLI_COMMON_OPTIONS,
  };
  /* Ids given on the command line override the config's, whatever their order. */
  const char *config = NULL, *ids[4] = {NULL, NULL, NULL, NULL};
  double seconds = 0;
  long count = 0;
  int seq = getpid() & 0xff;
  int opt, status;
  /* -f: --config's short option before -c was the convention (docs name it). */
  while ((opt = vlff_cli_next(&cli, argc, argv, "c:f:n:b:C:a:t:N:s:", opts, &status)) != -1) {
    char *end;
    switch (opt) {
      case VLFF_CLI_EXIT: return status;
      case 'c':
      case 'f': config = optarg; break;
      case 'n': ids[0] = optarg; break;
      case 'b': ids[1] = optarg; break;
      case 'C': ids[2] = optarg; break;
      case 'a': ids[3] = optarg; break;
      case 't':
        errno = 0;
        seconds = strtod(optarg, &end);
        if (errno || end == optarg || *end || !(seconds > 0 && seconds <= 1e6))
          return vlff_cli_usage_error(&cli, "--seconds: expected a number of seconds in (0, 1e6], got '%s'",
                                      VLFF_Q(optarg));
        break;
      case 'N': count = num(optarg, "--count", 1, LONG_MAX); break;
      case 's': seq = (int)num(optarg, "--seq", 0, 255); break;
      default: return vlff_cli_usage_error(&cli, "option '%s' not handled", VLFF_Q(argv[optind - 1]));
    }
  }
  int nargs = argc - optind;
  bool dbc = nargs >= 1 && !strcmp(argv[optind], "dbc");
  if (dbc && nargs != 1) return vlff_cli_usage_error(&cli, "dbc takes no arguments");
  if (!dbc && nargs < 2) return vlff_cli_usage_error(&cli, "expected IFACE dump, IFACE send CMD, or dbc");
  const char *verb = dbc ? "dbc" : argv[optind + 1];
  if (!dbc && strcmp(verb, "dump") && strcmp(verb, "send"))
    return vlff_cli_usage_error(&cli, "unknown command '%s' (dump, send or dbc)", VLFF_Q(verb));
  if (!strcmp(verb, "dump") && nargs != 2)
    return vlff_cli_usage_error(&cli, "dump: unexpected argument '%s'", VLFF_Q(argv[optind + 2]));
  struct vlff_can_command cmd = {.seq = (uint8_t)seq};
  if (!strcmp(verb, "send") && send_parse(argc - optind - 2, argv + optind + 2, &cmd)) return 2;
  static const char *const names[4] = {"--node-id", "--status-base-id", "--command-id", "--ack-id"};
  static const long id_lo[4] = {1, 0, 0, 0}, id_hi[4] = {127, 0x7FF, 0x7FF, 0x7FF};
  long id_val[4];
  for (int i = 0; i < 4; i++)
    if (ids[i]) id_val[i] = num(ids[i], names[i], id_lo[i], id_hi[i]);

  struct vlff_config cfg;
  char err[512];
  const char *path = vlff_config_find(config, err, sizeof err);
  if (path) {
    if (vlff_config_load(path, &cfg, err, sizeof err) < 0) return vlff_cli_config_error(err);
  } else if (dbc) {
    /* A DBC for the wrong node decodes nothing: no guessing here. */
    return vlff_cli_error(&cli, "%s", err);
  } else {
    fprintf(stderr, "vlff-can: %s; using the default ids\n", err);
    vlff_config_defaults(&cfg);
  }
  /* The config's own ids are checked before any given here replaces one,
   * so that a refusal blames the one at fault. */
  const bool given = ids[0] || ids[1] || ids[2] || ids[3];
  if (given && path && vlff_can_check_config(&cfg.can, err, sizeof err)) {
    fprintf(stderr, "%s: %s\n", path, err);
    return 1;
  }
  int *fields[4] = {&cfg.can.node_id, &cfg.can.status_base_id, &cfg.can.command_id, &cfg.can.ack_id};
  for (int i = 0; i < 4; i++)
    if (ids[i]) *fields[i] = (int)id_val[i];
  if (dbc) {
    if (vlff_can_write_dbc(&cfg.can, stdout, err, sizeof err)) {
      /* ids given here: the command line is wrong, not the config */
      if (given)
        return vlff_cli_usage_error(&cli, "the ids given on the command line do not fit together: %s", err);
      if (path) fprintf(stderr, "%s: %s\n", path, err);
      else fprintf(stderr, "vlff-can: %s\n", err);
      return 1;
    }
    return 0;
  }
  const char *iface = argv[optind];
  if (!strcmp(verb, "dump")) return dump(&cfg, iface, seconds, count);
  return send_cmd(&cfg, iface, cmd, seconds > 0 ? seconds : 1.0);
}
