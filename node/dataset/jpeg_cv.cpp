// JPEG decoding through OpenCV imgcodecs, behind a C interface: no C++ type
// or exception crosses it.
#include <cstdlib>
#include <cstring>
#include <exception>
#include <vector>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

extern "C" {
#include "dataset_internal.h"
}

extern "C" int vlff_cv_decode_jpeg(const uint8_t *buf, size_t len, int max_side, int *w, int *h,
                                   uint8_t **rgb, char *err, size_t errlen) {
  try {
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
    cv::cvtColor(bgr, out, cv::COLOR_BGR2RGB);
    size_t n = (size_t)out.cols * out.rows * 3;
    uint8_t *p = (uint8_t *)std::malloc(n);
    if (!p) {
      vlff_errf(err, errlen, "out of memory");
      return -1;
    }
    for (int y = 0; y < out.rows; y++) std::memcpy(p + (size_t)y * out.cols * 3, out.ptr(y), (size_t)out.cols * 3);
    *w = out.cols, *h = out.rows, *rgb = p;
    return 0;
  } catch (const std::exception &e) {
    vlff_errf(err, errlen, "%s", e.what());
  } catch (...) {
    vlff_errf(err, errlen, "unknown error");
  }
  return -1;
}

extern "C" int vlff_cv_encode_jpeg(const uint8_t *rgb, int w, int h, int quality, uint8_t **out, size_t *len,
                                   char *err, size_t errlen) {
  try {
    cv::Mat src(h, w, CV_8UC3, const_cast<uint8_t *>(rgb)), bgr;
    cv::cvtColor(src, bgr, cv::COLOR_RGB2BGR);
    std::vector<uchar> buf;
    if (!cv::imencode(".jpg", bgr, buf, {cv::IMWRITE_JPEG_QUALITY, quality})) {
      vlff_errf(err, errlen, "JPEG encoding failed");
      return -1;
    }
    uint8_t *p = (uint8_t *)std::malloc(buf.size());
    if (!p) {
      vlff_errf(err, errlen, "out of memory");
      return -1;
    }
    std::memcpy(p, buf.data(), buf.size());
    *out = p, *len = buf.size();
    return 0;
  } catch (const std::exception &e) {
    vlff_errf(err, errlen, "%s", e.what());
  } catch (...) {
    vlff_errf(err, errlen, "unknown error");
  }
  return -1;
}
