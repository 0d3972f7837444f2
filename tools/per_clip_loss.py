"""Training loss of a wrinkle checkpoint per training clip: which clips the model fails on.

For each clip, ``--windows`` random windows of ``--frames`` frames, each on a random shape of a
bank of ``--shapes`` uniform adult shapes, run from h0 = 0 through fit + GRU + LBS
(``training.train_wrinkle.garment_frames``, arms lifted as in training); printed per clip: the
SNUG loss (eq. 5.7 with inertia) with the exact inside test at collision stiffness ``--k``
(J/m^3), its strain and collision terms (J per window, mean and max over the windows), and the
fraction of vertex-frames inside the body (winding number).

    python tools/per_clip_loss.py --garment longsleeve --fit <fit.pt> --wrinkle <wrinkle.pt>   # ~35 s, one core
(``python -m training.import_onnx --garment longsleeve --out build/imported`` makes both from the shipped ONNX.)
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from inference.body import NEUTRAL_PHENOTYPES, BodyModel
from inference.garment import GarmentCatalog
from training.datasets import TRAIN_CLIPS, MotionBank, ShapeBank, WindowLifter, sample_adult_phenotypes
from training.physics import ClothGeometry
from training.train_fit import load_fit
from training.candidates import candidates
from training.train_wrinkle import garment_frames, make_batch, snug_loss, wrinkle_from_checkpoint


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--garment", required=True)
    p.add_argument("--fit", type=Path, required=True)
    p.add_argument("--wrinkle", type=Path, required=True)
    p.add_argument("--clips", default=",".join(TRAIN_CLIPS))
    p.add_argument("--k", type=float, default=3e7, help="collision stiffness, J/m^3")
    p.add_argument("--shapes", type=int, default=24)
    p.add_argument("--windows", type=int, default=12)
    p.add_argument("--frames", type=int, default=12)
    p.add_argument("--seed", type=int, default=5)
    args = p.parse_args()
    torch.set_num_threads(1)
    rng = np.random.default_rng(args.seed)
    body = BodyModel.load()
    asset = GarmentCatalog.load().get(args.garment)
    neutral = body.shape(NEUTRAL_PHENOTYPES[None])
    cloth = ClothGeometry.from_asset(asset, torch.float32).with_collision_stiffness(args.k, None, None)
    bank = ShapeBank.build(body, asset, sample_adult_phenotypes(args.shapes, rng, corners=False), 8)
    fit, _ = load_fit(args.fit)
    model, _ = wrinkle_from_checkpoint(torch.load(args.wrinkle, weights_only=False))
    model.eval()
    with torch.no_grad():
        fitted = bank.retarget + fit(torch.as_tensor(bank.phenotypes)).numpy()
    weights = torch.as_tensor(asset.skin_weights.astype(np.float32))
    n, T = args.windows, args.frames
    for clip in args.clips.split(","):
        motions = MotionBank.cached((clip,), body, neutral, None)
        starts = rng.choice(motions.windows_of(T), n)
        shape_idx = rng.integers(0, len(bank), n)
        with torch.no_grad():
            batch = make_batch(body, bank, fitted, motions, shape_idx, motions.window_frames(starts, T), WindowLifter(body, bank, motions))
            x = garment_frames(model, batch, weights, model.initial_state(n))
            flat = x.reshape(-1, *x.shape[2:])
            batch.candidates = candidates(batch.body_points, flat, 8)
            inside = torch.as_tensor(bank.inside_mask(body, shape_idx, batch.transforms.numpy(), flat.numpy()))
            loss, terms = snug_loss(cloth, x, batch, 1.0 / motions.fps, inside)
        collision = terms["collision"].numpy()
        print(f"{clip}: loss {float(loss):,.1f} J, strain {float(terms['strain'].mean()):,.1f} J, collision mean {collision.mean():,.1f} "
              f"max {collision.max():,.1f} J, inside {float(inside.float().mean()) * 100:.3f} %", flush=True)


if __name__ == "__main__":
    main()
