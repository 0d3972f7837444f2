"""How faithful a projection into the canonical space is (thesis eq. 6.9): each projected
simulation posed again through eq. 6.7 (``DiffusedBody.pose``) against the simulation itself.

    python tools/projection_check.py build/canonical/train/<garment>_*.npz [build/canonical/validation/...]

Per file (``training.train_canonical``'s projections; the simulation beside it under
``build/reference/train`` or ``build/reference/newton``): the % of vertex-frames inside the posed
body (exact winding number) of the simulation and of pose(X_proj), the mean reconstruction
error (mm), and the folded faces (%) and roughness (deg) of both (``inference.metrics.realism``).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from inference.body import BodyModel  # noqa: E402
from inference.canonical import CanonicalModels  # noqa: E402
from inference.garment import GarmentCatalog  # noqa: E402
from inference.metrics import inside_mask, realism  # noqa: E402
from training.projection import reference_transforms  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("projections", type=Path, nargs="+")
    args = ap.parse_args(argv)
    body, catalog, d = BodyModel.load(), GarmentCatalog.load(), CanonicalModels().diffused
    print("| projection | inside % sim / pose(X) | error mm | folded % sim / pose(X) | rough deg sim / pose(X) |\n|---|---|---|---|---|")
    for proj in args.projections:
        sub = "newton" if proj.parent.name == "validation" else "train"
        with np.load(ROOT / "build" / "reference" / sub / proj.name, allow_pickle=False) as f:
            meta, sim, body_frames = json.loads(str(f["metadata"])), f["vertices"], f["body_vertices"]
        X = np.load(proj, allow_pickle=False)["canonical"]
        asset = catalog.get(meta["garment"])
        transforms, rest = reference_transforms(body, meta)
        T = min(len(X), len(sim))
        tr = transforms[:T] if transforms.ndim == 4 else transforms[0, :T]
        posed = d.pose(X[:T], d.offsets(rest), tr)
        rs, rp = (realism(v, asset.faces, asset.rest_vertices, asset.edges) for v in (sim[:T], posed))
        ins = [100 * inside_mask(v, body_frames[:T], body.faces).mean() for v in (sim[:T], posed)]
        err = 1e3 * np.linalg.norm(posed - sim[:T], axis=-1).mean()
        print(f"| {proj.name} | {ins[0]:.3f} / {ins[1]:.3f} | {err:.1f} | {rs['folded_pct']:.2f} / {rp['folded_pct']:.2f} | "
              f"{rs['roughness_deg']:.1f} / {rp['roughness_deg']:.1f} |")


if __name__ == "__main__":
    main()
