#!/usr/bin/python3
"""Copy the whole published map through libvlff-shm's snapshot API (ctypes, no build step).

Usage: read_map.py [--lib PATH] [--points FILE] MAP_NAME
Prints the version, the grid and each prompt's voxel count; with --points
(one "x y z" line per point, metres) also "x y z label prompt" per point,
read from the same consistent copy.
"""
import argparse, ctypes, ctypes.util, sys

ap = argparse.ArgumentParser()
ap.add_argument("--lib", default=ctypes.util.find_library("vlff-shm") or "libvlff-shm.so.2")
ap.add_argument("--points")
ap.add_argument("map")
a = ap.parse_args()

FREE, UNKNOWN = 0xFFFE, 0xFFFF


class Grid(ctypes.Structure):  # struct vlff_map_grid
    _fields_ = [("origin", ctypes.c_double * 3), ("voxel_size", ctypes.c_double), ("dims", ctypes.c_uint32 * 3),
                ("labels", ctypes.POINTER(ctypes.c_uint16)), ("confidence", ctypes.POINTER(ctypes.c_uint8))]


class LabelImage(ctypes.Structure):  # struct vlff_map_label_image
    _fields_ = [("width", ctypes.c_uint32), ("height", ctypes.c_uint32),
                ("labels", ctypes.POINTER(ctypes.c_uint16)), ("confidence", ctypes.POINTER(ctypes.c_uint8)),
                ("fx", ctypes.c_double), ("fy", ctypes.c_double), ("cx", ctypes.c_double), ("cy", ctypes.c_double),
                ("pose", ctypes.c_double * 16), ("t_ns", ctypes.c_uint64)]


class Info(ctypes.Structure):  # struct vlff_map_info
    _fields_ = [("version", ctypes.c_uint64), ("publish_ns", ctypes.c_uint64), ("generation", ctypes.c_uint32),
                ("prompt_count", ctypes.c_int), ("grid", Grid), ("has_label_image", ctypes.c_int),
                ("label_image", LabelImage)]


lib = ctypes.CDLL(a.lib, use_errno=True)
vp = ctypes.c_void_p
for fn, res, args in [("vlff_map_attach", vp, [ctypes.c_char_p]), ("vlff_map_detach", None, [vp]),
                      ("vlff_map_snapshot_new", vp, [vp]), ("vlff_map_snapshot_free", None, [vp]),
                      ("vlff_map_snapshot_take", ctypes.c_int, [vp, vp]),
                      ("vlff_map_snapshot_info", ctypes.c_int, [vp, ctypes.POINTER(Info)]),
                      ("vlff_map_snapshot_label_at", ctypes.c_uint16,
                       [vp, ctypes.c_double, ctypes.c_double, ctypes.c_double, ctypes.POINTER(ctypes.c_uint8)]),
                      ("vlff_map_snapshot_prompt", ctypes.c_char_p, [vp, ctypes.c_uint16]),
                      ("vlff_shm_last_message", ctypes.c_char_p, [])]:
    getattr(lib, fn).restype, getattr(lib, fn).argtypes = res, args


def die(what):
    sys.exit(f"read_map: {what}: {lib.vlff_shm_last_message().decode()}")


m = lib.vlff_map_attach(a.map.encode())
if not m:
    die(a.map)
snap = lib.vlff_map_snapshot_new(m)
try:
    info = Info()
    if not snap or lib.vlff_map_snapshot_take(m, snap) < 0 or lib.vlff_map_snapshot_info(snap, ctypes.byref(info)) < 0:
        die(a.map)
    g = info.grid
    n = g.dims[0] * g.dims[1] * g.dims[2]
    if info.version == 0 or n == 0:
        sys.exit(f"read_map: {a.map}: no map published yet")
    # The labels as one copy: index i + dims0 * (j + dims1 * k) is voxel (i, j, k).
    labels = ctypes.string_at(g.labels, 2 * n)
    labels = memoryview(labels).cast("H")
    prompts = [lib.vlff_map_snapshot_prompt(snap, k).decode() for k in range(info.prompt_count)]
    print(f"version {info.version} origin {g.origin[0]:.3f} {g.origin[1]:.3f} {g.origin[2]:.3f} "
          f"voxel_size {g.voxel_size:.3f} dims {g.dims[0]} {g.dims[1]} {g.dims[2]}")
    counts = {}
    for v in labels:
        counts[v] = counts.get(v, 0) + 1
    for k, p in enumerate(prompts):
        print(f"prompt {k} {p} voxels {counts.get(k, 0)}")
    print(f"free {counts.get(FREE, 0)} unknown {counts.get(UNKNOWN, 0)}")
    if a.points:
        conf = ctypes.c_uint8()
        for line in open(a.points):
            if not line.strip():
                continue
            x, y, z = (float(t) for t in line.split()[:3])
            lab = lib.vlff_map_snapshot_label_at(snap, x, y, z, ctypes.byref(conf))
            name = prompts[lab] if lab < len(prompts) else "free" if lab == FREE else "unknown"
            print(f"{x:g} {y:g} {z:g} {lab} {name}")
finally:
    lib.vlff_map_snapshot_free(snap)
    lib.vlff_map_detach(m)
