"""Command line of the physics reference: one catalog garment along a motion clip, to an ``.npz``.

``python -m training.simulate --garment tshirt --clip walk --frames 60
--out build/reference/tshirt_walk.npz`` writes the sequence (vertices, faces, the drape, the
motion), the metadata (settings, material, timings, machine, git commit) and the convergence log
(``SimulationLog.arrays``).
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import subprocess
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from inference.body import NEUTRAL_PHENOTYPES, BodyModel
from training.physics import ClothGeometry
from training.simulate.drivers import quasi_static_drape, simulate_sequence
from training.simulate.settings import SolverSettings

log = logging.getLogger(__name__)


def _git_commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True, cwd=Path(__file__).parent).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def main(argv: list[str] | None = None) -> None:
    from inference.garment import GarmentCatalog
    from training.protocol import SourceClips, clip_motion

    p = argparse.ArgumentParser(prog="python -m training.simulate", description="Physics reference simulation of a catalog garment along a motion clip.")
    p.add_argument("--garment", required=True, help="garment id (assets/garments/<id>)")
    p.add_argument("--clip", required=True, help="motion clip id (assets/motions, or a CMU clip of training/sources)")
    p.add_argument("--frames", type=int, default=60, help="frames to simulate from --start (default 60)")
    p.add_argument("--start", type=int, default=0, help="first clip frame")
    p.add_argument("--phenotypes", type=float, nargs=6, default=NEUTRAL_PHENOTYPES.tolist(), metavar="P", help="body phenotypes (default neutral)")
    p.add_argument("--substeps", type=int, default=2)
    p.add_argument("--lead-in", type=int, default=15, help="frames from the rest pose to the clip's first pose (simulate_sequence)")
    p.add_argument("--max-iterations", type=int, default=SolverSettings.max_iterations)
    p.add_argument("--force-tolerance", type=float, default=SolverSettings.force_tolerance)
    p.add_argument("--dtype", choices=("float64", "float32"), default="float64")
    p.add_argument("--threads", type=int, default=1, help="torch threads (1: fastest for these sizes, and on a shared machine)")
    p.add_argument("--save-body", action="store_true", help="also store the posed body vertices (T, M, 3)")
    p.add_argument("--out", type=Path, required=True, help="output .npz")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    torch.set_num_threads(args.threads)

    settings = SolverSettings(dtype=args.dtype, max_iterations=args.max_iterations, force_tolerance=args.force_tolerance)
    body = BodyModel.load()
    asset = GarmentCatalog.load().get(args.garment)
    phen = np.asarray(args.phenotypes, np.float32)
    shape = body.shape(phen[None])
    clip = SourceClips(body).load(args.clip)
    # the service's import of the clip (no arm lift: the reference simulates the clip as captured)
    motion = clip_motion(body, shape, clip, min(args.start + args.frames, clip.num_frames), lift=False)
    rotations, translation = motion.rotations[args.start:], motion.translation[args.start:]

    t0 = time.perf_counter()
    drape, drape_log = quasi_static_drape(asset, body, phen, settings)
    t_drape = time.perf_counter() - t0
    log.info("quasi-static drape: %d steps, %.1f s, static |g| %.3g N (converged %s)", len(drape_log), t_drape,
             drape_log[-1].grad_norm_end_n if drape_log else float("nan"), drape_log[-1].converged if drape_log else True)
    t1 = time.perf_counter()
    frames, sim_log = simulate_sequence(asset, body, phen, rotations, translation, clip.fps, args.substeps, settings, drape=drape, lead_in_frames=args.lead_in)
    t_sim = time.perf_counter() - t1
    sim_log.solves = drape_log + sim_log.solves
    dyn = sim_log.summary("dynamic")
    meta = {
        "garment": args.garment, "clip": args.clip, "start": args.start, "frames": int(len(frames)),
        "fps": clip.fps, "substeps": args.substeps, "settings": asdict(settings),
        "material": asdict(ClothGeometry.from_asset(asset).material),
        "seconds_drape": t_drape, "seconds_simulation": t_sim,
        "lead_in": args.lead_in, "seconds_per_frame": t_sim / (len(frames) - 1 + args.lead_in),
        "cpu_seconds_per_clip_frame": float(np.mean(sim_log.frame_cpu_seconds[1:])) if len(frames) > 1 else 0.0,
        "dynamic_solves": dyn, "lead_in_solves": sim_log.summary("lead_in"), "settle_solves": sim_log.summary("settle"),
        "machine": f"{platform.machine()} {platform.processor()}, {os.cpu_count()} CPUs, torch threads {torch.get_num_threads()}",
        "load_average_1min_end": os.getloadavg()[0],
        "git_commit": _git_commit(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    body_frames = None
    if args.save_body:
        _, transforms = body.pose(shape.rest_bone_poses, rotations[None], translation[None])
        body_frames = body.skin(shape.rest_vertices, transforms)[0]
    np.savez_compressed(
        args.out,
        vertices=frames, faces=asset.faces.astype(np.int32), drape=drape,
        phenotypes=phen, rotations=rotations, translation=translation, fps=np.float32(clip.fps),
        metadata=np.str_(json.dumps(meta)),
        **({"body_vertices": body_frames} if body_frames is not None else {}),
        **sim_log.arrays(),
    )
    log.info("wrote %s: %d frames, %.2f s/frame; dynamic solves %s", args.out, len(frames), meta["seconds_per_frame"], json.dumps(dyn))
