"""Train the fit regressor R_G (thesis ch. 4.2.2) self-supervised on the static energy (SNUG ch. 5.2.4).

    min_theta  E_shape [ L_strain + L_bending + L_gravity + L_collision ]   (eq. 5.7, no inertia)
    x(beta) = retarget_fit(beta) + R_G(beta; theta)     (garment on the shaped body, rest A-pose)

Shapes are drawn uniformly over the adult phenotype box, its 64 corners included, from a bank
precomputed once (``training.datasets.ShapeBank``): the retarget fit, the shaped body near the
garment, its normals and the KD-tree collision candidates of every shape. 20 other shapes
(another seed) are held out for the metrics.

Run (one garment; writes build/models/<garment>/fit.pt with its config and metrics):
    python -m training.train_fit --garment tshirt --minutes 8
    python -m training.train_fit --garment tshirt --smoke      # CI: a few steps, tiny bank
Then ``python -m training.train_wrinkle`` and ``python -m training.export_onnx``.
"""
from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from inference.body import BodyModel
from inference.fit_basis import farthest_nodes, geodesic_rbf_basis
from inference.garment import GarmentCatalog
from inference.metrics import inside_mask
from training.datasets import CACHE_DIR, REPO_ROOT, ShapeBank, harmonic_basis, sample_adult_phenotypes
from training.candidates import candidates
from training.cli import run as run_cli
from training.manifest import git_commit
from training.models import FitRegressor
from training.physics import TRAIN_K_COLLISION, ClothGeometry, body_signed_distances, energy_terms
from training.reference import waistband_vertices

log = logging.getLogger(__name__)

CHECKPOINT_DIR = REPO_ROOT / "build" / "models"


@dataclass(frozen=True)
class FitConfig:
    """One fit-regressor training run (saved with the model)."""

    garment: str = "tshirt"
    minutes: float = 8.0  # wall-clock training budget (the bank build is not counted)
    max_steps: int = 100_000  # stop earlier than the budget after this many steps
    bank_shapes: int = 512  # training shapes: the 64 box corners + uniform samples in the adult box
    eval_shapes: int = 20  # held-out uniform shapes (seed + 1) for the metrics
    candidates: int = 8  # KD-tree collision candidates per garment vertex (eq. 5.12's d(x))
    k_collision: float | None = TRAIN_K_COLLISION  # eq. 5.12 stiffness of the training loss, J/m^3 (None: the material's)
    collision_cap_m: float | None = None  # training loss: collision penalty linear beyond this depth, m (None: cubic)
    collision_margin_m: float | None = None  # training loss: eps of eq. 5.12, m (None: the material's 2 mm)
    basis_size: int = 128  # output basis size (training.models.OutputBasis): harmonics, or nodes of the geodesic basis
    basis: str = "harmonics"  # "harmonics" (ships in fit.onnx) or "geodesic" (inference.fit_basis: only node ids and sigma ship)
    hidden: int = 128  # MLP width (thesis ch. 4.3: one hidden layer of 20 was enough with supervision)
    layers: int = 2  # hidden layers
    batch_size: int = 16  # shapes per step
    lr: float = 1e-4  # Adam, first phase (SNUG's 1e-3 diverged with the stiff collision term: measured)
    lr_final: float = 3e-5  # Adam after ``lr_drop`` of the budget (SNUG §5.3.1: 1e-3 then 1e-4)
    lr_drop: float = 0.7  # fraction of the budget (time or steps) after which lr = lr_final
    grad_clip: float = 1.0  # global gradient-norm clip against deep-collision batches (cubic penalty,
    # k = 1e5), as in the GRU. It does not make a continued training stable: with and without it,
    # continuing a trained T-shirt or dress fit at 1e-3 or 3e-4 diverged after 200-1400 steps
    # (measured); the v3 T-shirt and jacket fits trained from scratch at 1e-3 -> 1e-4 in 10 min.
    fresh_candidates: bool = True  # re-select the collision candidates at the current prediction every step
    pin_waistband: float = 0.0  # N/m: a spring per waistband vertex (training.reference.waistband_vertices) holding a bottom's waist on the retarget fit, as the newton reference pins it (0: free)
    exact_inside: bool = False  # collision loss: vertices inside the closed rest skin by the exact winding number pulled to their closest skin vertex (physics.collision_energy)
    init: str | None = None  # warm start: a fit.pt checkpoint to continue from (its wall time is added)
    seed: int = 0
    threads: int = 1  # torch intra-op threads (the CPU is shared)
    device: str = "cpu"  # torch device of the model and the loss (the held-out evaluation runs on the CPU)
    log_every: int = 50


def exact_inside(bank: ShapeBank, faces: np.ndarray, shape_idx: np.ndarray, x: torch.Tensor) -> torch.Tensor:
    """Garment vertices x (B, V, 3) inside the closed shaped rest skin of bank shapes ``shape_idx``
    (B,) by the winding number (``inference.metrics.inside_mask``, the evaluation's test): (B, V)
    bool on x's device, not differentiated."""
    mask = inside_mask(x.detach().cpu().numpy(), bank.rest_vertices[shape_idx], faces)
    return torch.as_tensor(mask).to(x.device)


def evaluate_fit(model: FitRegressor | None, cloth: ClothGeometry, bank: ShapeBank, faces: np.ndarray | None = None) -> dict:
    """Mean static energy terms (J) over ``bank`` of retarget + R_G (model None: the retarget
    alone), mean / max vertex distance to the retarget (cm), and the fraction of garment
    vertices closer to the body than the collision margin (d < eps) and inside it (d < 0) by
    the tangent-plane distance of eq. 5.12 (candidates selected at the evaluated positions);
    with the body's ``faces``, also the fraction inside by the exact winding-number test."""
    with torch.no_grad():
        x0 = torch.as_tensor(bank.retarget)
        x = x0 + model(torch.as_tensor(bank.phenotypes)) if model is not None else x0
        cand = candidates(torch.as_tensor(bank.body_points), x, bank.candidates.shape[-1])
        terms = energy_terms(cloth, x, torch.as_tensor(bank.body_points), torch.as_tensor(bank.body_normals), cand)
        d = body_signed_distances(x, torch.as_tensor(bank.body_points), torch.as_tensor(bank.body_normals), cand)
        dist = (x - x0).norm(dim=-1)
    out = {f"{k}_j": float(v.mean()) for k, v in terms.items()}
    out["static_j"] = float(sum(v for v in terms.values()).mean())
    out["distance_to_retarget_cm_mean"] = float(dist.mean() * 100)
    out["distance_to_retarget_cm_max"] = float(dist.max() * 100)
    out["within_margin_fraction"] = float((d < cloth.material.collision_margin_m).float().mean())
    out["inside_fraction"] = float((d < 0).float().mean())
    if faces is not None:
        out["inside_fraction_exact"] = float(exact_inside(bank, faces, np.arange(len(bank)), x).float().mean())
    return out


def output_basis(asset, config: FitConfig, smoke: bool = False) -> tuple[np.ndarray, dict | None]:
    """R_G's output basis (V, K) and, for the geodesic one, what rebuilds it at runtime
    (``inference.fit_basis``: node ids and sigma, metres; None for the harmonics, which ship)."""
    if config.basis == "harmonics":
        cache = None if smoke else CACHE_DIR / f"{config.garment}_harmonics_{config.basis_size}.npy"
        return harmonic_basis(asset.num_vertices, asset.edges, config.basis_size, cache), None
    if config.basis == "geodesic":
        nodes, sigma = farthest_nodes(asset.vertices, asset.edges, config.basis_size)
        spec = {"kind": "geodesic", "nodes": nodes.tolist(), "sigma_m": sigma}
        return geodesic_rbf_basis(asset.vertices, asset.edges, nodes, sigma), spec
    raise ValueError(f"basis: {config.basis!r} is neither 'harmonics' nor 'geodesic'")


def train_fit(config: FitConfig, smoke: bool = False, out_dir: Path = CHECKPOINT_DIR) -> dict:
    """Train R_G for ``config.garment``; write ``out_dir/<garment>/fit.pt``; return the record."""
    torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed)
    device = torch.device(config.device)
    rng = np.random.default_rng(config.seed)
    body = BodyModel.load()
    asset = GarmentCatalog.load().get(config.garment)
    cloth = ClothGeometry.from_asset(asset, torch.float32)  # the physical material: metrics
    train_cloth = cloth.with_collision_stiffness(config.k_collision, config.collision_cap_m, config.collision_margin_m).to(device)  # the training loss

    t_bank = time.perf_counter()
    basis, basis_spec = output_basis(asset, config, smoke)
    bank = ShapeBank.build(body, asset, sample_adult_phenotypes(config.bank_shapes, rng), config.candidates)
    held_out = ShapeBank.build(body, asset, sample_adult_phenotypes(config.eval_shapes, np.random.default_rng(config.seed + 1), corners=False), config.candidates)
    bank_s = time.perf_counter() - t_bank
    log.info("%s: %d vertices, bank of %d shapes (%d body vertices kept) in %.1f s", config.garment, asset.num_vertices, len(bank), len(bank.body_index), bank_s)

    model = FitRegressor(basis, config.hidden, config.layers)
    init_wall_s, init_steps = 0.0, 0
    if config.init:
        init_model, init_record = load_fit(Path(config.init))
        model.load_state_dict(init_model.state_dict())
        init_wall_s, init_steps = init_record["train_wall_s"], init_record["steps"]
    trees = [cKDTree(p) for p in bank.body_points] if config.fresh_candidates and device.type == "cpu" else None
    model.to(device)
    opt = torch.optim.Adam(model.parameters(), lr=config.lr)
    P = torch.as_tensor(bank.phenotypes).to(device)
    X0 = torch.as_tensor(bank.retarget).to(device)
    BP, BN = torch.as_tensor(bank.body_points).to(device), torch.as_tensor(bank.body_normals).to(device)
    C = torch.as_tensor(bank.candidates.astype(np.int64)).to(device)

    pinned = torch.as_tensor(waistband_vertices(asset) if config.pin_waistband > 0 else np.zeros(0, np.int64)).to(device)
    budget_s = config.minutes * 60.0
    t0 = time.perf_counter()
    step, history = 0, []
    while step < config.max_steps and time.perf_counter() - t0 < budget_s:
        progress = max((time.perf_counter() - t0) / budget_s, step / config.max_steps)
        for g in opt.param_groups:  # SNUG §5.3.1: lr 1e-3, then 1e-4
            g["lr"] = config.lr if progress < config.lr_drop else config.lr_final
        idx_np = rng.integers(0, len(bank), config.batch_size)
        idx = torch.as_tensor(idx_np).to(device)
        x = X0[idx] + model(P[idx])  # eq. 4.2 without R_L: retarget fit + R_G
        cand = candidates(BP[idx], x, config.candidates, None if trees is None else [trees[i] for i in idx_np]) if config.fresh_candidates else C[idx]
        inside = exact_inside(bank, body.faces, idx_np, x) if config.exact_inside else None
        terms = energy_terms(train_cloth, x, BP[idx], BN[idx], cand, inside=inside)
        if len(pinned):  # 0.5 k |R_G|^2 at the waistband: the reference's kinematic waist, J
            terms["pin"] = 0.5 * config.pin_waistband * (x[:, pinned] - X0[idx][:, pinned]).pow(2).sum((1, 2))
        loss = sum(terms.values()).mean()  # L_static, eq. 5.7 (+ the waistband's springs)
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
        opt.step()
        step += 1
        if step % config.log_every == 0 or step == 1:
            history.append({"step": step, "seconds": time.perf_counter() - t0, "loss_j": float(loss.detach()), **{k: float(v.detach().mean()) for k, v in terms.items()}})
            log.info("step %d %.0f s: L_static %.5f J (%s)", step, history[-1]["seconds"], float(loss.detach()), ", ".join(f"{k} {float(v.detach().mean()):.4f}" for k, v in terms.items()))
    wall_s = time.perf_counter() - t0

    model.eval().cpu()
    metrics = {"held_out_learned": evaluate_fit(model, cloth, held_out, body.faces), "held_out_retarget": evaluate_fit(None, cloth, held_out, body.faces)}
    log.info("held-out static energy: learned %.5f J vs retarget %.5f J; distance to retarget %.2f cm",
             metrics["held_out_learned"]["static_j"], metrics["held_out_retarget"]["static_j"], metrics["held_out_learned"]["distance_to_retarget_cm_mean"])
    record = {
        "model": "fit",
        "config": asdict(config),
        "smoke": smoke,
        "steps": step + init_steps,
        "train_wall_s": wall_s + init_wall_s,
        "this_run": {"steps": step, "wall_s": wall_s, "init": config.init, "init_steps": init_steps, "init_wall_s": init_wall_s},
        "bank_build_s": bank_s,
        "metrics": metrics,
        "history": history,
        "git_commit": git_commit(),
        "torch": torch.__version__,
    }
    path = out_dir / config.garment / ("fit_smoke.pt" if smoke else "fit.pt")
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"record": record, "state_dict": model.state_dict(), "basis": basis, "basis_spec": basis_spec, "hidden": config.hidden,
                "layers": config.layers}, path)
    log.info("wrote %s (%d steps, %.1f min)", path, step, wall_s / 60)
    return record


def load_fit(path: Path) -> tuple[FitRegressor, dict]:
    """A trained R_G and its record from a ``fit.pt`` checkpoint."""
    ck = torch.load(path, weights_only=False)
    model = FitRegressor(ck["basis"], ck["hidden"], ck["layers"])
    model.load_state_dict(ck["state_dict"])
    return model.eval(), ck["record"]


SMOKE = dict(minutes=0.25, max_steps=5, bank_shapes=6, eval_shapes=3, basis_size=16, hidden=16, batch_size=2, log_every=1)


def main(argv: list[str] | None = None) -> None:
    run_cli(argv, __doc__.split("\n")[0], FitConfig, train_fit, SMOKE, "a few steps on a tiny bank (CI)", CHECKPOINT_DIR)


if __name__ == "__main__":
    main()
