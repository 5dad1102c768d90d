// The C++ side of dnn_shim.h: every entry point catches everything, so
// OpenCV's exceptions become error strings before they reach C.
#include "dnn_shim.h"

#include <cstdarg>
#include <cstdio>
#include <exception>
#include <string>
#include <vector>

#include <opencv2/core.hpp>
#include <opencv2/core/cuda.hpp>
#include <opencv2/dnn.hpp>
#include <opencv2/imgproc.hpp>
#include "log.h"

struct vlff_dnn {
  cv::dnn::Net net;
  std::string path;
  std::vector<std::string> out_names;
  std::vector<cv::Mat> outs;
};


// OpenCV's messages span lines; keep the first meaningful one.
static std::string one_line(const std::exception &e) {
  std::string s = e.what();
  const cv::Exception *ce = dynamic_cast<const cv::Exception *>(&e);
  if (ce && !ce->err.empty()) s = ce->err;
  for (char &c : s)
    if (c == '\n' || c == '\r') c = ' ';
  if (s.size() > 300) s.resize(300);
  return s;
}

extern "C" struct vlff_dnn *vlff_dnn_open(const char *path, bool want_cuda, bool *used_cuda, char *err,
                                          size_t errlen) {
  if (used_cuda) *used_cuda = false;
  if (!path || !*path) {
    vlff_errf(err, errlen, "no ONNX model path given");
    return nullptr;
  }
  vlff_dnn *d = nullptr;
  try {
    d = new vlff_dnn;
    d->path = path;
    d->net = cv::dnn::readNetFromONNX(path);
    if (d->net.empty()) {
      vlff_errf(err, errlen, "%s: OpenCV loaded an empty network", path);
      delete d;
      return nullptr;
    }
    d->net.enableFusion(false);
    bool cuda = want_cuda && cv::cuda::getCudaEnabledDeviceCount() > 0;
    if (cuda) {
      d->net.setPreferableBackend(cv::dnn::DNN_BACKEND_CUDA);
      d->net.setPreferableTarget(cv::dnn::DNN_TARGET_CUDA);
    } else {
      d->net.setPreferableBackend(cv::dnn::DNN_BACKEND_OPENCV);
      d->net.setPreferableTarget(cv::dnn::DNN_TARGET_CPU);
    }
    if (used_cuda) *used_cuda = cuda;
    d->out_names = d->net.getUnconnectedOutLayersNames();
    if (d->out_names.empty() || d->out_names.size() > VLFF_DNN_MAX_OUTPUTS) {
      vlff_errf(err, errlen, "%s: model has %zu outputs, expected 1 to %d", path, d->out_names.size(),
              VLFF_DNN_MAX_OUTPUTS);
      delete d;
      return nullptr;
    }
    return d;
  } catch (const std::exception &e) {
    vlff_errf(err, errlen, "%s: cannot load ONNX model: %s", path, one_line(e).c_str());
  } catch (...) {
    vlff_errf(err, errlen, "%s: cannot load ONNX model: unknown exception", path);
  }
  delete d;
  return nullptr;
}

extern "C" void vlff_dnn_close(struct vlff_dnn *d) { delete d; }

extern "C" int vlff_dnn_run(struct vlff_dnn *d, const float *input, const int *shape, int ndim,
                            struct vlff_tensor *out, int max_out, char *err, size_t errlen) {
  if (!d || !input || !shape || ndim < 1 || ndim > VLFF_DNN_MAX_DIMS || !out || max_out < 1) {
    vlff_errf(err, errlen, "vlff_dnn_run: bad arguments");
    return -1;
  }
  try {
    // OpenCV only reads the input blob; the const_cast avoids a copy.
    cv::Mat blob(ndim, shape, CV_32F, const_cast<float *>(input));
    d->net.setInput(blob);
    d->outs.clear();
    d->net.forward(d->outs, d->out_names);
    int n = (int)d->outs.size() < max_out ? (int)d->outs.size() : max_out;
    for (int i = 0; i < n; i++) {
      cv::Mat &m = d->outs[(size_t)i];
      if (m.type() != CV_32F || !m.isContinuous() || m.dims > VLFF_DNN_MAX_DIMS) {
        vlff_errf(err, errlen, "%s: output %d is not a continuous float32 tensor of <= %d dims", d->path.c_str(), i,
                VLFF_DNN_MAX_DIMS);
        return -1;
      }
      out[i].ndim = m.dims;
      out[i].count = m.total();
      for (int k = 0; k < m.dims; k++) out[i].shape[k] = m.size[k];
      out[i].data = m.ptr<float>();
    }
    return n;
  } catch (const std::exception &e) {
    vlff_errf(err, errlen, "%s: inference failed: %s", d->path.c_str(), one_line(e).c_str());
  } catch (...) {
    vlff_errf(err, errlen, "%s: inference failed: unknown exception", d->path.c_str());
  }
  return -1;
}

extern "C" int vlff_dnn_resize(const uint8_t *src, int w, int h, int channels, uint8_t *dst, int dw, int dh,
                               char *err, size_t errlen) {
  if (!src || !dst || w < 1 || h < 1 || dw < 1 || dh < 1 || channels < 1 || channels > 4) {
    vlff_errf(err, errlen, "resize: bad arguments");
    return -1;
  }
  try {
    cv::Mat s(h, w, CV_8UC(channels), const_cast<uint8_t *>(src));
    cv::Mat t(dh, dw, CV_8UC(channels), dst);
    bool shrink = dw < w && dh < h;
    cv::resize(s, t, t.size(), 0, 0, shrink ? cv::INTER_AREA : cv::INTER_LINEAR);
    return 0;
  } catch (const std::exception &e) {
    vlff_errf(err, errlen, "resize: %s", one_line(e).c_str());
  }
  return -1;
}

extern "C" int vlff_dnn_set_threads(int n, char *err, size_t errlen) {
  if (n < 0) {
    vlff_errf(err, errlen, "OpenCV threads: %d is negative", n);
    return -1;
  }
  try {
    cv::setNumThreads(n);
    return 0;
  } catch (const std::exception &e) {
    vlff_errf(err, errlen, "OpenCV threads: %s", one_line(e).c_str());
  }
  return -1;
}
