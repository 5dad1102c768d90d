// test_scannet's JPEG writer (a ScanNet colour frame), through OpenCV
// imgcodecs: the node only ever decodes JPEG (node/dataset/jpeg_cv.cpp).
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <vector>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "jpeg_write.h"

int test_jpeg_encode(const uint8_t *rgb, int w, int h, int quality, uint8_t **out, size_t *len) {
  try {
    cv::Mat src(h, w, CV_8UC3, const_cast<uint8_t *>(rgb)), bgr;
    cv::cvtColor(src, bgr, cv::COLOR_RGB2BGR);
    std::vector<uchar> buf;
    if (!cv::imencode(".jpg", bgr, buf, {cv::IMWRITE_JPEG_QUALITY, quality})) return -1;
    *out = static_cast<uint8_t *>(std::malloc(buf.size()));
    if (!*out) return -1;
    std::memcpy(*out, buf.data(), buf.size());
    *len = buf.size();
    return 0;
  } catch (...) {
    return -1;
  }
}
