// JPEG decoding through OpenCV imgcodecs,
// behind a C interface: no C++ type or exception crosses it.
#include <cstdlib>
#include <cstring>
#include <exception>
#include <vector>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

extern "C" {
#include "dataset_internal.h"
}

// Runs f, turning any exception into err and -1.
template <class F> static int guarded(char *err, size_t errlen, F f) {
  try {
    return f();
  } catch (const std::exception &e) {
    vlff_errf(err, errlen, "%s", e.what());
  } catch (...) {
    vlff_errf(err, errlen, "unknown error");
  }
  return -1;
}

// A malloc'd copy the C side frees.
static int copy_out(const uint8_t *src, size_t n, uint8_t **out, char *err, size_t errlen) {
  uint8_t *p = (uint8_t *)std::malloc(n);
  if (!p) {
    vlff_errf(err, errlen, "out of memory");
    return -1;
  }
  std::memcpy(p, src, n);
  *out = p;
  return 0;
}

extern "C" int vlff_cv_decode_jpeg(const uint8_t *buf, size_t len, int max_side, int *w, int *h,
                                   uint8_t **rgb, char *err, size_t errlen) {
  return guarded(err, errlen, [&] {
    if (len > (size_t)INT32_MAX) {
      vlff_errf(err, errlen, "file too large");
      return -1;
    }
    cv::Mat raw(1, (int)len, CV_8UC1, const_cast<uint8_t *>(buf));
    cv::Mat bgr = cv::imdecode(raw, cv::IMREAD_COLOR);
    if (bgr.empty()) {
      vlff_errf(err, errlen, "cannot be decoded");
      return -1;
    }
    if (bgr.cols > max_side || bgr.rows > max_side) {
      vlff_errf(err, errlen, "%dx%d is larger than %d pixels a side", bgr.cols, bgr.rows, max_side);
      return -1;
    }
    cv::Mat out;
    cv::cvtColor(bgr, out, cv::COLOR_BGR2RGB); // a fresh, continuous matrix
    if (copy_out(out.ptr(0), (size_t)out.cols * out.rows * 3, rgb, err, errlen) < 0) return -1;
    *w = out.cols, *h = out.rows;
    return 0;
  });
}
