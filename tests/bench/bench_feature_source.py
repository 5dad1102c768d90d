#!/usr/bin/python3
"""scripts/bench e2e, its feature-source part: the cost per frame of the
shipped extractor (node/vlm/extractor/vlff_extractor.py, the no-GPU feature
source) serving 640x480 RGB frames from a frame ring with a numpy model, at
D=512 and 60x80 and 120x160 feature maps: read the newest frame, the model,
the float16 conversion and check, the write into the feature ring. The
baseline measured in the same run is the frame read alone (ring copy,
validation, the colour plane as an array); the model's own share at 120x160
is given too, so that the extractor's part is the difference.

The model: each feature is a fixed linear map (a 1x1 convolution) of the
colour averaged over the block of pixels under the feature pixel, as a
stand-in for a network on a CPU.

Prints key=value pairs on one line (no RESULT: e2e.sh appends them to its
own line). Usage: bench_feature_source.py --lib libvlff-shm.so.2 [--frames N]
"""
import argparse
import ctypes
import os
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "../../node/vlm/extractor"))
import vlff_extractor as vx  # noqa: E402

W, H, DIM = 640, 480, 512


def numpy_model(h, w):
    rng = np.random.default_rng(7)
    proj = rng.standard_normal((DIM, 3)).astype(np.float32)
    bias = rng.standard_normal((DIM, 1, 1)).astype(np.float32) * 0.1

    def features(rgb):
        by, bx = rgb.shape[0] // h, rgb.shape[1] // w
        pooled = rgb[:h * by, :w * bx].reshape(h, by, w, bx, 3).mean(axis=(1, 3), dtype=np.float32) / 255.0
        return (proj @ pooled.reshape(h * w, 3).T).reshape(DIM, h, w) + bias

    return features


class FrameWriter:
    """A camera's side of the frame ring, written through libvlff-shm."""

    def __init__(self, lib, name):
        self.lib = lib
        u32, u64, vp = ctypes.c_uint32, ctypes.c_uint64, ctypes.c_void_p
        lib.vlff_frame_slot_size.restype, lib.vlff_frame_slot_size.argtypes = u64, [u32, u32, u32, u32]
        lib.vlff_frame_layout.restype, lib.vlff_frame_layout.argtypes = u64, [vp, u64, u32, u32, u32, u32]
        lib.vlff_shm_unlink.restype, lib.vlff_shm_unlink.argtypes = ctypes.c_int, [ctypes.c_char_p]
        slot = lib.vlff_frame_slot_size(W, H, vx.PIX_RGB8, 0)
        params = vx.RingParams(vx.RECORD_FRAME, 8, slot, 0o600, None)
        self.ring = lib.vlff_ring_create(name.encode(), ctypes.byref(params))
        if not self.ring:
            raise vx.ShmError(lib.vlff_shm_last_message().decode())
        self.slot = slot
        self.image = np.random.default_rng(3).integers(0, 256, (H, W, 3), dtype=np.uint8)

    def write(self, frame_id):
        rec = self.lib.vlff_ring_reserve(self.ring, None)
        hdr = vx.FrameHdr.from_address(rec)
        n = self.lib.vlff_frame_layout(rec, self.slot, W, H, vx.PIX_RGB8, 0)
        hdr.frame_id = frame_id
        p = hdr.plane[vx.PLANE_COLOR]
        dst = np.ctypeslib.as_array((ctypes.c_uint8 * (p.stride * H)).from_address(rec + p.offset))
        dst.reshape(H, p.stride)[:, :W * 3] = self.image.reshape(H, W * 3)
        if self.lib.vlff_ring_commit(self.ring, n) != 0:
            raise vx.ShmError(self.lib.vlff_shm_last_message().decode())


def measure(lib_path, h, w, frames):
    """(ms per frame all told, ms of the read alone, ms of the model alone),
    medians over the frames (a shared host's other work lands on a few)."""
    tag = f"/vlff-bench-fs{os.getpid()}-{h}"
    lib = vx.load_library(lib_path)
    cam = FrameWriter(lib, tag + "-f")
    fn = numpy_model(h, w)
    total, read, model = [], [], []
    try:
        with vx.Extractor(tag + "-f", tag + "-x", DIM, h, w, fn, lib=lib_path, mode=0o600) as ex:
            for k in range(frames + 2):  # two to warm up
                cam.write(k)
                t0 = time.perf_counter()
                hdr, rgb = ex.next_frame(1.0)
                t1 = time.perf_counter()
                feats = fn(rgb)
                t2 = time.perf_counter()
                ex.publish(hdr, feats)
                t3 = time.perf_counter()
                if k >= 2:
                    total.append(t3 - t0)
                    read.append(t1 - t0)
                    model.append(t2 - t1)
            if ex.skipped or ex.failed:
                raise RuntimeError(f"{ex.skipped} frames skipped, {ex.failed} failed: the bench serves every one")
    finally:
        lib.vlff_ring_close(cam.ring)
        for s in ("-f", "-x"):
            lib.vlff_shm_unlink((tag + s).encode())
    return tuple(1e3 * statistics.median(x) for x in (total, read, model))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--lib", required=True, help="libvlff-shm.so.2 of the build")
    ap.add_argument("--frames", type=int, default=30)
    a = ap.parse_args()
    small, read, _ = measure(a.lib, 60, 80, a.frames)
    large, _, model = measure(a.lib, 120, 160, a.frames)
    print(f"feature_source_ms_per_frame={small:.2f} feature_source_ms_per_frame_120x160={large:.2f} "
          f"feature_source_read_ms={read:.2f} feature_source_model_ms_120x160={model:.2f}")


if __name__ == "__main__":
    main()
