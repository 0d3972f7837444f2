"""Pack training checkpoints (``fit.pt``, ``wrinkle.pt``) into small, pickle-free ``.npz`` files
and back, to move them to and from a lent GPU machine (its transfer limit is 64 MiB a call).

Packed: the state dict without the output basis buffer (rebuilt from ``basis`` on unpacking), the
raw basis, the scalar hyper-parameters and the record (JSON). ``--half`` stores the large
weight matrices and the basis in float16 (transfer only: the unpacked model is float32, its
outputs move by ~1e-3 of a displacement, tens of micrometres).

    python tools/device_checkpoints.py pack build/models/tshirt/wrinkle.pt build/gpu/ckpt/tshirt_wrinkle.npz --half
    python tools/device_checkpoints.py unpack build/gpu/ckpt/tshirt_wrinkle.npz build/models/tshirt/wrinkle.pt
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from training.models import OutputBasis  # noqa: E402

HALF_MIN_NUMEL = 10_000  # arrays at least this large go to float16 with --half


def pack(src: Path, dst: Path, half: bool) -> None:
    ck = torch.load(src, weights_only=False, map_location="cpu")
    out: dict[str, np.ndarray] = {}
    for k, v in ck["state_dict"].items():
        if k == "output.basis":
            continue
        a = v.numpy()
        out["sd/" + k] = a.astype(np.float16) if half and a.dtype == np.float32 and a.size >= HALF_MIN_NUMEL else a
    for k, v in ck.items():
        if k == "state_dict":
            continue
        if k == "record":
            out["record"] = np.array(json.dumps(v))
        elif k == "basis":
            out["basis"] = np.asarray(v, np.float16 if half else np.float32)
        else:
            out[k] = np.asarray(v)
    dst.parent.mkdir(parents=True, exist_ok=True)
    np.savez(dst, **out)


def unpack(src: Path, dst: Path) -> None:
    with np.load(src, allow_pickle=False) as z:
        basis = z["basis"].astype(np.float32)
        ck: dict = {"basis": basis, "state_dict": {}}
        for k in z.files:
            if k.startswith("sd/"):
                a = z[k]
                ck["state_dict"][k[3:]] = torch.as_tensor(a.astype(np.float32) if a.dtype == np.float16 else a)
            elif k == "record":
                ck["record"] = json.loads(str(z[k]))
            elif k != "basis":
                a = z[k]
                ck[k] = a.item() if a.ndim == 0 else a
    ck["state_dict"]["output.basis"] = OutputBasis(basis).basis
    dst.parent.mkdir(parents=True, exist_ok=True)
    torch.save(ck, dst)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("action", choices=("pack", "unpack"))
    p.add_argument("src", type=Path)
    p.add_argument("dst", type=Path)
    p.add_argument("--half", action="store_true", help="float16 weights and basis (pack only)")
    a = p.parse_args()
    pack(a.src, a.dst, a.half) if a.action == "pack" else unpack(a.src, a.dst)


if __name__ == "__main__":
    main()
