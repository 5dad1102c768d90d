// OpenCV behind a C interface (see cvshim.h). Every entry point is a
// try/catch wall: OpenCV reports bad input by throwing cv::Exception, and an
// exception unwinding into C frames is undefined behaviour.
#include "cvshim.h"
#include "depthreg.h"
#include "files.h"

#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <initializer_list>
#include <memory>
#include <new>
#include <string>
#include <vector>

#include <opencv2/calib3d.hpp>
#include <opencv2/core.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

namespace {

void set_err(char *err, size_t errlen, const char *where, const char *what) {
  if (err && errlen) std::snprintf(err, errlen, "%s: %s", where, what);
}

template <typename F>
int guarded(const char *where, char *err, size_t errlen, F &&f) {
  try {
    return f();
  } catch (const cv::Exception &e) {
    set_err(err, errlen, where, e.err.c_str());
  } catch (const std::exception &e) {
    set_err(err, errlen, where, e.what());
  } catch (...) {
    set_err(err, errlen, where, "unknown C++ exception");
  }
  return -1;
}

// Calibration files are a few kilobytes; the cap keeps a wrong path (a disk
// image, a log) from being read whole.
constexpr size_t kCalibMaxBytes = 16u << 20;

// Opens a calibration file as OpenCV FileStorage (format: FORMAT_AUTO or a
// forced one). The file is read whole through vlff_read_file, which takes
// only regular files: OpenCV's own open would block for ever on a FIFO and
// read a device without end. Parsed from memory, so OpenCV never opens the
// path itself (nor prints its own error line for it).
int open_storage(cv::FileStorage &fs, const char *path, int format, const char *what, char *err, size_t errlen) {
  uint8_t *bytes = nullptr;
  size_t len = 0;
  if (vlff_read_file(path, kCalibMaxBytes, &bytes, &len, err, errlen) < 0) return -1;
  std::unique_ptr<uint8_t, decltype(&std::free)> owned(bytes, &std::free);
  fs.open(std::string(reinterpret_cast<const char *>(bytes), len),
          cv::FileStorage::READ | cv::FileStorage::MEMORY | format);
  if (!fs.isOpened()) {
    set_err(err, errlen, path, what);
    return -1;
  }
  return 0;
}

// GenICam names a Bayer pattern by the first row's first two pixels; OpenCV
// names it by the second row's second and third. Hence the apparent swap.
int bayer_code(vlff_pix_t fmt) {
  switch (fmt) {
  case VLFF_PIX_BAYER_RG8: return cv::COLOR_BayerBG2RGB;
  case VLFF_PIX_BAYER_BG8: return cv::COLOR_BayerRG2RGB;
  case VLFF_PIX_BAYER_GR8: return cv::COLOR_BayerGB2RGB;
  case VLFF_PIX_BAYER_GB8: return cv::COLOR_BayerGR2RGB;
  default: return -1;
  }
}

}  // namespace

struct vlff_cv_undistort {
  cv::Mat map1, map2;
  int w, h;
};

struct vlff_cv_stereo {
  cv::Mat lmap1, lmap2, rmap1, rmap2;
  cv::Ptr<cv::StereoSGBM> sgbm;
  cv::Mat rect_r, gray_l, gray_r, disp;
  double k[4];
  double baseline;
  int w, h;
};

extern "C" int vlff_cv_compress_rgb(const uint8_t *rgb, size_t stride, int w, int h, int png, int quality,
                                    uint8_t **out, size_t *len, char *err, size_t errlen) {
  return guarded(png ? "encode PNG" : "encode JPEG", err, errlen, [&]() -> int {
    cv::Mat bgr;
    cv::cvtColor(cv::Mat(h, w, CV_8UC3, const_cast<uint8_t *>(rgb), stride), bgr, cv::COLOR_RGB2BGR);
    std::vector<uchar> buf;
    std::vector<int> params;
    if (!png) params = {cv::IMWRITE_JPEG_QUALITY, quality};
    if (!cv::imencode(png ? ".png" : ".jpg", bgr, buf, params)) {
      set_err(err, errlen, png ? "encode PNG" : "encode JPEG", "OpenCV could not encode the image");
      return -1;
    }
    uint8_t *p = static_cast<uint8_t *>(std::malloc(buf.size() ? buf.size() : 1));
    if (!p) {
      set_err(err, errlen, png ? "encode PNG" : "encode JPEG", "out of memory");
      return -1;
    }
    std::memcpy(p, buf.data(), buf.size());
    *out = p;
    *len = buf.size();
    return 0;
  });
}

extern "C" int vlff_cv_to_rgb(const void *src, size_t sstride, int w, int h, vlff_pix_t fmt,
                              uint8_t *dst, size_t dstride, char *err, size_t errlen) {
  return guarded("convert to RGB8", err, errlen, [&]() -> int {
    cv::Mat out(h, w, CV_8UC3, dst, dstride);
    void *s = const_cast<void *>(src);
    switch (fmt) {
    case VLFF_PIX_RGB8: cv::Mat(h, w, CV_8UC3, s, sstride).copyTo(out); return 0;
    case VLFF_PIX_BGR8: cv::cvtColor(cv::Mat(h, w, CV_8UC3, s, sstride), out, cv::COLOR_BGR2RGB); return 0;
    case VLFF_PIX_MONO8: cv::cvtColor(cv::Mat(h, w, CV_8UC1, s, sstride), out, cv::COLOR_GRAY2RGB); return 0;
    default: break;
    }
    int code = bayer_code(fmt);
    if (code < 0) {
      set_err(err, errlen, "convert to RGB8", "pixel format is not a colour format");
      return -1;
    }
    if (w < 2 || h < 2) {
      set_err(err, errlen, "convert to RGB8", "Bayer image smaller than 2x2");
      return -1;
    }
    cv::cvtColor(cv::Mat(h, w, CV_8UC1, s, sstride), out, code);
    // cvtColor reallocates instead of failing when the sizes disagree; that
    // would silently leave the slot unwritten.
    if (out.data != dst) {
      set_err(err, errlen, "convert to RGB8", "output was reallocated");
      return -1;
    }
    return 0;
  });
}

extern "C" int vlff_cv_resize_rgb(const uint8_t *src, size_t sstride, int sw, int sh, uint8_t *dst,
                                  size_t dstride, int dw, int dh, char *err, size_t errlen) {
  return guarded("resample RGB8", err, errlen, [&]() -> int {
    cv::Mat in(sh, sw, CV_8UC3, const_cast<uint8_t *>(src), sstride);
    cv::Mat out(dh, dw, CV_8UC3, dst, dstride);
    int interp = dw <= sw && dh <= sh ? cv::INTER_AREA : cv::INTER_LINEAR;
    cv::resize(in, out, cv::Size(dw, dh), 0, 0, interp);
    // resize reallocates instead of failing when the sizes disagree; that
    // would silently leave the slot unwritten.
    if (out.data != dst) {
      set_err(err, errlen, "resample RGB8", "output was reallocated");
      return -1;
    }
    return 0;
  });
}

extern "C" struct vlff_cv_undistort *vlff_cv_undistort_new(int w, int h, const double k[4],
                                                           const double dist[5], char *err,
                                                           size_t errlen) {
  vlff_cv_undistort *u = nullptr;
  int rc = guarded("undistortion maps", err, errlen, [&]() -> int {
    u = new vlff_cv_undistort();
    u->w = w;
    u->h = h;
    cv::Matx33d K(k[0], 0, k[2], 0, k[1], k[3], 0, 0, 1);
    cv::Mat D(1, 5, CV_64F, const_cast<double *>(dist));
    cv::initUndistortRectifyMap(K, D, cv::noArray(), K, cv::Size(w, h), CV_16SC2, u->map1, u->map2);
    return 0;
  });
  if (rc) {
    delete u;
    return nullptr;
  }
  return u;
}

extern "C" int vlff_cv_undistort_apply(struct vlff_cv_undistort *u, const void *src, size_t sstride,
                                       void *dst, size_t dstride, int channels, int bytes_per_sample,
                                       char *err, size_t errlen) {
  return guarded("undistort", err, errlen, [&]() -> int {
    int type = bytes_per_sample == 2 ? CV_MAKETYPE(CV_16U, channels) : CV_MAKETYPE(CV_8U, channels);
    cv::Mat in(u->h, u->w, type, const_cast<void *>(src), sstride);
    cv::Mat out(u->h, u->w, type, dst, dstride);
    int interp = bytes_per_sample == 2 ? cv::INTER_NEAREST : cv::INTER_LINEAR;
    cv::remap(in, out, u->map1, u->map2, interp, cv::BORDER_CONSTANT, cv::Scalar::all(0));
    return 0;
  });
}

extern "C" void vlff_cv_undistort_free(struct vlff_cv_undistort *u) { delete u; }

static int read_mat(const cv::FileStorage &fs, const char *key, double *out, int rows, int cols,
                    bool allow_short, char *err, size_t errlen, const char *path) {
  cv::Mat m;
  fs[key] >> m;
  if (m.empty()) return 1;
  m.convertTo(m, CV_64F);
  int n = (int)m.total();
  if (allow_short ? (n < 4 || n > 14) : n != rows * cols) {
    char what[160];
    std::snprintf(what, sizeof what, "key '%s': expected %dx%d matrix, got %dx%d", key, rows, cols,
                  m.rows, m.cols);
    set_err(err, errlen, path, what);
    return -1;
  }
  m = m.reshape(1, 1);
  for (int i = 0; i < rows * cols; i++) out[i] = i < n ? m.at<double>(0, i) : 0.0;
  for (int i = 0; i < rows * cols; i++)
    if (!std::isfinite(out[i])) {
      char what[160];
      std::snprintf(what, sizeof what, "key '%s': element %d is not finite", key, i);
      set_err(err, errlen, path, what);
      return -1;
    }
  return 0;
}

extern "C" int vlff_cv_calib_load(const char *path, struct vlff_cv_calib *out, char *err,
                                  size_t errlen) {
  std::memset(out, 0, sizeof *out);
  return guarded(path, err, errlen, [&]() -> int {
    cv::FileStorage fs;
    if (open_storage(fs, path, cv::FileStorage::FORMAT_YAML, "cannot open as OpenCV calibration YAML", err,
                     errlen) < 0)
      return -1;
    if (!fs["image_width"].empty()) fs["image_width"] >> out->width;
    if (!fs["image_height"].empty()) fs["image_height"] >> out->height;
    int a = read_mat(fs, "camera_matrix", out->k, 3, 3, false, err, errlen, path);
    if (a < 0) return -1;
    int b = read_mat(fs, "distortion_coefficients", out->dist, 1, 5, true, err, errlen, path);
    if (b < 0) return -1;
    out->has_mono = a == 0;
    int s[6] = {
        read_mat(fs, "M1", out->k1, 3, 3, false, err, errlen, path),
        read_mat(fs, "D1", out->d1, 1, 5, true, err, errlen, path),
        read_mat(fs, "M2", out->k2, 3, 3, false, err, errlen, path),
        read_mat(fs, "D2", out->d2, 1, 5, true, err, errlen, path),
        read_mat(fs, "R", out->r, 3, 3, false, err, errlen, path),
        read_mat(fs, "T", out->t, 3, 1, false, err, errlen, path),
    };
    int present = 0;
    for (int v : s) {
      if (v < 0) return -1;
      present += v == 0;
    }
    if (present != 0 && present != 6) {
      set_err(err, errlen, path, "stereo calibration needs all of M1 D1 M2 D2 R T");
      return -1;
    }
    out->has_stereo = present == 6;
    if (!out->has_mono && !out->has_stereo) {
      set_err(err, errlen, path, "neither camera_matrix nor stereo keys M1 D1 M2 D2 R T found");
      return -1;
    }
    if (out->has_mono && !(out->k[0] > 0 && out->k[4] > 0)) {
      set_err(err, errlen, path, "camera_matrix has non-positive focal length");
      return -1;
    }
    return 0;
  });
}

extern "C" struct vlff_cv_stereo *vlff_cv_stereo_new(const struct vlff_cv_calib *c, int w, int h,
                                                     int disparities, char *err, size_t errlen) {
  vlff_cv_stereo *s = nullptr;
  int rc = guarded("stereo rectification", err, errlen, [&]() -> int {
    if (!c->has_stereo) {
      set_err(err, errlen, "stereo rectification", "calibration has no stereo keys (M1 D1 M2 D2 R T)");
      return -1;
    }
    s = new vlff_cv_stereo();
    s->w = w;
    s->h = h;
    cv::Mat K1(3, 3, CV_64F, const_cast<double *>(c->k1)), K2(3, 3, CV_64F, const_cast<double *>(c->k2));
    cv::Mat D1(1, 5, CV_64F, const_cast<double *>(c->d1)), D2(1, 5, CV_64F, const_cast<double *>(c->d2));
    cv::Mat R(3, 3, CV_64F, const_cast<double *>(c->r)), T(3, 1, CV_64F, const_cast<double *>(c->t));
    cv::Mat R1, R2, P1, P2, Q;
    cv::stereoRectify(K1, D1, K2, D2, cv::Size(w, h), R, T, R1, R2, P1, P2, Q,
                      cv::CALIB_ZERO_DISPARITY, 0);
    cv::initUndistortRectifyMap(K1, D1, R1, P1, cv::Size(w, h), CV_16SC2, s->lmap1, s->lmap2);
    cv::initUndistortRectifyMap(K2, D2, R2, P2, cv::Size(w, h), CV_16SC2, s->rmap1, s->rmap2);
    s->k[0] = P1.at<double>(0, 0);
    s->k[1] = P1.at<double>(1, 1);
    s->k[2] = P1.at<double>(0, 2);
    s->k[3] = P1.at<double>(1, 2);
    s->baseline = cv::norm(T);
    if (!(s->k[0] > 0) || !(s->baseline > 0)) {
      set_err(err, errlen, "stereo rectification", "degenerate calibration (focal length or baseline is 0)");
      return -1;
    }
    int nd = (disparities + 15) / 16 * 16;
    int block = 5;
    s->sgbm = cv::StereoSGBM::create(0, nd, block, 8 * 3 * block * block, 32 * 3 * block * block, 1,
                                     63, 10, 100, 2, cv::StereoSGBM::MODE_SGBM);
    return 0;
  });
  if (rc) {
    delete s;
    return nullptr;
  }
  return s;
}

extern "C" void vlff_cv_stereo_geometry(const struct vlff_cv_stereo *s, double k[4], double *baseline_m) {
  std::memcpy(k, s->k, sizeof s->k);
  *baseline_m = s->baseline;
}

extern "C" int vlff_cv_stereo_compute(struct vlff_cv_stereo *s, const uint8_t *left, size_t lstride,
                                      const uint8_t *right, size_t rstride, uint8_t *rect_left,
                                      size_t rect_stride, float *depth_m, size_t depth_stride,
                                      char *err, size_t errlen) {
  return guarded("stereo depth", err, errlen, [&]() -> int {
    cv::Mat l(s->h, s->w, CV_8UC3, const_cast<uint8_t *>(left), lstride);
    cv::Mat r(s->h, s->w, CV_8UC3, const_cast<uint8_t *>(right), rstride);
    cv::Mat rl(s->h, s->w, CV_8UC3, rect_left, rect_stride);
    cv::remap(l, rl, s->lmap1, s->lmap2, cv::INTER_LINEAR);
    cv::remap(r, s->rect_r, s->rmap1, s->rmap2, cv::INTER_LINEAR);
    cv::cvtColor(rl, s->gray_l, cv::COLOR_RGB2GRAY);
    cv::cvtColor(s->rect_r, s->gray_r, cv::COLOR_RGB2GRAY);
    s->sgbm->compute(s->gray_l, s->gray_r, s->disp);
    const double fb = s->k[0] * s->baseline;
    for (int y = 0; y < s->h; y++) {
      const int16_t *d = s->disp.ptr<int16_t>(y);
      float *o = (float *)((char *)depth_m + (size_t)y * depth_stride);
      for (int x = 0; x < s->w; x++)
        o[x] = d[x] > 0 ? (float)(fb * 16.0 / d[x]) : 0.0f; // SGBM disparities are fixed-point x16
    }
    return 0;
  });
}

extern "C" void vlff_cv_stereo_free(struct vlff_cv_stereo *s) { delete s; }

// The first of several accepted names present in the file, or nullptr.
static const char *first_key(const cv::FileStorage &fs, std::initializer_list<const char *> names) {
  for (const char *n : names)
    if (!fs[n].empty()) return n;
  return nullptr;
}

// A matrix of one of the accepted element counts into out; -1 with err naming
// the file and key otherwise. Returns the element count.
static int read_doubles(const cv::FileStorage &fs, const char *path, std::initializer_list<const char *> names,
                        std::initializer_list<int> counts, double *out, char *err, size_t errlen) {
  const char *key = first_key(fs, names);
  char what[200];
  if (!key) {
    std::snprintf(what, sizeof what, "key '%s' missing", *names.begin());
    set_err(err, errlen, path, what);
    return -1;
  }
  cv::Mat m;
  fs[key] >> m;
  int n = m.empty() ? 0 : (int)m.total() * m.channels();
  bool ok = false;
  for (int c : counts) ok = ok || n == c;
  if (!ok || (m.rows != 1 && m.cols != 1 && n != 9)) {
    std::snprintf(what, sizeof what, "key '%s': %dx%d matrix has an unexpected shape", key, m.rows, m.cols);
    set_err(err, errlen, path, what);
    return -1;
  }
  m.convertTo(m, CV_64F);
  m = m.reshape(1, 1);
  for (int i = 0; i < n; i++) {
    out[i] = m.at<double>(0, i);
    if (!std::isfinite(out[i])) {
      std::snprintf(what, sizeof what, "key '%s': element %d is not finite", key, i);
      set_err(err, errlen, path, what);
      return -1;
    }
  }
  return n;
}

extern "C" int vlff_cv_rgbd_calib_read(const char *path, struct vlff_rgbd_calib *out, double *t_unit_m,
                                       char *err, size_t errlen) {
  std::memset(out, 0, sizeof *out);
  *t_unit_m = 1;
  return guarded(path, err, errlen, [&]() -> int {
    cv::FileStorage fs;
    if (open_storage(fs, path, cv::FileStorage::FORMAT_AUTO,
                     "cannot open as an OpenCV FileStorage YAML or XML file", err, errlen) < 0)
      return -1;
    if (read_doubles(fs, path, {"K1", "M1", "cameraMatrix1"}, {9}, out->kd, err, errlen) < 0 ||
        read_doubles(fs, path, {"K2", "M2", "cameraMatrix2"}, {9}, out->kc, err, errlen) < 0 ||
        read_doubles(fs, path, {"T"}, {3}, out->t, err, errlen) < 0)
      return -1;
    out->nd = read_doubles(fs, path, {"D1", "distCoeffs1"}, {4, 5, 8, 12, 14}, out->dd, err, errlen);
    if (out->nd < 0) return -1;
    out->nc = read_doubles(fs, path, {"D2", "distCoeffs2"}, {4, 5, 8, 12, 14}, out->dc, err, errlen);
    if (out->nc < 0) return -1;
    for (int n : {out->nd, out->nc})
      if (n > VLFF_DIST_MAX) {
        set_err(err, errlen, path,
                "distortion with thin-prism or tilt terms (12 or 14 coefficients) is not supported: "
                "calibrate with 4, 5 or 8");
        return -1;
      }
    double r[9];
    int nr = read_doubles(fs, path, {"R"}, {3, 9}, r, err, errlen);
    if (nr < 0) return -1;
    if (nr == 3) {
      cv::Mat rv(3, 1, CV_64F, r), rm;
      cv::Rodrigues(rv, rm);
      for (int i = 0; i < 9; i++) out->r[i] = rm.at<double>(i / 3, i % 3);
    } else {
      std::memcpy(out->r, r, sizeof r);
    }
    if (!fs["translation_unit_m"].empty()) {
      if (!fs["translation_unit_m"].isReal() && !fs["translation_unit_m"].isInt()) {
        set_err(err, errlen, path, "key 'translation_unit_m': expected a number");
        return -1;
      }
      fs["translation_unit_m"] >> *t_unit_m;
    }
    const char *size_keys[4] = {"depth_width", "depth_height", "color_width", "color_height"};
    int *sizes[4] = {&out->depth_w, &out->depth_h, &out->color_w, &out->color_h};
    for (int i = 0; i < 4; i++) {
      cv::FileNode n = fs[size_keys[i]];
      if (n.empty()) continue;
      if (!n.isInt()) {
        char what[120];
        std::snprintf(what, sizeof what, "key '%s': expected an integer", size_keys[i]);
        set_err(err, errlen, path, what);
        return -1;
      }
      n >> *sizes[i];
    }
    return 0;
  });
}
