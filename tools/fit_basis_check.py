"""How well the geodesic output basis (``inference.fit_basis``) holds a fit regressor's output, and
what R_G costs per request (docs/benchmarks.md, "A compact fit regressor for the catalog garments").

    python tools/fit_basis_check.py projection [--garment tshirt]   # residual of the shipped R_G on Phi
    python tools/fit_basis_check.py cost [--garment crewtee --garment tshirt]
    python tools/fit_basis_check.py waist --garment shorts --checkpoint build/models/shorts/fit.pt   # training extra

projection: the garment's shipped R_G (``fit.onnx``) on 200 random adult bodies (seed 5),
least squares onto Phi for K nodes and sigma = a multiple of the covering radius r; prints the
residual per vertex (mean / p99 / max, mm) against R_G's mean displacement.
cost: loading the model (the geodesic basis is rebuilt then) and one R_G call for one body (best
and median of 50, one thread).
waist: a trained fit checkpoint's R_G at the garment's waistband loop (``training.reference``'s,
the loop newton pins) on the protocol's bodies: mean |R_G| and mean vertical move, mm, there and
over the whole garment (a free R_G lets a bottom's waist slide down; ``train_fit --pin-waistband``).
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from inference.fit_basis import farthest_nodes, geodesic_rbf_basis  # noqa: E402
from inference.garment import GarmentCatalog  # noqa: E402
from inference.learned import LearnedModels  # noqa: E402
from training.datasets import sample_adult_phenotypes  # noqa: E402


def projection(garment: str) -> None:
    asset = GarmentCatalog.load().get(garment)
    y = LearnedModels().get(garment).fit(sample_adult_phenotypes(200, np.random.default_rng(5), corners=False))  # (B, V, 3)
    flat = y.transpose(1, 0, 2).reshape(asset.num_vertices, -1)
    mean_mm = np.linalg.norm(y, axis=-1).mean() * 1e3
    print(f"| K (r) | sigma | residual mean / p99 / max, mm (R_G mean {mean_mm:.1f} mm) |\n|---|---|---|")
    for k in (64, 128, 192, 256):
        nodes, r = farthest_nodes(asset.vertices, asset.edges, k)
        for scale in (0.5, 1.0, 1.5, 2.0):
            phi = geodesic_rbf_basis(asset.vertices, asset.edges, nodes, r * scale)
            coef, *_ = np.linalg.lstsq(phi, flat, rcond=None)
            e = np.linalg.norm((phi @ coef - flat).reshape(asset.num_vertices, -1, 3), axis=-1) * 1e3
            print(f"| {k} ({r * 100:.1f} cm) | {scale} r | {e.mean():.1f} / {np.percentile(e, 99):.1f} / {e.max():.1f} |")


def cost(garments: list[str]) -> None:
    p = np.full((1, 6), 0.5, np.float32)
    for g in garments:
        models = LearnedModels()
        t = time.perf_counter()
        lg = models.get(g)
        load = time.perf_counter() - t
        for _ in range(5):
            lg.fit(p)
        ts = []
        for _ in range(50):
            t = time.perf_counter()
            lg.fit(p)
            ts.append(time.perf_counter() - t)
        kind = "geodesic" if lg.fit_basis is not None else "harmonic"
        print(f"{g} ({kind}, {lg.num_vertices} vertices): load {load * 1e3:.0f} ms, R_G {min(ts) * 1e3:.2f} ms best / {np.median(ts) * 1e3:.2f} median")


def waist(garment: str, checkpoint: str) -> None:
    import torch

    from training.protocol import BODIES
    from training.reference import waistband_vertices
    from training.train_fit import load_fit

    model, _ = load_fit(Path(checkpoint))
    w = waistband_vertices(GarmentCatalog.load().get(garment))
    for body in ("neutral", "heavy", "val-far", "light-tall"):
        with torch.no_grad():
            d = model(torch.as_tensor(np.asarray(BODIES[body], np.float32)[None])).numpy()[0]
        print(f"{body}: waistband |R_G| {np.linalg.norm(d[w], axis=1).mean() * 1e3:.1f} mm, dz {d[w, 2].mean() * 1e3:.1f} mm; "
              f"whole garment |R_G| {np.linalg.norm(d, axis=1).mean() * 1e3:.1f} mm, dz {d[:, 2].mean() * 1e3:.1f} mm")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    sub.add_parser("projection").add_argument("--garment", default="tshirt")
    sub.add_parser("cost").add_argument("--garment", action="append")
    w = sub.add_parser("waist")
    w.add_argument("--garment", default="shorts")
    w.add_argument("--checkpoint", required=True)
    args = ap.parse_args()
    if args.cmd == "projection":
        projection(args.garment)
    elif args.cmd == "waist":
        waist(args.garment, args.checkpoint)
    else:
        cost(args.garment or ["crewtee", "tshirt"])


if __name__ == "__main__":
    main()
