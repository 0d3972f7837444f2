"""Static energy of a garment on one body in the rest pose: the learned model, the retarget, plain
LBS and a quasi-static physics drape (``training.simulate.quasi_static_drape``, the minimiser of
strain + bending + gravity + collision, eq. 5.7-5.12), each with its inside fraction (exact
winding test) and strain + bending + gravity (J; gravity relative to the retarget's).

It asks whether a baseline's energy is within reach of a garment that stays outside the body:
give the drape the training's stiff collision term (``--k``, J/m^3); with the material's
k = 250 it sinks into the body (measured: 45 % of the heavy body's dress inside).

    python tools/static_drape_energy.py --garment dress --phenotypes "[1,1,1,1,1,1]" --k 1e5   # ~35 min, one core
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from inference.body import NEUTRAL_PHENOTYPES, BodyModel  # noqa: E402
from inference.garment import GarmentCatalog  # noqa: E402
from inference.metrics import inside_mask  # noqa: E402
from inference.pipeline import PoseSequence, drape  # noqa: E402
from training.evaluate import METHODS, _with, per_frame_energies  # noqa: E402
from training.physics import ClothGeometry  # noqa: E402
from training.simulate import SolverSettings, quasi_static_drape  # noqa: E402

FRAMES = 3  # a still rest pose, long enough for the GRU and the inertia term


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--garment", default="dress")
    p.add_argument("--phenotypes", default="[1,1,1,1,1,1]", help="JSON list of 6 values in [0, 1]")
    p.add_argument("--k", type=float, help="collision stiffness of the drape, J/m^3 (default: the material's)")
    p.add_argument("--settle-steps", type=int, default=SolverSettings().settle_steps, help="most proximal steps of the drape")
    p.add_argument("--out", type=Path, default=Path("build/reference"), help="the drape is saved here (.npy, metres)")
    args = p.parse_args(argv)
    phen = np.asarray(json.loads(args.phenotypes), np.float32)
    body = BodyModel.load()
    asset = GarmentCatalog.load().get(args.garment)
    shape, neutral = body.shape(phen[None]), body.shape(NEUTRAL_PHENOTYPES[None])
    still = PoseSequence(np.zeros((FRAMES, body.num_bones, 3), np.float32), np.zeros((FRAMES, 3), np.float32), 30.0)
    _, transforms = body.pose(shape.rest_bone_poses, still.rotations[None], still.translation[None])
    posed = body.skin(shape.rest_vertices, transforms)[0, :1]  # (1, Vb, 3): the rest pose as drape() poses it
    offset = (posed[0] - shape.rest_vertices[0]).mean(0)
    cloth = ClothGeometry.from_asset(asset, torch.float32)

    frames = {m: drape(body, shape, still, [asset], _with(o, guard=False), neutral=neutral).garments[0].vertices for m, o in METHODS.items()}
    settings = SolverSettings(settle_steps=args.settle_steps)
    sim_cloth = ClothGeometry.from_asset(asset, settings.torch_dtype)
    if args.k:
        sim_cloth = sim_cloth.with_collision_stiffness(args.k)
    t0 = time.perf_counter()
    ref, logs = quasi_static_drape(asset, body, phen, settings, sim_cloth)
    last = logs[-1]
    print(f"quasi-static drape: {time.perf_counter() - t0:.0f} s, {len(logs)} settle steps, converged {last.converged}, "
          f"largest residual force {last.max_force_n:.3g} N")
    frames["physics drape"] = np.repeat((ref + offset)[None], FRAMES, 0)
    args.out.mkdir(parents=True, exist_ok=True)
    np.save(args.out / f"{args.garment}_static_rest_{'-'.join(f'{v:g}' for v in phen)}_k{args.k}.npy", ref)

    energies = {m: per_frame_energies(cloth, x, still.fps) for m, x in frames.items()}
    g0 = energies["retarget"]["gravity"]
    print("| method | inside % | strain J | bending J | gravity J | strain + bending + gravity J |")
    print("|---|---|---|---|---|---|")
    for m, x in frames.items():
        e = energies[m]
        inside = float(inside_mask(x[:1], posed, body.faces).mean()) * 100
        total = e["strain"] + e["bending"] + e["gravity"] - g0
        print(f"| {m} | {inside:.3f} | {e['strain']:.4f} | {e['bending']:.5f} | {e['gravity'] - g0:+.4f} | {total:.4f} |")


if __name__ == "__main__":
    main()
