/* The records carried by rings: frames, features and poses, their layout helpers,
 * validation (a record in shared memory is external input like any other) and the
 * pose lookup by timestamp. */
#include "shm_internal.h"

#include <errno.h>
#include <math.h>
#include <stdio.h>

_Static_assert(sizeof(struct vlff_frame_hdr) == 512, "frame header layout is part of the ABI");
_Static_assert(sizeof(struct vlff_feature_hdr) == 128, "feature header layout is part of the ABI");
_Static_assert(sizeof(struct vlff_pose_rec) == 144, "pose record layout is part of the ABI");

API unsigned vlff_pixfmt_bpp(uint32_t fmt) {
  switch (fmt) {
  case VLFF_PIX_RGB8:
  case VLFF_PIX_BGR8: return 3;
  case VLFF_PIX_MONO8:
  case VLFF_PIX_BAYER_RG8:
  case VLFF_PIX_BAYER_BG8:
  case VLFF_PIX_BAYER_GR8:
  case VLFF_PIX_BAYER_GB8: return 1;
  case VLFF_PIX_MONO16:
  case VLFF_PIX_DEPTH_U16_MM: return 2;
  case VLFF_PIX_DEPTH_F32_M: return 4;
  default: return 0;
  }
}

API const char *vlff_pixfmt_name(uint32_t fmt) {
  switch (fmt) {
  case VLFF_PIX_NONE: return "none";
  case VLFF_PIX_RGB8: return "RGB8";
  case VLFF_PIX_BGR8: return "BGR8";
  case VLFF_PIX_MONO8: return "Mono8";
  case VLFF_PIX_MONO16: return "Mono16";
  case VLFF_PIX_BAYER_RG8: return "BayerRG8";
  case VLFF_PIX_BAYER_BG8: return "BayerBG8";
  case VLFF_PIX_BAYER_GR8: return "BayerGR8";
  case VLFF_PIX_BAYER_GB8: return "BayerGB8";
  case VLFF_PIX_DEPTH_U16_MM: return "DepthU16mm";
  case VLFF_PIX_DEPTH_F32_M: return "DepthF32m";
  default: return "unknown";
  }
}

static bool is_depth(uint32_t f) { return f == VLFF_PIX_DEPTH_U16_MM || f == VLFF_PIX_DEPTH_F32_M; }

API uint64_t vlff_frame_slot_size(uint32_t w, uint32_t h, uint32_t color_fmt, uint32_t depth_fmt) {
  unsigned cb = vlff_pixfmt_bpp(color_fmt);
  if (!w || !h || w > 65536 || h > 65536 || !cb || is_depth(color_fmt))
    return 0;
  if (depth_fmt != VLFF_PIX_NONE && !is_depth(depth_fmt))
    return 0;
  uint64_t n = align64(sizeof(struct vlff_frame_hdr)) + align64((uint64_t)w * h * cb);
  if (depth_fmt)
    n += align64((uint64_t)w * h * vlff_pixfmt_bpp(depth_fmt));
  return n;
}

API uint64_t vlff_frame_layout(struct vlff_frame_hdr *hdr, uint64_t slot_size, uint32_t w, uint32_t h,
                               uint32_t color_fmt, uint32_t depth_fmt) {
  uint64_t need = vlff_frame_slot_size(w, h, color_fmt, depth_fmt);
  if (!hdr || !need || need > slot_size)
    return 0;
  memset(hdr, 0, sizeof *hdr);
  hdr->hdr_size = sizeof *hdr;
  hdr->nplanes = depth_fmt ? 2 : 1;
  uint64_t off = align64(sizeof *hdr);
  uint32_t fmts[2] = {color_fmt, depth_fmt};
  for (unsigned i = 0; i < hdr->nplanes; i++) {
    struct vlff_plane *p = &hdr->plane[i];
    p->width = w;
    p->height = h;
    p->format = fmts[i];
    p->stride = w * vlff_pixfmt_bpp(fmts[i]);
    p->offset = off;
    p->size = (uint64_t)p->stride * h;
    off += align64(p->size);
  }
  return off;
}

static int bad_frame(const char *why, unsigned plane) {
  shm_err(VLFF_SHM_ERR_CORRUPT, EBADMSG, "frame record: %s (plane %u)", why, plane);
  return -1;
}

static bool all_finite(const double *v, int n) {
  for (int i = 0; i < n; i++)
    if (!isfinite(v[i]))
      return false;
  return true;
}

API int vlff_frame_validate(const void *record, size_t len) {
  if (!record || len < sizeof(struct vlff_frame_hdr))
    return bad_frame("shorter than its header", 0);
  struct vlff_frame_hdr h;
  memcpy(&h, record, sizeof h);
  if (h.hdr_size != sizeof h)
    return bad_frame("header size differs from this library's", 0);
  if (h.nplanes < 1 || h.nplanes > VLFF_FRAME_MAX_PLANES)
    return bad_frame("plane count not 1 or 2", 0);
  for (unsigned i = 0; i < h.nplanes; i++) {
    const struct vlff_plane *p = &h.plane[i];
    unsigned bpp = vlff_pixfmt_bpp(p->format);
    if (!bpp)
      return bad_frame("unknown pixel format", i);
    if (i == VLFF_PLANE_COLOR && is_depth(p->format))
      return bad_frame("color plane holds a depth format", i);
    if (i == VLFF_PLANE_DEPTH && !is_depth(p->format))
      return bad_frame("depth plane holds a color format", i);
    if (!p->width || !p->height || p->width > 65536 || p->height > 65536)
      return bad_frame("width or height out of range", i);
    if ((uint64_t)p->stride < (uint64_t)p->width * bpp)
      return bad_frame("stride shorter than a row", i);
    if (p->size != (uint64_t)p->stride * p->height)
      return bad_frame("size is not stride * height", i);
    if (p->offset < sizeof h || p->offset > len || p->size > len - p->offset)
      return bad_frame("pixels outside the record", i);
    if (p->offset % 64) /* the header's contract; vlff_frame_layout keeps it */
      return bad_frame("plane offset not 64-aligned", i);
  }
  /* Planes that share bytes: a depth plane laid inside the colour plane was
   * read from colour bytes, and only the trainer's pose check caught it. */
  if (h.nplanes == 2 && h.plane[0].offset < h.plane[1].offset + h.plane[1].size &&
      h.plane[1].offset < h.plane[0].offset + h.plane[0].size)
    return bad_frame("planes overlap", 1);
  if (h.nplanes == 2 && (h.plane[1].width != h.plane[0].width || h.plane[1].height != h.plane[0].height))
    return bad_frame("depth and color sizes differ", 1);
  if ((h.flags & VLFF_FRAME_INTRINSICS_VALID) &&
      (!all_finite(&h.fx, 1) || !all_finite(&h.fy, 1) || !all_finite(&h.cx, 1) || !all_finite(&h.cy, 1) ||
       h.fx <= 0 || h.fy <= 0))
    return bad_frame("intrinsics flagged valid but not finite/positive", 0);
  if ((h.flags & VLFF_FRAME_POSE_VALID) && !all_finite(h.pose, 16))
    return bad_frame("pose flagged valid but not finite", 0);
  return 0;
}

API const void *vlff_frame_plane(const void *record, unsigned i) {
  const struct vlff_frame_hdr *h = record;
  if (!h || i >= h->nplanes || i >= VLFF_FRAME_MAX_PLANES || h->plane[i].format == VLFF_PIX_NONE)
    return NULL;
  return (const uint8_t *)record + h->plane[i].offset;
}

API uint64_t vlff_feature_slot_size(uint32_t dim, uint32_t h, uint32_t w) {
  if (!dim || !h || !w || dim > 65536 || h > 65536 || w > 65536)
    return 0;
  return align64(sizeof(struct vlff_feature_hdr)) + align64(2ull * dim * h * w);
}

API uint64_t vlff_feature_layout(struct vlff_feature_hdr *hdr, uint64_t slot_size, uint32_t dim, uint32_t h,
                                 uint32_t w) {
  uint64_t need = vlff_feature_slot_size(dim, h, w);
  if (!hdr || !need || need > slot_size)
    return 0;
  memset(hdr, 0, sizeof *hdr);
  hdr->hdr_size = sizeof *hdr;
  hdr->dtype = VLFF_FEAT_F16;
  hdr->dim = dim;
  hdr->height = h;
  hdr->width = w;
  hdr->data_offset = align64(sizeof *hdr);
  hdr->data_size = 2ull * dim * h * w;
  return need;
}

API int vlff_feature_validate(const void *record, size_t len) {
  struct vlff_feature_hdr h;
  if (!record || len < sizeof h) {
    shm_err(VLFF_SHM_ERR_CORRUPT, EBADMSG, "feature record: shorter than its header");
    return -1;
  }
  memcpy(&h, record, sizeof h);
  const char *why = NULL;
  if (h.hdr_size != sizeof h)
    why = "header size differs from this library's";
  else if (h.dtype != VLFF_FEAT_F16)
    why = "dtype is not float16";
  else if (!h.dim || !h.height || !h.width || h.dim > 65536 || h.height > 65536 || h.width > 65536)
    why = "dimensions out of range";
  else if (h.data_size != 2ull * h.dim * h.height * h.width)
    why = "data size is not 2*D*h*w";
  else if (h.data_offset < sizeof h || h.data_offset > len || h.data_size > len - h.data_offset)
    why = "data outside the record";
  if (why) {
    shm_err(VLFF_SHM_ERR_CORRUPT, EBADMSG, "feature record: %s", why);
    return -1;
  }
  return 0;
}

/* ---- poses */

API void vlff_pose_quaternion(const double m[16], double q[4]) {
  /* Shepperd: pick the largest diagonal term to keep the square root well away from 0. */
  double r00 = m[0], r11 = m[5], r22 = m[10], tr = r00 + r11 + r22;
  if (tr > 0) {
    double s = sqrt(tr + 1.0) * 2;
    q[0] = 0.25 * s;
    q[1] = (m[9] - m[6]) / s;
    q[2] = (m[2] - m[8]) / s;
    q[3] = (m[4] - m[1]) / s;
  } else if (r00 > r11 && r00 > r22) {
    double s = sqrt(1.0 + r00 - r11 - r22) * 2;
    q[0] = (m[9] - m[6]) / s;
    q[1] = 0.25 * s;
    q[2] = (m[1] + m[4]) / s;
    q[3] = (m[2] + m[8]) / s;
  } else if (r11 > r22) {
    double s = sqrt(1.0 + r11 - r00 - r22) * 2;
    q[0] = (m[2] - m[8]) / s;
    q[1] = (m[1] + m[4]) / s;
    q[2] = 0.25 * s;
    q[3] = (m[6] + m[9]) / s;
  } else {
    double s = sqrt(1.0 + r22 - r00 - r11) * 2;
    q[0] = (m[4] - m[1]) / s;
    q[1] = (m[2] + m[8]) / s;
    q[2] = (m[6] + m[9]) / s;
    q[3] = 0.25 * s;
  }
  double n = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  for (int i = 0; i < 4; i++)
    q[i] /= n;
}

static void quat_to_mat(const double q[4], double m[16]) {
  double w = q[0], x = q[1], y = q[2], z = q[3];
  m[0] = 1 - 2 * (y * y + z * z);
  m[1] = 2 * (x * y - z * w);
  m[2] = 2 * (x * z + y * w);
  m[4] = 2 * (x * y + z * w);
  m[5] = 1 - 2 * (x * x + z * z);
  m[6] = 2 * (y * z - x * w);
  m[8] = 2 * (x * z - y * w);
  m[9] = 2 * (y * z + x * w);
  m[10] = 1 - 2 * (x * x + y * y);
  m[12] = m[13] = m[14] = 0;
  m[15] = 1;
}

API int vlff_pose_interpolate(const struct vlff_pose_rec *a, const struct vlff_pose_rec *b, uint64_t t,
                              double out[16]) {
  if (!a || !b || !out || t < a->t_ns || t > b->t_ns || !all_finite(a->pose, 16) || !all_finite(b->pose, 16)) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "pose interpolation: time outside [a, b] or non-finite pose");
    return -1;
  }
  double u = b->t_ns == a->t_ns ? 0.0 : (double)(t - a->t_ns) / (double)(b->t_ns - a->t_ns);
  double qa[4], qb[4], q[4];
  vlff_pose_quaternion(a->pose, qa);
  vlff_pose_quaternion(b->pose, qb);
  double d = qa[0] * qb[0] + qa[1] * qb[1] + qa[2] * qb[2] + qa[3] * qb[3];
  if (d < 0) { /* take the short way round */
    d = -d;
    for (int i = 0; i < 4; i++)
      qb[i] = -qb[i];
  }
  double wa, wb;
  if (d > 0.9995) { /* nearly parallel: lerp is exact enough and avoids 0/0 */
    wa = 1 - u;
    wb = u;
  } else {
    double th = acos(d), s = sin(th);
    wa = sin((1 - u) * th) / s;
    wb = sin(u * th) / s;
  }
  double n = 0;
  for (int i = 0; i < 4; i++) {
    q[i] = wa * qa[i] + wb * qb[i];
    n += q[i] * q[i];
  }
  n = sqrt(n);
  for (int i = 0; i < 4; i++)
    q[i] /= n;
  quat_to_mat(q, out);
  for (int r = 0; r < 3; r++)
    out[4 * r + 3] = (1 - u) * a->pose[4 * r + 3] + u * b->pose[4 * r + 3];
  return 0;
}

API int vlff_pose_lookup(struct vlff_ring *poses, uint64_t t, uint64_t tol, struct vlff_pose_rec *out) {
  if (!poses || !out || vlff_ring_slot_size(poses) < sizeof(struct vlff_pose_rec)) {
    shm_err(VLFF_SHM_ERR_INVAL, EINVAL, "vlff_pose_lookup: not a pose ring");
    return -1;
  }
  uint64_t h = vlff_ring_head(poses), n_slots = vlff_ring_slots(poses);
  if (h == 0) {
    shm_err(VLFF_SHM_OK, ENOENT, "vlff_pose_lookup: no pose published yet");
    return -1;
  }
  struct vlff_pose_rec above, cur;
  bool have_above = false;
  uint64_t oldest = h > n_slots ? h - n_slots : 0;
  /* Newest first: frames usually ask about the recent past. Poses are published in
   * time order; one that is not is skipped like a torn one. */
  for (uint64_t n = h; n-- > oldest;) {
    if (!shm_ring_peek(poses, n, &cur, sizeof cur))
      break; /* overwritten: everything older is gone too */
    if (!all_finite(cur.pose, 16))
      continue;
    if (cur.t_ns == t) {
      *out = cur;
      return 0;
    }
    if (cur.t_ns > t) {
      if (!have_above || cur.t_ns <= above.t_ns) {
        above = cur;
        have_above = true;
      }
      continue;
    }
    /* cur is the newest pose before t. */
    if (!have_above) {
      shm_err(VLFF_SHM_OK, EAGAIN, "vlff_pose_lookup: t=%llu is newer than every pose (newest %llu)",
              (unsigned long long)t, (unsigned long long)cur.t_ns);
      return -1;
    }
    if (t - cur.t_ns > tol || above.t_ns - t > tol) {
      shm_err(VLFF_SHM_OK, ERANGE, "vlff_pose_lookup: poses around t=%llu are %llu ns before and %llu ns after, "
              "tolerance %llu", (unsigned long long)t, (unsigned long long)(t - cur.t_ns),
              (unsigned long long)(above.t_ns - t), (unsigned long long)tol);
      return -1;
    }
    *out = cur;
    out->t_ns = t;
    out->flags = cur.flags | above.flags;
    return vlff_pose_interpolate(&cur, &above, t, out->pose);
  }
  shm_err(VLFF_SHM_OK, have_above ? ERANGE : ENOENT, "vlff_pose_lookup: t=%llu is older than every pose held",
          (unsigned long long)t);
  return -1;
}
