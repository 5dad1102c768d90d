#!/usr/bin/python3
"""Read the map label at a world point through libvlff-shm (ctypes, no build step).

Usage: read_label.py [--lib PATH] MAP_NAME X Y Z
Prints: label <id> confidence <0..255> prompt <text>
"""
import argparse, ctypes, ctypes.util, sys

ap = argparse.ArgumentParser()
ap.add_argument("--lib", default=ctypes.util.find_library("vlff-shm") or "libvlff-shm.so.2")
ap.add_argument("map"), ap.add_argument("x", type=float), ap.add_argument("y", type=float), ap.add_argument("z", type=float)
a = ap.parse_args()

lib = ctypes.CDLL(a.lib, use_errno=True)
lib.vlff_map_attach.restype = ctypes.c_void_p
lib.vlff_map_attach.argtypes = [ctypes.c_char_p]
lib.vlff_map_detach.argtypes = [ctypes.c_void_p]
lib.vlff_map_label_at.argtypes = [ctypes.c_void_p, ctypes.c_double, ctypes.c_double, ctypes.c_double,
                                  ctypes.POINTER(ctypes.c_uint16), ctypes.POINTER(ctypes.c_uint8)]
lib.vlff_map_prompt.argtypes = [ctypes.c_void_p, ctypes.c_uint16, ctypes.c_char_p, ctypes.c_size_t]
lib.vlff_shm_last_message.restype = ctypes.c_char_p

m = lib.vlff_map_attach(a.map.encode())
if not m:
    sys.exit("read_label: " + lib.vlff_shm_last_message().decode())
label, conf, text = ctypes.c_uint16(), ctypes.c_uint8(), ctypes.create_string_buffer(64)
try:
    if lib.vlff_map_label_at(m, a.x, a.y, a.z, ctypes.byref(label), ctypes.byref(conf)) < 0:
        sys.exit("read_label: " + lib.vlff_shm_last_message().decode())
    name = text.value.decode() if lib.vlff_map_prompt(m, label.value, text, 64) == 0 else "-"
    print(f"label {label.value} confidence {conf.value} prompt {name}")
finally:
    lib.vlff_map_detach(m)
