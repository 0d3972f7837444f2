"""A wider output basis for the wrinkle GRU: manifold harmonics + collision-correction modes.

R_L's displacements live in the span of K smooth manifold harmonics per coordinate
(``training.models.OutputBasis``); the corrections that make a drape collision-free (the guard
and exact repair of the runtime, ``inference.guard``, ``inference.repair``) are local, and only
~30 % of their squared norm lies in that span (docs/archive/evaluation-ch4-ch5.md, session 8). Here:

1. ``correction_modes``: drape the garment with the learned model on clips other than 01_01 and
   several bodies, take the correction d = guarded - raw of every n-th frame, map it to the rest
   pose by the inverse of each vertex's blended skinning transform, d_rest = M_v^-1 d with
   M_v = sum_j w_vj R_j (thesis eq. 4.3), and keep the first principal components (SVD of the
   stacked 3V vectors, not centred).
2. ``extend_checkpoint``: append the x, y and z parts of those modes as basis columns,
   orthogonalised against the harmonics and scaled to unit RMS like them; the head's new rows
   start at 0, so the extended model's output equals the original's until it is trained.
3. ``truncate_checkpoint``: after training, keep rank r of the appended block: with A the head's
   rows for those columns (weights and bias of the three coordinates side by side), A = U S V^T,
   columns Q U_r and head rows U_r^T A (the output changes only by the dropped singular values).

Run (the v6 jacket, session 8):
    python -m training.correction_modes modes --garment jacket --models <v5 models dir> --out build/modes_jacket.npy
    python -m training.correction_modes extend --modes build/modes_jacket.npy --count 64 \\
        --checkpoint build/models/jacket/wrinkle.pt --out build/ck/jacket_init.pt
    python -m training.train_wrinkle --garment jacket --init build/ck/jacket_init.pt --exact-inside 1 --window 12 ...
    python -m training.correction_modes truncate --checkpoint <trained wrinkle.pt> --keep 192 --rank 136 --out <wrinkle.pt>
Units: metres.
"""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np
import torch

log = logging.getLogger(__name__)

# Clips of the modes, in this order (the v6 jacket's): never 01_01 (the spec's test sequence).
# walk = CMU 02_01, run = 02_03 (training clips), dance = CMU 131_03.
MODE_CLIPS = ("walk", "dance", "run")
# Bodies of the modes: the evaluation's five (neutral and four corners of the adult box).
MODE_EVERY = 6


def _rest_corrections(inputs, garment: str, phenotypes: np.ndarray, every: int, models=None) -> np.ndarray:
    """Guard + repair corrections of the learned drape on ``inputs.clip`` (``Inputs``), rest-pose
    frame: (T', V, 3) metres."""
    from inference.pipeline import DrapeOptions, drape
    from training.evaluate_collisions import shaped_motion

    body, asset = inputs.body, inputs.catalog.get(garment)
    shape, motion = shaped_motion(body, inputs.clip, phenotypes)
    # the learned model, named (not the garment's default); shaped_motion has lifted the arms already
    options = DrapeOptions(fit="learned", dynamics="learned", lift_arms=False)
    raw = drape(body, shape, motion, [asset], options.replace(guard=False), neutral=inputs.neutral, models=models).garments[0].vertices[::every]
    guarded = drape(body, shape, motion, [asset], options, neutral=inputs.neutral, models=models).garments[0].vertices[::every]
    _, transforms = body.pose(shape.rest_bone_poses, motion.rotations[None, ::every], motion.translation[None, ::every])
    blend = np.einsum("vj,tjab->tvab", asset.skin_weights.astype(np.float64), transforms[0, :, :, :3, :3].astype(np.float64))
    return np.linalg.solve(blend, (guarded - raw).astype(np.float64)[..., None])[..., 0]


def correction_modes(garment: str, count: int = 128, clips: tuple[str, ...] = MODE_CLIPS, every: int = MODE_EVERY, models=None) -> np.ndarray:
    """First ``count`` principal components of the rest-pose corrections of the learned model in
    ``models`` (``inference.learned.LearnedModels``; default: the shipped one), (count, V * 3) float32."""
    from training.evaluate import BODIES
    from training.evaluate_collisions import Inputs

    if "01_01" in clips:
        raise ValueError("01_01 is the spec's test sequence: never derive model parameters from it")
    fields = []
    for clip_id in clips:
        inputs = Inputs.load(clip_id)
        for name, phenotypes in BODIES.items():
            d = _rest_corrections(inputs, garment, phenotypes, every, models)
            fields.append(d.reshape(len(d), -1))
            log.info("%s %s %s: %d correction fields", garment, clip_id, name, len(d))
    _, s, vt = np.linalg.svd(np.concatenate(fields), full_matrices=False)
    log.info("%d fields; first singular values %s", sum(len(f) for f in fields), np.round(s[:5], 3))
    return vt[:count].astype(np.float32)


def extend_checkpoint(ck: dict, modes: np.ndarray) -> dict:
    """Wrinkle checkpoint dict with its basis extended by the x, y, z parts of ``modes`` (M, V*3)."""
    basis = np.asarray(ck["basis"], np.float64)
    V, K = basis.shape
    m = np.asarray(modes, np.float64).reshape(len(modes), V, 3)
    extra = np.concatenate([m[:, :, 0], m[:, :, 1], m[:, :, 2]]).T  # (V, 3M)
    hq, _ = np.linalg.qr(basis)
    extra = extra - hq @ (hq.T @ extra)
    q, r = np.linalg.qr(extra)
    diag = np.abs(np.diag(r))
    q = q[:, diag > 1e-6 * diag.max()] * np.sqrt(V)  # unit RMS columns, like the harmonics
    new = np.concatenate([basis, q], 1).astype(np.float32)
    return _with_basis(ck, new, _pad_head(ck["state_dict"], K, new.shape[1]))


def truncate_checkpoint(ck: dict, keep: int, rank: int) -> tuple[dict, float]:
    """Checkpoint dict with basis columns beyond ``keep`` reduced to ``rank`` (module doc, step 3);
    returns it and the fraction of the block's squared singular values kept."""
    basis = np.asarray(ck["basis"], np.float64)
    V, K = basis.shape
    sd = ck["state_dict"]
    w = sd["head.weight"].double().numpy().reshape(K, 3, -1)  # head rows k * 3 + coordinate
    b = sd["head.bias"].double().numpy().reshape(K, 3)
    a = np.concatenate([w[keep:, d, :] for d in range(3)] + [b[keep:]], 1)
    u, s, _ = np.linalg.svd(a, full_matrices=False)
    ur = u[:, :rank]
    new_basis = np.concatenate([basis[:, :keep], basis[:, keep:] @ ur], 1).astype(np.float32)
    new_w = np.concatenate([w[:keep], np.einsum("er,edh->rdh", ur, w[keep:])]).reshape(-1, w.shape[-1])
    new_b = np.concatenate([b[:keep], ur.T @ b[keep:]]).reshape(-1)
    state = dict(sd, **{"head.weight": torch.as_tensor(new_w, dtype=torch.float32), "head.bias": torch.as_tensor(new_b, dtype=torch.float32)})
    return _with_basis(ck, new_basis, state), float((s[:rank] ** 2).sum() / (s ** 2).sum())


def _pad_head(sd: dict, old: int, new: int) -> dict:
    w, b = sd["head.weight"], sd["head.bias"]
    return dict(sd, **{"head.weight": torch.cat([w, torch.zeros(3 * (new - old), w.shape[1])]), "head.bias": torch.cat([b, torch.zeros(3 * (new - old))])})


def _with_basis(ck: dict, basis: np.ndarray, state: dict) -> dict:
    from training.models import OutputBasis

    state = dict(state, **{"output.basis": OutputBasis(basis).basis.clone()})  # pre-multiplied by the coefficient unit
    return dict(ck, basis=basis, state_dict=state)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)
    m = sub.add_parser("modes", help="principal components of the guard's corrections")
    m.add_argument("--garment", required=True)
    m.add_argument("--count", type=int, default=128)
    m.add_argument("--out", type=Path, required=True)
    m.add_argument("--models", type=Path, help="learned models directory whose corrections are taken (default: assets/models; the v6 garments: the model each was widened from)")
    e = sub.add_parser("extend", help="append correction modes to a wrinkle checkpoint's basis")
    e.add_argument("--modes", type=Path, required=True)
    e.add_argument("--count", type=int, default=64)
    t = sub.add_parser("truncate", help="reduce the appended columns of a trained checkpoint to a rank")
    t.add_argument("--keep", type=int, default=192, help="leading basis columns kept as they are (the harmonics)")
    t.add_argument("--rank", type=int, required=True)
    for q in (e, t):
        q.add_argument("--checkpoint", type=Path, required=True)
        q.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    if args.command == "modes":
        args.out.parent.mkdir(parents=True, exist_ok=True)
        from inference.learned import LearnedModels

        np.save(args.out, correction_modes(args.garment, args.count, models=LearnedModels(args.models) if args.models else None))
        return
    ck = torch.load(args.checkpoint, weights_only=False, map_location="cpu")
    if args.command == "extend":
        out = extend_checkpoint(ck, np.load(args.modes, allow_pickle=False)[: args.count])
    else:
        out, kept = truncate_checkpoint(ck, args.keep, args.rank)
        out["record"] = dict(out["record"], output_truncation={"keep": args.keep, "rank": args.rank, "singular_energy_kept": kept})
        log.info("kept %.6f of the squared singular values", kept)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    torch.save(out, args.out)
    log.info("%s: basis %s -> %s", args.out, np.asarray(ck["basis"]).shape, out["basis"].shape)


if __name__ == "__main__":
    main()
