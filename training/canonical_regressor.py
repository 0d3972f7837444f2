"""Recurrent regressor into the canonical VAE's latent space (thesis ch. 6.4, eq. 6.17-6.18), torch.

    z_t = R(beta, gamma_1..t)                                              (eq. 6.1 in the subspace)
    L_R = L_pos + rho_1 L_vel + rho_2 L_acc                                (eq. 6.18)

L_pos = mean |z_t - z*_t|_1, L_vel and L_acc the same on the first and second differences in
time (per frame), z*_t = mu(E(X*_t)) the VAE encoding of the canonical projection of a physics
simulation (``training.projection``). gamma is the service's motion descriptor
(``inference.motion.descriptor``, eq. 6.17 adapted), beta the six phenotypes. Architecture as
the ch. 4 wrinkle model's (``training.models.WrinkleGRU``): GRU layers over [normalised
phenotypes, normalised gamma], a linear head to the latent; a whole sequence in one call with an
initial state in and the final state out.

With ``RegressorConfig.posed_weight`` = w > 0 the loss is L_R + w E_col, E_col the posed-space
collision energy (``training.posed_collision``: SNUG's hinge against the simulation's own posed
body) of a few decoded and posed frames per window, the decoder frozen: the regressor picks,
among the latents near its target, those whose posed garment stays out of the body.

The posed garment of frame t is then eq. 6.7: M_G(D(z_t), beta, theta_t) with the diffused
body's W~ and B~s at the decoded canonical points (``training.projection.CanonicalBody``).

Units: metres, seconds. Batch first.
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import nn

from training.models import GAMMA_CLIP_STD, PHENOTYPE_LABELS, PhenotypeNormaliser

# Parity of z (the VAE's latent, unitless) between torch and the float16-stored ONNX regressor.
HALF_TOLERANCE = 2e-3


@dataclass(frozen=True)
class RegressorConfig:
    hidden: int = 256
    layers: int = 2  # thesis: 2 GRU layers (of 500)
    rho_vel: float = 0.5  # thesis rho_1
    rho_acc: float = 0.1  # thesis rho_2
    lr: float = 1e-3
    steps: int = 1500
    window: int = 40  # frames per training window (from the first frame)
    batch: int = 8
    seed: int = 0
    # the posed-space collision term (``training.posed_collision``): weight per metre of mean
    # depth below eps (0: off), the frames of each window it is evaluated on per step, eps
    posed_weight: float = 0.0
    posed_frames: int = 4
    posed_eps_m: float = 0.003


class CanonicalRegressor(nn.Module):
    """R: phenotypes (B, 6), gamma (B, T, F), h0 (L, B, H) -> z (B, T, latent), hT."""

    def __init__(self, latent: int, gamma_mean: np.ndarray, gamma_std: np.ndarray, config: RegressorConfig = RegressorConfig()):
        super().__init__()
        self.layers, self.hidden = config.layers, config.hidden
        self.normalise = PhenotypeNormaliser()
        self.register_buffer("gamma_mean", torch.as_tensor(np.asarray(gamma_mean, np.float32)))
        self.register_buffer("gamma_std", torch.as_tensor(np.asarray(gamma_std, np.float32)))
        self.gru = nn.GRU(len(PHENOTYPE_LABELS) + len(gamma_mean), config.hidden, num_layers=config.layers, batch_first=True)
        self.head = nn.Linear(config.hidden, latent)

    def initial_state(self, batch: int) -> torch.Tensor:
        return torch.zeros(self.layers, batch, self.hidden)

    def forward(self, phenotypes: torch.Tensor, gamma: torch.Tensor, h0: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        g = torch.clamp((gamma - self.gamma_mean) / self.gamma_std, -GAMMA_CLIP_STD, GAMMA_CLIP_STD)
        p = self.normalise(phenotypes)[:, None, :].expand(-1, gamma.shape[1], -1)
        y, h_t = self.gru(torch.cat([p, g], dim=-1), h0)
        return self.head(y), h_t


def regressor_loss(z: torch.Tensor, target: torch.Tensor, config: RegressorConfig) -> torch.Tensor:
    """eq. 6.18 on (B, T, latent) sequences."""
    pos = (z - target).abs().mean()
    vel = (z.diff(dim=1) - target.diff(dim=1)).abs().mean()
    acc = (z.diff(n=2, dim=1) - target.diff(n=2, dim=1)).abs().mean()
    return pos + config.rho_vel * vel + config.rho_acc * acc


def train_regressor(sequences: list[dict], latent: int, config: RegressorConfig = RegressorConfig(),
                    decoder: nn.Module | None = None) -> tuple[CanonicalRegressor, dict]:
    """sequences: dicts with ``phenotypes`` (6,), ``gamma`` (T, F), ``z`` (T, latent), all
    starting at the simulation's first frame (the GRU starts from h0 = 0 there, as at runtime).
    Windows of ``config.window`` frames always start at a sequence's first frame.

    With ``config.posed_weight`` > 0 the loss adds that weight times the posed-space collision
    energy (``training.posed_collision``) of ``config.posed_frames`` random frames per window,
    decoded by ``decoder`` (frozen) and posed on the sequence's ``posed``
    (``training.posed_collision.PosedFrames``)."""
    from training.posed_collision import collision_energy, pose_frames, posed_distance

    posed_on = config.posed_weight > 0
    if posed_on:
        if decoder is None or any("posed" not in s for s in sequences):
            raise ValueError("the posed collision term needs the decoder and every sequence's posed frames")
        for p in decoder.parameters():
            p.requires_grad_(False)
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    gammas = np.concatenate([s["gamma"] for s in sequences])
    model = CanonicalRegressor(latent, gammas.mean(0), np.maximum(gammas.std(0), 1e-3), config)
    opt = torch.optim.Adam(model.parameters(), lr=config.lr)
    t0 = time.perf_counter()
    history = []
    for step in range(config.steps):
        idx = rng.integers(0, len(sequences), config.batch)
        T = min(config.window, min(len(sequences[i]["z"]) for i in idx))
        ph = torch.as_tensor(np.stack([sequences[i]["phenotypes"] for i in idx]), dtype=torch.float32)
        g = torch.as_tensor(np.stack([sequences[i]["gamma"][:T] for i in idx]), dtype=torch.float32)
        zt = torch.as_tensor(np.stack([sequences[i]["z"][:T] for i in idx]), dtype=torch.float32)
        z, _ = model(ph, g, model.initial_state(len(idx)))
        loss = regressor_loss(z, zt, config)
        record = {"step": step, "regressor": float(loss.detach())}  # eq. 6.18 alone
        if posed_on:
            energy = 0.0
            for b, i in enumerate(idx):
                frames = np.sort(rng.choice(T, min(config.posed_frames, T), replace=False))
                pf = sequences[i]["posed"]
                x = pose_frames(pf.body, decoder(z[b, frames]), pf.transforms[frames])
                energy = energy + collision_energy(posed_distance(x, pf, frames), config.posed_eps_m) / len(idx)
            loss = loss + config.posed_weight * energy
            record["posed_collision_m"] = float(energy.detach())
        record["loss"] = float(loss.detach())
        opt.zero_grad()
        loss.backward()
        opt.step()
        if step % 250 == 0 or step == config.steps - 1:
            history.append(record)
    return model.eval(), {"config": asdict(config), "train_wall_s": round(time.perf_counter() - t0, 1), "history": history,
                          "sequences": len(sequences)}


def export_regressor(model: CanonicalRegressor, path, seed: int = 0, tolerance: float = 1e-4, half: bool = True) -> dict:
    """regressor.onnx: phenotypes (B, 6), gamma (B, T, F), h0 (L, B, H) -> z (B, T, latent), hT
    (L, B, H), a whole sequence per call (the ONNX GRU op); parity with torch over several B, T.

    half: the weights stored as float16 (``training.export_onnx.half_weights``; 3.6 -> 1.8 MB),
    parity within HALF_TOLERANCE instead of ``tolerance``. On the T-shirt's validation walk
    (02_02, 40 frames, neutral and heavy) z moved by <= 2.2e-4 and the posed vertices by <= 0.1
    mm (mean 0.001 mm); the decoder stays float32 (stored as float16 it moved them by up to 0.48
    mm, beyond its 1e-4 m parity)."""
    import warnings

    import onnxruntime as ort

    from training.export_onnx import OPSET, _random_phenotypes, _sha256, half_weights

    model = model.eval()
    F, L, H = len(model.gamma_mean), model.layers, model.hidden
    rng = np.random.default_rng(seed)
    mean, std = model.gamma_mean.numpy(), model.gamma_std.numpy()

    def gamma(B: int, T: int) -> np.ndarray:
        return (mean + std * rng.standard_normal((B, T, F))).astype(np.float32)

    args = (torch.as_tensor(_random_phenotypes(2, rng)), torch.as_tensor(gamma(2, 4)), torch.zeros(L, 2, H))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the exporter's note on GRU batch sizes: h0 is an input here
        torch.onnx.export(model, args, str(path), input_names=["phenotypes", "gamma", "h0"], output_names=["z", "hT"],
                          opset_version=OPSET, dynamo=False,
                          dynamic_axes={"phenotypes": {0: "B"}, "gamma": {0: "B", 1: "T"}, "h0": {1: "B"}, "z": {0: "B", 1: "T"}, "hT": {1: "B"}})
    if half:
        half_weights(path)
        tolerance = max(tolerance, HALF_TOLERANCE)
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    worst = 0.0
    for B, T in ((1, 1), (1, 9), (3, 5)):
        p, g = _random_phenotypes(B, rng), gamma(B, T)
        h0 = (0.1 * rng.standard_normal((L, B, H))).astype(np.float32)
        z, hT = sess.run(None, {"phenotypes": p, "gamma": g, "h0": h0})
        with torch.no_grad():
            rz, rh = model(torch.as_tensor(p), torch.as_tensor(g), torch.as_tensor(h0))
        worst = max(worst, float(np.abs(z - rz.numpy()).max()), float(np.abs(hT - rh.numpy()).max()))
    if not worst <= tolerance:
        raise RuntimeError(f"{path.name}: parity {worst:.3g} exceeds {tolerance}")
    return {"file": path.name, "sha256": _sha256(path), "bytes": path.stat().st_size, "opset": OPSET,
            "inputs": {"phenotypes": ["B", 6], "gamma": ["B", "T", F], "h0": [L, "B", H]},
            "outputs": {"z": ["B", "T", int(model.head.out_features)], "hT": [L, "B", H]}, "parity_max_abs": worst,
            "weights": "float16" if half else "float32"}
