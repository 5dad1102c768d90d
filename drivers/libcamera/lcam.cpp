// libcamera behind a C interface (see lcam.h). libcamera completes requests
// on its own thread; the completion handler only queues the request, and
// the caller's thread does all the work in vlff_lcam_grab(), so the frame
// pipeline and the sink stay single-threaded as their contracts require.
#include "lcam.h"
#include "clock.h"

#include <cerrno>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstdio>
#include <cstring>
#include <deque>
#include <exception>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include <sys/mman.h>
#include <time.h>

#include <libcamera/libcamera.h>

using namespace libcamera;

namespace {

struct Mapping {
  void *addr = MAP_FAILED;
  size_t len = 0;
  size_t offset = 0;
};

struct FormatName {
  const char *genicam;
  PixelFormat fmt;
  vlff_pix_t pix;
};

// DRM fourccs name components from the most significant byte: RGB888 is
// B,G,R in memory, i.e. what GenICam calls BGR8.
const FormatName kFormats[] = {
    {"RGB8", formats::BGR888, VLFF_PIX_RGB8},         {"BGR8", formats::RGB888, VLFF_PIX_BGR8},
    {"Mono8", formats::R8, VLFF_PIX_MONO8},            {"BayerRG8", formats::SRGGB8, VLFF_PIX_BAYER_RG8},
    {"BayerBG8", formats::SBGGR8, VLFF_PIX_BAYER_BG8}, {"BayerGR8", formats::SGRBG8, VLFF_PIX_BAYER_GR8},
    {"BayerGB8", formats::SGBRG8, VLFF_PIX_BAYER_GB8},
};

std::unique_ptr<CameraManager> g_cm;

}  // namespace

struct vlff_lcam {
  std::shared_ptr<Camera> cam;
  std::unique_ptr<CameraConfiguration> config;
  std::unique_ptr<FrameBufferAllocator> alloc;
  std::vector<std::unique_ptr<Request>> requests;
  std::vector<Mapping> maps;  // per buffer, indexed by Request cookie
  Stream *stream = nullptr;
  vlff_pix_t pix = VLFF_PIX_NONE;
  bool acquired = false, started = false;
  std::mutex mu;
  std::condition_variable cv;
  std::deque<Request *> done;
  bool disconnected = false;
  uint64_t incomplete = 0, timeouts = 0;

  void onCompleted(Request *r) {
    std::lock_guard<std::mutex> l(mu);
    done.push_back(r);
    cv.notify_one();
  }
  void onDisconnected() {
    std::lock_guard<std::mutex> l(mu);
    disconnected = true;
    cv.notify_one();
  }
};

static void fail(char *err, size_t errlen, int e, const char *fmt, const std::string &a = "",
                 const std::string &b = "") {
  std::snprintf(err, errlen, fmt, a.c_str(), b.c_str());
  errno = e;
}

static void teardown(vlff_lcam *c) {
  if (!c) return;
  if (c->cam) {
    if (c->started) c->cam->stop();  // cancels and completes every queued request
    c->cam->requestCompleted.disconnect(c);
    c->cam->disconnected.disconnect(c);
  }
  for (auto &m : c->maps)
    if (m.addr != MAP_FAILED) munmap(m.addr, m.len);
  c->requests.clear();
  if (c->alloc && c->stream) c->alloc->free(c->stream);
  c->alloc.reset();
  if (c->cam && c->acquired) c->cam->release();
  c->cam.reset();
  c->config.reset();
  delete c;
  if (g_cm) {
    g_cm->stop();
    g_cm.reset();
  }
}

// The stages of vlff_lcam_open: each returns false with err (and errno)
// set; the caller tears down what was built.

// The camera camera.device names (an index or an id), acquired.
static bool pick_camera(vlff_lcam *c, const std::string &want, char *err, size_t errlen) {
  // The list holds a reference to every camera: it must be gone before
  // teardown() stops the manager, or the cameras outlive it.
  bool none = false;
  std::string list;
  {
    auto cams = g_cm->cameras();
    none = cams.empty();
    char *end = nullptr;
    long idx = want.empty() ? 0 : std::strtol(want.c_str(), &end, 10);
    bool by_index = want.empty() || (end && !*end);
    for (size_t i = 0; i < cams.size(); i++) {
      if ((by_index && (long)i == idx) || (!by_index && cams[i]->id() == want)) c->cam = cams[i];
      list += (i ? ", " : "") + std::to_string(i) + "=" + cams[i]->id();
    }
  }
  if (none) {
    fail(err, errlen, ENODEV,
         "key 'camera.device': libcamera found no cameras at all (no sensor driver bound, or no /dev/media*; "
         "looking for '%s')",
         want);
    return false;
  }
  if (!c->cam) {
    fail(err, errlen, ENODEV, "key 'camera.device': no libcamera camera '%s' (have: %s)", want, list);
    return false;
  }
  if (c->cam->acquire()) {
    fail(err, errlen, ENODEV, "key 'camera.device': camera '%s' is in use by another process", c->cam->id());
    return false;
  }
  c->acquired = true;
  return true;
}

// One video stream in the configured format and size, exactly.
static bool configure_stream(vlff_lcam *c, const struct vlff_cfg_camera *cfg, const FormatName *fn, char *err,
                             size_t errlen) {
  c->config = c->cam->generateConfiguration({StreamRole::VideoRecording});
  if (!c->config || c->config->size() != 1) {
    fail(err, errlen, EINVAL, "key 'camera.device': camera '%s' offers no video stream", c->cam->id());
    return false;
  }
  StreamConfiguration &sc = c->config->at(0);
  sc.pixelFormat = fn->fmt;
  if (cfg->width && cfg->height) sc.size = Size(cfg->width, cfg->height);
  sc.bufferCount = 4;
  if (c->config->validate() == CameraConfiguration::Invalid) {
    fail(err, errlen, EINVAL, "key 'camera.pixel_format': camera '%s' cannot be configured for %s", c->cam->id(),
         cfg->pixel_format);
    return false;
  }
  if (sc.pixelFormat != fn->fmt) {
    fail(err, errlen, EINVAL, "key 'camera.pixel_format': camera offers %s instead of %s", sc.pixelFormat.toString(),
         cfg->pixel_format);
    return false;
  }
  if (cfg->width && cfg->height &&
      (sc.size.width != (unsigned)cfg->width || sc.size.height != (unsigned)cfg->height)) {
    fail(err, errlen, EINVAL, "key 'camera.width': camera offers %s instead of the configured %s",
         sc.size.toString(), std::to_string(cfg->width) + "x" + std::to_string(cfg->height));
    return false;
  }
  if (c->cam->configure(c->config.get())) {
    fail(err, errlen, EINVAL, "key 'camera.pixel_format': camera '%s' refused configuration %s", c->cam->id(),
         sc.toString());
    return false;
  }
  c->stream = sc.stream();
  c->pix = fn->pix;
  return true;
}

// Frame buffers allocated and mapped, one request per buffer.
static bool map_buffers(vlff_lcam *c, char *err, size_t errlen) {
  c->alloc = std::make_unique<FrameBufferAllocator>(c->cam);
  if (c->alloc->allocate(c->stream) <= 0) {
    fail(err, errlen, ENODEV, "libcamera: cannot allocate buffers for '%s'", c->cam->id());
    return false;
  }
  const auto &bufs = c->alloc->buffers(c->stream);
  c->maps.resize(bufs.size());
  for (size_t i = 0; i < bufs.size(); i++) {
    const FrameBuffer::Plane &pl = bufs[i]->planes()[0];
    Mapping &m = c->maps[i];
    m.offset = pl.offset;
    m.len = pl.offset + pl.length;
    m.addr = mmap(nullptr, m.len, PROT_READ, MAP_SHARED, pl.fd.get(), 0);
    if (m.addr == MAP_FAILED) {
      fail(err, errlen, ENODEV, "libcamera: cannot map a frame buffer: %s", std::strerror(errno));
      return false;
    }
    std::unique_ptr<Request> r = c->cam->createRequest(i);
    if (!r || r->addBuffer(c->stream, bufs[i].get())) {
      fail(err, errlen, ENODEV, "libcamera: cannot create a request");
      return false;
    }
    c->requests.push_back(std::move(r));
  }
  return true;
}

// Exposure, gain and frame rate fixed as configured; streaming with every
// request queued.
static bool start_camera(vlff_lcam *c, const struct vlff_cfg_camera *cfg, char *err, size_t errlen) {
  c->cam->requestCompleted.connect(c, &vlff_lcam::onCompleted);
  c->cam->disconnected.connect(c, &vlff_lcam::onDisconnected);
  ControlList ctrls(controls::controls);
  const ControlInfoMap &info = c->cam->controls();
  if (info.count(&controls::AeEnable)) ctrls.set(controls::AeEnable, false);
  if (info.count(&controls::ExposureTime)) ctrls.set(controls::ExposureTime, (int32_t)cfg->exposure_us);
  if (info.count(&controls::AnalogueGain))
    ctrls.set(controls::AnalogueGain, (float)std::pow(10.0, cfg->gain_db / 20.0));
  if (info.count(&controls::FrameDurationLimits)) {
    int64_t d = (int64_t)std::llround(1e6 / cfg->frame_rate);
    ctrls.set(controls::FrameDurationLimits, Span<const int64_t, 2>({d, d}));
  }
  if (c->cam->start(&ctrls)) {
    fail(err, errlen, ENODEV, "libcamera: camera '%s' failed to start", c->cam->id());
    return false;
  }
  c->started = true;
  for (auto &r : c->requests)
    if (c->cam->queueRequest(r.get())) {
      fail(err, errlen, ENODEV, "libcamera: cannot queue a request");
      return false;
    }
  return true;
}

extern "C" struct vlff_lcam *vlff_lcam_open(const struct vlff_cfg_camera *cfg, char *err, size_t errlen) {
  vlff_lcam *c = nullptr;
  try {
    const FormatName *fn = nullptr;
    for (const auto &f : kFormats)
      if (!std::strcmp(f.genicam, cfg->pixel_format)) fn = &f;
    if (!fn) {
      fail(err, errlen, EINVAL, "key 'camera.pixel_format': libcamera backend takes RGB8, BGR8, Mono8 or Bayer*8, got '%s'",
           cfg->pixel_format);
      return nullptr;
    }
    if (!g_cm) {
      g_cm = std::make_unique<CameraManager>();
      if (g_cm->start()) {
        g_cm.reset();
        fail(err, errlen, ENODEV, "libcamera: camera manager failed to start");
        return nullptr;
      }
    }
    c = new vlff_lcam();
    if (pick_camera(c, cfg->device, err, errlen) && configure_stream(c, cfg, fn, err, errlen) &&
        map_buffers(c, err, errlen) && start_camera(c, cfg, err, errlen)) {
      std::fprintf(stderr, "libcamera: '%s' streaming %s\n", c->cam->id().c_str(),
                   c->config->at(0).toString().c_str());
      return c;
    }
  } catch (const std::exception &e) {
    fail(err, errlen, ENODEV, "libcamera: %s", e.what());
  } catch (...) {
    fail(err, errlen, ENODEV, "libcamera: unknown C++ exception");
  }
  teardown(c);
  return nullptr;
}

extern "C" int vlff_lcam_grab(struct vlff_lcam *c, int timeout_ms, struct vlff_pipe *pipe, struct vlff_sink *sink,
                              const struct vlff_pose_source *poses) {
  try {
    Request *r = nullptr;
    {
      std::unique_lock<std::mutex> l(c->mu);
      c->cv.wait_for(l, std::chrono::milliseconds(timeout_ms), [c] { return !c->done.empty() || c->disconnected; });
      if (c->disconnected) return -1;
      if (c->done.empty()) {
        c->timeouts++;
        return 0;
      }
      r = c->done.front();
      c->done.pop_front();
    }
    int rc = 0;
    FrameBuffer *fb = r->findBuffer(c->stream);
    if (r->status() != Request::RequestComplete || !fb ||
        fb->metadata().status != FrameMetadata::FrameSuccess || r->cookie() >= c->maps.size()) {
      c->incomplete++;
    } else {
      const StreamConfiguration &sc = c->config->at(0);
      const Mapping &m = c->maps[r->cookie()];
      struct vlff_raw_frame raw = {};
      raw.data = (const uint8_t *)m.addr + m.offset;
      raw.size = fb->metadata().planes()[0].bytesused;
      raw.stride = sc.stride;
      raw.width = (int)sc.size.width;
      raw.height = (int)sc.size.height;
      raw.pix = c->pix;
      raw.device_frame_id = fb->metadata().sequence;
      auto ts = r->metadata().get(controls::SensorTimestamp);
      raw.device_ns = ts ? (uint64_t)*ts : fb->metadata().timestamp;
      // V4L2 stamps buffers on CLOCK_MONOTONIC, the host clock we report.
      uint64_t now = vlff_now_ns();
      raw.host_ns = raw.device_ns && raw.device_ns <= now && now - raw.device_ns < 1000000000u ? raw.device_ns : now;
      rc = vlff_pipe_push(pipe, &raw, sink, poses) == 0 ? 1 : 0;
    }
    r->reuse(Request::ReuseBuffers);
    if (c->cam->queueRequest(r)) return -1;
    return rc;
  } catch (...) {
    return -1;
  }
}

extern "C" void vlff_lcam_close(struct vlff_lcam *c) {
  try {
    teardown(c);
  } catch (...) {
  }
}

extern "C" void vlff_lcam_counters(const struct vlff_lcam *c, uint64_t *incomplete, uint64_t *timeouts) {
  *incomplete = c->incomplete;
  *timeouts = c->timeouts;
}
