#!/usr/bin/python3
"""External feature extractor for vlff, over shared memory (ctypes, libvlff-shm).

Reads frames from the node's frame ring, computes dense features with any
Python function (LSeg in PyTorch on a GPU, typically) and publishes them as
[D,h,w] float16 records tagged with the frame id into a feature ring, which
this process creates and owns (one producer per ring). The node joins them
to its keyframes by id and drops keyframes whose features do not arrive
within vlm.feature_timeout_s.

A feature function slower than the camera never falls behind: each frame
served is the newest in the ring when the previous one is done, and the
frames passed over are counted (skipped) and summarised on stderr every
5 s, as are features refused (wrong shape, non-finite after the float16
conversion, or beyond +-1000, as the node refuses).

Library use:
    from vlff_extractor import Extractor
    def features(rgb):            # rgb: uint8 [H,W,3]; return float [D,h,w]
        ...
    Extractor("/vlff-frames", "/vlff-features", dim=512, height=120, width=160,
              fn=features).run()

Command line (FN is module_path.py:function):
    vlff_extractor.py --frames /vlff-frames --features /vlff-features \\
        --dim 512 --height 120 --width 160 --fn my_lseg.py:features

Installed as share/vlff/extractor/vlff_extractor.py under the prefix; that
copy loads the libvlff-shm.so.2 installed beside it unless --lib says.
"""
import argparse
import ctypes
import ctypes.util
import errno
import importlib.util
import os
import signal
import sys
import time

import numpy as np

# The installed copy's path to the library directory, relative to its own
# directory (CMake fills it in); the source tree's copy keeps the marker.
INSTALLED_LIBDIR = "@VLFF_EXTRACTOR_LIBDIR@"
REPORT_S = 5.0

RECORD_FRAME, RECORD_FEATURE = 2, 3
PIX_RGB8, PIX_BGR8 = 1, 2
PLANE_COLOR = 0


class Plane(ctypes.Structure):
    _fields_ = [("width", ctypes.c_uint32), ("height", ctypes.c_uint32), ("stride", ctypes.c_uint32),
                ("format", ctypes.c_uint32), ("offset", ctypes.c_uint64), ("size", ctypes.c_uint64)]


class FrameHdr(ctypes.Structure):
    """The leading fields of struct vlff_frame_hdr (vlff/shm.h)."""
    _fields_ = [("hdr_size", ctypes.c_uint32), ("flags", ctypes.c_uint32), ("frame_id", ctypes.c_uint64),
                ("t_device_ns", ctypes.c_uint64), ("t_host_ns", ctypes.c_uint64), ("sensor_id", ctypes.c_uint32),
                ("nplanes", ctypes.c_uint32), ("plane", Plane * 2)]


class FeatureHdr(ctypes.Structure):
    """struct vlff_feature_hdr (vlff/shm.h), 128 bytes."""
    _fields_ = [("hdr_size", ctypes.c_uint32), ("dtype", ctypes.c_uint32), ("frame_id", ctypes.c_uint64),
                ("t_host_ns", ctypes.c_uint64), ("sensor_id", ctypes.c_uint32), ("dim", ctypes.c_uint32),
                ("height", ctypes.c_uint32), ("width", ctypes.c_uint32), ("data_offset", ctypes.c_uint64),
                ("data_size", ctypes.c_uint64), ("reserved", ctypes.c_uint8 * 72)]


class RingParams(ctypes.Structure):
    _fields_ = [("record_kind", ctypes.c_uint32), ("slots", ctypes.c_uint32), ("slot_size", ctypes.c_uint64),
                ("mode", ctypes.c_uint32), ("group", ctypes.c_char_p)]


class RingView(ctypes.Structure):
    _fields_ = [("data", ctypes.c_void_p), ("len", ctypes.c_size_t), ("seq", ctypes.c_uint64),
                ("generation", ctypes.c_uint32), ("new_generation", ctypes.c_uint32)]


def default_library():
    """The installed library beside an installed copy, else the system's."""
    if not INSTALLED_LIBDIR.startswith("@"):
        here = os.path.dirname(os.path.realpath(__file__))
        cand = os.path.normpath(os.path.join(here, INSTALLED_LIBDIR, "libvlff-shm.so.2"))
        if os.path.exists(cand):
            return cand
    return ctypes.util.find_library("vlff-shm") or "libvlff-shm.so.2"


def load_library(path=None):
    lib = ctypes.CDLL(path or default_library(), use_errno=True)
    vp, u32, u64, sz = ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint64, ctypes.c_size_t
    sigs = {
        "vlff_ring_attach": (vp, [ctypes.c_char_p, u32]),
        "vlff_ring_create": (vp, [ctypes.c_char_p, ctypes.POINTER(RingParams)]),
        "vlff_ring_close": (None, [vp]),
        "vlff_ring_slot_size": (u64, [vp]),
        "vlff_ring_head": (u64, [vp]),
        "vlff_ring_seek_newest": (None, [vp]),
        "vlff_ring_read_latest": (ctypes.c_ssize_t, [vp, vp, sz, ctypes.POINTER(RingView)]),
        "vlff_ring_read_copy": (ctypes.c_ssize_t, [vp, vp, sz, ctypes.POINTER(RingView), u64]),
        "vlff_ring_reserve": (vp, [vp, ctypes.POINTER(u64)]),
        "vlff_ring_commit": (ctypes.c_int, [vp, sz]),
        "vlff_frame_validate": (ctypes.c_int, [vp, sz]),
        "vlff_feature_slot_size": (u64, [u32, u32, u32]),
        "vlff_feature_layout": (u64, [ctypes.POINTER(FeatureHdr), u64, u32, u32, u32]),
        "vlff_shm_last_message": (ctypes.c_char_p, []),
    }
    for name, (res, args) in sigs.items():
        f = getattr(lib, name)
        f.restype, f.argtypes = res, args
    return lib


class ShmError(RuntimeError):
    pass


class Extractor:
    """Frame ring in, feature ring out. fn(rgb uint8 [H,W,3]) -> [D,h,w]."""

    def __init__(self, frames, features, dim, height, width, fn, slots=8, lib=None, mode=0o640):
        self.lib = load_library(lib)
        self.dim, self.height, self.width, self.fn = dim, height, width, fn
        self.frames = self.lib.vlff_ring_attach(frames.encode(), RECORD_FRAME)
        if not self.frames:
            raise ShmError(self._msg())
        slot = self.lib.vlff_feature_slot_size(dim, height, width)
        if not slot:
            raise ShmError(f"bad feature geometry D={dim} {width}x{height}")
        params = RingParams(RECORD_FEATURE, slots, slot, mode, None)
        self.features = self.lib.vlff_ring_create(features.encode(), ctypes.byref(params))
        if not self.features:
            self.lib.vlff_ring_close(self.frames)
            raise ShmError(self._msg())
        self.slot_size = slot
        self.buf = ctypes.create_string_buffer(self.lib.vlff_ring_slot_size(self.frames))
        self.done = self.failed = self.skipped = 0
        self.last_seq = None  # ring record number of the newest frame taken
        self._since = {"done": 0, "failed": 0, "skipped": 0}
        self._last_error = ""
        self._report_t = time.monotonic()

    def _msg(self):
        m = self.lib.vlff_shm_last_message()
        return m.decode() if m else os.strerror(ctypes.get_errno())

    def close(self):
        if self.frames:
            self.lib.vlff_ring_close(self.frames)
        if self.features:
            self.lib.vlff_ring_close(self.features)
        self.frames = self.features = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def next_frame(self, timeout_s=1.0):
        """(header, rgb [H,W,3] uint8) of the newest frame not taken yet, or None
        on timeout. Frames that came while the previous one was being served are
        passed over for the newest and counted in self.skipped: features of a
        stale frame would only expire in the node."""
        view = RingView()
        n = self.lib.vlff_ring_read_copy(self.frames, self.buf, len(self.buf), ctypes.byref(view),
                                         int(timeout_s * 1e9))
        if n < 0:
            e = ctypes.get_errno()
            if e in (errno.ETIMEDOUT, errno.EAGAIN, errno.EINTR):
                return None
            raise ShmError(self._msg())
        if self.lib.vlff_ring_head(self.frames) > view.seq + 1:
            # Newer frames wait: copy the newest, then move the cursor past it
            # (a frame committed between the two is passed over and counted).
            latest = RingView()
            m = self.lib.vlff_ring_read_latest(self.frames, self.buf, len(self.buf), ctypes.byref(latest))
            if m < 0:
                raise ShmError(self._msg())
            self.lib.vlff_ring_seek_newest(self.frames)
            n, view = m, latest
        if self.last_seq is not None and view.seq <= self.last_seq:
            return self.next_frame(timeout_s)  # one already passed over: wait for a newer one
        if self.last_seq is not None:
            self._count("skipped", view.seq - self.last_seq - 1)
        self.last_seq = view.seq
        if self.lib.vlff_frame_validate(self.buf, n) != 0:
            raise ShmError(self._msg())
        hdr = FrameHdr.from_buffer_copy(self.buf)  # the header only (.raw would copy the slot)
        p = hdr.plane[PLANE_COLOR]
        if p.format not in (PIX_RGB8, PIX_BGR8):
            raise ShmError(f"frame {hdr.frame_id}: color format {p.format}, this client takes RGB8/BGR8")
        raw = np.frombuffer(self.buf, dtype=np.uint8, count=p.stride * p.height, offset=p.offset)
        rgb = raw.reshape(p.height, p.stride)[:, :p.width * 3].reshape(p.height, p.width, 3)
        if p.format == PIX_BGR8:
            rgb = rgb[:, :, ::-1]
        return hdr, np.ascontiguousarray(rgb)

    def publish(self, hdr, feats):
        """Write feats [D,h,w] for the frame of hdr into the feature ring."""
        f = np.asarray(feats)
        if f.shape != (self.dim, self.height, self.width):
            raise ValueError(f"frame {hdr.frame_id}: features {f.shape}, expected {(self.dim, self.height, self.width)}")
        slot = self.lib.vlff_ring_reserve(self.features, None)
        if not slot:
            raise ShmError(self._msg())
        out = FeatureHdr.from_address(slot)
        if not self.lib.vlff_feature_layout(ctypes.byref(out), self.slot_size, self.dim, self.height, self.width):
            raise ShmError("feature layout does not fit the slot")
        # Converted straight into the slot in one pass whatever the input's
        # type and layout (no array of the record's size to allocate and copy
        # per frame), and checked there, as the node checks the record: a
        # value beyond float16's range is infinite there too. The check reads
        # the bits (exponent all ones = Inf or NaN) in one integer pass;
        # float16 arithmetic in numpy is emulated per element. Refused
        # features are not committed: the next frame reserves the same slot.
        n = self.dim * self.height * self.width
        bits = np.ctypeslib.as_array((ctypes.c_uint16 * n).from_address(slot + out.data_offset)).view("<u2")
        with np.errstate(over="ignore", invalid="ignore"):
            np.copyto(bits.view("<f2").reshape(f.shape), f, casting="unsafe")
        # The node also refuses magnitudes beyond 1000 (node/common/bounds.h,
        # VLFF_FEATURE_MAX_ABS_F16: 0x63D0 is 1000 in float16 bits): no model's.
        if int(np.max(bits & np.uint16(0x7FFF), initial=0)) > 0x63D0:
            raise ValueError(f"frame {hdr.frame_id}: non-finite features or values beyond +-1000 (NaN, Inf, "
                             "or a magnitude no vision-language model gives)")
        out.frame_id, out.t_host_ns, out.sensor_id = hdr.frame_id, hdr.t_host_ns, hdr.sensor_id
        if self.lib.vlff_ring_commit(self.features, out.data_offset + 2 * n) != 0:
            raise ShmError(self._msg())

    def _count(self, what, k=1):
        setattr(self, what, getattr(self, what) + k)
        self._since[what] += k

    def report(self, force=False):
        """One stderr line of what happened since the last one, at most every
        REPORT_S seconds and only when frames were skipped or refused."""
        now = time.monotonic()
        if not force and now - self._report_t < REPORT_S:
            return
        s = self._since
        if s["skipped"] or s["failed"]:
            line = (f"vlff_extractor: last {now - self._report_t:.0f} s: {s['done']} frames served, "
                    f"{s['skipped']} skipped for newer ones ({self.skipped} in all)")
            if s["failed"]:
                line += f", {s['failed']} refused ({self.failed} in all; latest: {self._last_error})"
            print(line, file=sys.stderr, flush=True)
        self._since = dict.fromkeys(s, 0)
        self._report_t = now

    def run(self, max_frames=0, idle_timeout_s=0):
        """Serve frames until max_frames (0 = forever) or idle_timeout_s without one."""
        idle = 0.0
        while not max_frames or self.done + self.failed < max_frames:
            self.report()
            got = self.next_frame(1.0)
            if got is None:
                idle += 1.0
                if idle_timeout_s and idle >= idle_timeout_s:
                    break
                continue
            idle = 0.0
            hdr, rgb = got
            try:
                self.publish(hdr, self.fn(rgb))
                self._count("done")
            except (ValueError, FloatingPointError) as e:
                if not self.failed:  # the first in full, later ones in the summaries
                    print(f"vlff_extractor: {e}", file=sys.stderr, flush=True)
                self._last_error = str(e)
                self._count("failed")
        self.report(force=True)


def load_fn(spec):
    path, _, name = spec.rpartition(":")
    if not path or not name:
        sys.exit(f"--fn {spec}: expected file.py:function")
    s = importlib.util.spec_from_file_location("vlff_user_features", path)
    if s is None or not os.path.isfile(path):
        sys.exit(f"vlff_extractor: --fn {spec}: {path} is not a Python file")
    mod = importlib.util.module_from_spec(s)
    s.loader.exec_module(mod)
    fn = getattr(mod, name, None)
    if not callable(fn):
        sys.exit(f"vlff_extractor: --fn {spec}: {path} defines no function {name}")
    return fn


def _stop(signum, frame):
    raise KeyboardInterrupt  # unwinds to main(), which prints the totals


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--lib", help="path of libvlff-shm.so (default: the system's)")
    ap.add_argument("--frames", required=True, help="frame ring name (shm.ring)")
    ap.add_argument("--features", required=True, help="feature ring to create (shm.feature_ring)")
    ap.add_argument("--dim", type=int, required=True)
    ap.add_argument("--height", type=int, required=True)
    ap.add_argument("--width", type=int, required=True)
    ap.add_argument("--slots", type=int, default=8)
    ap.add_argument("--fn", required=True, help="file.py:function, rgb [H,W,3] uint8 -> [D,h,w]")
    ap.add_argument("--max-frames", type=int, default=0, help="exit after this many frames (0 = never)")
    ap.add_argument("--idle-exit", type=float, default=0, help="exit after this many seconds without frames")
    a = ap.parse_args()
    try:
        with Extractor(a.frames, a.features, a.dim, a.height, a.width, load_fn(a.fn), a.slots, a.lib) as ex:
            print(f"vlff_extractor: {a.frames} -> {a.features} [{a.dim},{a.height},{a.width}]", flush=True)
            # SIGTERM (systemd, timeout) ends it as Ctrl-C does: the totals, exit 0
            signal.signal(signal.SIGTERM, _stop)
            try:
                ex.run(a.max_frames, a.idle_exit)
            except KeyboardInterrupt:
                ex.report(force=True)
            print(f"vlff_extractor: {ex.done} frames, {ex.failed} failed, {ex.skipped} skipped", flush=True)
    except ShmError as e:
        sys.exit(f"vlff_extractor: {e}")


if __name__ == "__main__":
    main()
