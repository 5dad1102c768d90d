/*
 * vlff configuration: one YAML file parsed into typed structs.
 *
 * Contract
 *  - vlff_config_defaults() fills every field with its documented default;
 *    configs/default.yaml lists exactly those values (a test checks this).
 *  - vlff_config_load*() start from the defaults and apply the file. Any
 *    error (syntax, unknown key, wrong type, value out of range) rejects the
 *    whole file: the output struct is then left holding the defaults, and
 *    err receives one line "file:line:column: key 'a.b': expected <what>,
 *    got <what>". Unknown keys are errors so that typos never pass silently.
 *  - Strings are stored NUL-terminated in fixed arrays; over-long values are
 *    errors, never truncated. A string value holding a NUL or a control
 *    character (C0, tab and newline included, or DEL) is an error.
 *  - Every prompt of prompts.sets passes vlff_prompt_check() (vlff/shm.h),
 *    the rule of the prompt mailbox and the embeddings file format: a set
 *    the node is configured with is one the mailbox would accept.
 *  - The struct is plain data: copy it freely; it owns no memory.
 *  - A file nested deeper than VLFF_CONFIG_MAX_DEPTH levels, or with more
 *    than VLFF_CONFIG_MAX_EVENTS YAML events, VLFF_CONFIG_MAX_ANCHORS
 *    anchors (&a), VLFF_CONFIG_MAX_ALIASES aliases (*a) or
 *    VLFF_CONFIG_MAX_DIRECTIVES directives (%TAG, %YAML), is refused before
 *    it is loaded ("file:line:col: nesting deeper than ...", "more than 64
 *    YAML anchors ..."), so a hostile file costs time in proportion to its
 *    size.
 *  - A key is set once: the same key twice in a mapping, or one key spelt
 *    both dotted and nested (shm.ring: beside shm: {ring:}), is an error, in
 *    every mapping (prompts.sets entries included). A key holding a NUL
 *    byte is an error, and so is a NUL in any value (a number, a boolean or
 *    an enum as well as a string), never cut short at the NUL.
 *  - Integers are decimal or hexadecimal (0x2a); one written with a leading
 *    0 (010) is an error asking for decimal, since YAML 1.1 readers take it
 *    as octal and YAML 1.2 readers as decimal. shm.mode, a file mode, is
 *    the exception: it is octal and must be written with its leading 0
 *    (0640). Numbers that are not integers are decimal only.
 *  - Shared-memory names (shm.ring, pose_ring, map, prompts, feature_ring)
 *    must be valid POSIX names ('/' then 1..248 characters, no other '/')
 *    and distinct from each other.
 *  - Files are opened as regular files only (files.h): a FIFO or device at
 *    the config's path is refused, never waited on.
 *  - Thread-safe: no global state.
 */
#ifndef VLFF_CONFIG_H
#define VLFF_CONFIG_H

#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdbool.h>

#define VLFF_CFG_STR 128
#define VLFF_CFG_PATH 256
#define VLFF_PROMPT_LEN 64
/* A prompt set of the node: at most what the map's prompt table and the
 * mailbox carry (VLFF_SHM_MAX_PROMPTS in vlff/shm.h). */
#define VLFF_MAX_PROMPTS 32
/* Prompts the field and the evidence score at once: vlff-eval scores
 * ScanNet's NYU40 label set (40 classes) in one pass. */
#define VLFF_FIELD_MAX_PROMPTS 64
#define VLFF_MAX_PROMPT_SETS 8
#define VLFF_CONFIG_MAX_DEPTH 32
#define VLFF_CONFIG_MAX_EVENTS 100000
/* No shipped config uses an anchor, alias or directive; a hand-written one
 * may share a value (one intrinsics list for two cameras, a prompt list for
 * two sets) through a few. libyaml's loader compares every new anchor with
 * every earlier one and looks each alias up among them, so these bound its
 * work to a few thousand string compares; its parser does the same for
 * %TAG directives. 256 aliases outnumber the schema's keys (245). */
#define VLFF_CONFIG_MAX_ANCHORS 64
#define VLFF_CONFIG_MAX_ALIASES 256
#define VLFF_CONFIG_MAX_DIRECTIVES 16

enum vlff_log_level { VLFF_LOG_ERROR, VLFF_LOG_WARN, VLFF_LOG_INFO, VLFF_LOG_DEBUG };
enum vlff_source_kind { VLFF_SOURCE_SIM, VLFF_SOURCE_RING };
enum vlff_feature_source { VLFF_FEAT_SIM, VLFF_FEAT_MODEL, VLFF_FEAT_RING };
enum vlff_feat_loss { VLFF_FEAT_LOSS_L2, VLFF_FEAT_LOSS_L1, VLFF_FEAT_LOSS_COS };
enum vlff_sampling { VLFF_SAMPLING_DEPTH, VLFF_SAMPLING_UNIFORM };
enum vlff_label_image { VLFF_LABEL_IMAGE_SURFACE, VLFF_LABEL_IMAGE_RENDER };
enum vlff_trajectory { VLFF_TRAJ_WALK, VLFF_TRAJ_ORBIT };
enum vlff_sim_layout { VLFF_LAYOUT_ROOM, VLFF_LAYOUT_FLAT, VLFF_LAYOUT_BUILDING };
enum vlff_camera_kind { VLFF_CAM_ARAVIS, VLFF_CAM_LIBCAMERA };
enum vlff_depth_camera_kind { VLFF_DCAM_NONE, VLFF_DCAM_ARAVIS };
enum vlff_trigger_mode { VLFF_TRIG_FREERUN, VLFF_TRIG_SOFTWARE, VLFF_TRIG_HARDWARE };
enum vlff_gpio_mode { VLFF_GPIO_OFF, VLFF_GPIO_OUTPUT, VLFF_GPIO_INPUT };
enum vlff_depth_kind { VLFF_DEPTH_NONE, VLFF_DEPTH_STREAM, VLFF_DEPTH_STEREO };
enum vlff_depth_unit { VLFF_DEPTH_UNIT_MM, VLFF_DEPTH_UNIT_M };
enum vlff_pose_clock { VLFF_POSE_CLOCK_MONOTONIC, VLFF_POSE_CLOCK_REALTIME };
enum vlff_pose_stamp { VLFF_POSE_STAMP_SOURCE, VLFF_POSE_STAMP_HOST };

struct vlff_prompt_set {
  char name[VLFF_PROMPT_LEN];
  int count;
  char text[VLFF_MAX_PROMPTS][VLFF_PROMPT_LEN];
};

struct vlff_cfg_node {
  int log_level;                   /* enum vlff_log_level */
  char state_dir[VLFF_CFG_PATH];   /* checkpoints live here */
  double checkpoint_period_s;      /* 0 = only on SIGTERM / command */
  bool resume;                     /* start from state_dir's checkpoint (false: remove it, start anew) */
  double run_seconds;              /* 0 = run until signalled */
  int threads;                     /* 0 = one per core */
  double cpu_budget;               /* cores the whole process may use (0.1..256); 0 = no limit */
};

struct vlff_cfg_shm {
  char ring[VLFF_CFG_STR];         /* frame ring segment name ("/vlff-frames") */
  int ring_slots;
  int max_width, max_height;       /* slot size: largest frame accepted */
  char pose_ring[VLFF_CFG_STR];
  int pose_slots;
  char map[VLFF_CFG_STR];
  int map_max_voxels;              /* map segment capacity */
  int map_far_max_mb;              /* the far map beside it (far.h), MiB; 0: a slide's voxels dropped, counted */
  int label_max_width, label_max_height;
  char prompts[VLFF_CFG_STR];      /* prompt mailbox segment */
  char feature_ring[VLFF_CFG_STR];
  char group[VLFF_CFG_STR];        /* owning group, "" = creator's */
  int mode;                        /* permission bits, 0640 or 0660 */
};

struct vlff_cfg_source {
  int kind;                        /* enum vlff_source_kind */
  int features;                    /* enum vlff_feature_source */
  double pose_tolerance_s;         /* frame<->pose timestamp match */
  bool allow_sim_features;         /* features: sim with kind: ring, forced (tests, demos) */
  double pose_wait_s;              /* a keyframe candidate newer than every pose waits this long */
};

/* sim.changes: what happens to the scene's objects, and when. */
#define VLFF_SIM_MAX_CHANGES 16
#define VLFF_SIM_OBJECT_LEN 40
enum vlff_sim_action { VLFF_SIM_MOVE, VLFF_SIM_REMOVE, VLFF_SIM_ADD };
struct vlff_sim_change {
  double time_s;                   /* sim time (frame index / sim.rate_hz) it happens at */
  char object[VLFF_SIM_OBJECT_LEN]; /* "<class>" or "<class>#<n>": the n-th (from 1) of that class, as built */
  int action;                      /* enum vlff_sim_action */
  bool has_to;
  double to[2];                    /* move, add: the new centre of its footprint, world x y in m */
};

struct vlff_cfg_sim {
  int seed;
  double rate_hz;
  int width, height;               /* its features have field.feature_dim dimensions */
  double difficulty;               /* 0 = clean features, 1 = very noisy */
  int trajectory;                  /* enum vlff_trajectory (room layout) */
  int layout;                      /* enum vlff_sim_layout */
  int flats;                       /* building layout: flats off the corridor */
  double object_bias;              /* 0..1: per-object feature bias every view shares */
  double speed_mps;
  double depth_noise_m;
  double depth_hole_frac;
  double depth_max_m;
  int frames;                      /* frames per trajectory loop */
  int range_first, range_count;    /* stream only frames first..first+count-1 of the loop (count 0: all) */
  double bad_pose_frac;            /* fraction of frames with corrupted poses */
  /* The simulated world's box (the room, flat or building fills it); all
   * zero: field.scene_min/max. A node with field.grow starts in a first box
   * smaller than the world (vlff_config_sim_box). */
  double scene_min[3], scene_max[3];
  int change_count;                /* sim.changes, in the order written */
  struct vlff_sim_change changes[VLFF_SIM_MAX_CHANGES];
};

struct vlff_cfg_field;
/* The simulated world's box: sim.scene_min/max when set, else the field's. */
void vlff_config_sim_box(const struct vlff_cfg_sim *sim, const struct vlff_cfg_field *field, double lo[3],
                         double hi[3]);

struct vlff_cfg_field {
  int feature_dim;                 /* D */
  int hash_levels;
  int hash_features;
  int hash_log2_size;
  int base_resolution;
  int finest_resolution;
  int freq_bands;                  /* L of the frequency encoding */
  int geo_dim;                     /* geometric code */
  int density_width, density_layers;
  int color_width, color_layers;
  int feature_width, feature_layers;
  int sh_degree;
  double scene_min[3], scene_max[3];
  char scene_box_file[VLFF_CFG_PATH]; /* a bbox.txt that sets scene_min/max ("" = none) */
  /* The box grows where depth lands (field.h "Growth"): scene_min/max are
   * then the first box, and the learned cells keep their size in metres. */
  bool grow;
  double world_limit_m;            /* growth stays within +-this of the origin */
};

struct vlff_cfg_train {
  double lr;
  double beta1, beta2, eps;
  double weight_decay;
  double weight_average;           /* queries read an EMA of the MLP weights with this decay (0 = the latest) */
  double lr_decay;                 /* multiplier applied every lr_decay_steps */
  int lr_decay_steps;
  int rays_per_step;
  int warmup_steps;                /* node: a young field's steps grow from rays_per_step / 4 over these */
  int warmup_levels;               /* node: a young field starts on this many hash levels (0 = all) */
  int warmup_level_steps;          /* node: ... and adds the finer ones over these steps */
  int samples_per_ray;
  int sampling;                    /* enum vlff_sampling */
  double depth_weight;
  double feature_weight;
  int feature_loss;                /* enum vlff_feat_loss */
  double class_balance;            /* 0..1: ray drawing evens out the raw features' prompt classes */
  double error_sampling;           /* >= 0: ray drawing follows each occupancy cell's feature loss */
  double near_m;
  double depth_noise_m;            /* the depth sensor's noise sigma at 1 m, growing with range squared */
  int occupancy_resolution;
  double occupancy_cell_m;         /* a growing field's cubic cells (m); 0: the first box's own (each side / resolution) */
  double occupancy_max_mb;         /* a growing field's occupancy cells stay within this */
  int occupancy_update_steps;
  double image_scale;              /* training images scaled by this */
};

struct vlff_cfg_keyframes {
  double rate_hz;                  /* keyframe selection upper bound */
  double min_translation_m;
  double min_rotation_deg;
  int memory_mb;                   /* keyframe store budget */
  int page_mb;                     /* disk in node.state_dir for evicted keyframes (0: dropped) */
  int max_keyframes;
  int start_after;                 /* train once this many are held */
  int recent;                      /* the newest this many share half the rays */
  double bad_pose_threshold_m;     /* the map's depth error a good frame shows (select.h) */
  int posecheck_min_steps;         /* the map judges poses only after this much training */
};

struct vlff_cfg_publish {
  double rate_hz;
  double voxel_size_m;
  int label_width, label_height;
  int label_image;                 /* enum vlff_label_image */
  double free_density;             /* below: free; unobserved stays unknown */
  double evidence_weight;          /* w of the fused features beside the field's (0: field alone; evidence.h) */
  int field_trust_rays;            /* training rays in a cell before the field counts fully beside evidence (0: always) */
  double lost_class_ratio;         /* a class the fitted field keeps at under this share of evidence's is read from evidence (0: off) */
  double evidence_voxel_m;         /* their voxel edge */
  int evidence_max_mb;             /* memory for those features */
  int evidence_page_mb;            /* disk in node.state_dir for what that memory gives up (0: dropped) */
  double label_hysteresis;         /* a voxel's label changes without new evidence only past this margin (hold.h) */
  double region_weight;            /* a label image cell's vote with its image region beside its own scores (0: off; regions.h) */
};

struct vlff_cfg_prompts {
  int active;                      /* index into sets */
  char templ[VLFF_CFG_STR];        /* prompt template, "{}" = the class */
  char embeddings[VLFF_CFG_PATH];  /* precomputed prompt->vector file */
  int set_count;
  bool sets_named;                 /* the file gave prompts.sets (else an embeddings file defines the prompts) */
  struct vlff_prompt_set sets[VLFF_MAX_PROMPT_SETS];
};

struct vlff_cfg_can {
  bool enabled;
  char interface[32];
  int node_id;                     /* 1..127, CANopen */
  int heartbeat_ms;
  int status_ms;
  int status_base_id;
  int command_id;
  int ack_id;
  bool fd;
  int rt_priority;                 /* SCHED_FIFO priority of the CAN thread, 0 = normal */
  int heartbeat_spin_max_us;       /* cap on the early wake + spin before a heartbeat, 0 = sleep only */
};

struct vlff_cfg_camera {
  int kind;                        /* enum vlff_camera_kind */
  char device[VLFF_CFG_STR];       /* IP, serial, "Fake", libcamera id or index */
  char pixel_format[32];
  int width, height;               /* 0 = sensor maximum */
  int offset_x, offset_y;
  double exposure_us;
  double gain_db;
  double frame_rate;
  int packet_size;
  int trigger;                     /* enum vlff_trigger_mode */
  char trigger_line[32];
  int sensor_id;
  double intrinsics[4];            /* fx fy cx cy; 0 = unknown */
  double distortion[5];            /* k1 k2 p1 p2 k3 */
  char calibration[VLFF_CFG_PATH]; /* OpenCV calibration YAML */
  int depth;                       /* enum vlff_depth_kind */
  int depth_unit;                  /* enum vlff_depth_unit of the depth plane */
  double depth_scale_m;            /* metres per count: a range camera's (set from depth_camera.scale_m) */
  double stereo_baseline_m;
  int stereo_disparities;
  double reconnect_max_s;
};

/* A range camera beside the colour camera (camera.depth: stream): its
 * frames are paired with the colour camera's by time and registered into
 * it, one frame record per pair. */
struct vlff_cfg_depth_camera {
  int kind;                        /* enum vlff_depth_camera_kind */
  char device[VLFF_CFG_STR];
  char pixel_format[32];           /* Mono16 or Coord3D_C16 */
  int width, height;               /* 0 = sensor maximum */
  double exposure_us;
  double frame_rate;
  int packet_size;
  int trigger;                     /* enum vlff_trigger_mode */
  char trigger_line[32];
  double scale_m;                  /* metres per count */
  char calibration[VLFF_CFG_PATH]; /* depth-to-colour OpenCV FileStorage file */
  double pair_tolerance_s;         /* largest colour-depth time difference paired */
  /* Size of the records (colour resampled, depth registered directly at
   * it): 0 x 0 = the colour camera's, else of its aspect ratio within 1 %. */
  int register_width, register_height;
};

struct vlff_cfg_gpio {
  int mode;                        /* enum vlff_gpio_mode */
  char chip[VLFF_CFG_STR];
  char line[VLFF_CFG_STR];         /* name or number */
  double rate_hz;
  double pulse_us;
  bool active_low;
  double debounce_us;
};

/* vlff-pose: TUM lines into the pose ring. */
struct vlff_cfg_pose {
  char udp[VLFF_CFG_STR];          /* listen address "host:port"; "" = a file or standard input */
  int clock;                       /* enum vlff_pose_clock of the lines' stamps */
  double clock_offset_s;           /* added to every stamp */
  int stamp;                       /* enum vlff_pose_stamp */
  double latency_s;                /* stamp host: receipt minus this */
  double extrinsic[7];             /* camera in the body frame: tx ty tz qx qy qz qw */
  double quat_tolerance;           /* |norm - 1| normalised; beyond, refused */
  bool extra_fields;               /* numbers after the eighth ignored, not refused */
  int source_id;                   /* written into every record */
  char udp_peer[VLFF_CFG_STR];     /* "addr[:port]": datagrams from other senders refused; "" = any sender */
  double future_tolerance_s;       /* stamps further ahead of the clock refused (clock error); 0 = no check */
  int out_of_order_reset;          /* this many out-of-order lines in a row restart the order; 0 = never */
};

struct vlff_cfg_vlm {
  char image_model[VLFF_CFG_PATH];
  char text_model[VLFF_CFG_PATH];
  char bpe_vocab[VLFF_CFG_PATH];
  int input_width, input_height;
  double mean[3], std[3];
  bool bgr;
  bool normalize;
  bool cuda;
  double feature_timeout_s;
};

/* vlff-dds: the bridge to DDS with ROS 2's wire conventions (docs/dds.md).
 * Its command-line options override these. Topics, in the order of on[]
 * and qos[] (their config names: dds.<name>, dds.qos.<name>.*). */
enum vlff_dds_topic_id {
  VLFF_DDS_MAP,                     /* map: PointCloud2 */
  VLFF_DDS_STATUS,                  /* status: DiagnosticArray */
  VLFF_DDS_PROMPTS_IN,              /* prompts_in: String (in) */
  VLFF_DDS_PROMPTS,                 /* prompts: String, the map's prompt list */
  VLFF_DDS_LABEL_IMAGE,             /* label_image: Image mono16 */
  VLFF_DDS_LABEL_IMAGE_COMPRESSED,  /* label_image/compressed: CompressedImage png */
  VLFF_DDS_CAMERA_IMAGE,            /* camera/image_raw: Image */
  VLFF_DDS_CAMERA_IMAGE_COMPRESSED, /* camera/image_raw/compressed: CompressedImage jpeg */
  VLFF_DDS_CAMERA_INFO,             /* camera/camera_info: CameraInfo */
  VLFF_DDS_TF,                      /* <namespace>/tf: TFMessage */
  VLFF_DDS_MAP_UPDATES,             /* map/updates: PointCloud2 of the changed voxels */
  VLFF_DDS_NTOPICS
};
enum { VLFF_DDS_BEST_EFFORT = 0, VLFF_DDS_RELIABLE = 1 };
enum { VLFF_DDS_VOLATILE = 0, VLFF_DDS_TRANSIENT_LOCAL = 1 };
struct vlff_cfg_dds_qos {
  int reliability; /* VLFF_DDS_BEST_EFFORT / _RELIABLE */
  int durability;  /* VLFF_DDS_VOLATILE / _TRANSIENT_LOCAL */
  int depth;       /* history: keep last depth */
};
/* vlff-merge's fleet (dds.merge): robots' maps over DDS into one. */
#define VLFF_MAX_MERGE_ROBOTS 8
struct vlff_cfg_merge_robot {
  char ns[VLFF_CFG_STR];  /* its vlff-dds's dds.namespace */
  double transform[4];    /* its map -> world: x y z (m), then yaw about +z (degrees), applied yaw first */
  bool has_transform;     /* transform given; else the one the robot publishes on its tf */
};
struct vlff_cfg_dds_merge {
  char map[VLFF_CFG_STR];  /* the fleet's map segment */
  char ns[VLFF_CFG_STR];   /* the fleet's ROS namespace */
  double bounds[6];        /* world box x0 y0 z0 x1 y1 z1, m */
  double voxel_size_m;
  char frame_id[VLFF_CFG_STR]; /* the fleet's (world) frame: its map's frame_id, the parent read on robots' tf */
  double half_life_s;      /* recency: a robot's evidence this much older than the newest counts half */
  int robot_count;         /* dds.merge.robots */
  struct vlff_cfg_merge_robot robots[VLFF_MAX_MERGE_ROBOTS];
};
struct vlff_cfg_dds {
  int domain_id;                   /* DDS domain, 0..232 (ROS_DOMAIN_ID) */
  char ns[VLFF_CFG_STR];           /* ROS namespace "/robot1", "" = none: topics rt<ns>/vlff/... */
  char frame_id[VLFF_CFG_STR];     /* header frame_id of the map, status and the pose's parent */
  char camera_frame_id[VLFF_CFG_STR]; /* frame_id of the images and camera info, the pose's child */
  bool on[VLFF_DDS_NTOPICS];       /* which topics are published (taken, for prompts_in) */
  struct vlff_cfg_dds_qos qos[VLFF_DDS_NTOPICS];
  double status_hz;                /* status messages per second */
  double poll_hz;                  /* map segment checks per second */
  double map_full_period_s;        /* slowest resend of the whole map while it changes */
  double image_hz;                 /* most images (label, camera) per second each */
  double prompt_rate_hz;           /* most prompt posts per second; more are refused as a flood */
  int max_prompt_bytes;            /* longest prompt message taken */
  int jpeg_quality;                /* camera/image_raw/compressed */
  double history_max_mb;           /* what all topics' keep-last histories may hold together, MiB */
  struct vlff_cfg_dds_merge merge;
};
/* A DDS message's header, field list and frame ids, beyond its data. */
#define VLFF_DDS_MSG_OVERHEAD 1024u
/* The largest status message (DiagnosticArray of two statuses; the bridge
 * asserts that its fixed storage fits). */
#define VLFF_DDS_STATUS_MAX_BYTES 16384u

/* The whole file: one section per module, each module given only its own
 * section (and what it names of another, passed as values). */
struct vlff_config {
  struct vlff_cfg_node node;
  struct vlff_cfg_shm shm;
  struct vlff_cfg_source source;
  struct vlff_cfg_sim sim;
  struct vlff_cfg_field field;
  struct vlff_cfg_train train;
  struct vlff_cfg_keyframes keyframes;
  struct vlff_cfg_publish publish;
  struct vlff_cfg_prompts prompts;
  struct vlff_cfg_can can;
  struct vlff_cfg_camera camera;
  struct vlff_cfg_depth_camera depth_camera;
  struct vlff_cfg_gpio gpio;
  struct vlff_cfg_pose pose;
  struct vlff_cfg_vlm vlm;
  struct vlff_cfg_dds dds;
};

void vlff_config_defaults(struct vlff_config *cfg);

/* The config a program runs with, by the search path every vlff program
 * follows: path (its --config) when given, else $VLFF_CONFIG when set and not
 * empty, else vlff_config_default_path() when that file exists. Returns the
 * chosen path (path itself, the environment's string, or a static string);
 * a path chosen from --config or $VLFF_CONFIG is returned even when it does
 * not exist (loading it then says so). NULL when nothing was found, with err
 * naming every place looked at. */
const char *vlff_config_find(const char *path, char *err, size_t errlen);

/* The installed config: <sysconfdir>/vlff/vlff.yaml of the install the
 * program runs from (its bindir's parent is the prefix; /etc/vlff/vlff.yaml
 * for prefix /usr), when that file exists; else that of the prefix the build
 * was configured for. vlm.bpe_vocab's default follows the same rule. */
const char *vlff_config_default_path(void);

/* Load a YAML file. Returns 0, or -1 with err filled ("file:line:col: ..."). */
int vlff_config_load(const char *path, struct vlff_config *cfg, char *err, size_t errlen);

/* The same from memory; name is used in messages. */
int vlff_config_load_mem(const char *buf, size_t len, const char *name, struct vlff_config *cfg,
                         char *err, size_t errlen);

/* Write every key with its effective value as "a.b: value" lines. */
void vlff_config_dump(const struct vlff_config *cfg, FILE *out);

/* Number of scalar/array keys in the schema and the dotted path of key i. */
size_t vlff_config_key_count(void);
const char *vlff_config_key_path(size_t i);

/* True when source.features is sim while frames come from a camera ring
 * and source.allow_sim_features does not force it: the simulator's
 * features would be paired with another scene's images. Loading refuses
 * such a file; vlff_node_create() refuses such a struct. */
bool vlff_config_sim_features_misused(const struct vlff_config *cfg);

/* The largest message of DDS topic id (enum vlff_dds_topic_id) in bytes,
 * from the sizes its source can have under cfg: the map's shm.map_max_voxels
 * points, the frame ring's shm.max_width x max_height pixels, the label
 * image's shm.label_max_*, dds.max_prompt_bytes; map_updates: the bytes of
 * vlff_config_dds_update_points() points. 0 for an id out of range. */
uint64_t vlff_config_dds_message_max(const struct vlff_config *cfg, int id);

/* The most points one map/updates message may carry: what dds.history_max_mb
 * leaves after the other switched-on topics' histories (each its depth times
 * its largest message), divided among the updates' depth; 0 when nothing is
 * left. Loading refuses a config that leaves less than one point, naming the
 * depth that took the most; the bridge sends the whole map instead of a
 * larger update. */
uint64_t vlff_config_dds_update_points(const struct vlff_config *cfg);

/* Stable 64-bit hash of the fields that shape learned state (field.*),
 * stored in checkpoints so a mismatched model is refused. */
uint64_t vlff_config_field_hash(const struct vlff_cfg_field *field);

#endif
