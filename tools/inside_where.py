"""Where a garment's vertices are inside the body: per frames file, the share inside (all, and
away from the body's self-intersections, ``inference.metrics.collision_rates``' clean share), the
depth of the clean ones (mm) and the bones they lie over (the largest skinning weight of the
nearest body vertex).

    python tools/inside_where.py build/canonical_model/trousers/validation_02_02_30_20_heavy_before.npz [...]

A file holds ``vertices`` (T, V, 3) and ``body_vertices`` (T, Vb, 3), metres (``training.train_canonical``'s
frames before and after the final stage, or a reference simulation).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import scipy.spatial

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from inference.body import BodyModel  # noqa: E402
from inference.metrics import inside_mask, near_self_intersection, unsigned_distance  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("frames", nargs="+", type=Path)
    ap.add_argument("--bones", type=int, default=8, help="bones listed per file")
    args = ap.parse_args(argv)
    body = BodyModel.load()
    for path in args.frames:
        with np.load(path, allow_pickle=False) as f:
            X, B = f["vertices"], f["body_vertices"]
        inside = inside_mask(X, B, body.faces)
        depth = unsigned_distance(X, B, body.faces)[0]
        excluded = near_self_intersection(X, B, body.faces)  # collision_rates' exclusion, 2 cm
        clean = inside & ~excluded
        bones = np.concatenate([body.dense_weights[scipy.spatial.cKDTree(B[t]).query(X[t][clean[t]])[1]].argmax(1)
                                for t in range(len(X)) if clean[t].any()] or [np.zeros(0, np.int64)])
        names, counts = np.unique(np.asarray(body.bone_names)[bones], return_counts=True)
        order = np.argsort(-counts)[: args.bones]
        print(f"{path.name}: inside {100 * inside.mean():.3f} %, clean {100 * clean.sum() / max((~excluded).sum(), 1):.3f} %")
        if clean.any():
            p50, p90, top = np.percentile(depth[clean] * 1e3, [50, 90, 100])
            print(f"  clean depth mm: p50 {p50:.1f}, p90 {p90:.1f}, max {top:.1f}")
            print("  over: " + ", ".join(f"{names[i]} {100 * counts[i] / counts.sum():.0f} %" for i in order))


if __name__ == "__main__":
    main()
