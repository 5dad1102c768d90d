/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * vlff-view: the live viewer. Reads the map segment and the frame ring like any
 * controller and serves them to Foxglove (foxglove.websocket.v1) and to its own page
 * on one port, until SIGINT/SIGTERM.
 */
#include "cli.h"
#include "config.h"
#include "files.h"
#include "log.h"
#include "mcap.h"
#include "page.h"
#include "view.h"
#include "vlff/escape.h"

#include <errno.h>
#include <getopt.h>
#include <limits.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

static struct vlff_view *running;

static void on_signal(int sig) {
  (void)sig;
  if (running) vlff_view_stop(running);
}

static const struct vlff_cli cli = {
    "vlff-view",
    "Usage: vlff-view [OPTIONS]\n"
    "Serve the node's live map, camera and status to Foxglove (foxglove.websocket.v1)\n"
    "and to a built-in web page, on one port.\n"
    "\n"
    "  -c, --config FILE       the node's config: the map's and the camera's frame ids (dds.frame_id,\n"
    "                          dds.camera_frame_id) and the segments (shm.map, shm.ring, shm.prompts),\n"
    "                          which --map, --frames and --prompts override (without it: frames world\n"
    "                          and camera, the default segments)\n"
    "  -l, --listen ADDR       IP address or interface to listen on (default 127.0.0.1; 0.0.0.0 = all)\n"
    "  -p, --port N            port (default 8765; 0 = any free port, printed on start)\n"
    "  -m, --map NAME          map segment (default /vlff-map)\n"
    "  -f, --frames NAME       frame ring for the camera image (default /vlff-frames; \"\" = none)\n"
    "      --prompts NAME      prompt mailbox (default /vlff-prompts)\n"
    "      --token-file FILE   enable posting prompt sets; clients must send the token in FILE\n"
    "      --image-hz HZ       most camera images per second (default 2, 0.1..60)\n"
    "      --map-hz HZ         most map updates per second, each with all changes since the last\n"
    "                          (default 2, 0.1..100)\n"
    "      --grid-hz HZ        most /map/grid messages per second while the map changes (default 1,\n"
    "                          0.1..10)\n"
    "      --grid-z M          /map/grid as the slice of the map at height M (m, in the map's frame)\n"
    "                          instead of the highest occupied voxel of each column\n"
    "      --poll-hz HZ        segment checks per second (default 50, 1..1000)\n"
    "      --max-clients N     clients at once (default 10, 1..1000)\n"
    "      --max-queue-mb MB   unsent bytes after which a slow client is dropped (default 32, 0.25..4096)\n"
    "      --max-request-kb KB largest client message (default 64)\n"
    "      --allow-origin URL  also accept this origin (http[s]://HOST[:PORT]) and its HOST[:PORT] as Host;\n"
    "                          repeatable (default: the listening address's own names and port only)\n"
    "      --head-timeout S    seconds for a connection's whole request head (default 5, 1..60)\n"
    "      --idle-timeout S    seconds a WebSocket client may stay silent, pinged after a third\n"
    "                          of it (default 30, 3..3600)\n"
    "      --www DIR           the page's files (default: installed with the program)\n"
    "      --record FILE       also write every message of every channel to FILE, an MCAP recording\n"
    "                          (zstd-compressed chunks of at most 1 s; Foxglove opens it); a directory:\n"
    "                          a new file there per run, vlff-view-YYYYmmdd-HHMMSS.mcap (local time);\n"
    "                          an existing FILE is refused unless --force is given\n"
    "      --force             let --record FILE replace an existing file\n"
    "      --record-map-s S    while the map changes, the whole map into the recording every S seconds,\n"
    "                          each opening a chunk, for readers that seek (default 10, 1..3600)\n"
    "      --record-level N    zstd level of the recording's chunks (default 3, 1..19; 0 = none)\n"
    "      --play FILE         serve the MCAP recording FILE instead of the segments, at its recorded\n"
    "                          rate, from the first subscription on\n"
    "      --play-rate R       play R times as fast as recorded (default 1, 0.01..100)\n"
    "  -v, --verbose           log connections (twice: libwebsockets' notices too)\n"
    "  -V, --version           print the version and exit\n"
    "  -h, --help              print this help and exit\n"
    "\n"
    "Examples:\n"
    "  vlff-view --map /vlff-demo-map --frames /vlff-demo-frames --prompts /vlff-demo-prompts\n"
    "  vlff-view --listen 0.0.0.0 --token-file /etc/vlff/view.token\n"
    "  vlff-view --record run.mcap     (later: vlff-view --play run.mcap)\n"
    "Then open http://127.0.0.1:8765/ or connect Foxglove to ws://127.0.0.1:8765.\n",
};

static int parse_num(const char *opt, const char *s, double lo, double hi, double *out) {
  char *end;
  errno = 0;
  double x = strtod(s, &end);
  if (errno || end == s || *end || !(x >= lo && x <= hi)) {
    vlff_cli_usage_error(&cli, "--%s '%s' is not a number in %g..%g", opt, VLFF_Q(s), lo, hi);
    return -1;
  }
  *out = x;
  return 0;
}

/* The token: the first line of a regular file of at most 4 KiB, 8..256 characters.
 * Read through vlff_read_file so that a FIFO, device or directory named there is
 * refused at once instead of blocking start-up on open() or read(). */
static char *read_token(const char *path) {
  uint8_t *buf;
  size_t len;
  char err[512];
  if (vlff_read_file(path, 4096, &buf, &len, err, sizeof err) != 0) {
    vlff_cli_error(&cli, "--token-file %s", err);
    return NULL;
  }
  char *line = (char *)buf;
  line[strcspn(line, "\r\n")] = 0;
  size_t n = strlen(line);
  if (n < 8 || n > 256) {
    fprintf(stderr, "vlff-view: %s:1: the token must be 8..256 characters on the first line (found %zu)\n", path, n);
    free(buf);
    return NULL;
  }
  return line;
}

/* --record DIR: a file of its own for this run, named by the local start time;
 * a name taken (a restart within the second, a clock set back) gets -2, -3, ...
 * rather than replacing an earlier run's recording. */
static const char *record_path(const char *arg, char *buf, size_t cap) {
  struct stat st;
  if (stat(arg, &st) != 0 || !S_ISDIR(st.st_mode)) return arg;
  time_t now = time(NULL);
  struct tm tm;
  char stamp[32];
  if (!localtime_r(&now, &tm) || !strftime(stamp, sizeof stamp, "%Y%m%d-%H%M%S", &tm)) return arg;
  size_t n = strlen(arg);
  const char *sep = n && arg[n - 1] == '/' ? "" : "/";
  for (int i = 1; i <= 1000; i++) {
    char suffix[16] = "";
    if (i > 1) snprintf(suffix, sizeof suffix, "-%d", i);
    int k = snprintf(buf, cap, "%s%svlff-view-%s%s.mcap", arg, sep, stamp, suffix);
    if (k <= 0 || (size_t)k >= cap) return arg;
    if (lstat(buf, &st) != 0 && errno == ENOENT) return buf;
  }
  return buf; /* a thousand runs in one second: the last name is replaced */
}

static int is_dir_with_index(const char *dir) {
  char p[PATH_MAX];
  struct stat st;
  return snprintf(p, sizeof p, "%s/index.html", dir) < (int)sizeof p && stat(p, &st) == 0;
}

/* The page's files: beside a build-tree program (www/), else where the install puts
 * them (bin/../share/vlff/view). */
static int default_www(char *out, size_t cap) {
  char exe[PATH_MAX];
  if (vlff_exe_dir(exe, sizeof exe) != 0) return -1;
  if (snprintf(out, cap, "%.*s/www", PATH_MAX - 64, exe) < (int)cap && is_dir_with_index(out)) return 0;
  if (snprintf(out, cap, "%.*s/../share/vlff/view", PATH_MAX - 64, exe) < (int)cap && is_dir_with_index(out)) return 0;
  return -1;
}

int main(int argc, char **argv) {
  vlff_log_start(); /* log stamps count from the start, not from the first line */
  enum { OPT_PROMPTS = 256, OPT_TOKEN, OPT_IMAGE_HZ, OPT_MAP_HZ, OPT_POLL_HZ, OPT_MAX_CLIENTS, OPT_QUEUE, OPT_REQUEST, OPT_WWW,
         OPT_ALLOW_ORIGIN, OPT_HEAD_TIMEOUT, OPT_IDLE_TIMEOUT, OPT_RECORD, OPT_RECORD_LEVEL, OPT_RECORD_MAP, OPT_PLAY, OPT_PLAY_RATE,
         OPT_GRID_HZ, OPT_GRID_Z, OPT_FORCE };
  static const struct option opts[] = {
      {"config", required_argument, NULL, 'c'},     {"listen", required_argument, NULL, 'l'},     {"port", required_argument, NULL, 'p'},
      {"map", required_argument, NULL, 'm'},        {"frames", required_argument, NULL, 'f'},
      {"prompts", required_argument, NULL, OPT_PROMPTS}, {"token-file", required_argument, NULL, OPT_TOKEN},
      {"image-hz", required_argument, NULL, OPT_IMAGE_HZ}, {"map-hz", required_argument, NULL, OPT_MAP_HZ}, {"poll-hz", required_argument, NULL, OPT_POLL_HZ},
      {"max-clients", required_argument, NULL, OPT_MAX_CLIENTS}, {"max-queue-mb", required_argument, NULL, OPT_QUEUE},
      {"max-request-kb", required_argument, NULL, OPT_REQUEST}, {"www", required_argument, NULL, OPT_WWW},
      {"allow-origin", required_argument, NULL, OPT_ALLOW_ORIGIN},
      {"head-timeout", required_argument, NULL, OPT_HEAD_TIMEOUT},
      {"idle-timeout", required_argument, NULL, OPT_IDLE_TIMEOUT},
      {"record", required_argument, NULL, OPT_RECORD},
      {"record-level", required_argument, NULL, OPT_RECORD_LEVEL},
      {"record-map-s", required_argument, NULL, OPT_RECORD_MAP},
      {"play", required_argument, NULL, OPT_PLAY},
      {"play-rate", required_argument, NULL, OPT_PLAY_RATE},
      {"grid-hz", required_argument, NULL, OPT_GRID_HZ},
      {"grid-z", required_argument, NULL, OPT_GRID_Z},
      {"force", no_argument, NULL, OPT_FORCE},
      {"verbose", no_argument, NULL, 'v'},          VLFF_CLI_COMMON_OPTIONS};
  struct vlff_view_params vp = {.address = "127.0.0.1", .port = 8765, .prompts_name = "/vlff-prompts",
                                .poll_hz = 50, .max_clients = 10, .max_queue_bytes = 32u << 20,
                                .max_request_bytes = 64u << 10, .record_map_s = 10};
  struct vlff_feed_params fp = {.map_name = "/vlff-map", .frames_name = "/vlff-frames", .image_hz = 2, .map_hz = 2, .brick = 4};
  const char *token_file = NULL, *www = NULL, *record = NULL, *play = NULL, *config = NULL;
  int seg_given[3] = {0, 0, 0}; /* --map, --frames, --prompts */
  int record_level = 3;
  bool record_level_set = false, play_rate_set = false, force = false;
  double play_rate = 1;
  double x;
  int c, status;
  static const char *origins[VLFF_ALLOW_MAX];
  struct vlff_allow check_origin;
  while ((c = vlff_cli_next(&cli, argc, argv, "c:l:p:m:f:v", opts, &status)) != -1) {
    switch (c) {
    case VLFF_CLI_EXIT: return status;
    case 'l': vp.address = optarg; break;
    case 'p':
      if (parse_num("port", optarg, 0, 65535, &x) || x != (int)x) return 2;
      vp.port = (int)x;
      break;
    case 'c': config = optarg; break;
    case 'm': fp.map_name = optarg, seg_given[0] = 1; break;
    case 'f': fp.frames_name = optarg, seg_given[1] = 1; break;
    case OPT_PROMPTS: vp.prompts_name = optarg, seg_given[2] = 1; break;
    case OPT_TOKEN: token_file = optarg; break;
    case OPT_IMAGE_HZ:
      if (parse_num("image-hz", optarg, 0.1, 60, &fp.image_hz)) return 2;
      break;
    case OPT_MAP_HZ:
      if (parse_num("map-hz", optarg, 0.1, 100, &fp.map_hz)) return 2;
      break;
    case OPT_POLL_HZ:
      if (parse_num("poll-hz", optarg, 1, 1000, &vp.poll_hz)) return 2;
      break;
    case OPT_MAX_CLIENTS:
      if (parse_num("max-clients", optarg, 1, 1000, &x)) return 2;
      vp.max_clients = (int)x;
      break;
    case OPT_QUEUE:
      if (parse_num("max-queue-mb", optarg, 0.25, 4096, &x)) return 2;
      vp.max_queue_bytes = (size_t)(x * (1 << 20));
      break;
    case OPT_REQUEST:
      if (parse_num("max-request-kb", optarg, 1, 16384, &x)) return 2;
      vp.max_request_bytes = (size_t)(x * 1024);
      break;
    case OPT_WWW: www = optarg; break;
    case OPT_ALLOW_ORIGIN: {
      char why[200];
      check_origin.n_origins = 0;
      if (vlff_allow_origin(&check_origin, optarg, why, sizeof why))
        return vlff_cli_usage_error(&cli, "--allow-origin %s", why);
      if (vp.n_allow_origins == VLFF_ALLOW_MAX)
        return vlff_cli_usage_error(&cli, "--allow-origin: at most %d", VLFF_ALLOW_MAX);
      origins[vp.n_allow_origins++] = optarg;
      vp.allow_origins = origins;
      break;
    }
    case OPT_HEAD_TIMEOUT:
      if (parse_num("head-timeout", optarg, 1, 60, &vp.head_timeout_s)) return 2;
      break;
    case OPT_IDLE_TIMEOUT:
      if (parse_num("idle-timeout", optarg, 3, 3600, &vp.idle_timeout_s)) return 2;
      break;
    case OPT_RECORD: record = optarg; break;
    case OPT_RECORD_LEVEL:
      if (parse_num("record-level", optarg, 0, 19, &x) || x != (int)x) return 2;
      record_level_set = true;
      record_level = (int)x;
      break;
    case OPT_RECORD_MAP:
      if (parse_num("record-map-s", optarg, 1, 3600, &vp.record_map_s)) return 2;
      break;
    case OPT_PLAY: play = optarg; break;
    case OPT_PLAY_RATE:
      if (parse_num("play-rate", optarg, 0.01, 100, &play_rate)) return 2;
      play_rate_set = true;
      break;
    case OPT_GRID_HZ:
      if (parse_num("grid-hz", optarg, 0.1, 10, &fp.grid_hz)) return 2;
      break;
    case OPT_GRID_Z:
      /* a height a map can have: the grids vlff holds are metres to kilometres */
      if (parse_num("grid-z", optarg, -10000, 10000, &fp.grid_z)) return 2;
      fp.grid_slice = 1;
      break;
    case OPT_FORCE: force = true; break;
    case 'v': vp.verbose++; break;
    default: return vlff_cli_usage_error(&cli, "option '%s' not handled", VLFF_Q(argv[optind - 1]));
    }
  }
  if (optind < argc) return vlff_cli_usage_error(&cli, "unexpected argument '%s'", VLFF_Q(argv[optind]));
  /* the config loader checks the frame ids (tf2 names, distinct) and the segment
   * names as it does for every program */
  static struct vlff_config cfg;
  if (config) {
    char err[1024];
    vlff_config_defaults(&cfg);
    if (vlff_config_load(config, &cfg, err, sizeof err)) return vlff_cli_config_error(err);
    fp.world_frame = cfg.dds.frame_id;
    fp.camera_frame = cfg.dds.camera_frame_id;
    if (!seg_given[0]) fp.map_name = cfg.shm.map;
    if (!seg_given[1]) fp.frames_name = cfg.shm.ring;
    if (!seg_given[2]) vp.prompts_name = cfg.shm.prompts;
  }
  if (fp.map_name[0] != '/') return vlff_cli_usage_error(&cli, "--map '%s' must start with '/'", VLFF_Q(fp.map_name));
  char wwwbuf[PATH_MAX];
  if (www) {
    if (!is_dir_with_index(www)) return vlff_cli_usage_error(&cli, "--www %s: no index.html there", www);
    vp.www_dir = www;
  } else if (default_www(wwwbuf, sizeof wwwbuf) == 0) {
    vp.www_dir = wwwbuf;
  } else {
    return vlff_cli_error(&cli, "the page's files are not installed beside the program; pass --www DIR");
  }
  if (record && play) return vlff_cli_usage_error(&cli, "--record and --play exclude each other");
  /* an option of a mode not asked for would be ignored without a word */
  if (record_level_set && !record) return vlff_cli_usage_error(&cli, "--record-level without --record");
  if (play_rate_set && !play) return vlff_cli_usage_error(&cli, "--play-rate without --play");
  if (force && !record) return vlff_cli_usage_error(&cli, "--force without --record");
  /* a point cloud piece is a fraction of a client's queue: a whole map of any size
   * reaches a client that reads, piece after piece */
  fp.cloud_piece_bytes = vp.max_queue_bytes / 8 < (1u << 20) ? vp.max_queue_bytes / 8 : (1u << 20);
  /* a grid or depth image is one message: one above the queue limit would drop
   * every client of its channel */
  fp.max_message_bytes = vp.max_queue_bytes / 2;
  char *token = NULL;
  if (token_file && !(token = read_token(token_file))) return 1;
  vp.token = token;

  struct vlff_feed *feed = NULL;
  struct vlff_view *v = NULL;
  if (play) {
    if ((vp.play = vlff_view_play_open(play))) vlff_view_play_rate(vp.play, play_rate);
  } else {
    feed = vlff_feed_new(&fp);
  }
  char record_buf[PATH_MAX];
  if (record) record = record_path(record, record_buf, sizeof record_buf);
  struct stat rst;
  if (record && feed && !force && record != record_buf && lstat(record, &rst) == 0) {
    /* a recording named on the command line is likely a run worth keeping: a
     * second run with the same line must not replace it without a word */
    vlff_cli_error(&cli, "--record %s: the file exists; pass --force to replace it, or give a directory for a "
                         "new file per run",
                   record);
    vlff_feed_free(feed);
    free(token);
    return 1;
  }
  if (record && feed) {
    char why[512];
    struct vlff_mcap_writer_params mp = {.library = "vlff-view " VLFF_VERSION, .zstd_level = record_level};
    if (!(vp.record = vlff_mcap_writer_open(record, &mp, why, sizeof why))) vlff_cli_error(&cli, "--record %s", why);
  }
  if ((feed || vp.play) && (!record || vp.record)) v = vlff_view_new(&vp, feed);
  if (!v) {
    vlff_mcap_writer_close(vp.record, NULL, 0);
    vlff_view_play_free(vp.play);
    vlff_feed_free(feed);
    free(token);
    return 1;
  }
  struct sigaction sa = {.sa_handler = on_signal};
  sigemptyset(&sa.sa_mask);
  running = v;
  sigaction(SIGINT, &sa, NULL);
  sigaction(SIGTERM, &sa, NULL);
  signal(SIGPIPE, SIG_IGN);
  /* a recording past the file size limit (ulimit -f) is a write error that stops
   * the recording, not a signal that ends the viewer */
  signal(SIGXFSZ, SIG_IGN);
  if (play)
    printf("vlff-view: serving http://%s:%d/ (Foxglove: ws://%s:%d) recording %s, %llu messages on %d channels\n",
           vp.address, vlff_view_port(v), vp.address, vlff_view_port(v), play,
           (unsigned long long)vlff_view_play_total(vp.play), vlff_view_play_channels(vp.play));
  else
    printf("vlff-view: serving http://%s:%d/ (Foxglove: ws://%s:%d) map %s%s%s%s\n", vp.address, vlff_view_port(v),
           vp.address, vlff_view_port(v), fp.map_name, token ? ", prompt posting enabled" : "",
           record ? ", recording to " : "", record ? record : "");
  fflush(stdout);
  int rc = vlff_view_run(v);
  running = NULL;
  vlff_view_free(v);
  if (vp.record) {
    char why[512];
    uint64_t msgs = vlff_mcap_writer_messages(vp.record);
    if (vlff_mcap_writer_close(vp.record, why, sizeof why)) {
      vlff_log(VLFF_LOG_WARN, "vlff-view", "--record %s", why);
      rc = -1;
    } else {
      printf("vlff-view: recorded %llu messages to %s\n", (unsigned long long)msgs, record);
    }
  }
  vlff_view_play_free(vp.play);
  vlff_feed_free(feed);
  free(token);
  return rc ? 1 : 0;
}
