#!/usr/bin/python3
"""Export LSeg's image encoder (DPT on a ViT + the 1x1 head to CLIP space) to
ONNX for vlff's OpenCV 4.6 runtime.

Examples:
  # a real LSeg checkpoint (e.g. demo_e200.ckpt, ViT-L/16), 320x256 input
  export_lseg.py --checkpoint demo_e200.ckpt --width 320 --height 256 --out lseg.onnx
  # the same architecture with random weights (tests, benchmarks)
  export_lseg.py --random --arch vitl16 --width 320 --height 256 --out lseg-rand.onnx
  export_lseg.py --random --small --out small.onnx --reference refdir

The model contract: input "image" [1,3,H,W] normalised RGB (LSeg was trained
with mean = std = 0.5: set vlm.mean/vlm.std accordingly), output "features"
[1,D,H/2,W/2]. H and W must be multiples of 32.
"""
import argparse
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from common import export, load_into, load_state_dict  # noqa: E402
from vlff_models import LSegImage  # noqa: E402

ARCHS = {
    # name: dim, depth, heads, hooks, reassemble features, fusion width, D, pos grid
    "vitl16": dict(dim=1024, depth=24, heads=16, hooks=(5, 11, 17, 23), feats=(256, 512, 1024, 1024),
                   features=256, out_c=512, pos_grid=24),
    "vitb16": dict(dim=768, depth=12, heads=12, hooks=(2, 5, 8, 11), feats=(96, 192, 384, 768),
                   features=256, out_c=512, pos_grid=24),
    # the same architecture, scaled down for CI
    "small": dict(dim=64, depth=4, heads=4, hooks=(0, 1, 2, 3), feats=(16, 32, 64, 64),
                  features=32, out_c=32, pos_grid=4),
}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--checkpoint", help="LSeg checkpoint (.ckpt / state dict)")
    src.add_argument("--random", action="store_true", help="random weights (no checkpoint)")
    ap.add_argument("--arch", choices=sorted(ARCHS), default="vitl16")
    ap.add_argument("--small", action="store_true", help="same as --arch small, 64x64 input")
    ap.add_argument("--width", type=int, default=None)
    ap.add_argument("--height", type=int, default=None)
    ap.add_argument("--no-bn", action="store_true", help="fusion blocks without batch norm")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", required=True, help="ONNX file to write")
    ap.add_argument("--reference", help="directory: write a test image and PyTorch's output for it")
    ap.add_argument("--mean", type=float, nargs=3, default=[0.5, 0.5, 0.5])
    ap.add_argument("--std", type=float, nargs=3, default=[0.5, 0.5, 0.5])
    a = ap.parse_args()
    arch = "small" if a.small else a.arch
    width = a.width or (64 if arch == "small" else 320)
    height = a.height or (64 if arch == "small" else 256)
    torch.manual_seed(a.seed)
    try:
        model = LSegImage(height, width, bn=not a.no_bn, **ARCHS[arch]).eval()
    except ValueError as e:
        sys.exit(f"export_lseg: {e}")
    if a.random:
        model.init_random(a.seed)
    else:
        sd = load_state_dict(a.checkpoint)
        sd = {k[4:] if k.startswith("net.") else k: v for k, v in sd.items()}
        load_into(model, sd, a.checkpoint)

    ref = None
    if a.reference:
        rng = np.random.default_rng(a.seed)
        img = rng.integers(0, 256, size=(height, width, 3), dtype=np.uint8)
        x = (img.astype(np.float32) / 255.0 - np.array(a.mean, np.float32)) / np.array(a.std, np.float32)
        x = torch.from_numpy(x.transpose(2, 0, 1).copy())[None]
        with torch.no_grad():
            ref = model(x)[0].numpy().astype(np.float32)  # the original, unfolded model
    model.prepare_export()
    dummy = torch.zeros(1, 3, height, width)
    if ref is not None:
        with torch.no_grad():
            folded = model(x)[0].numpy()
        err = float(np.abs(folded - ref).max())
        if err > 1e-3 * max(1.0, float(np.abs(ref).max())):
            sys.exit(f"export_lseg: folding LayerNorm changed the output by {err}")
    export(model, dummy, a.out, "image", "features")
    if a.reference:
        os.makedirs(a.reference, exist_ok=True)
        img.tofile(os.path.join(a.reference, "image.rgb"))
        ref.tofile(os.path.join(a.reference, "image_ref.f32"))
        with open(os.path.join(a.reference, "image_ref.txt"), "w") as f:
            f.write(f"{width} {height} {ref.shape[0]} {ref.shape[1]} {ref.shape[2]}\n")
        print(f"reference: {width}x{height} image -> features {list(ref.shape)}")


if __name__ == "__main__":
    main()
