"""Shared by the export scripts: ONNX export in the form OpenCV 4.6 runs."""
import os
import sys

import torch

OPSET = 13  # <= 16: no LayerNormalization op; what OpenCV 4.6's importer knows best
BANNED_OPS = {"LayerNormalization", "ArgMax", "Expand"}


def export(model, dummy, path, input_name, output_name):
    """Export to path atomically and check the graph's ops."""
    import onnx

    tmp = f"{path}.tmp{os.getpid()}"
    with torch.no_grad():
        torch.onnx.export(model, dummy, tmp, opset_version=OPSET, input_names=[input_name],
                          output_names=[output_name], do_constant_folding=True)
    m = onnx.load(tmp)
    onnx.checker.check_model(m)
    ops = {n.op_type for n in m.graph.node}
    bad = ops & BANNED_OPS
    if bad:
        os.unlink(tmp)
        sys.exit(f"export: graph holds ops OpenCV 4.6 cannot run: {sorted(bad)}")
    with open(tmp, "rb") as f:
        os.fsync(f.fileno())
    os.replace(tmp, path)
    print(f"wrote {path} (opset {OPSET}, {len(m.graph.node)} nodes, ops: {' '.join(sorted(ops))})")


def load_state_dict(path):
    """A checkpoint as a flat state dict: TorchScript archives (CLIP's .pt),
    Lightning checkpoints ({'state_dict': ...}) or plain state dicts."""
    try:
        return torch.jit.load(path, map_location="cpu").state_dict()
    except (RuntimeError, ValueError):
        pass
    ck = torch.load(path, map_location="cpu")
    if isinstance(ck, dict) and "state_dict" in ck:
        ck = ck["state_dict"]
    if not isinstance(ck, dict):
        sys.exit(f"{path}: not a state dict or TorchScript archive")
    return ck


def load_into(model, sd, path):
    """Load sd into model; every model parameter must be in the checkpoint."""
    res = model.load_state_dict(sd, strict=False)
    missing = [k for k in res.missing_keys if not k.endswith("num_batches_tracked")]
    if missing:
        sys.exit(f"{path}: checkpoint lacks {len(missing)} parameters, e.g. {missing[:5]}")
    if res.unexpected_keys:
        print(f"{path}: ignored {len(res.unexpected_keys)} entries not in this model "
              f"(e.g. {res.unexpected_keys[:3]})")
