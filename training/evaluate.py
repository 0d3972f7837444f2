"""Evaluation of the learned garment model against the baselines and the physics reference
(issue 3, Part 7; thesis table 5.1 for the energies, table 6.2 for the vertex error).

Run: ``python -m training.evaluate --clip 01_01 --every 8 --write docs/archive/evaluation-ch4-ch5.md``

Methods (``inference.pipeline.drape`` with these options):
    learned  : retarget + R_G + R_L, then LBS (fit='learned', dynamics='learned')
    retarget : the .mhclo retarget fit, then LBS (fit='retarget', dynamics='none')
    lbs      : the neutral template, plain LBS (fit='none', dynamics='none')

For every garment x body (``BODIES``: neutral + 4 corners of the adult box) x method on the clip:
- inside % before and after the guard, exact ray-crossing winding test against the posed skin
  (``inference.metrics.collision_rates``; "clean" excludes vertices within 2 cm of LBS
  self-intersecting skin, DESIGN.md §5), on every ``every``-th frame;
- mean strain, bending, gravity (relative to the retarget method's on the same frames, so that
  the body's own motion cancels) and inertia energy per frame, J, over all frames, before the guard
  (``training.physics`` with the garment's physical material, eq. 5.6-5.11).

Against the physics reference (``training.simulate``), when its files exist under
``build/reference``:
- dynamic: ``<garment>_<clip>.npz`` (neutral body, ``python -m training.simulate --clip 01_01
  --frames 60 --out build/reference/<garment>_01_01.npz``): mean vertex error in cm over its
  frames, each method after the guard (``reference_errors``);
- static: ``<garment>_static.npz`` (``python -m training.evaluate --reference-static``: quasi-static
  drapes of held-out shapes): mean vertex error in cm of the learned fit and of the retarget.

Settle check: the dress on the walk clip, then the body held still in the last pose; the hem's
speed per frame after the stop (learned dynamics; the baselines stop dead by construction).
"""
from __future__ import annotations

import argparse
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from inference.body import NEUTRAL_PHENOTYPES, BodyModel
from inference.garment import GarmentCatalog
from inference.learned import LearnedModels, default_models
from inference.metrics import collision_rates
from inference.motion.clips import ClipLibrary
from inference.pipeline import DrapeOptions, PoseSequence, drape
from training.datasets import REPO_ROOT, sample_adult_phenotypes
from training.evaluate_collisions import Inputs, shaped_motion
from training.physics import ClothGeometry, energy_terms, inertia_energy

log = logging.getLogger(__name__)

REFERENCE_DIR = REPO_ROOT / "build" / "reference"
BODIES: dict[str, np.ndarray] = {
    "neutral": NEUTRAL_PHENOTYPES,
    "light [0,.77,0,0,0,0]": np.array([0.0, 0.77, 0.0, 0.0, 0.0, 0.0], np.float32),
    "heavy [1,1,1,1,1,1]": np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1.0], np.float32),
    "[0,.77,0,1,1,0]": np.array([0.0, 0.77, 0.0, 1.0, 1.0, 0.0], np.float32),
    "[1,1,1,0,0,1]": np.array([1.0, 1.0, 1.0, 0.0, 0.0, 1.0], np.float32),
}
METHODS: dict[str, DrapeOptions] = {
    # the motions come with the arms already lifted (``shaped_motion``), as the service runs them
    "learned": DrapeOptions(fit="learned", dynamics="learned", lift_arms=False),
    "retarget": DrapeOptions(fit="retarget", dynamics="none", lift_arms=False),
    "lbs": DrapeOptions(fit="none", dynamics="none", lift_arms=False),
}
ENERGY_TERMS = ("strain", "bending", "gravity", "inertia")
STATIC_SEED = 12345  # held-out shapes of the static reference (the fit trains on seed 0, evaluates on seed 1)


@dataclass
class Row:
    body: str
    garment: str
    method: str
    frames: int  # frames of the clip (energies)
    collision_frames: int  # frames tested for collisions
    before: dict
    after: dict
    energies_j: dict  # mean per frame
    seconds: float = 0.0


@dataclass
class ReferenceRow:
    garment: str
    frames: int  # reference frames compared (clip frames start .. start + frames - 1)
    start: int
    error_cm: dict  # method -> mean vertex error over frames and vertices, after the guard
    residual_force_n: float  # median over the reference's clip solves of the largest per-vertex residual force


@dataclass
class StaticRow:
    garment: str
    shapes: int
    learned_cm: float
    retarget_cm: float
    residual_force_n: float  # median over shapes of the reference's largest per-vertex residual force


@dataclass
class SettleResult:
    stop_frame: int
    hem_speed_mm_per_frame: list[float] = field(default_factory=list)  # learned; k = 0: last moving frame -> first still one


def per_frame_energies(cloth: ClothGeometry, frames: np.ndarray, fps: float, chunk: int = 64) -> dict[str, float]:
    """Mean strain, bending, gravity and inertia energy per frame, J.
    frames : (T, V, 3) metres ; inertia (eq. 5.6, dt = 1/fps) over frames 2..T-1."""
    x = torch.as_tensor(np.asarray(frames), dtype=cloth.dtype)
    sums = {k: 0.0 for k in ENERGY_TERMS}
    with torch.no_grad():
        for s in range(0, len(x), chunk):
            terms = energy_terms(cloth, x[s : s + chunk])
            for k in ("strain", "bending", "gravity"):
                sums[k] += float(terms[k].sum())
        if len(x) > 2:
            sums["inertia"] = float(inertia_energy(cloth, x[2:], x[1:-1], x[:-2], 1.0 / fps).sum()) * len(x) / (len(x) - 2)
    return {k: v / len(x) for k, v in sums.items()}


def reference_errors(clip_id: str, garments: list[str], methods: dict[str, DrapeOptions] = METHODS, models: LearnedModels | None = None) -> list[ReferenceRow]:
    """Mean vertex error (cm) of every method, after the guard, against the dynamic reference
    ``build/reference/<garment>_<clip>.npz`` (``training.simulate``, neutral body) where it exists.
    The methods run the clip from its frame 0 (the GRU's state builds up as at runtime)."""
    body = BodyModel.load()
    catalog = GarmentCatalog.load()
    # the reference was simulated on the clip as retargeted (arms not lifted)
    shape, full = shaped_motion(body, ClipLibrary().load(clip_id), NEUTRAL_PHENOTYPES, lift=False)
    rows = []
    for gid in garments:
        path = REFERENCE_DIR / f"{gid}_{clip_id}.npz"
        if not path.exists():
            continue
        with np.load(path, allow_pickle=False) as z:
            ref = np.asarray(z["vertices"], np.float32)
            meta = json.loads(str(z["metadata"]))
        start = int(meta["start"])
        end = start + len(ref)
        motion = PoseSequence(full.rotations[:end], full.translation[:end], full.fps)
        errors = {}
        for method, options in methods.items():
            ours = drape(body, shape, motion, [catalog.get(gid)], _with(options, guard=True), neutral=shape, models=models).garments[0].vertices[start:end]
            errors[method] = float(np.linalg.norm(ours - ref, axis=-1).mean() * 100.0)
        force = meta.get("dynamic_solves", {}).get("max_force_n_median", float("nan"))
        rows.append(ReferenceRow(gid, len(ref), start, errors, float(force)))
        log.info("%s vs reference %s: %s cm", gid, path.name, {k: round(v, 2) for k, v in errors.items()})
    return rows


def evaluate(clip_id: str = "01_01", every: int = 8, garments: list[str] | None = None, bodies: dict[str, np.ndarray] = BODIES,
             methods: dict[str, DrapeOptions] = METHODS, models: LearnedModels | None = None) -> list[Row]:
    """Every (body, garment, method): collisions before/after the guard and energies per frame.
    models: the learned-model registry (default: the shipped ``assets/models``)."""
    inputs = Inputs.load(clip_id)
    body, catalog, clip, neutral = inputs.body, inputs.catalog, inputs.clip, inputs.neutral
    rows = []
    for body_name, phenotypes in bodies.items():
        shape, motion = shaped_motion(body, clip, phenotypes)
        _, transforms = body.pose(shape.rest_bone_poses, motion.rotations[None, ::every], motion.translation[None, ::every])
        body_sub = body.skin(shape.rest_vertices, transforms)  # (1, T', Vb, 3)
        for gid in garments or catalog.ids():
            asset = catalog.get(gid)
            cloth = ClothGeometry.from_asset(asset, torch.float32)
            for method, options in methods.items():
                t0 = time.perf_counter()
                raw = drape(body, shape, motion, [asset], _with(options, guard=False), neutral=neutral, models=models).garments[0].vertices
                guarded = drape(body, shape, motion, [asset], _with(options, guard=True), neutral=neutral, models=models).garments[0].vertices
                before = collision_rates(raw[None, ::every], body_sub, body.faces)
                after = collision_rates(guarded[None, ::every], body_sub, body.faces)
                energies = per_frame_energies(cloth, raw, clip.fps)
                rows.append(Row(body_name, gid, method, len(raw), body_sub.shape[1], before, after, energies, time.perf_counter() - t0))
                log.info("%s %s %s: inside %.3f%% -> %.3f%% (clean %.3f -> %.3f); E %s (%.0f s)", body_name, gid, method,
                         before["inside_pct"], after["inside_pct"], before["inside_pct_clean"], after["inside_pct_clean"],
                         {k: round(v, 4) for k, v in energies.items()}, rows[-1].seconds)
            group = rows[-len(methods):]  # gravity relative to the retarget's (the body's own motion cancels)
            g0 = next((r.energies_j["gravity"] for r in group if r.method == "retarget"), 0.0)
            for r in group:
                r.energies_j["gravity"] -= g0
    return rows


def _with(options: DrapeOptions, **changes) -> DrapeOptions:
    return options.replace(**changes)


# ---------------------------------------------------------------------------------- static fit
def build_static_reference(garment: str, shapes: int = 20, max_steps: int | None = None) -> Path:
    """Quasi-static drapes (``training.simulate.quasi_static_drape``) of ``garment`` on ``shapes``
    held-out adult shapes (seed ``STATIC_SEED``, uniform, no corners); writes
    ``build/reference/<garment>_static.npz`` (phenotypes, vertices, residual forces)."""
    from training.simulate import SolverSettings, quasi_static_drape

    body = BodyModel.load()
    asset = GarmentCatalog.load().get(garment)
    phen = sample_adult_phenotypes(shapes, np.random.default_rng(STATIC_SEED), corners=False)
    settings = SolverSettings()
    verts, forces = [], []
    for i, p in enumerate(phen):
        t0 = time.perf_counter()
        x, solves = quasi_static_drape(asset, body, p, settings)
        verts.append(x)
        forces.append(solves[-1].max_force_n if solves else float("nan"))
        log.info("%s static %d/%d: %d solves, last max force %.4f N, %.0f s", garment, i + 1, len(phen), len(solves), forces[-1], time.perf_counter() - t0)
    REFERENCE_DIR.mkdir(parents=True, exist_ok=True)
    path = REFERENCE_DIR / f"{garment}_static.npz"
    np.savez(path, phenotypes=phen, vertices=np.stack(verts).astype(np.float32), max_force_n=np.asarray(forces, np.float32))
    return path


def evaluate_static(garments: list[str], models: LearnedModels | None = None) -> list[StaticRow]:
    """Mean vertex error (cm) of the learned fit (retarget + R_G) and of the retarget against the
    quasi-static drapes of ``build/reference/<garment>_static.npz``, rest pose."""
    body = BodyModel.load()
    catalog = GarmentCatalog.load()
    models = models or default_models()
    rows = []
    for gid in garments:
        path = REFERENCE_DIR / f"{gid}_static.npz"
        if not path.exists():
            continue
        with np.load(path, allow_pickle=False) as z:
            phen, ref, force = z["phenotypes"], z["vertices"], z["max_force_n"]
        asset = catalog.get(gid)
        shape = body.shape(phen)
        retarget = asset.retarget_fit(body.hm08_vertices(shape))
        learned = retarget + models.get(gid).fit(phen)
        rows.append(StaticRow(gid, len(phen), float(np.linalg.norm(learned - ref, axis=-1).mean() * 100), float(np.linalg.norm(retarget - ref, axis=-1).mean() * 100),
                              float(np.median(force))))
    return rows


# ------------------------------------------------------------------------------ settle check
def settle_check(garment: str = "dress", clip_id: str = "walk", move_frames: int = 60, hold_frames: int = 45, models: LearnedModels | None = None) -> SettleResult:
    """Learned dynamics after the body stops: ``move_frames`` of the clip, then its last pose held
    for ``hold_frames``; the hem (lowest 5 % of the rest garment) speed per frame, mm/frame, in the
    body's frame (the body is still, so world = body frame)."""
    body = BodyModel.load()
    asset = GarmentCatalog.load().get(garment)
    shape, m = shaped_motion(body, ClipLibrary().load(clip_id), NEUTRAL_PHENOTYPES)
    rot = np.concatenate([m.rotations[:move_frames], np.repeat(m.rotations[move_frames - 1 : move_frames], hold_frames, 0)])
    trans = np.concatenate([m.translation[:move_frames], np.repeat(m.translation[move_frames - 1 : move_frames], hold_frames, 0)])
    out = drape(body, shape, PoseSequence(rot, trans, m.fps), [asset], _with(METHODS["learned"], guard=False), models=models).garments[0].vertices
    z = asset.rest_vertices[:, 2]
    hem = z <= np.quantile(z, 0.05)
    speed = np.linalg.norm(np.diff(out[:, hem], axis=0), axis=-1).mean(axis=1) * 1000.0  # (T-1,) mm per frame
    return SettleResult(move_frames, [float(s) for s in speed[move_frames - 1 :]])


# ---------------------------------------------------------------------------------- the report
def markdown(rows: list[Row], static: list[StaticRow], settle: SettleResult | None, command: str, every: int,
             references: list[ReferenceRow] = ()) -> str:
    lines = [f"Command: `{command}`", ""]
    lines += [
        "| body | garment | method | inside before guard (all / clean) % | inside after guard (all / clean) % | strain J | bending J | gravity J | inertia J |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        e = r.energies_j
        lines.append(f"| {r.body} | {r.garment} | {r.method} | {r.before['inside_pct']:.3f} / {r.before['inside_pct_clean']:.3f} | "
                     f"{r.after['inside_pct']:.3f} / {r.after['inside_pct_clean']:.3f} | {e['strain']:.4f} | {e['bending']:.5f} | "
                     f"{e['gravity']:+.4f} | {e['inertia']:.5f} |")
    if rows:
        lines += ["", f"Energies: mean per frame over all {rows[0].frames} frames, before the guard, the garment's physical material "
                  "(SNUG §5.3.1); gravity relative to the retarget's on the same frames. Collisions: every "
                  f"{every}th frame ({rows[0].collision_frames} frames)."]
    if references:
        names = list(references[0].error_cm)
        lines += ["", "Mean vertex error against the physics reference (`training.simulate`, neutral body, after the guard):", "",
                  "| garment | clip frames | " + " | ".join(f"{n} cm" for n in names) + " | reference residual force (median of max) N |",
                  "|---|---|" + "---|" * len(names) + "---|"]
        lines += [f"| {r.garment} | {r.start}-{r.start + r.frames - 1} | " + " | ".join(f"{r.error_cm[n]:.2f}" for n in names) + f" | {r.residual_force_n:.4f} |"
                  for r in references]
    if static:
        lines += ["", "Fit regressor against quasi-static drapes (rest pose, held-out shapes):", "",
                  "| garment | shapes | learned fit error cm | retarget error cm | reference residual force (median of max) N |", "|---|---|---|---|---|"]
        lines += [f"| {s.garment} | {s.shapes} | {s.learned_cm:.2f} | {s.retarget_cm:.2f} | {s.residual_force_n:.4f} |" for s in static]
    if settle is not None:
        sp = settle.hem_speed_mm_per_frame
        picks = [k for k in (0, 1, 2, 5, 10, 20, 30, 44) if k < len(sp)]
        lines += ["", f"Settle check (dress, walk for {settle.stop_frame} frames then still; learned dynamics): hem speed, mm per frame, "
                  "k frames after the stop:", "", "| " + " | ".join(f"k={k}" for k in picks) + " |", "|" + "---|" * len(picks),
                  "| " + " | ".join(f"{sp[k]:.2f}" for k in picks) + " |"]
    return "\n".join(lines)


BEGIN, END = "<!-- training.evaluate: begin -->", "<!-- training.evaluate: end -->"


def write_section(path: Path, text: str) -> None:
    """Replace the generated section of ``path`` (between the BEGIN/END markers) or append it."""
    doc = path.read_text() if path.exists() else "# Evaluation\n"
    block = f"{BEGIN}\n{text}\n{END}"
    if BEGIN in doc and END in doc:
        doc = doc[: doc.index(BEGIN)] + block + doc[doc.index(END) + len(END) :]
    else:
        doc = doc.rstrip() + "\n\n## Learned model against the baselines and the physics reference (issue 3)\n\n" + block + "\n"
    path.write_text(doc)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--clip", default="01_01")
    p.add_argument("--every", type=int, default=8, help="collision test on every n-th frame")
    p.add_argument("--garments", nargs="*")
    p.add_argument("--bodies", nargs="*", choices=list(BODIES), help="default: all")
    p.add_argument("--reference-static", type=int, metavar="SHAPES", help="first build the quasi-static references with this many shapes")
    p.add_argument("--reference-only", action="store_true", help="only build the references (with --reference-static)")
    p.add_argument("--no-settle", action="store_true")
    p.add_argument("--models", type=Path, help="learned models directory (default: assets/models)")
    p.add_argument("--write", type=Path, help="write the tables into this Markdown file (its generated section)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    garments = args.garments or GarmentCatalog.load().ids()
    if args.reference_static:
        for g in garments:
            build_static_reference(g, args.reference_static)
    if args.reference_only:
        return
    bodies = {k: BODIES[k] for k in args.bodies} if args.bodies else BODIES
    models = LearnedModels(args.models) if args.models else None
    rows = evaluate(args.clip, args.every, garments, bodies, models=models)
    static = evaluate_static(garments, models)
    references = reference_errors(args.clip, garments, models=models)
    settle = None if args.no_settle or "dress" not in garments else settle_check(models=models)
    command = "python -m training.evaluate " + " ".join(argv if argv is not None else __import__("sys").argv[1:])
    text = markdown(rows, static, settle, command, args.every, references)
    print(text)
    if args.write:
        write_section(args.write, text)


if __name__ == "__main__":
    main()
