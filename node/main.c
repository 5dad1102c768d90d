/*
 * vlff-node: the learner process. Parses its command line and config, then
 * runs until SIGINT/SIGTERM (or node.run_seconds). Signals only set a flag;
 * all shutdown work happens on the main thread.
 */
#include <errno.h>
#include <getopt.h>
#include <grp.h>
#include <signal.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>

#include "cli.h"
#include "clock.h"
#include "config.h"
#include "dataset.h" /* the PNG and PLY writers of --snapshot */
#include "log.h"
#include "node.h"
#include "service.h"
#ifdef VLFF_HAVE_SIM
#include "sim_source.h"
#endif
#include "vlff/escape.h"
#include "vlff/shm.h"
#ifdef VLFF_HAVE_CAN
#include "can_status.h"
#include "vlff_can.h"
#endif

#ifndef VLFF_SYSCONFDIR
#error "VLFF_SYSCONFDIR must come from the install's sysconfdir (CMake)"
#endif

static const struct vlff_cli cli = {
    "vlff-node",
    "Usage: vlff-node [OPTIONS]\n"
    "Learn a vision-language feature field online and publish segmented maps.\n"
    "\n"
    "  -c, --config FILE        run with this YAML config; without it $VLFF_CONFIG,\n"
    "                           then " VLFF_SYSCONFDIR "/vlff/vlff.yaml; none found is an error\n"
    "                           (installed elsewhere: vlff/vlff.yaml in that install's sysconfdir)\n"
    "      --check-config FILE  validate FILE, print the effective config, exit 0/1\n"
    "      --status             print a live progress line on the terminal\n"
    "      --fresh              start anew: remove node.state_dir's checkpoints instead of\n"
    "                           resuming them (node.resume: false)\n"
    "      --snapshot DIR       on exit, write DIR/strip.png (image | segmentation | truth)\n"
    "                           and DIR/map.ply (the labelled map)\n"
    "  -V, --version            print the version and exit\n"
    "  -h, --help               print this help and exit\n"
    "\n"
    "Examples:\n"
    "  vlff-node --config " VLFF_SYSCONFDIR "/vlff/demo-sim.yaml\n"
    "  vlff-node --check-config configs/aravis-gige.yaml\n",
};

#ifdef VLFF_HAVE_CAN
/* Runs on the CAN thread: commands only queue work for the trainer, so the
 * bus never waits on learning. */
static int on_can_command(void *ctx, const struct vlff_can_command *cmd) {
  return vlff_node_command(ctx, cmd->code, cmd->arg) == 0 ? VLFF_CAN_RES_OK : VLFF_CAN_RES_BUSY;
}

static void can_publish_status(struct vlff_can *can, const struct vlff_node_status *st, double dropped_per_s) {
  struct vlff_can_status cs;
  enum vlff_can_nmt nmt;
  vlff_node_can_status(st, dropped_per_s, (int64_t)vlff_now_ns(), &cs, &nmt);
  vlff_can_set_status(can, &cs);
  vlff_can_set_state(can, nmt);
}
#endif


/* " (no pose 193, no depth 2)": the reasons behind the refused count, for
 * the status line; empty when nothing was refused. */
static void refusals_text(const struct vlff_node_status *st, char *out, size_t len) {
  size_t k = 0;
  out[0] = 0;
  for (int r = 1; r < VLFF_REFUSED_COUNT && k < len; r++)
    if (st->refused[r])
      k += (size_t)snprintf(out + k, len - k, "%s%s %lld", k ? ", " : " (", vlff_refusal_name(r), st->refused[r]);
  if (k && k < len) snprintf(out + k, len - k, ")");
}

/* --snapshot DIR checked before the run, not after it: a DIR that is a file,
 * whose parent is missing, or too long for dir/strip.png learned so only at
 * exit, after the whole run. 0, or -1 with why. */
static int snapshot_dir_problem(const char *dir, char *why, size_t len) {
  struct stat st;
  if (!*dir) return snprintf(why, len, "an empty name, expected a directory"), -1;
  if (strlen(dir) > 4000) return snprintf(why, len, "a name of %zu bytes, longer than the 4000 taken", strlen(dir)), -1;
  if (stat(dir, &st) == 0)
    return S_ISDIR(st.st_mode) ? 0 : (snprintf(why, len, "exists and is not a directory"), -1);
  if (errno != ENOENT) return snprintf(why, len, "%s", strerror(errno)), -1;
  /* made at exit: its parent must be there */
  char parent[4096];
  const char *slash = strrchr(dir, '/');
  snprintf(parent, sizeof parent, "%.*s", slash ? (slash == dir ? 1 : (int)(slash - dir)) : 1, slash ? dir : ".");
  if (stat(parent, &st) != 0 || !S_ISDIR(st.st_mode))
    return snprintf(why, len, "its parent %s is not a directory (the node makes only DIR itself)", VLFF_Q(parent)),
           -1;
  return 0;
}

/* --snapshot: the final map for people, dir/strip.png and dir/map.ply. */
static int write_snapshot(struct vlff_node *node, const char *dir, char *err, size_t errlen) {
  if (mkdir(dir, 0755) != 0 && errno != EEXIST) return snprintf(err, errlen, "%s: %s", dir, strerror(errno)), -1;
  struct vlff_snapshot snap;
  if (vlff_node_snapshot(node, &snap, err, errlen)) return -1;
  char path[4096];
  snprintf(path, sizeof path, "%s/strip.png", dir);
  int rc = vlff_png_write(path, snap.strip, snap.width, snap.height, 3, 0, err, errlen);
  snprintf(path, sizeof path, "%s/map.ply", dir);
  if (rc == 0) rc = vlff_ply_write(path, snap.xyz, snap.rgb, snap.label, snap.n, err, errlen);
  vlff_snapshot_free(&snap);
  return rc < 0 ? -1 : 0;
}

/* The simulator's source and hooks when the config uses the simulator
 * (source.kind: sim or source.features: sim), else none: the one place
 * that knows every source kind. 0, or -1 with the reason in err. */
static int source_open(const struct vlff_config *cfg, void **src, struct vlff_source_hooks *hooks, char *err,
                       size_t errlen) {
  memset(hooks, 0, sizeof *hooks);
  *src = NULL;
  if (cfg->source.kind != VLFF_SOURCE_SIM && cfg->source.features != VLFF_FEAT_SIM) return 0;
#ifdef VLFF_HAVE_SIM
  *src = vlff_sim_source_create(cfg, hooks, err, errlen);
  return *src ? 0 : -1;
#else
  snprintf(err, errlen, "%s: this vlff-node was built without the simulator",
           cfg->source.kind == VLFF_SOURCE_SIM ? "source.kind: sim" : "source.features: sim");
  return -1;
#endif
}

static void source_close(void *src) {
#ifdef VLFF_HAVE_SIM
  vlff_sim_source_destroy(src);
#else
  (void)src;
#endif
}

/* --check-config: what start-up would refuse is refused here too, short of
 * making segments or opening the CAN bus: the CAN keys together, the
 * segments' group, the simulator the config asks for, and the node's own
 * checks with the files it loads (a text encoder for the prompts, the
 * embeddings file, the models and vocabulary; vlff_node_check). */
static int check_config(const char *path) {
  static struct vlff_config cfg;
  char err[1024];
  if (vlff_config_load(path, &cfg, err, sizeof err)) return vlff_cli_config_error(err);
#ifdef VLFF_HAVE_CAN
  if (vlff_can_check_config(&cfg.can, err, sizeof err)) {
    fprintf(stderr, "%s: %s\n", path, err);
    return 1;
  }
#endif
  if (cfg.shm.group[0]) {
    char *end;
    long gid = strtol(cfg.shm.group, &end, 10);
    if (!(*end == 0 && gid >= 0) && !getgrnam(cfg.shm.group)) {
      fprintf(stderr, "%s: key 'shm.group': no group '%s' on this machine\n", path, cfg.shm.group);
      return 1;
    }
  }
  struct vlff_source_hooks hooks;
  void *src;
  int bad = source_open(&cfg, &src, &hooks, err, sizeof err) || vlff_node_check(&cfg, &hooks, true, err, sizeof err);
  source_close(src);
  if (bad) {
    fprintf(stderr, "%s: %s\n", path, err);
    return 1;
  }
  vlff_config_dump(&cfg, stdout);
  fprintf(stderr, "%s: OK\n", path);
  return 0;
}

/* The running node and what main's loop feeds from it. */
struct run {
  struct vlff_config cfg;
  void *source; /* the simulator's, when the config uses it (source_open) */
  struct vlff_node *node;
#ifdef VLFF_HAVE_CAN
  struct vlff_can *can;
  long long last_dropped;
  double last_can;
#endif
  struct vlff_service svc;
  bool status_view;
  double t0, last_line;
};

/* The node (with the simulator's hooks when the config uses them) and its
 * CAN side. 0, or 1 with the reason logged. */
static int start(struct run *r) {
  char err[512];
  struct vlff_source_hooks hooks;
  r->node = source_open(&r->cfg, &r->source, &hooks, err, sizeof err)
                ? NULL
                : vlff_node_create(&r->cfg, &hooks, err, sizeof err);
  if (!r->node) {
    VLFF_ERROR("node", "%s", err);
    source_close(r->source);
    return 1;
  }
#ifdef VLFF_HAVE_CAN
  if (r->cfg.can.enabled) {
    if (vlff_can_check_config(&r->cfg.can, err, sizeof err)) {
      VLFF_ERROR("node", "%s", err);
      vlff_node_destroy(r->node, false);
      source_close(r->source);
      return 1;
    }
    r->can = vlff_can_open(&r->cfg.can, r->cfg.prompts.set_count, on_can_command, r->node);
    if (!r->can) VLFF_ERROR("node", "CAN on %s could not start; running without it", r->cfg.can.interface);
  }
#else
  if (r->cfg.can.enabled) VLFF_WARN("node", "can.enabled, but this vlff-node was built without SocketCAN");
#endif
  /* Under systemd (Type=notify) the node is ready once its threads run; with
   * WatchdogSec the watchdog is fed only while both the trainer and the
   * ingest thread pass their loops, so a hung thread gets the node restarted
   * even though this main loop still runs. */
  vlff_service_ready(&r->svc);
  r->t0 = vlff_seconds();
  return 0;
}

/* One pass of main's loop: the watchdog, CAN status, the --status line. */
static void tick(struct run *r, double now) {
  struct vlff_node_status st;
  uint64_t t = vlff_now_ns();
  if (vlff_service_watchdog_due(&r->svc, t)) {
    vlff_node_status(r->node, &st);
    uint64_t stale = r->svc.watchdog_ns / 2;
    if (t - st.trainer_beat_ns < stale && t - st.ingest_beat_ns < stale) vlff_service_watchdog();
    else VLFF_WARN("node", "watchdog not fed: trainer %.1f s, ingest %.1f s since their last loop",
                   (double)(t - st.trainer_beat_ns) * 1e-9, (double)(t - st.ingest_beat_ns) * 1e-9);
  }
#ifdef VLFF_HAVE_CAN
  if (r->can && now - r->last_can >= 0.1) {
    vlff_node_status(r->node, &st);
    long long dropped = st.frames_lost + st.frames_invalid + st.poses_rejected;
    can_publish_status(r->can, &st, (double)(dropped - r->last_dropped) / (now - r->last_can));
    r->last_dropped = dropped;
    r->last_can = now;
  }
#endif
  if (r->status_view && now - r->last_line >= 0.5) {
    r->last_line = now;
    vlff_node_status(r->node, &st);
    char m2[16] = "  -  ", m3[16] = "  -  ", why[256];
    if (st.miou2d >= 0) snprintf(m2, sizeof m2, "%5.1f", st.miou2d);
    if (st.miou3d >= 0) snprintf(m3, sizeof m3, "%5.1f", st.miou3d);
    refusals_text(&st, why, sizeof why);
    /* The process's CPU use in cores, against node.cpu_budget when set. */
    char cpu[48] = "cpu -";
    if (st.cpu_used >= 0) snprintf(cpu, sizeof cpu, "cpu %.2f", st.cpu_used);
    if (st.cpu_budget > 0) snprintf(cpu + strlen(cpu), sizeof cpu - strlen(cpu), " of %.2f", st.cpu_budget);
    /* Memory against its limits, MiB: keyframes, evidence, the process. */
    char mem[192] = "mem -";
    if (st.mem_rss_mb >= 0)
      snprintf(mem, sizeof mem, "mem kf %.0f/%.0f ev %.0f/%.0f rss %.0f MiB", st.mem_keyframes_mb,
               st.mem_keyframes_limit_mb, st.mem_evidence_mb, st.mem_evidence_limit_mb, st.mem_rss_mb);
    /* A box that grew (field.grow): its size, and the keyframes it could not grow to. */
    if (st.box_growths || st.box_refused)
      snprintf(mem + strlen(mem), sizeof mem - strlen(mem), " box %.0fx%.0fx%.0f m%s", st.box_hi[0] - st.box_lo[0],
               st.box_hi[1] - st.box_lo[1], st.box_hi[2] - st.box_lo[2], st.box_refused ? " CAPPED" : "");
    /* The far map, once the grid slid (docs/field.md "Beyond the caps"). */
    if (st.box_slides)
      snprintf(mem + strlen(mem), sizeof mem - strlen(mem), " far %.1f/%.0f MiB%s", st.far_mb, st.far_limit_mb,
               st.far_dropped ? " DROPPING" : "");
    /* Keyframes on disk (keyframes.page_mb), once the store has paged any. */
    if (st.keyframes_paged_out || st.keyframes_dropped)
      snprintf(mem + strlen(mem), sizeof mem - strlen(mem), " kf paged %lld%s", st.keyframes_paged,
               st.keyframes_dropped ? " DROPPING" : "");
    vlff_log_status("[%6.1f s] frames %lld (%.1f/s%s) refused %lld%s kf %d rej %lld | it %lld (%.1f/s) loss %.4f "
                    "psnr %.1f | %s | %s | map v%llu flips %lld mIoU 2D %s 3D %s%s%s   ",
                    now - r->t0, st.frames_in, st.fps_in,
                    (st.error_flags & VLFF_NODE_ERR_CAMERA_LOST) ? ", CAMERA LOST: none lately" : "",
                    st.frames_invalid, why, st.keyframes, st.poses_rejected, st.iteration, st.it_per_s, st.loss,
                    st.psnr, cpu, mem, (unsigned long long)st.map_version, st.label_flips, m2, m3,
                    st.adjusted[0] ? " | adjusted: " : "",
                    st.adjusted);
  }
}

/* Stops CAN first (its command callback points at the node), writes the
 * snapshot, and the node's final checkpoint. The exit status. */
static int finish(struct run *r, const char *snapshot_dir) {
  vlff_log_status_end();
  vlff_service_stopping();
  VLFF_INFO("node", "stopping (%s)", vlff_cli_stop == SIGTERM ? "SIGTERM"
                                     : vlff_cli_stop == SIGINT ? "SIGINT"
                                     : vlff_cli_stop == SIGHUP ? "SIGHUP"
                                                                : "run_seconds reached");
#ifdef VLFF_HAVE_CAN
  vlff_can_close(r->can);
#endif
  /* The stop line's counts are those the threads stopped with. */
  vlff_node_join(r->node);
  struct vlff_node_status st;
  vlff_node_status(r->node, &st);
  int rc = 0;
  char err[512];
  if (snapshot_dir) {
    if (write_snapshot(r->node, snapshot_dir, err, sizeof err)) {
      VLFF_ERROR("node", "snapshot: %s", err);
      rc = 1;
    } else {
      VLFF_INFO("node", "snapshot written to %s/strip.png and %s/map.ply", snapshot_dir, snapshot_dir);
    }
  }
  vlff_node_destroy(r->node, true);
  source_close(r->source);
  char why[256];
  refusals_text(&st, why, sizeof why);
  VLFF_INFO("node", "stopped: %lld iterations, %d keyframes (%lld evicted, %lld dropped: the trainer was busy), "
            "%lld frames in, %lld refused%s, %lld lost, %lld poses rejected, map version %llu",
            st.iteration, st.keyframes, st.keyframes_evicted, st.candidates_dropped, st.frames_in, st.frames_invalid,
            why, st.frames_lost, st.poses_rejected, (unsigned long long)st.map_version);
  if (st.box_growths || st.box_refused)
    VLFF_INFO("node", "the box grew %lld times, to [%.1f, %.1f] x [%.1f, %.1f] x [%.1f, %.1f] m; %lld growths refused",
              st.box_growths, st.box_lo[0], st.box_hi[0], st.box_lo[1], st.box_hi[1], st.box_lo[2], st.box_hi[2],
              st.box_refused);
  if (st.box_slides)
    VLFF_INFO("node", "the map slid %lld times at shm.map_max_voxels; its far map holds %lld blocks, %.1f of "
                      "shm.map_far_max_mb %.0f MiB, %lld blocks dropped",
              st.box_slides, st.far_blocks, st.far_mb, st.far_limit_mb, st.far_dropped);
  if (st.keyframes_paged_out || st.keyframes_dropped)
    VLFF_INFO("node", "keyframes beyond keyframes.memory_mb: %lld in the page file (%lld paged out, %lld brought "
                      "back), %lld dropped",
              st.keyframes_paged, st.keyframes_paged_out, st.keyframes_paged_in, st.keyframes_dropped);
  if (st.evidence_paged_out || st.evidence_dropped)
    VLFF_INFO("node", "evidence beyond publish.evidence_max_mb: %lld voxels in the page file (%lld paged out, %lld "
                      "brought back), %lld given up",
              st.evidence_paged, st.evidence_paged_out, st.evidence_paged_in, st.evidence_dropped);
  return rc;
}

int main(int argc, char **argv) {
  vlff_node_process_setup();
  /* first: a stop signal while the config loads (50 ms after start) killed
   * the node with an empty log; caught, it stops after start-up, cleanly */
  vlff_cli_catch_stop();
  enum { OPT_CHECK = 256, OPT_STATUS, OPT_SNAPSHOT, OPT_FRESH };
  static const struct option opts[] = {
      {"config", required_argument, NULL, 'c'},
      {"check-config", required_argument, NULL, OPT_CHECK},
      {"status", no_argument, NULL, OPT_STATUS},
      {"snapshot", required_argument, NULL, OPT_SNAPSHOT},
      {"fresh", no_argument, NULL, OPT_FRESH},
      VLFF_CLI_COMMON_OPTIONS,
  };
  static struct run r;
  const char *config_path = NULL, *check_path = NULL, *snapshot_dir = NULL;
  int c, exit_status;
  bool fresh = false;
  while ((c = vlff_cli_next(&cli, argc, argv, "c:", opts, &exit_status)) != -1) {
    switch (c) {
    case VLFF_CLI_EXIT: return exit_status;
    case 'c': config_path = optarg; break;
    case OPT_CHECK: check_path = optarg; break;
    case OPT_STATUS: r.status_view = true; break;
    case OPT_SNAPSHOT: snapshot_dir = optarg; break;
    case OPT_FRESH: fresh = true; break;
    default: return vlff_cli_usage_error(&cli, "option '%s' not handled", argv[optind - 1]);
    }
  }
  if (optind < argc) return vlff_cli_usage_error(&cli, "unexpected argument '%s'", argv[optind]);
  if (check_path) return check_config(check_path);
  char why[512];
  if (snapshot_dir && snapshot_dir_problem(snapshot_dir, why, sizeof why))
    return vlff_cli_usage_error(&cli, "--snapshot '%s': %s", VLFF_Q(snapshot_dir), why);
  /* Never the built-in defaults: a node started by mistake would create
   * segments and write checkpoints nobody asked for. */
  char err[512];
  config_path = vlff_config_find(config_path, err, sizeof err);
  if (!config_path) return vlff_cli_error(&cli, "%s", err);
  if (vlff_config_load(config_path, &r.cfg, err, sizeof err)) return vlff_cli_config_error(err);
  if (fresh) r.cfg.node.resume = false;
  vlff_log_set_level(r.cfg.node.log_level);
  VLFF_INFO("node", "vlff-node %s starting, config %s", vlff_version(), config_path);
  if (start(&r)) return 1;
  while (!vlff_cli_stop && !vlff_node_finished(r.node)) {
    struct timespec ts = {0, 50 * 1000 * 1000};
    nanosleep(&ts, NULL);
    tick(&r, vlff_seconds());
  }
  return finish(&r, snapshot_dir);
}
