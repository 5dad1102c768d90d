/*
 * TUM RGB-D trajectory lines -> pose ring records: the parser and checks
 * behind vlff-pose, as a library so that the unit tests drive exactly what
 * the program runs.
 *
 * A line is "t tx ty tz qx qy qz qw": a stamp in seconds, the position in
 * metres and the orientation as a unit quaternion (Hamilton, scalar last),
 * the pose of the tracked frame in the tracker's world (ORB-SLAM3's
 * CameraTrajectory.txt, RTAB-Map's and OpenVINS' TUM exports). Blank lines
 * and lines starting with '#' are skipped.
 *
 * A feed turns lines into camera-to-world records for the node:
 *   - stamp: t * 1e9 + clock offset (VLFF_TUM_STAMP_SOURCE), or the host's
 *     CLOCK_MONOTONIC at receipt minus a latency (VLFF_TUM_STAMP_HOST);
 *   - pose: the line's pose times the body-to-camera extrinsic, so a
 *     tracker that reports its IMU's (body's) pose gives the camera's.
 * Numbers are plain decimals ("-1.25", ".5", "2e-3"); hexadecimal ("0x10"),
 * and anything else strtod(3) would take, is malformed; "nan" and "inf" are
 * not finite.
 *
 * Refused (counted per reason, never written): malformed lines, NaN or
 * infinite values, quaternions whose norm is off 1 by more than the
 * tolerance (smaller deviations are normalised), stamps equal to the
 * previous accepted one (duplicate) or older (out of order), record stamps
 * ahead of the clock (now_ns, the pose ring's CLOCK_MONOTONIC) by more than
 * the future tolerance (clock error: a wrong clock or offset, or a line
 * forged far ahead), lines holding a NUL byte, and lines of
 * VLFF_TUM_LINE_MAX bytes or more.
 *
 * Recovery: a stream whose lines stay older than the last accepted one
 * (the tracker restarted its clock, or a forged line got in ahead of it)
 * is not locked out: the out_of_order_reset-th such line in a row is taken
 * as the stream's new start (accepted, and the order goes on from it),
 * counted in resets.
 *
 * Contract: no allocation, no global state; a feed is used by one thread.
 * Errors are returned as enum vlff_tum_result with a one-line reason in
 * the caller's buffer.
 */
#ifndef VLFF_TUM_H
#define VLFF_TUM_H

#include <stddef.h>
#include <stdint.h>

#include "vlff/shm.h"

/* A line of this many bytes or more (its newline not counted) is no TUM
 * line: refused as too long, and a reader need not hold more of it. */
#define VLFF_TUM_LINE_MAX 65536
/* No tracker's position lies farther from its origin (Earth-centred
 * coordinates reach 6.4e6 m): beyond, a line is refused as out of range. */
#define VLFF_TUM_MAX_POSITION_M 1e7

enum vlff_tum_result {
  VLFF_TUM_OK = 0,         /* a record was produced */
  VLFF_TUM_SKIP,           /* blank line or comment */
  VLFF_TUM_MALFORMED,      /* not eight numbers */
  VLFF_TUM_NOT_FINITE,     /* NaN or infinity */
  VLFF_TUM_BAD_QUATERNION, /* norm off 1 by more than the tolerance */
  VLFF_TUM_DUPLICATE,      /* same stamp as the previous accepted line */
  VLFF_TUM_OUT_OF_ORDER,   /* older than the previous accepted line */
  VLFF_TUM_BAD_STAMP,      /* negative, or beyond the clock's range after the offset */
  VLFF_TUM_CLOCK,          /* ahead of the clock by more than the future tolerance */
  VLFF_TUM_NUL,            /* a NUL byte in the line (or its datagram) */
  VLFF_TUM_TOO_LONG,       /* VLFF_TUM_LINE_MAX bytes or more */
  VLFF_TUM_FOREIGN,        /* a datagram from another sender than the bound peer (the reader counts it) */
  VLFF_TUM_FAR,            /* a position coordinate beyond VLFF_TUM_MAX_POSITION_M */
  VLFF_TUM_RESULTS
};

/* Short fixed name of a result ("out of order"). */
const char *vlff_tum_result_name(int result);

/* One parsed line. */
struct vlff_tum_sample {
  double t;          /* seconds, as written */
  int64_t t_ns;      /* the same in nanoseconds, exact for plain decimals ("1305031102.175304") */
  double p[3];       /* metres */
  double q[4];       /* x y z w, as written */
};

/* Parses one line (NUL-terminated, a trailing newline allowed) without any
 * check beyond the syntax and finiteness. With extra_fields, numbers after
 * the eighth (covariances, as OpenVINS' recorder appends) are allowed and
 * ignored; without, they are MALFORMED. Returns VLFF_TUM_OK, SKIP,
 * MALFORMED or NOT_FINITE, with why filled for the last two. A stamp
 * beyond the range of int64 nanoseconds is MALFORMED. */
int vlff_tum_parse(const char *line, int extra_fields, struct vlff_tum_sample *out, char *why, size_t whylen);

/* Row-major 4x4 rigid transform of a position and a unit quaternion (x y z w). */
void vlff_tum_matrix(const double p[3], const double q[4], double out[16]);

enum vlff_tum_stamp { VLFF_TUM_STAMP_SOURCE = 0, VLFF_TUM_STAMP_HOST = 1 };

struct vlff_tum_feed_params {
  int stamp;                  /* enum vlff_tum_stamp */
  int64_t clock_offset_ns;    /* SOURCE: added to t * 1e9 */
  int64_t latency_ns;         /* HOST: subtracted from the receipt time */
  double quat_tolerance;      /* largest |norm - 1| that is normalised, not refused */
  double body_to_camera[16];  /* camera pose in the body frame; identity = the line is the camera's */
  uint32_t source_id;         /* written into every record */
  int extra_fields;           /* numbers after the eighth are ignored, not refused */
  int64_t future_tolerance_ns; /* SOURCE: a record stamp ahead of now_ns by more is refused (CLOCK); 0 = no check */
  uint32_t out_of_order_reset; /* this many out-of-order lines in a row restart the order; 0 = never */
};

struct vlff_tum_feed {
  struct vlff_tum_feed_params p;
  int have_last;
  int64_t last_t_ns;          /* stamp of the last accepted line, as written */
  uint64_t last_ns;           /* its record's stamp */
  uint64_t accepted;
  uint64_t refused[VLFF_TUM_RESULTS]; /* per result; [OK] and [SKIP] unused */
  uint32_t out_of_order_run;  /* out-of-order lines since the last accepted one */
  uint64_t resets;            /* times the order restarted (out_of_order_reset) */
  int64_t reset_from_t_ns;    /* the last accepted stamp the latest reset gave up */
};

/* params->body_to_camera must be a rigid transform: -1 with why otherwise. */
int vlff_tum_feed_init(struct vlff_tum_feed *f, const struct vlff_tum_feed_params *params, char *why,
                       size_t whylen);

/* Feeds one line of len bytes (its newline stripped), received at host
 * time now_ns (CLOCK_MONOTONIC); line[len] must be a NUL (the reader's
 * terminator). A NUL among the len bytes is refused (NUL), as is len >=
 * VLFF_TUM_LINE_MAX (TOO_LONG: a reader that stopped holding an overlong
 * line passes what it held). On VLFF_TUM_OK *out holds the record to
 * write; on a refusal the feed's counter for it is incremented and why says
 * what is wrong. When the line restarted the order (see Recovery above) the
 * result is OK and resets has grown by one. */
int vlff_tum_feed_buf(struct vlff_tum_feed *f, const char *line, size_t len, uint64_t now_ns,
                      struct vlff_pose_rec *out, char *why, size_t whylen);

/* vlff_tum_feed_buf of a NUL-terminated line. */
int vlff_tum_feed_line(struct vlff_tum_feed *f, const char *line, uint64_t now_ns, struct vlff_pose_rec *out,
                       char *why, size_t whylen);

/* Counts a refusal the reader decided (FOREIGN: a datagram from another
 * sender; NUL: a datagram holding a NUL, refused whole). */
void vlff_tum_feed_count(struct vlff_tum_feed *f, int result);

/* Total of refused lines. */
uint64_t vlff_tum_feed_refused(const struct vlff_tum_feed *f);

#endif
