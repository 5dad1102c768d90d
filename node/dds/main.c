/* SPDX-License-Identifier: BSD-3-Clause */
/*
 * vlff-dds: the bridge to DDS. Reads the node's map segment and serves the
 * map and status over Cyclone DDS with ROS 2's wire conventions, and posts
 * the prompt sets it receives to the prompt mailbox, until SIGINT/SIGTERM.
 */
#include "cli.h"
#include "config.h"
#include "dds.h"
#include "log.h"
#include "vlff/escape.h"

#include <errno.h>
#include <getopt.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

static const struct vlff_cli cli = {
    "vlff-dds",
    "Usage: vlff-dds [OPTIONS]\n"
    "Publish the node's map (sensor_msgs/PointCloud2), prompt list (std_msgs/String),\n"
    "label and camera images (sensor_msgs/Image, CompressedImage, CameraInfo), camera\n"
    "pose (tf2_msgs/TFMessage) and status (diagnostic_msgs/DiagnosticArray) over DDS\n"
    "as ROS 2 topics, and post prompt sets received on <namespace>/vlff/prompts_in\n"
    "(std_msgs/String, a JSON list) to the prompt mailbox.\n"
    "\n"
    "  -c, --config FILE       the config (default: $VLFF_CONFIG, then the installed vlff.yaml)\n"
    "      --check-config FILE validate FILE, print the bridge's effective settings, exit 0/1\n"
    "  -d, --domain N          DDS domain id (dds.domain_id, 0..232)\n"
    "  -n, --namespace NS      ROS namespace, \"/robot1\" or \"\" (dds.namespace)\n"
    "      --frame-id ID       header frame_id (dds.frame_id)\n"
    "  -m, --map NAME          map segment (shm.map)\n"
    "      --prompts NAME      prompt mailbox (shm.prompts)\n"
    "      --frames NAME       frame ring, the camera (shm.ring)\n"
    "      --no-map            do not publish the map (dds.map: false)\n"
    "      --no-status         do not publish the status (dds.status: false)\n"
    "      --no-prompts        take no prompt sets (dds.prompts_in: false)\n"
    "      --seconds S         stop after S seconds (default: run until signalled)\n"
    "  -v, --verbose           log every map sent\n"
    "  -V, --version           print the version and exit\n"
    "  -h, --help              print this help and exit\n"
    "\n"
    "Examples:\n"
    "  vlff-dds -c /etc/vlff/vlff.yaml --namespace /robot1\n"
    "  ros2 topic echo /robot1/vlff/status   # on any machine of the network\n",
};

enum { OPT_CHECK = 256, OPT_FRAME, OPT_PROMPTS, OPT_FRAMES, OPT_NO_MAP, OPT_NO_STATUS, OPT_NO_PROMPTS, OPT_SECONDS };

/* A YAML single-quoted scalar of s ('' for '). */
static void put_quoted(char *out, size_t len, const char *s) {
  size_t n = 0;
  if (n < len) out[n++] = '\'';
  for (; *s && n + 3 < len; s++) {
    if (*s == '\'') out[n++] = '\'';
    out[n++] = *s;
  }
  if (n + 1 < len) out[n++] = '\'';
  out[n < len ? n : len - 1] = 0;
}

int main(int argc, char **argv) {
  static const struct option opts[] = {{"config", required_argument, NULL, 'c'},
                                       {"check-config", required_argument, NULL, OPT_CHECK},
                                       {"domain", required_argument, NULL, 'd'},
                                       {"namespace", required_argument, NULL, 'n'},
                                       {"frame-id", required_argument, NULL, OPT_FRAME},
                                       {"map", required_argument, NULL, 'm'},
                                       {"prompts", required_argument, NULL, OPT_PROMPTS},
                                       {"frames", required_argument, NULL, OPT_FRAMES},
                                       {"no-map", no_argument, NULL, OPT_NO_MAP},
                                       {"no-status", no_argument, NULL, OPT_NO_STATUS},
                                       {"no-prompts", no_argument, NULL, OPT_NO_PROMPTS},
                                       {"seconds", required_argument, NULL, OPT_SECONDS},
                                       {"verbose", no_argument, NULL, 'v'},
                                       VLFF_CLI_COMMON_OPTIONS};
  const char *path = NULL, *domain = NULL, *ns = NULL, *frame = NULL, *map = NULL, *prompts = NULL,
             *frames = NULL;
  bool check = false, no_map = false, no_status = false, no_prompts = false, verbose = false;
  double seconds = 0;
  int c, status;
  while ((c = vlff_cli_next(&cli, argc, argv, "c:d:n:m:v", opts, &status)) != -1) {
    char *end;
    switch (c) {
    case VLFF_CLI_EXIT: return status;
    case 'c': path = optarg; break;
    case OPT_CHECK: path = optarg, check = true; break;
    case 'd': domain = optarg; break;
    case 'n': ns = optarg; break;
    case OPT_FRAME: frame = optarg; break;
    case 'm': map = optarg; break;
    case OPT_PROMPTS: prompts = optarg; break;
    case OPT_FRAMES: frames = optarg; break;
    case OPT_NO_MAP: no_map = true; break;
    case OPT_NO_STATUS: no_status = true; break;
    case OPT_NO_PROMPTS: no_prompts = true; break;
    case 'v': verbose = true; break;
    case OPT_SECONDS:
      errno = 0;
      seconds = strtod(optarg, &end);
      if (errno || end == optarg || *end || !(seconds > 0 && seconds <= 1e9))
        return vlff_cli_usage_error(&cli, "--seconds '%s' is not a number in (0, 1e9]", VLFF_Q(optarg));
      break;
    default: return vlff_cli_usage_error(&cli, "option '%s' not handled", VLFF_Q(argv[optind - 1]));
    }
  }
  if (optind != argc) return vlff_cli_usage_error(&cli, "unexpected argument '%s'", VLFF_Q(argv[optind]));

  static struct vlff_config cfg, over;
  char err[1024];
  vlff_config_defaults(&cfg);
  const char *found = vlff_config_find(path, err, sizeof err);
  if (found && vlff_config_load(found, &cfg, err, sizeof err)) return vlff_cli_config_error(err);

  /* The overrides pass the config's own checks: they are loaded as a
   * config of their own, named after the options in messages. */
  char yaml[2560], q[5][600];
  put_quoted(q[0], sizeof q[0], ns ? ns : "");
  put_quoted(q[1], sizeof q[1], frame ? frame : "");
  put_quoted(q[2], sizeof q[2], map ? map : "");
  put_quoted(q[3], sizeof q[3], prompts ? prompts : "");
  put_quoted(q[4], sizeof q[4], frames ? frames : "");
  int n = snprintf(yaml, sizeof yaml, "%s", domain || ns || frame ? "dds:\n" : "");
  if (domain) n += snprintf(yaml + n, sizeof yaml - (size_t)n, "  domain_id: %s\n", domain);
  if (ns) n += snprintf(yaml + n, sizeof yaml - (size_t)n, "  namespace: %s\n", q[0]);
  if (frame) n += snprintf(yaml + n, sizeof yaml - (size_t)n, "  frame_id: %s\n", q[1]);
  if (map || prompts || frames) n += snprintf(yaml + n, sizeof yaml - (size_t)n, "shm:\n");
  if (map) n += snprintf(yaml + n, sizeof yaml - (size_t)n, "  map: %s\n", q[2]);
  if (prompts) n += snprintf(yaml + n, sizeof yaml - (size_t)n, "  prompts: %s\n", q[3]);
  if (frames) n += snprintf(yaml + n, sizeof yaml - (size_t)n, "  ring: %s\n", q[4]);
  if (n >= (int)sizeof yaml || strchr(domain ? domain : "", '\n') ||
      vlff_config_load_mem(yaml, strlen(yaml), "(command line)", &over, err, sizeof err))
    return vlff_cli_usage_error(&cli, "%s", n >= (int)sizeof yaml ? "options too long" : err);
  if (domain) cfg.dds.domain_id = over.dds.domain_id;
  if (ns) snprintf(cfg.dds.ns, sizeof cfg.dds.ns, "%s", over.dds.ns);
  if (frame) snprintf(cfg.dds.frame_id, sizeof cfg.dds.frame_id, "%s", over.dds.frame_id);
  if (map) snprintf(cfg.shm.map, sizeof cfg.shm.map, "%s", over.shm.map);
  if (prompts) snprintf(cfg.shm.prompts, sizeof cfg.shm.prompts, "%s", over.shm.prompts);
  if (frames) snprintf(cfg.shm.ring, sizeof cfg.shm.ring, "%s", over.shm.ring);
  if (no_map) cfg.dds.on[VLFF_DDS_MAP] = false;
  if (no_status) cfg.dds.on[VLFF_DDS_STATUS] = false;
  if (no_prompts) cfg.dds.on[VLFF_DDS_PROMPTS_IN] = false;
  if (!strcmp(cfg.shm.map, cfg.shm.prompts))
    return vlff_cli_usage_error(&cli, "the map segment and the prompt mailbox are both '%s'", VLFF_Q(cfg.shm.map));

  for (int i = VLFF_DDS_LABEL_IMAGE_COMPRESSED; i <= VLFF_DDS_CAMERA_IMAGE_COMPRESSED; i += 2)
    if (cfg.dds.on[i] && !vlff_dds_can_compress())
      return vlff_cli_error(&cli, "dds.%s: this build has no image encoder (built without OpenCV): set it false",
                            vlff_dds_topic_key(i));
  struct vlff_dds_opts o = {0};
  o.dds = cfg.dds;
  snprintf(o.map, sizeof o.map, "%s", cfg.shm.map);
  snprintf(o.prompts, sizeof o.prompts, "%s", cfg.shm.prompts);
  snprintf(o.frames, sizeof o.frames, "%s", cfg.shm.ring);
  /* DiagnosticStatus.hardware_id: the computer the node runs on (a fleet
   * tells its robots apart by it and by the namespace). */
  if (gethostname(o.hardware_id, sizeof o.hardware_id - 1) != 0) snprintf(o.hardware_id, sizeof o.hardware_id, "vlff");
  o.run_seconds = seconds;
  o.update_points_max = vlff_config_dds_update_points(&cfg);
  char topic[VLFF_DDS_NTOPICS][300];
  for (int i = 0; i < VLFF_DDS_NTOPICS; i++)
    if (vlff_dds_topic_of(topic[i], sizeof topic[i], o.dds.ns, i) < 0)
      return vlff_cli_usage_error(&cli, "dds.namespace '%s' too long for a topic name", VLFF_Q(o.dds.ns));
  if (check) {
    static const char *const rel[] = {"best_effort", "reliable"}, *const dur[] = {"volatile", "transient_local"};
    printf("config: %s\n", found ? found : "(none: defaults)");
    printf("dds.domain_id: %d\n", o.dds.domain_id);
    printf("dds.namespace: \"%s\"\n", o.dds.ns);
    printf("dds.frame_id: \"%s\"\n", o.dds.frame_id);
    printf("dds.camera_frame_id: \"%s\"\n", o.dds.camera_frame_id);
    printf("dds.map_full_period_s: %g\n", o.dds.map_full_period_s);
    printf("dds.history_max_mb: %g (map updates of up to %llu points)\n", o.dds.history_max_mb,
           (unsigned long long)o.update_points_max);
    for (int i = 0; i < VLFF_DDS_NTOPICS; i++) {
      const struct vlff_cfg_dds_qos *qq = &o.dds.qos[i];
      const char *from = i == VLFF_DDS_MAP || i == VLFF_DDS_MAP_UPDATES || i == VLFF_DDS_PROMPTS || i == VLFF_DDS_LABEL_IMAGE ||
                                 i == VLFF_DDS_LABEL_IMAGE_COMPRESSED || i == VLFF_DDS_STATUS
                             ? o.map
                         : i == VLFF_DDS_PROMPTS_IN ? o.prompts
                         : i == VLFF_DDS_TF         ? "frames or label image"
                                                    : o.frames;
      if (o.dds.on[i])
        printf("%s: %s %s %s (%s, %s, keep last %d)\n", vlff_dds_topic_key(i), topic[i],
               i == VLFF_DDS_PROMPTS_IN ? "->" : "<-", from, rel[qq->reliability], dur[qq->durability], qq->depth);
      else
        printf("%s: (off)\n", vlff_dds_topic_key(i));
    }
    return 0;
  }
  vlff_log_set_level(verbose ? VLFF_LOG_DEBUG : (enum vlff_log_level)cfg.node.log_level);
  vlff_cli_catch_stop();
  struct vlff_dds *b = vlff_dds_create(&o, err, sizeof err);
  if (!b) return vlff_cli_error(&cli, "%s", err);
  VLFF_INFO("dds", "domain %d, namespace \"%s\": from %s and %s", o.dds.domain_id, o.dds.ns, o.map, o.frames);
  int rc = vlff_dds_run(b);
  const struct vlff_dds_counts *k = vlff_dds_counts(b);
  VLFF_INFO("dds", "stopping: %llu whole maps, %llu map updates, %llu status messages sent; %llu prompt sets posted, "
                   "refused: %llu oversized, %llu flood, %llu malformed, %llu invalid, %llu mailbox busy",
            (unsigned long long)k->maps_sent, (unsigned long long)k->map_updates_sent,
            (unsigned long long)k->status_sent, (unsigned long long)k->prompts_posted,
            (unsigned long long)k->prompts_oversized, (unsigned long long)k->prompts_flood,
            (unsigned long long)k->prompts_malformed, (unsigned long long)k->prompts_invalid,
            (unsigned long long)k->prompts_busy);
  vlff_dds_destroy(b);
  return rc < 0 ? 1 : 0;
}
