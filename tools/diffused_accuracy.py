"""Accuracy of the diffused body (``assets/body/diffused.npz``, thesis eq. 6.4-6.5) in the rest
pose, where its fields can be compared with the body's own:

- at the canonical body's skin vertices: B~s of the heaviest adult against its true offsets (mm),
  W~ against the body's folded skinning weights (L1 per vertex), |SDF| (mm);
- every garment shaped by eq. 6.8, T_G(X, beta) = X + B~s(X, beta), X its template, against the
  .mhclo retarget: % of its vertices inside the shaped rest body (exact winding number), on
  extreme and training-only adults (no motion, no test clip).

    python tools/diffused_accuracy.py [--diffused assets/body/diffused.npz]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from inference.body import BodyModel  # noqa: E402
from inference.diffused import DEFAULT_PATH, DiffusedBody  # noqa: E402
from inference.garment import GarmentCatalog  # noqa: E402
from inference.mesh import major_components  # noqa: E402
from inference.metrics import inside_mask  # noqa: E402
from training.protocol import BODIES  # noqa: E402

SHAPES = {"heavy": BODIES["heavy"], "light-tall": BODIES["light-tall"], "train-slim": BODIES["train-slim"],
          "smallest": np.array([0, 0.5, 0, 0, 0, 0], np.float32), "big-male": np.array([1, 0.5, 1, 1, 1, 1], np.float32)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--diffused", type=Path, default=DEFAULT_PATH)
    args = p.parse_args()
    body, catalog = BodyModel.load(), GarmentCatalog.load()
    t0 = time.perf_counter()
    d = DiffusedBody.load(args.diffused)
    print(f"load {time.perf_counter() - t0:.2f} s, {args.diffused.stat().st_size / 1e6:.1f} MB, {d.grid.fine_count} band nodes")
    V0 = d.neutral_vertices
    skin = major_components(body.faces, len(V0))
    heavy = body.shape(BODIES["heavy"][None]).rest_vertices[0]
    err = np.linalg.norm(V0 + d.shape_offsets(V0, d.offsets(heavy)) - heavy, axis=1)[skin] * 1e3
    print(f"B~s of the heavy adult at the skin vertices: mean {err.mean():.2f} mm, p99 {np.percentile(err, 99):.2f} mm, max {err.max():.2f} mm")
    with np.load(args.diffused, allow_pickle=False) as f:
        folded = f["vertex_weights"].astype(np.float32)
    l1 = np.abs(d.weights(V0[skin]) - folded[skin]).sum(1)
    print(f"W~ at the skin vertices, L1 to the body's: mean {l1.mean():.4f}, p90 {np.percentile(l1, 90):.4f}, max {l1.max():.3f}")
    s = np.abs(d.sdf(V0[skin])) * 1e3
    print(f"|SDF| at the skin vertices: mean {s.mean():.2f} mm, max {s.max():.2f} mm\n")
    print("| garment | " + " | ".join(f"{n} diffused / retarget %" for n in SHAPES) + " |")
    print("|---|" + "---|" * len(SHAPES))
    for g in catalog.ids():
        asset = catalog.get(g)
        cells = []
        for ph in SHAPES.values():
            shape = body.shape(ph[None])
            rest = shape.rest_vertices
            shaped = d.deshaped_to_shaped(asset.vertices, d.offsets(rest[0]))
            retarget = asset.retarget_fit(body.hm08_vertices(shape))
            a, b = (100 * inside_mask(np.asarray(x, np.float32).reshape(1, -1, 3), rest, body.faces)[0].mean() for x in (shaped, retarget))
            cells.append(f"{a:.2f} / {b:.2f}")
        print(f"| {g} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
