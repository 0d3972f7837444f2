"""The command line shared by the training scripts (``training.train_fit``, ``training.train_wrinkle``):
one option per tunable field of the run's config dataclass, plus ``--smoke`` and ``--out``."""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
from pathlib import Path
from typing import Callable

log = logging.getLogger(__name__)

# config field -> (option, help); an option is offered when the config has the field
OPTIONS = {
    "minutes": ("--minutes", "wall-clock training budget, minutes (bank building not counted)"),
    "max_steps": ("--max-steps", "stop after this many steps"),
    "threads": ("--threads", "torch intra-op threads"),
    "device": ("--device", "torch device of the model and the loss (cpu, cuda)"),
    "pose_workers": ("--pose-workers", "processes that pose the next batches while one trains (0: in turn)"),
    "inside_workers": ("--inside-workers", "processes that split the exact inside test of each step by windows (0: in this one)"),
    "init": ("--init", "continue from this checkpoint (warm start)"),
    "k_collision": ("--k-collision", "collision stiffness of the training loss, J/m^3"),
    "collision_cap_m": ("--collision-cap", "collision penalty linear beyond this depth, m"),
    "collision_margin_m": ("--collision-margin", "collision margin eps of the training loss, m (default: the material's)"),
    "window_frames": ("--window", "frames per training window (SNUG: 3; longer: the GRU state is trained over more steps)"),
    "exact_inside": ("--exact-inside", "collision loss with the exact (winding-number) inside test: 1 or 0"),
    "lr": ("--lr", "Adam learning rate of the first phase"),
    "lr_final": ("--lr-final", "Adam learning rate after lr_drop of the budget"),
    "corner_fraction": ("--corner-fraction", "share of training windows on the 64 box corners of the shape bank (default: uniform over the bank)"),
    "pin_waistband": ("--pin-waistband", "fit regressor: spring stiffness holding a bottom's waistband on the retarget fit, N/m (0: free)"),
    "basis": ("--basis", "output basis of the fit regressor: harmonics (ships in fit.onnx) or geodesic (rebuilt at runtime)"),
    "basis_size": ("--basis-size", "output basis size: harmonics, or the geodesic basis' nodes"),
    "clips": ("--clips", "training clips, comma-separated CMU ids (training.datasets: AMC or BVH_CLIPS)"),
}


def _clips(text: str) -> tuple[str, ...]:
    """A comma-separated list of clip ids."""
    ids = tuple(c.strip() for c in text.split(",") if c.strip())
    if not ids:
        raise argparse.ArgumentTypeError("expected at least one clip id")
    return ids


def _flag(text: str) -> bool:
    """A boolean option's value: 1/0, true/false, yes/no."""
    value = text.strip().lower()
    if value not in ("1", "0", "true", "false", "yes", "no"):
        raise argparse.ArgumentTypeError(f"expected 1 or 0, got {text!r}")
    return value in ("1", "true", "yes")


def run(argv: list[str] | None, description: str, config_cls, train: Callable, smoke: dict, smoke_help: str, checkpoint_dir: Path) -> dict:
    """Parse ``argv`` into ``config_cls`` (defaults from the dataclass, ``smoke`` overrides with
    ``--smoke``), run ``train(config, smoke=..., out_dir=...)`` and log its metrics."""
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--garment", required=True)
    defaults = {f.name: f.default for f in dataclasses.fields(config_cls)}
    for name, (flag, help_text) in OPTIONS.items():
        if name in defaults:
            kind = str if name in ("init", "device", "basis") else int if name in ("max_steps", "threads", "pose_workers", "inside_workers", "window_frames", "basis_size") else float
            if isinstance(defaults[name], bool):
                kind = _flag
            if name == "clips":
                kind = _clips
            p.add_argument(flag, dest=name, type=kind, default=defaults[name], help=f"{help_text} (default {defaults[name]})")
    p.add_argument("--smoke", action="store_true", help=smoke_help)
    p.add_argument("--out", type=Path, default=checkpoint_dir)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    kw = {name: getattr(args, name) for name in OPTIONS if name in defaults}
    kw["garment"] = args.garment
    if args.smoke:
        kw.update(smoke)
    record = train(config_cls(**kw), smoke=args.smoke, out_dir=args.out)
    log.info("metrics: %s", json.dumps(record["metrics"], indent=1))
    return record
