"""Train the wrinkle GRU R_L (thesis ch. 4.2.3) self-supervised with the SNUG loss (ch. 5.2.3-5.2.5).

    x_t = W( retarget_fit(beta) + R_G(beta) + R_L(beta, gamma_1..t), beta, theta_t, W_c )   (eq. 4.2-4.3)
    L   = L_inertia(x_2; x_1, x_0) + sum_t L_static(x_t; posed body at t)          (eq. 5.5-5.12)

SNUG protocol (§5.2.5, §5.3.1): 3-frame windows of CMU clips on the neutral body, each paired
with a new random shape from the bank (the root translation scaled to that body's legs), GRU
initial state h0 ~ N(0, 0.1), batch 16, Adam lr 1e-3 then 1e-4 in SNUG; here 3e-4 then 3e-5, because
the collision term of the loss is 400x stiffer than SNUG's (``training.physics.TRAIN_K_COLLISION``)
and continued linearly beyond 5 mm of depth (LBS squeezes cannot be freed; measured on the
T-shirt, 6 min: lr 1e-3 diverged, the uncapped cubic left 5.7 % of vertex-frames inside on 02_02
vs 3.6 % capped; fit-only 3.8 %). R_G is the frozen fit
regressor (``build/models/<garment>/fit.pt`` from ``training.train_fit``). Skinning uses the
garment's own weights (the dress: its diffused weights, as they are). Collision candidates are
the KD-tree candidates of the shape bank in the rest pose (``training.datasets.ShapeBank``):
the closest of the k rest-pose neighbours is taken in the posed frame.

Training clips: ``training.datasets.TRAIN_CLIPS`` (never 01_01 or 131_03); validation: 02_02, run as one
sequence from h0 = 0 on held-out shapes, energies per frame against the fit-only baseline
(R_L = 0).

Run (writes build/models/<garment>/wrinkle.pt with its config and metrics):
    python -m training.train_wrinkle --garment tshirt --minutes 8
    python -m training.train_wrinkle --garment tshirt --smoke     # CI: a few steps
    python -m training.train_wrinkle --garment tshirt --device cuda --pose-workers 4 --init <wrinkle.pt>
    python -m training.train_wrinkle --garment tshirt --exact-inside 1 --window 12   # the evaluation's inside test in the loss
    python -m training.train_wrinkle --garment tshirt --device cuda --exact-inside 1 --window 12 --pose-workers 1 --inside-workers 3
On a GPU the model, the loss and the collision-candidate search run there (~0.14 s per step on
an H100 with five runs sharing it, against ~0.9 s on one core here); the numpy posing of the
windows (FK, arm lifting) runs in ``--pose-workers`` forked processes, ahead of the steps, in the
sequential order; ``--inside-workers`` splits the exact inside test of each step (numpy, ~2 s for
a 12-frame batch on one core here) by windows over forked processes (measured with ``--exact-inside 1
--window 12``: ~1.4 s per step with three runs sharing an H100, one pose and three inside workers
each, against ~4.5 s on one core here). ``tools/device_checkpoints.py`` packs checkpoints to move them to such a machine.
"""
from __future__ import annotations

import logging
import time
import multiprocessing
from collections import deque
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
import torch

from inference.body import NEUTRAL_PHENOTYPES, BodyModel
from inference.garment import GarmentCatalog
from training.datasets import (
    CACHE_DIR,
    TRAIN_CLIPS,
    VALIDATION_CLIP,
    WINDOW_FRAMES,
    N_CORNERS,
    MotionBank,
    ShapeBank,
    harmonic_basis,
    WindowLifter,
    pose_windows,
    sample_adult_phenotypes,
)
from training.candidates import candidates
from training.cli import run as run_cli
from training.manifest import git_commit
from training.models import WrinkleGRU
from training.physics import TRAIN_K_COLLISION, ClothGeometry, body_signed_distances, energy_terms, inertia_energy
from training.train_fit import CHECKPOINT_DIR, load_fit

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class WrinkleConfig:
    """One wrinkle-GRU training run (saved with the model)."""

    garment: str = "tshirt"
    minutes: float = 8.0  # wall-clock training budget (banks not counted)
    max_steps: int = 100_000
    bank_shapes: int = 256  # training shapes: 64 box corners + uniform (a new one per window)
    corner_fraction: float | None = None  # share of windows drawn from the 64 box corners (None: uniform over the bank, 64/256)
    candidates: int = 8  # KD-tree collision candidates per garment vertex
    k_collision: float | None = TRAIN_K_COLLISION  # eq. 5.12 stiffness of the training loss, J/m^3 (None: the material's)
    collision_cap_m: float | None = 0.005  # training loss: collision penalty linear beyond this depth (ClothGeometry.with_collision_stiffness)
    collision_margin_m: float | None = None  # training loss: eps of eq. 5.12, m (None: the material's 2 mm)
    basis_size: int = 192  # manifold harmonics of the output basis
    hidden: int = 256  # GRU width (SNUG §5.2.5: 4 GRUs of 256, tanh)
    layers: int = 4
    h0_std: float = 0.1  # h0 ~ N(0, 0.1) per window (SNUG §5.2.5)
    batch_size: int = 16  # windows per step (SNUG §5.3.1)
    window_frames: int = WINDOW_FRAMES  # frames per window (SNUG: 3; the loss of eq. 5.5 over frames 0..T-1)
    lr: float = 3e-4  # Adam, then lr_final after lr_drop of the budget (SNUG §5.3.1: 1e-3, 1e-4; with the stiff
    lr_final: float = 3e-5  # collision term 1e-3 diverged after ~4 min, measured on the T-shirt)
    lr_drop: float = 0.7
    grad_clip: float = 1.0  # global gradient-norm clip (energy spikes from deep collisions)
    clips: tuple[str, ...] = TRAIN_CLIPS
    validation_clip: str = VALIDATION_CLIP
    validation_shapes: int = 4  # neutral + held-out uniform shapes
    validation_frames: int = 120  # first frames of the validation clip
    max_clip_frames: int | None = None  # truncate clips (smoke runs)
    fresh_candidates: bool = True  # re-select collision candidates in every posed frame (``training.candidates``)
    exact_inside: bool = False  # collision loss: vertices inside the closed posed skin by the exact winding number pulled to their closest skin vertex (physics.collision_energy)
    lift_arms: bool = True  # train on the poses the service drapes: arms lifted out of the torso (inference.motion.self_contact)
    init: str | None = None  # warm start: a wrinkle.pt checkpoint to continue from (its wall time is added)
    seed: int = 0
    threads: int = 1
    device: str = "cpu"  # torch device of the model and the loss ("cuda": the banks and poses stay numpy on the CPU)
    pose_workers: int = 0  # processes that pose the next batches (FK, arm lifting) while this one trains (0: in turn)
    inside_workers: int = 0  # processes that split the exact inside test of each step by windows (0: in this one)
    log_every: int = 25


def draw_shapes(rng: np.random.Generator, bank_size: int, n: int, corner_fraction: float | None = None) -> np.ndarray:
    """n bank indices, one per window: uniform over the bank, or, with ``corner_fraction``, a box
    corner (the bank's first ``N_CORNERS`` shapes, ``sample_adult_phenotypes``) with that
    probability and a uniform non-corner shape otherwise (the extremes are where the collisions are)."""
    if corner_fraction is None:
        return rng.integers(0, bank_size, n)
    if not 0.0 <= corner_fraction <= 1.0 or bank_size <= N_CORNERS:
        raise ValueError(f"corner_fraction {corner_fraction} needs 0..1 and a bank of more than {N_CORNERS} shapes, got {bank_size}")
    corner = rng.random(n) < corner_fraction
    return np.where(corner, rng.integers(0, N_CORNERS, n), rng.integers(N_CORNERS, bank_size, n))


def skin_torch(rest: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """LBS in torch (thesis eq. 4.3): x[n, v] = sum_j w[v, j] T[n, j] rest[n, v].

    rest : (N, V, 3) metres ; weights : (V, J) ; transforms : (N, J, 4, 4) (rows 0-2 used)
    returns (N, V, 3)
    """
    N, J = transforms.shape[:2]
    # M[n, v, i, k] = sum_j w[v, j] T[n, j, i, k]
    M = torch.matmul(weights, transforms[:, :, :3, :].reshape(N, J, 12)).reshape(N, -1, 3, 4)
    return torch.einsum("nvik,nvk->nvi", M[..., :3], rest) + M[..., 3]


def skin_points_and_normals_torch(points: torch.Tensor, normals: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``inference.body.skin_points_and_normals`` in torch: points by the blended transforms,
    normals by the blended rotations, renormalised. points, normals (N, V, 3) ; weights (V, J) ;
    transforms (N, J, 4, 4) ; returns (N, V, 3) x 2."""
    rotations = transforms.clone()
    rotations[..., :3, 3] = 0.0
    n = skin_torch(normals, weights, rotations)
    return skin_torch(points, weights, transforms), n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def posed_body_torch(bank: ShapeBank, shape_idx: np.ndarray, transforms: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Kept body vertices and unit normals of bank shapes posed by ``transforms`` (B, T, J, 4, 4),
    returns (B*T, M, 3) x 2."""
    B, T = transforms.shape[:2]
    pts = torch.as_tensor(bank.body_points[shape_idx])[:, None].expand(-1, T, -1, -1).reshape(B * T, -1, 3)
    nrm = torch.as_tensor(bank.body_normals[shape_idx])[:, None].expand(-1, T, -1, -1).reshape(B * T, -1, 3)
    return skin_points_and_normals_torch(pts, nrm, torch.as_tensor(bank.body_weights), transforms.reshape(B * T, *transforms.shape[2:]))


@dataclass
class WindowBatch:
    """Tensors of one batch of B windows of T frames (see ``make_batch``)."""

    phenotypes: torch.Tensor  # (B, 6)
    gamma: torch.Tensor  # (B, T, F)
    fitted: torch.Tensor  # (B, V, 3) unposed retarget + R_G
    transforms: torch.Tensor  # (B, T, J, 4, 4)
    body_points: torch.Tensor  # (B*T, M, 3)
    body_normals: torch.Tensor  # (B*T, M, 3)
    candidates: torch.Tensor  # (B*T, V, k) int64

    def to(self, device: torch.device | str) -> "WindowBatch":
        """The same batch on ``device``."""
        return WindowBatch(*(getattr(self, f.name).to(device) for f in fields(self)))


def make_batch(body: BodyModel, bank: ShapeBank, fitted: np.ndarray, motions: MotionBank, shape_idx: np.ndarray, frames: np.ndarray,
               lifter: WindowLifter | None = None) -> WindowBatch:
    """Pose windows ``frames`` (B, T) on bank shapes ``shape_idx`` (B,) (numpy FK, torch LBS),
    with the arms lifted out of the torso by ``lifter`` (as at runtime) when given."""
    return batch_from_poses(bank, fitted, shape_idx, *pose_windows(body, bank, shape_idx, motions, frames, lifter))


def batch_from_poses(bank: ShapeBank, fitted: np.ndarray, shape_idx: np.ndarray, transforms: np.ndarray, gamma: np.ndarray) -> WindowBatch:
    """The batch of windows posed by ``training.datasets.pose_windows`` (transforms (B, T, J, 4, 4), gamma (B, T, F))."""
    T = transforms.shape[1]
    tf = torch.as_tensor(transforms)
    bp, bn = posed_body_torch(bank, shape_idx, tf)
    cand = torch.as_tensor(bank.candidates[shape_idx].astype(np.int64))
    cand = cand[:, None].expand(-1, T, -1, -1).reshape(-1, *cand.shape[1:])
    return WindowBatch(torch.as_tensor(bank.phenotypes[shape_idx]), torch.as_tensor(gamma), torch.as_tensor(fitted[shape_idx]), tf, bp, bn, cand)


# (body, bank, motions, lifter) of the run, inherited by forked pose workers (``_pose_job``)
_POSE_CONTEXT: tuple | None = None


def _pose_job(shape_idx: np.ndarray, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    body, bank, motions, lifter = _POSE_CONTEXT
    return pose_windows(body, bank, shape_idx, motions, frames, lifter)


def _inside_job(shape_idx: np.ndarray, transforms: np.ndarray, points: np.ndarray) -> np.ndarray:
    body, bank, _, _ = _POSE_CONTEXT
    return bank.inside_mask(body, shape_idx, transforms, points)


def inside_of_batch(bank: ShapeBank, body: BodyModel, shape_idx: np.ndarray, transforms: np.ndarray, points: np.ndarray,
                    pool: ProcessPoolExecutor | None, parts: int) -> np.ndarray:
    """``ShapeBank.inside_mask`` of a batch (windows ``shape_idx`` (B,), ``transforms`` (B, T, J, 4, 4),
    ``points`` (B*T, V, 3) metres), split by windows over ``parts`` jobs of ``pool`` (None: here)."""
    if pool is None or parts <= 1:
        return bank.inside_mask(body, shape_idx, transforms, points)
    T = transforms.shape[1]
    cuts = np.linspace(0, len(shape_idx), min(parts, len(shape_idx)) + 1).astype(int)
    jobs = [pool.submit(_inside_job, shape_idx[a:b], transforms[a:b], points[a * T:b * T]) for a, b in zip(cuts[:-1], cuts[1:])]
    return np.concatenate([j.result() for j in jobs])


def garment_frames(model: WrinkleGRU | None, batch: WindowBatch, weights: torch.Tensor, h0: torch.Tensor | None) -> torch.Tensor:
    """Posed garments (B, T, V, 3): skin(fitted + R_L) per frame (model None: R_L = 0)."""
    B, T = batch.gamma.shape[:2]
    unposed = batch.fitted[:, None].expand(-1, T, -1, -1)
    if model is not None:
        delta, _ = model(batch.phenotypes, batch.gamma, h0)
        unposed = unposed + delta
    x = skin_torch(unposed.reshape(B * T, -1, 3), weights, batch.transforms.reshape(B * T, *batch.transforms.shape[2:]))
    return x.reshape(B, T, -1, 3)


def snug_loss(cloth: ClothGeometry, x: torch.Tensor, batch: WindowBatch, dt_s: float, inside: torch.Tensor | None = None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """SNUG loss (eq. 5.5) of windows x (B, T, V, 3): L_static summed over the T frames (eq. 5.7)
    + L_inertia of every frame t >= 2 from its two predecessors (eq. 5.6); mean over the batch.
    inside: optional (B*T, V) bool, the exact inside test (``ShapeBank.inside_mask``) for the
    collision term. Returns the loss and its terms (B,) J."""
    B, T = x.shape[:2]
    flat = x.reshape(B * T, -1, 3)
    terms = {k: v.reshape(B, T).sum(1) for k, v in energy_terms(cloth, flat, batch.body_points, batch.body_normals, batch.candidates, inside=inside).items()}
    terms["inertia"] = sum(inertia_energy(cloth, x[:, t], x[:, t - 1], x[:, t - 2], dt_s) for t in range(2, T))
    return sum(terms.values()).mean(), terms


def validate(model: WrinkleGRU, cloth: ClothGeometry, body: BodyModel, bank: ShapeBank, fitted: np.ndarray, motions: MotionBank, weights: torch.Tensor, frames: int,
             fresh: bool = True, lifter: WindowLifter | None = None) -> dict:
    """Whole-sequence run (h0 = 0) of the validation clip on every bank shape: mean energy terms
    per frame (J) of the learned garment and of the fit-only baseline (R_L = 0); collision
    candidates re-selected in every posed frame when ``fresh``; arms lifted by ``lifter``."""
    T = min(frames, int(motions.clip_start[1]))
    out: dict[str, dict[str, float]] = {}
    with torch.no_grad():
        acc: dict[str, dict[str, float]] = {"learned": {}, "fit_only": {}}
        for s in range(len(bank)):
            batch = make_batch(body, bank, fitted, motions, np.array([s]), np.arange(T)[None], lifter).to(weights.device)
            for name, m in (("learned", model), ("fit_only", None)):
                x = garment_frames(m, batch, weights, model.initial_state(1).to(weights.device) if m is not None else None)
                if fresh:
                    batch.candidates = candidates(batch.body_points, x.reshape(-1, *x.shape[2:]), batch.candidates.shape[-1])
                _, terms = snug_loss(cloth, x, batch, 1.0 / motions.fps)
                for k, v in terms.items():
                    per_frame = float(v.sum()) / (T if k != "inertia" else max(T - 2, 1))
                    acc[name][k] = acc[name].get(k, 0.0) + per_frame / len(bank)
                d = body_signed_distances(x.reshape(-1, *x.shape[2:]), batch.body_points, batch.body_normals, batch.candidates)
                acc[name]["inside_fraction"] = acc[name].get("inside_fraction", 0.0) + float((d < 0).float().mean()) / len(bank)
                if bank.rest_vertices is not None:
                    exact = bank.inside_mask(body, np.array([s]), batch.transforms.cpu().numpy(), x.reshape(-1, *x.shape[2:]).cpu().numpy())
                    acc[name]["inside_fraction_exact"] = acc[name].get("inside_fraction_exact", 0.0) + float(exact.mean()) / len(bank)
        for name, terms in acc.items():
            inside = terms.pop("inside_fraction")
            exact = terms.pop("inside_fraction_exact", None)
            out[name] = {f"{k}_j_per_frame": v for k, v in terms.items()}
            out[name]["static_j_per_frame"] = sum(v for k, v in terms.items() if k != "inertia")
            out[name]["inside_fraction"] = inside  # tangent-plane d < 0 of eq. 5.12, all frames and vertices
            if exact is not None:
                out[name]["inside_fraction_exact"] = exact  # winding number >= 1 (the evaluation's test)
    out["frames"] = T
    out["shapes"] = len(bank)
    return out


def train_wrinkle(config: WrinkleConfig, smoke: bool = False, out_dir: Path = CHECKPOINT_DIR) -> dict:
    """Train R_L for ``config.garment`` on top of its frozen R_G; write ``out_dir/<garment>/wrinkle.pt``."""
    torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed)
    device = torch.device(config.device)
    rng = np.random.default_rng(config.seed)
    gen = torch.Generator().manual_seed(config.seed)
    body = BodyModel.load()
    asset = GarmentCatalog.load().get(config.garment)
    cloth = ClothGeometry.from_asset(asset, torch.float32)  # the physical material: metrics
    neutral = body.shape(NEUTRAL_PHENOTYPES[None])

    t_bank = time.perf_counter()
    fit_path = out_dir / config.garment / ("fit_smoke.pt" if smoke else "fit.pt")
    fit_model, fit_record = load_fit(fit_path)
    for p in fit_model.parameters():
        p.requires_grad_(False)
    init_ck = torch.load(Path(config.init), weights_only=False, map_location="cpu") if config.init else None
    basis = init_ck["basis"] if init_ck else harmonic_basis(asset.num_vertices, asset.edges, config.basis_size, None if smoke else CACHE_DIR / f"{config.garment}_harmonics_{config.basis_size}.npy")
    bank = ShapeBank.build(body, asset, sample_adult_phenotypes(config.bank_shapes, rng), config.candidates)
    val_phen = np.concatenate([NEUTRAL_PHENOTYPES[None], sample_adult_phenotypes(config.validation_shapes - 1, np.random.default_rng(config.seed + 2), corners=False)])
    val_bank = ShapeBank.build(body, asset, val_phen, config.candidates)

    def fitted_for(b: ShapeBank) -> np.ndarray:
        with torch.no_grad():
            return b.retarget + fit_model(torch.as_tensor(b.phenotypes)).numpy()

    fitted, val_fitted = fitted_for(bank), fitted_for(val_bank)
    motions = MotionBank.cached(config.clips, body, neutral, config.max_clip_frames)
    val_motions = MotionBank.cached((config.validation_clip,), body, neutral, config.max_clip_frames or config.validation_frames)
    bank_s = time.perf_counter() - t_bank
    log.info("%s: %d vertices; %d shapes, %d training frames (%d windows) from %s; banks in %.1f s",
             config.garment, asset.num_vertices, len(bank), len(motions.gamma), len(motions.windows), ",".join(config.clips), bank_s)

    gamma_mean, gamma_std = motions.gamma_statistics()
    model = WrinkleGRU(basis, gamma_mean, gamma_std, config.hidden, config.layers)
    init_wall_s, init_steps = 0.0, 0
    if config.init:  # warm start; keeps the checkpoint's gamma statistics
        model, init_record = wrinkle_from_checkpoint(init_ck)
        model.train()
        gamma_mean, gamma_std = model.gamma_mean.numpy(), model.gamma_std.numpy()
        init_wall_s, init_steps = init_record["train_wall_s"], init_record["steps"]
    dt_s = 1.0 / motions.fps
    lifter = WindowLifter(body, bank, motions) if config.lift_arms else None
    val_lifter = WindowLifter(body, val_bank, val_motions) if config.lift_arms else None
    pool = inside_pool = None
    global _POSE_CONTEXT
    _POSE_CONTEXT = (body, bank, motions, lifter)
    if config.pose_workers > 0:  # forked before any CUDA use; the workers only run numpy
        pool = ProcessPoolExecutor(config.pose_workers, mp_context=multiprocessing.get_context("fork"))
    if config.exact_inside and config.inside_workers > 0:
        inside_pool = ProcessPoolExecutor(config.inside_workers, mp_context=multiprocessing.get_context("fork"))
    model.to(device)
    opt = torch.optim.Adam(model.parameters(), lr=config.lr)
    weights = torch.as_tensor(asset.skin_weights.astype(np.float32)).to(device)
    cloth = cloth.to(device)
    train_cloth = cloth.with_collision_stiffness(config.k_collision, config.collision_cap_m, config.collision_margin_m)  # the training loss
    metrics: dict = {}
    if config.init:  # the starting point on this run's validation (comparable with the result)
        model.eval()
        metrics["validation_init"] = validate(model, cloth, body, val_bank, val_fitted, val_motions, weights, config.validation_frames, config.fresh_candidates, val_lifter)
        model.train()
        log.info("validation of the initial model: learned static %.5f J/frame, inside %.4f",
                 metrics["validation_init"]["learned"]["static_j_per_frame"], metrics["validation_init"]["learned"]["inside_fraction"])

    windows = motions.windows_of(config.window_frames)

    def draw() -> tuple[np.ndarray, np.ndarray]:
        starts = rng.choice(windows, config.batch_size)
        shape_idx = draw_shapes(rng, len(bank), config.batch_size, config.corner_fraction)  # a new random shape per window
        return shape_idx, motions.window_frames(starts, config.window_frames)

    # with pose workers the next batches are posed while this one trains; the batches and their
    # order are those of the sequential loop (drawn here, in order)
    pending: deque = deque()
    if pool:
        for _ in range(2 * config.pose_workers):
            shape_idx, frames = draw()
            pending.append((shape_idx, pool.submit(_pose_job, shape_idx, frames)))
    budget_s = config.minutes * 60.0
    t0 = time.perf_counter()
    step, history = 0, []
    while step < config.max_steps and time.perf_counter() - t0 < budget_s:
        progress = max((time.perf_counter() - t0) / budget_s, step / config.max_steps)
        for g in opt.param_groups:  # SNUG §5.3.1: 1e-3, then 1e-4
            g["lr"] = config.lr if progress < config.lr_drop else config.lr_final
        if pool:
            shape_idx, job = pending.popleft()
            batch = batch_from_poses(bank, fitted, shape_idx, *job.result()).to(device)
            nxt_idx, nxt_frames = draw()
            pending.append((nxt_idx, pool.submit(_pose_job, nxt_idx, nxt_frames)))
        else:
            shape_idx, frames = draw()
            batch = make_batch(body, bank, fitted, motions, shape_idx, frames, lifter)
        h0 = model.initial_state(config.batch_size, config.h0_std, gen).to(device)  # h0 ~ N(0, 0.1)
        x = garment_frames(model, batch, weights, h0)
        if config.fresh_candidates:
            batch.candidates = candidates(batch.body_points, x.reshape(-1, *x.shape[2:]), config.candidates)
        inside = None
        if config.exact_inside:  # numpy on the CPU: the posed closed skin and its winding numbers
            inside = torch.as_tensor(inside_of_batch(bank, body, shape_idx, batch.transforms.cpu().numpy(), x.detach().reshape(-1, *x.shape[2:]).cpu().numpy(),
                                                     inside_pool, config.inside_workers)).to(device)
        loss, terms = snug_loss(train_cloth, x, batch, dt_s, inside)
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
        opt.step()
        step += 1
        if step % config.log_every == 0 or step == 1:
            history.append({"step": step, "seconds": time.perf_counter() - t0, "loss_j": float(loss.detach()), **{k: float(v.detach().mean()) for k, v in terms.items()}})
            log.info("step %d %.0f s: L %.5f J (%s)", step, history[-1]["seconds"], float(loss.detach()), ", ".join(f"{k} {float(v.detach().mean()):.5f}" for k, v in terms.items()))
    wall_s = time.perf_counter() - t0
    for p in (pool, inside_pool):
        if p:
            p.shutdown(cancel_futures=True)

    model.eval()
    t_val = time.perf_counter()
    metrics["validation"] = validate(model, cloth, body, val_bank, val_fitted, val_motions, weights, config.validation_frames, config.fresh_candidates, val_lifter)
    metrics["validation"]["clip"] = config.validation_clip
    log.info("validation %s (%.0f s): learned static %.5f J/frame, inertia %.6f; fit-only static %.5f, inertia %.6f",
             config.validation_clip, time.perf_counter() - t_val,
             metrics["validation"]["learned"]["static_j_per_frame"], metrics["validation"]["learned"]["inertia_j_per_frame"],
             metrics["validation"]["fit_only"]["static_j_per_frame"], metrics["validation"]["fit_only"]["inertia_j_per_frame"])
    record = {
        "model": "wrinkle",
        "config": asdict(config),
        "smoke": smoke,
        "steps": step + init_steps,
        "train_wall_s": wall_s + init_wall_s,
        "this_run": {"steps": step, "wall_s": wall_s, "init": config.init, "init_steps": init_steps, "init_wall_s": init_wall_s},
        "bank_build_s": bank_s,
        "training_frames": int(len(motions.gamma)),
        "training_windows": int(len(motions.windows)),
        "fit_checkpoint": {"path": str(fit_path.relative_to(out_dir)) if fit_path.is_relative_to(out_dir) else str(fit_path), "git_commit": fit_record.get("git_commit")},
        "metrics": metrics,
        "history": history,
        "git_commit": git_commit(),
        "torch": torch.__version__,
    }
    path = out_dir / config.garment / ("wrinkle_smoke.pt" if smoke else "wrinkle.pt")
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"record": record, "state_dict": {k: v.cpu() for k, v in model.state_dict().items()}, "basis": basis, "gamma_mean": gamma_mean, "gamma_std": gamma_std,
                "hidden": config.hidden, "layers": config.layers}, path)
    log.info("wrote %s (%d steps, %.1f min)", path, step, wall_s / 60)
    return record


def load_wrinkle(path: Path) -> tuple[WrinkleGRU, dict]:
    """A trained R_L and its record from a ``wrinkle.pt`` checkpoint."""
    return wrinkle_from_checkpoint(torch.load(path, weights_only=False, map_location="cpu"))


def wrinkle_from_checkpoint(ck: dict) -> tuple[WrinkleGRU, dict]:
    """A trained R_L and its record from a loaded ``wrinkle.pt`` checkpoint dict."""
    model = WrinkleGRU(ck["basis"], ck["gamma_mean"], ck["gamma_std"], ck["hidden"], ck["layers"])
    model.load_state_dict(ck["state_dict"])
    return model.eval(), ck["record"]


# CI smoke run: a few steps on two short clips and a tiny bank.
SMOKE = dict(minutes=0.5, max_steps=3, bank_shapes=3, basis_size=8, hidden=16, layers=2, batch_size=2, clips=("02_03",),
             validation_shapes=1, validation_frames=6, max_clip_frames=8, log_every=1)


def main(argv: list[str] | None = None) -> None:
    run_cli(argv, __doc__.split("\n")[0], WrinkleConfig, train_wrinkle, SMOKE, "a few steps on a tiny bank and a short clip (CI); needs fit_smoke.pt", CHECKPOINT_DIR)


if __name__ == "__main__":
    main()
