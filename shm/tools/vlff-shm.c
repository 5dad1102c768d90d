/* vlff-shm - look into vlff shared-memory segments from a shell.
 *
 * One line per fact, "key value" or fixed columns, so that the output can be pasted
 * into a bug report or scripted against; errors go to stderr with the library's
 * message and a non-zero exit status. */
#include "vlff/shm.h"
#include "vlff/escape.h"

#include "cli.h"
#include "dump_map.h"
#include "files.h"

#include <dirent.h>
#include <errno.h>
#include <inttypes.h>
#include <math.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

static const struct vlff_cli cli = {
  "vlff-shm",
  "Usage: vlff-shm [-h|--help] [-V|--version] <command> [arguments]\n"
  "\n"
  "Commands:\n"
  "  list                      vlff segments under /dev/shm, one per line\n"
  "  stat NAME                 header of a segment (kind, generation, creator, sizes)\n"
  "  dump-frame NAME FILE      newest frame of a frame ring to FILE (.ppm color, .pgm mono/depth)\n"
  "  dump-map NAME FILE        the map's current version to FILE (.ply: labelled voxels; else vlff-map binary)\n"
  "  label NAME X Y Z          label, confidence and prompt of the map voxel at world point X Y Z (m)\n"
  "  set-prompts [-t SECONDS] NAME TEXT...\n"
  "                            post a prompt set to a prompt mailbox and wait (default 5 s)\n"
  "                            for the learner's answer: prints 'accepted N' or 'refused N: why'\n"
  "  set-prompts [-t SECONDS] NAME -i N\n"
  "                            post \"switch to configured prompt set N\", same answer\n"
  "  watch NAME [COUNT]        print records of a ring / versions of a map as they come\n"
  "\n"
  "vlff-shm COMMAND --help describes a command.\n"
  "\n"
  "Examples:\n"
  "  vlff-shm list\n"
  "  vlff-shm stat /vlff-map\n"
  "  vlff-shm dump-frame /vlff-frames frame.ppm\n"
  "  vlff-shm dump-map /vlff-map map.ply\n"
  "  vlff-shm label /vlff-map 1.25 0.4 -0.1\n"
  "  vlff-shm set-prompts /vlff-prompts \"chair\" \"table\" \"door\"\n"
  "  vlff-shm watch /vlff-frames 100\n"
  "\n"
  "Exit status: 0 ok, 1 error, refusal or no answer in time (message on stderr), 2 usage.\n",
};

/* The library's message, which names the segment itself (and a system
 * call's error text); what is added only when the message does not start
 * with it ("vlff-shm: /x: /x: no such segment (No such file or directory)"
 * said everything twice). */
int vlff_shm_fail(const char *what) {
  const char *msg = vlff_shm_last_message(), *q = VLFF_Q(what);
  size_t l = strlen(q);
  if (!strncmp(msg, q, l) && msg[l] == ':')
    fprintf(stderr, "vlff-shm: %s\n", msg);
  else
    fprintf(stderr, "vlff-shm: %s: %s\n", q, msg);
  return 1;
}

static const char *kind_name(uint32_t k) {
  return k == VLFF_SHM_KIND_RING ? "ring" : k == VLFF_SHM_KIND_MAP ? "map" : k == VLFF_SHM_KIND_PROMPTS ? "prompts" : "?";
}
static const char *record_name(uint32_t k) {
  static const char *n[] = {"any", "raw", "frame", "feature", "pose"};
  return k < 5 ? n[k] : "?";
}

static void print_age(uint64_t last) {
  if (!last) {
    printf("-");
    return;
  }
  uint64_t now = vlff_shm_now_ns();
  printf("%.3fs", now > last ? (double)(now - last) / 1e9 : 0.0);
}

static int cmd_list(void) {
  DIR *d = opendir("/dev/shm");
  if (!d) {
    perror("vlff-shm: /dev/shm");
    return 1;
  }
  printf("%-32s %-8s %-8s %4s %8s %5s %12s %10s %s\n", "NAME", "KIND", "RECORDS", "GEN", "PID", "ALIVE", "BYTES",
         "HEAD", "AGE");
  struct dirent *e;
  while ((e = readdir(d))) {
    if (e->d_name[0] == '.' || strlen(e->d_name) > 240)
      continue;
    char name[300];
    snprintf(name, sizeof name, "/%s", e->d_name);
    struct vlff_shm_info in;
    if (vlff_shm_stat(name, &in) < 0) {
      int err = vlff_shm_last_error();
      /* Other programs' segments are not ours to list; broken vlff ones are. */
      if (err == VLFF_SHM_ERR_VERSION || err == VLFF_SHM_ERR_CORRUPT || err == VLFF_SHM_ERR_TRUNCATED ||
          err == VLFF_SHM_ERR_ABANDONED)
        printf("%-32s error: %s\n", VLFF_Q(name), vlff_shm_last_message());
      continue;
    }
    printf("%-32s %-8s %-8s %4" PRIu32 " %8d %5s %12" PRIu64 " %10" PRIu64 " ", VLFF_Q(name), kind_name(in.kind),
           in.kind == VLFF_SHM_KIND_RING ? record_name(in.record_kind) : "-", in.generation, (int)in.creator_pid,
           in.creator_alive ? "yes" : "no", in.total_size, in.head);
    print_age(in.last_ns);
    printf("\n");
  }
  closedir(d);
  return 0;
}

/* The writer's status block, one "key value" line each; a refusal reason's line
 * gives its count before its name, which may hold spaces. */
static int print_status(struct vlff_map *m, const char *name) {
  struct vlff_map_status st;
  if (vlff_map_get_status(m, &st) < 0) {
    if (errno == ENOENT) {
      printf("status none\n");
      return 0;
    }
    return vlff_shm_fail(name);
  }
  printf("status_age ");
  print_age(st.t_ns);
  printf("\nstatus_updates %" PRIu64 "\nstate %s\nstate_code %" PRId32 "\nerror_flags 0x%" PRIx32 "\n"
         "frames_in %" PRIu64 "\nframes_lost %" PRIu64 "\nframes_refused %" PRIu64 "\n",
         st.updates, VLFF_Q(st.state_name), st.state, st.error_flags, st.frames_in, st.frames_lost, st.frames_refused);
  for (uint32_t i = 0; i < st.reason_count; i++)
    printf("refused %" PRIu64 " %s\n", st.reason[i].count, VLFF_Q(st.reason[i].name));
  printf("keyframes %" PRIu64 "\nkeyframes_evicted %" PRIu64 "\niterations %" PRIu64 "\n"
         "iterations_per_s %.3f\nfps_in %.3f\nloss %.6g\nloss_rgb %.6g\nloss_depth %.6g\nloss_feat %.6g\n"
         "psnr %.3f\ncpu_budget %.3f\ncpu_used %.3f\nframe_to_map_ms_p50 %.1f\nframe_to_map_ms_p99 %.1f\n"
         "publish_interval_s %.3f\nlabel_flips %" PRIu64 "\nlabel_flips_refresh %" PRIu64 "\nlabel_flips_total %" PRIu64
         "\nlabel_flip_frac %.4f\nmem_keyframes_mb %.1f\nmem_keyframes_limit_mb %.1f\nmem_evidence_mb %.1f\n"
         "mem_evidence_limit_mb %.1f\nmem_field_mb %.1f\nmem_rss_mb %.1f\n",
         st.keyframes, st.keyframes_evicted, st.iterations, st.iterations_per_s, st.fps_in, st.loss, st.loss_rgb,
         st.loss_depth, st.loss_feat, st.psnr, st.cpu_budget, st.cpu_used, st.frame_to_map_ms_p50,
         st.frame_to_map_ms_p99, st.publish_interval_s, st.label_flips, st.label_flips_refresh, st.label_flips_total,
         st.label_flip_frac, st.mem_keyframes_mb, st.mem_keyframes_limit_mb, st.mem_evidence_mb,
         st.mem_evidence_limit_mb, st.mem_field_mb, st.mem_rss_mb);
  printf("keyframes_paged %" PRIu64 "\nkeyframes_paged_out %" PRIu64 "\nkeyframes_paged_in %" PRIu64
         "\nkeyframes_dropped %" PRIu64 "\nkeyframes_page_mb %.1f\nkeyframes_page_limit_mb %.1f\n"
         "evidence_paged %" PRIu64 "\nevidence_paged_out %" PRIu64 "\nevidence_paged_in %" PRIu64
         "\nevidence_dropped %" PRIu64 "\nbox_lo %.3f %.3f %.3f\nbox_hi %.3f %.3f %.3f\nbox_growths %" PRIu64
         "\nbox_refused %" PRIu64 "\n",
         st.keyframes_paged, st.keyframes_paged_out, st.keyframes_paged_in, st.keyframes_dropped, st.keyframes_page_mb,
         st.keyframes_page_limit_mb, st.evidence_paged, st.evidence_paged_out, st.evidence_paged_in,
         st.evidence_dropped, st.box_lo[0], st.box_lo[1], st.box_lo[2], st.box_hi[0], st.box_hi[1], st.box_hi[2],
         st.box_growths, st.box_refused);
  return 0;
}

static int cmd_stat(const char *name) {
  struct vlff_shm_info in;
  if (vlff_shm_stat(name, &in) < 0)
    return vlff_shm_fail(name);
  printf("name %s\nkind %s\nabi_version %" PRIu32 "\ngeneration %" PRIu32 "\ncreator_pid %d\ncreator_alive %s\n"
         "bytes %" PRIu64 "\n",
         VLFF_Q(name), kind_name(in.kind), in.abi_version, in.generation, (int)in.creator_pid,
         in.creator_alive ? "yes" : "no", in.total_size);
  if (in.kind == VLFF_SHM_KIND_RING)
    printf("records %s\nslots %" PRIu32 "\nslot_size %" PRIu64 "\nhead %" PRIu64 "\n", record_name(in.record_kind),
           in.slots, in.slot_size, in.head);
  else if (in.kind == VLFF_SHM_KIND_MAP)
    printf("max_voxels %" PRIu64 "\nversion %" PRIu64 "\n", in.slot_size, in.head);
  else
    printf("posts %" PRIu64 "\nstate_repairs %" PRIu64 "\nresyncs %" PRIu32 "\n", in.head, in.slot_size, in.slots);
  printf("last_update_age ");
  print_age(in.last_ns);
  printf("\n");
  if (in.kind == VLFF_SHM_KIND_MAP) {
    struct vlff_map *m = vlff_map_attach(name);
    if (!m)
      return vlff_shm_fail(name);
    struct vlff_map_snapshot *s = vlff_map_snapshot_new(m);
    struct vlff_map_info mi;
    if (!s || vlff_map_snapshot_take(m, s) < 0 || vlff_map_snapshot_info(s, &mi) < 0) {
      vlff_map_snapshot_free(s);
      vlff_map_detach(m);
      return vlff_shm_fail(name);
    }
    printf("grid_origin %.4f %.4f %.4f\ngrid_voxel_size %.4f\ngrid_dims %" PRIu32 " %" PRIu32 " %" PRIu32 "\n",
           mi.grid.origin[0], mi.grid.origin[1], mi.grid.origin[2], mi.grid.voxel_size, mi.grid.dims[0],
           mi.grid.dims[1], mi.grid.dims[2]);
    struct vlff_map_far far;
    if (vlff_map_snapshot_far(s, &far) == 0)
      printf("far_blocks %" PRIu32 "\nfar_bytes %" PRIu64 "\nfar_capacity %" PRIu64 "\n", far.nblocks,
             vlff_map_far_bytes(far.nblocks, far.nruns), vlff_map_far_capacity(m));
    for (int i = 0; i < mi.prompt_count; i++)
      printf("prompt %d %s\n", i, VLFF_Q(vlff_map_snapshot_prompt(s, (uint16_t)i)));
    if (mi.has_label_image)
      printf("label_image %" PRIu32 "x%" PRIu32 "\n", mi.label_image.width, mi.label_image.height);
    printf("writer_alive %s\n", vlff_map_writer_alive(m, 2000000000ull) ? "yes" : "no");
    int rc = print_status(m, name);
    vlff_map_snapshot_free(s);
    vlff_map_detach(m);
    return rc;
  }
  return 0;
}

/* The plane as a PNM image, written as dump-map writes its file: built in
 * memory, then renamed into place (vlff_write_file_atomic), so that a full
 * disk is an error rather than a cut image, and a FIFO or device at path was
 * refused before (vlff_check_output). */
static int write_image(const char *path, const struct vlff_plane *p, const uint8_t *px) {
  unsigned bpp = vlff_pixfmt_bpp(p->format);
  int color = p->format == VLFF_PIX_RGB8 || p->format == VLFF_PIX_BGR8;
  int wide = bpp >= 2 && !color;
  char *buf = NULL;
  size_t len = 0;
  FILE *f = open_memstream(&buf, &len);
  if (!f) {
    fprintf(stderr, "vlff-shm: %s: %s\n", VLFF_Q(path), strerror(errno));
    return 1;
  }
  fprintf(f, "P%c\n%" PRIu32 " %" PRIu32 "\n%d\n", color ? '6' : '5', p->width, p->height, wide ? 65535 : 255);
  for (uint32_t y = 0; y < p->height; y++) {
    const uint8_t *row = px + (uint64_t)y * p->stride;
    for (uint32_t x = 0; x < p->width; x++) {
      const uint8_t *q = row + (uint64_t)x * bpp;
      if (p->format == VLFF_PIX_BGR8) {
        fputc(q[2], f), fputc(q[1], f), fputc(q[0], f);
      } else if (color || bpp == 1) {
        fwrite(q, 1, bpp, f);
      } else {
        /* PGM 16-bit is big-endian; float metres are written as millimetres. */
        uint32_t v;
        if (p->format == VLFF_PIX_DEPTH_F32_M) {
          float m;
          memcpy(&m, q, 4);
          v = m > 0 && m < 65.535f ? (uint32_t)(m * 1000.0f + 0.5f) : 0;
        } else {
          uint16_t u;
          memcpy(&u, q, 2);
          v = u;
        }
        fputc((int)(v >> 8), f), fputc((int)(v & 255), f);
      }
    }
  }
  char err[512];
  int rc = 0;
  if (ferror(f) | fclose(f)) {
    fprintf(stderr, "vlff-shm: %s: out of memory for the image\n", VLFF_Q(path));
    rc = 1;
  } else if (vlff_write_file_atomic(path, buf, len, err, sizeof err) < 0) {
    fprintf(stderr, "vlff-shm: %s\n", err);
    rc = 1;
  }
  free(buf);
  return rc;
}

static int cmd_dump_frame(const char *name, const char *path) {
  char err[512];
  if (vlff_check_output(path, err, sizeof err) < 0) {
    fprintf(stderr, "vlff-shm: %s\n", err);
    return 1;
  }
  struct vlff_ring *r = vlff_ring_attach(name, VLFF_RECORD_FRAME);
  if (!r)
    return vlff_shm_fail(name);
  size_t cap = vlff_ring_slot_size(r);
  uint8_t *buf = malloc(cap);
  struct vlff_ring_view v;
  int rc = 1;
  if (!buf) {
    perror("vlff-shm");
  } else if (vlff_ring_read_latest(r, buf, cap, &v) < 0) {
    rc = vlff_shm_fail(name);
  } else if (vlff_frame_validate(buf, v.len) < 0) {
    rc = vlff_shm_fail("frame record");
  } else {
    const struct vlff_frame_hdr *h = (const struct vlff_frame_hdr *)buf;
    size_t plen = strlen(path);
    unsigned plane = VLFF_PLANE_COLOR;
    /* A .pgm request for a frame with depth and a color plane gets the depth. */
    if (plen > 4 && !strcmp(path + plen - 4, ".pgm") && h->nplanes == 2 && vlff_pixfmt_bpp(h->plane[0].format) == 3)
      plane = VLFF_PLANE_DEPTH;
    rc = write_image(path, &h->plane[plane], vlff_frame_plane(buf, plane));
    if (!rc)
      printf("seq %" PRIu64 " frame_id %" PRIu64 " sensor %" PRIu32 " t_host_ns %" PRIu64 " %" PRIu32 "x%" PRIu32
             " %s -> %s\n",
             v.seq, h->frame_id, h->sensor_id, h->t_host_ns, h->plane[plane].width, h->plane[plane].height,
             vlff_pixfmt_name(h->plane[plane].format), VLFF_Q(path));
  }
  free(buf);
  vlff_ring_close(r);
  return rc;
}

static int parse_double(const char *s, double *v) {
  char *end;
  errno = 0;
  *v = strtod(s, &end);
  /* A NaN or infinite coordinate names no point of the world. */
  return errno || end == s || *end || !isfinite(*v) ? -1 : 0;
}

static int cmd_label(const char *name, const double p[3]) {
  struct vlff_map *m = vlff_map_attach(name);
  if (!m)
    return vlff_shm_fail(name);
  uint16_t label;
  uint8_t conf;
  int rc = 0;
  if (vlff_map_label_at(m, p[0], p[1], p[2], &label, &conf) < 0) {
    rc = vlff_shm_fail(name);
  } else {
    char text[VLFF_SHM_PROMPT_LEN];
    if (label == VLFF_LABEL_FREE)
      snprintf(text, sizeof text, "(free)");
    else if (label == VLFF_LABEL_UNKNOWN)
      snprintf(text, sizeof text, "(unknown)");
    else if (vlff_map_prompt(m, label, text, sizeof text) < 0)
      snprintf(text, sizeof text, "(no prompt)");
    printf("label %u confidence %u prompt %s version %" PRIu64 "\n", label, conf, VLFF_Q(text), vlff_map_version(m));
  }
  vlff_map_detach(m);
  return rc;
}

/* texts[n] (n > 0), or the configured set idx (>= 0). */
static int cmd_set_prompts(const char *name, char **texts, int n, long idx, double timeout_s) {
  if (idx < 0 && vlff_prompt_check((const char *const *)texts, n) < 0) {
    fprintf(stderr, "vlff-shm: %s: %s\n", VLFF_Q(name), vlff_shm_last_message());
    return 1;
  }
  struct vlff_prompts *p = vlff_prompts_attach(name);
  if (!p)
    return vlff_shm_fail(name);
  int rc = idx >= 0 ? vlff_prompts_post_index(p, (int)idx) : vlff_prompts_post(p, (const char *const *)texts, n);
  if (rc < 0) {
    rc = vlff_shm_fail(name);
    vlff_prompts_close(p);
    return rc;
  }
  uint64_t seq = vlff_prompts_last_post(p);
  char why[128];
  int a = vlff_prompts_wait_answer(p, seq, (uint64_t)(timeout_s * 1e9), why, sizeof why);
  if (a == VLFF_PROMPT_ACCEPTED) {
    printf("accepted %" PRIu64 "\n", seq);
    rc = 0;
  } else if (a == VLFF_PROMPT_REFUSED) {
    printf("refused %" PRIu64 ": %s\n", seq, VLFF_Q(why));
    rc = 1;
  } else {
    rc = vlff_shm_fail(name);
  }
  vlff_prompts_close(p);
  return rc;
}

static volatile sig_atomic_t stop;
static void on_signal(int sig) { stop = sig; }

static int cmd_watch(const char *name, long count) {
  struct vlff_shm_info in;
  if (vlff_shm_stat(name, &in) < 0)
    return vlff_shm_fail(name);
  signal(SIGINT, on_signal);
  signal(SIGTERM, on_signal);
  long seen = 0;
  if (in.kind == VLFF_SHM_KIND_RING) {
    struct vlff_ring *r = vlff_ring_attach(name, VLFF_RECORD_ANY);
    if (!r)
      return vlff_shm_fail(name);
    int said_gone = 0;
    while (!stop && (count <= 0 || seen < count)) {
      struct vlff_ring_view v;
      if (vlff_ring_read_begin(r, &v, 500000000ull) < 0) {
        if (errno == ETIMEDOUT || errno == EINTR) {
          /* Waiting on a ring whose writer is gone would look like a hang:
           * said once (again after a new writer came and went). */
          struct vlff_shm_info now;
          if (vlff_shm_stat(name, &now) == 0) {
            if (!now.creator_alive && !said_gone)
              fprintf(stderr, "vlff-shm: %s: its writer (pid %d) is not running; waiting for a new one\n",
                      VLFF_Q(name), (int)now.creator_pid);
            said_gone = !now.creator_alive;
          }
          continue;
        }
        vlff_ring_close(r);
        return vlff_shm_fail(name);
      }
      struct vlff_frame_hdr fh;
      int is_frame = in.record_kind == VLFF_RECORD_FRAME && v.len >= sizeof fh;
      if (is_frame)
        memcpy(&fh, v.data, sizeof fh);
      if (vlff_ring_read_end(r, &v) < 0)
        continue;
      printf("seq %" PRIu64 " len %zu gen %" PRIu32 "%s lost %" PRIu64, v.seq, v.len, v.generation,
             v.new_generation ? " (new)" : "", vlff_ring_lost(r));
      if (is_frame)
        printf(" frame_id %" PRIu64 " sensor %" PRIu32 " t_host_ns %" PRIu64, fh.frame_id, fh.sensor_id, fh.t_host_ns);
      printf("\n");
      fflush(stdout);
      seen++;
    }
    vlff_ring_close(r);
    return 0;
  }
  if (in.kind == VLFF_SHM_KIND_MAP) {
    struct vlff_map *m = vlff_map_attach(name);
    if (!m)
      return vlff_shm_fail(name);
    uint64_t last = 0;
    while (!stop && (count <= 0 || seen < count)) {
      uint64_t v = vlff_map_version(m);
      if (v != last) {
        printf("version %" PRIu64 " age_ms %.1f writer_alive %s\n", v, (double)vlff_map_age_ns(m) / 1e6,
               vlff_map_writer_alive(m, 2000000000ull) ? "yes" : "no");
        fflush(stdout);
        last = v;
        seen++;
      }
      nanosleep(&(struct timespec){0, 10000000}, NULL);
    }
    vlff_map_detach(m);
    return 0;
  }
  fprintf(stderr, "vlff-shm: %s: watch works on rings and maps\n", VLFF_Q(name));
  return 1;
}

/* ---- the subcommands' command lines ------------------------------------ */

#define SUB_HELP "  -h, --help                print this help and exit\n"

static const struct vlff_cli cli_list = {
  "vlff-shm",
  "Usage: vlff-shm list\n"
  "The vlff segments under /dev/shm, one line each: name, kind, records, generation,\n"
  "creator pid and whether it lives, bytes, head, age of the last update. Segments\n"
  "that are vlff's but broken are listed with the reason.\n"
  "\n" SUB_HELP,
};
static const struct vlff_cli cli_stat = {
  "vlff-shm",
  "Usage: vlff-shm stat NAME\n"
  "The header of segment NAME (/vlff-map), one \"key value\" line each; for a map also\n"
  "its grid, prompts and the writer's status block.\n"
  "\n" SUB_HELP,
};
static const struct vlff_cli cli_dump = {
  "vlff-shm",
  "Usage: vlff-shm dump-frame NAME FILE\n"
  "The newest frame of frame ring NAME to FILE: .ppm for colour, .pgm for mono or depth\n"
  "(16-bit, millimetres; a colour+depth frame gives its depth to a .pgm).\n"
  "\n" SUB_HELP,
};
static const struct vlff_cli cli_dump_map = {
  "vlff-shm",
  "Usage: vlff-shm dump-map NAME FILE\n"
  "The current version of map NAME, copied consistently (vlff_map_snapshot_take), to FILE:\n"
  "FILE ending in .ply: binary little-endian PLY of the labelled voxels' centres (float x y z,\n"
  "uchar red green blue in the label palette, ushort label, uchar confidence), the prompts\n"
  "as 'comment prompt K TEXT' lines; any other FILE: the whole grid in the vlff-map binary\n"
  "format (docs/shm.md), free and unknown voxels included. Prints the version and the counts.\n"
  "\n" SUB_HELP,
};
static const struct vlff_cli cli_label = {
  "vlff-shm",
  "Usage: vlff-shm label NAME X Y Z\n"
  "Label, confidence and prompt of the voxel of map NAME at the world point X Y Z\n"
  "(metres, finite; negative coordinates need no \"--\": options end at NAME).\n"
  "\n" SUB_HELP,
};
static const struct vlff_cli cli_prompts = {
  "vlff-shm",
  "Usage: vlff-shm set-prompts [-t SECONDS] NAME TEXT...\n"
  "       vlff-shm set-prompts [-t SECONDS] NAME -i N\n"
  "Post a prompt set (or \"switch to configured set N\") to prompt mailbox NAME and wait\n"
  "for the learner's answer: prints 'accepted SEQ' (exit 0) or 'refused SEQ: why' (exit 1).\n"
  "A prompt that starts with '-' goes after \"--\".\n"
  "\n"
  "  -t, --timeout SECONDS     wait this long for the answer, (0, 3600] (default 5)\n"
  "  -i, --index N             the configured prompt set N (0..2147483647) instead of TEXTs\n" SUB_HELP,
};
static const struct vlff_cli cli_watch = {
  "vlff-shm",
  "Usage: vlff-shm watch NAME [COUNT]\n"
  "Print the records of ring NAME, or the versions of map NAME, as they come; stop after\n"
  "COUNT of them (a non-negative integer; 0 or none: until SIGINT/SIGTERM).\n"
  "\n" SUB_HELP,
};

/* A subcommand's own getopt pass when it has no options of its own: --help,
 * --version, usage errors. Returns the number of operands (at argv + optind),
 * or -1 with *status set when the program should exit. order: "+" for
 * operands that may look like options (negative numbers). */
static int sub_operands(const struct vlff_cli *sc, int argc, char **argv, const char *order, int min, int max,
                        int *status) {
  static const struct option opts[] = {VLFF_CLI_COMMON_OPTIONS};
  int o;
  vlff_cli_restart();
  while ((o = vlff_cli_next(sc, argc, argv, order, opts, status)) != -1) {
    if (o == VLFF_CLI_EXIT)
      return -1;
    return *status = vlff_cli_usage_error(sc, "option '%s' not handled", argv[optind - 1]), -1;
  }
  int n = argc - optind;
  if (n < min || n > max) {
    if (n > max)
      *status = vlff_cli_usage_error(sc, "%s: unexpected argument '%s'", argv[0], argv[optind + max]);
    else
      *status = vlff_cli_usage_error(sc, "%s: expected %d argument%s, got %d", argv[0], min, min == 1 ? "" : "s", n);
    return -1;
  }
  return n;
}

static int sub_label(int argc, char **argv) {
  int status;
  if (sub_operands(&cli_label, argc, argv, "+", 4, 4, &status) < 0)
    return status;
  double p[3];
  for (int i = 0; i < 3; i++)
    if (parse_double(argv[optind + 1 + i], &p[i]) < 0)
      return vlff_cli_usage_error(&cli_label, "label: %c '%s': expected a finite number of metres", "XYZ"[i],
                                  argv[optind + 1 + i]);
  return cmd_label(argv[optind], p);
}

static int sub_set_prompts(int argc, char **argv) {
  static const struct option opts[] = {
      {"timeout", required_argument, NULL, 't'}, {"index", required_argument, NULL, 'i'}, VLFF_CLI_COMMON_OPTIONS};
  double timeout_s = 5.0;
  long idx = -1;
  int o, status;
  char *end;
  vlff_cli_restart();
  while ((o = vlff_cli_next(&cli_prompts, argc, argv, "t:i:", opts, &status)) != -1) {
    switch (o) {
    case VLFF_CLI_EXIT: return status;
    case 't':
      errno = 0;
      timeout_s = strtod(optarg, &end);
      if (errno || end == optarg || *end || !(timeout_s > 0 && timeout_s <= 3600))
        return vlff_cli_usage_error(&cli_prompts, "set-prompts: --timeout '%s': expected seconds in (0, 3600]", optarg);
      break;
    case 'i':
      errno = 0;
      idx = strtol(optarg, &end, 10);
      if (errno || end == optarg || *end || idx < 0 || idx > INT32_MAX)
        return vlff_cli_usage_error(&cli_prompts, "set-prompts: --index '%s': expected a prompt set index in "
                                    "0..2147483647", optarg);
      break;
    default: return vlff_cli_usage_error(&cli_prompts, "option '%s' not handled", argv[optind - 1]);
    }
  }
  int n = argc - optind;
  if (n < 1)
    return vlff_cli_usage_error(&cli_prompts, "set-prompts: no mailbox NAME given");
  if (idx >= 0 && n > 1)
    return vlff_cli_usage_error(&cli_prompts, "set-prompts: --index and prompts '%s'... both given", argv[optind + 1]);
  if (idx < 0 && n < 2)
    return vlff_cli_usage_error(&cli_prompts, "set-prompts: no prompts given (TEXT... or -i N)");
  return cmd_set_prompts(argv[optind], argv + optind + 1, n - 1, idx, timeout_s);
}

static int sub_watch(int argc, char **argv) {
  int status, n = sub_operands(&cli_watch, argc, argv, "", 1, 2, &status);
  if (n < 0)
    return status;
  long count = 0;
  if (n == 2) {
    const char *c = argv[optind + 1];
    char *end;
    errno = 0;
    count = strtol(c, &end, 10);
    if (errno || end == c || *end || count < 0)
      return vlff_cli_usage_error(&cli_watch, "watch: COUNT '%s': expected a non-negative integer", c);
  }
  return cmd_watch(argv[optind], count);
}

int main(int argc, char **argv) {
  static const struct option opts[] = {VLFF_CLI_COMMON_OPTIONS};
  int o, status;
  /* '+': options end at the command, whose arguments and options are its own. */
  while ((o = vlff_cli_next(&cli, argc, argv, "+", opts, &status)) != -1) {
    if (o == VLFF_CLI_EXIT)
      return status;
    return vlff_cli_usage_error(&cli, "option '%s' not handled", argv[optind - 1]);
  }
  if (optind >= argc)
    return vlff_cli_usage_error(&cli, "no command given");
  /* The subcommand's argv: argv[0] its name, as getopt expects a program's. */
  argc -= optind;
  argv += optind;
  const char *c = argv[0];
  if (!strcmp(c, "list"))
    return sub_operands(&cli_list, argc, argv, "", 0, 0, &status) < 0 ? status : cmd_list();
  if (!strcmp(c, "stat"))
    return sub_operands(&cli_stat, argc, argv, "", 1, 1, &status) < 0 ? status : cmd_stat(argv[optind]);
  if (!strcmp(c, "dump-frame"))
    return sub_operands(&cli_dump, argc, argv, "", 2, 2, &status) < 0 ? status
                                                                     : cmd_dump_frame(argv[optind], argv[optind + 1]);
  if (!strcmp(c, "dump-map"))
    return sub_operands(&cli_dump_map, argc, argv, "", 2, 2, &status) < 0 ? status
                                                                         : vlff_dump_map(argv[optind], argv[optind + 1]);
  if (!strcmp(c, "label"))
    return sub_label(argc, argv);
  if (!strcmp(c, "set-prompts"))
    return sub_set_prompts(argc, argv);
  if (!strcmp(c, "watch"))
    return sub_watch(argc, argv);
  return vlff_cli_usage_error(&cli, "unknown command '%s'", c);
}
