#!/usr/bin/python3
"""Export CLIP's text transformer to ONNX for vlff's OpenCV 4.6 runtime.

Examples:
  # openai/CLIP's ViT-B-32.pt (LSeg's text encoder), any CLIP .pt works
  export_clip_text.py --checkpoint ViT-B-32.pt --out clip-text.onnx
  # the same architecture with random weights (tests, benchmarks)
  export_clip_text.py --random --out clip-text-rand.onnx
  export_clip_text.py --random --small --out small.onnx \\
      --reference-tokens tokens.txt --reference-out ref.f32

The model contract: input "x" [1,77,W], the token embeddings of the
prompt's ids (OpenCV 4.6 cannot gather with computed indices, so the node
looks ids up itself in OUT.tokemb, written beside the ONNX file), output
"embeddings" [1,77,P]: every position through the transformer, ln_final and
the text projection. The node reads the row at the end-of-text token (CLIP's
argmax of the ids) and L2-normalises it.

OUT.tokemb: 8 bytes "VLFFTOK1", uint32 vocab V, uint32 width W (little
endian), then V*W float32 row-major.
"""
import argparse
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from common import export, load_into, load_state_dict  # noqa: E402
from vlff_models import ClipText, TextGraph  # noqa: E402

SMALL = dict(width=64, layers=2, heads=4, embed_dim=32)
VITB = dict(width=512, layers=12, heads=8, embed_dim=512)


def dims_from(sd):
    """CLIP's build_model: the text tower's shape from its weights."""
    width = sd["ln_final.weight"].shape[0]
    layers = len({k.split(".")[2] for k in sd if k.startswith("transformer.resblocks.")})
    return dict(vocab=sd["token_embedding.weight"].shape[0], context=sd["positional_embedding"].shape[0],
                width=width, layers=layers, heads=width // 64, embed_dim=sd["text_projection"].shape[1])


def write_tokemb(table, path):
    tmp = f"{path}.tmp{os.getpid()}"
    with open(tmp, "wb") as f:
        f.write(b"VLFFTOK1")
        f.write(np.array(table.shape, dtype="<u4").tobytes())
        f.write(np.ascontiguousarray(table, dtype="<f4").tobytes())
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)
    print(f"wrote {path} ({table.shape[0]} x {table.shape[1]} token embeddings)")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--checkpoint", help="CLIP model (.pt TorchScript archive or state dict)")
    src.add_argument("--random", action="store_true", help="random weights, ViT-B/32's text tower")
    ap.add_argument("--small", action="store_true", help="with --random: a 2-layer, 64-wide tower, P=32")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", required=True)
    ap.add_argument("--reference-tokens", help="file of token contexts (77 ids a line) to run in PyTorch")
    ap.add_argument("--reference-out", help="raw float32 [K,P]: PyTorch's embeddings for those contexts")
    a = ap.parse_args()
    if a.checkpoint:
        sd = load_state_dict(a.checkpoint)
        model = ClipText(**dims_from(sd)).eval()
        load_into(model, sd, a.checkpoint)
    else:
        model = ClipText(**(SMALL if a.small else VITB)).eval()
        model.init_random(a.seed)
    ref = None
    if a.reference_tokens:
        ids = torch.tensor(np.loadtxt(a.reference_tokens, dtype=np.int64, ndmin=2))
        if ids.shape[1] != model.context:
            sys.exit(f"{a.reference_tokens}: {ids.shape[1]} ids a line, expected {model.context}")
        with torch.no_grad():
            ref = torch.cat([model.embed(ids[i:i + 1]) for i in range(ids.shape[0])]).numpy()
    model.prepare_export()
    if ref is not None:
        with torch.no_grad():
            folded = torch.cat([model.embed(ids[i:i + 1]) for i in range(ids.shape[0])]).numpy()
        err = float(np.abs(folded - ref).max())
        if err > 1e-3 * max(1.0, float(np.abs(ref).max())):
            sys.exit(f"export_clip_text: folding LayerNorm changed the output by {err}")
    width = model.token_embedding.weight.shape[1]
    export(TextGraph(model), torch.zeros(1, model.context, width), a.out, "x", "embeddings")
    write_tokemb(model.token_embedding.weight.detach().numpy(), a.out + ".tokemb")
    if ref is not None and a.reference_out:
        ref.astype(np.float32).tofile(a.reference_out)
        print(f"reference: {ref.shape[0]} prompts -> {ref.shape[1]}-dim embeddings")


if __name__ == "__main__":
    main()
