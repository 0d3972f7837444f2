"""Generative subspace of canonical garments (thesis ch. 6.3.4, eq. 6.13-6.16): a VAE, torch.

Data: canonical garments X (unposed, deshaped; ``training.projection``) of one garment.

    L_VAE = L_rec + l_lap L_laplacian + l_col L_collision + l_kl L_KL                  (eq. 6.13)
    L_rec       = mean_v |X_v - D(E(X))_v|_1                      (m)                   (eq. 6.14)
    L_laplacian = mean_v |(L X)_v - (L D(E(X)))_v|_1              (m)                   (eq. 6.15)
    L_collision = mean_v max(eps - SDF(D(E(X)))_v, 0)
                + mean_v max(eps - SDF(D(z))_v, 0),  z ~ N(0, I)  (m)                   (eq. 6.16)
    L_KL        = mean over the batch of KL(N(mu, sigma^2) | N(0, I)), summed over the latent

L is the mesh's uniform graph Laplacian (neighbour mean minus the vertex), SDF the constant
canonical body's signed distance (``inference.diffused``). The second collision term is the
thesis' self-supervised one: decoded random latents are checked against the one canonical body,
with no data, so the whole latent ball near the prior is pushed collision-free.

Network (smaller than the thesis' 4 x 2000 dense layers, which would be ~60 MB per garment and
several ms per frame on a CPU): the garment's displacement from its template lives in the K
smoothest manifold harmonics of its mesh (``training.datasets.harmonic_basis``, as the ch. 4
models), so the encoder reads the least-squares harmonic coefficients of X - X_template and the
decoder writes them:

    E: c(X) (3K) -> 2 x [dense, ReLU, LayerNorm] -> (mu, log sigma^2) (latent)
    D: z (latent) -> 2 x [dense, ReLU, LayerNorm] -> dense (3K) -> X_template + Phi c  (V, 3)

Training follows §6.5.2: first without collision and with the KL weight ramped from 0 (a phase
of reconstruction), then the collision weight ramped in to its final value, lower learning rate.
The decoder is exported to ONNX: z (B, latent) -> X (B, V, 3) metres.

Units: metres. Batch first.
"""
from __future__ import annotations

import argparse
import json
import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import torch
from torch import nn

from inference.diffused import DEFAULT_PATH, DiffusedBody
from training.datasets import graph_laplacian, harmonic_basis
from training.models import OutputBasis
from training.projection import TorchBandGrid

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class VAEConfig:
    """Sizes and loss weights (eq. 6.13); steps of each training phase."""

    latent: int = 25  # thesis: 25
    basis: int = 128  # harmonics per axis
    hidden: int = 256
    coeff_unit_m: float = 0.01
    lap_weight: float = 100.0  # thesis lambda_1
    collision_weight: float = 10.0  # thesis lambda_2, per metre of depth below eps
    kl_weight: float = 1e-4  # thesis lambda_3 = 1 on its own loss scale; here L_rec is in metres
    eps_m: float = 2e-3
    random_batch: int = 16  # decoded random latents per step (eq. 6.16's second term)
    batch: int = 32
    lr: float = 1e-3
    lr_final: float = 1e-4
    steps_reconstruction: int = 3000
    steps_collision: int = 2000
    seed: int = 0


def _block(n_in: int, n_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(n_in, n_out), nn.ReLU(), nn.LayerNorm(n_out))


class CanonicalDecoder(nn.Module):
    """D: z (B, latent) -> X (B, V, 3) metres (module docstring)."""

    def __init__(self, template: np.ndarray, basis: np.ndarray, config: VAEConfig):
        super().__init__()
        self.register_buffer("template", torch.as_tensor(np.asarray(template, np.float32)))
        self.output = OutputBasis(basis, config.coeff_unit_m)
        self.net = nn.Sequential(_block(config.latent, config.hidden), _block(config.hidden, config.hidden),
                                 nn.Linear(config.hidden, 3 * self.output.size))
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        return self.template + self.output(self.net(z))


class GarmentVAE(nn.Module):
    """E and D of eq. 6.13 for one garment."""

    def __init__(self, template: np.ndarray, basis: np.ndarray, config: VAEConfig):
        super().__init__()
        self.config = config
        self.decoder = CanonicalDecoder(template, basis, config)
        B = self.decoder.output.basis  # (V, K) metres per unit
        self.register_buffer("pinv", torch.linalg.pinv(B.double()).float())  # (K, V): least-squares coefficients
        self.encoder = nn.Sequential(_block(3 * B.shape[1], config.hidden), _block(config.hidden, config.hidden),
                                     nn.Linear(config.hidden, 2 * config.latent))

    def coefficients(self, X: torch.Tensor) -> torch.Tensor:
        """Least-squares harmonic coefficients of X - template: (B, V, 3) -> (B, 3K), axis-minor."""
        c = torch.einsum("kv,bvc->bkc", self.pinv, X - self.decoder.template)
        return c.reshape(len(X), -1)

    def encode(self, X: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = self.encoder(self.coefficients(X))
        return h[:, : self.config.latent], h[:, self.config.latent:].clamp(-10.0, 10.0)

    def forward(self, X: torch.Tensor, sample: bool = True) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        mu, logvar = self.encode(X)
        z = mu + torch.randn_like(mu) * torch.exp(0.5 * logvar) if sample else mu
        return self.decoder(z), mu, logvar


def laplacian_operator(num_vertices: int, edges: np.ndarray) -> torch.Tensor:
    """Uniform Laplacian (neighbour mean minus the vertex) as a sparse (V, V) torch tensor."""
    L = graph_laplacian(num_vertices, edges).tocsr()
    deg = np.asarray(L.diagonal())
    M = (-sp.diags(1.0 / np.maximum(deg, 1.0)) @ L).tocoo()
    return torch.sparse_coo_tensor(np.stack([M.row, M.col]), M.data.astype(np.float32), (num_vertices, num_vertices),
                                   check_invariants=False).coalesce()


class CanonicalSDF:
    """SDF of the canonical body from the diffused body's grid, differentiable (float32)."""

    def __init__(self, diffused: DiffusedBody):
        self.grid = TorchBandGrid(diffused.grid, diffused.sdf_tables["fine"], diffused.sdf_tables["coarse"], dtype=torch.float32)

    def __call__(self, X: torch.Tensor) -> torch.Tensor:
        """(B, V, 3) -> (B, V) metres, negative inside."""
        return self.grid(X.reshape(-1, 3)).reshape(X.shape[:-1])


def _laplace(L: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    B, V, _ = X.shape
    return torch.sparse.mm(L, X.permute(1, 0, 2).reshape(V, -1)).reshape(V, B, 3).permute(1, 0, 2)


def vae_losses(model: GarmentVAE, X: torch.Tensor, L: torch.Tensor, sdf: CanonicalSDF, random_batch: int) -> dict[str, torch.Tensor]:
    """The terms of eq. 6.13 on a batch X (B, V, 3)."""
    c = model.config
    Y, mu, logvar = model(X)
    z = torch.randn(random_batch, c.latent)
    Yr = model.decoder(z)
    return {
        "rec": (Y - X).abs().sum(-1).mean(),
        "laplacian": (_laplace(L, Y) - _laplace(L, X)).abs().sum(-1).mean(),
        "collision_data": torch.clamp(c.eps_m - sdf(Y), min=0.0).mean(),
        "collision_random": torch.clamp(c.eps_m - sdf(Yr), min=0.0).mean(),
        "kl": (-0.5 * (1.0 + logvar - mu ** 2 - logvar.exp()).sum(-1)).mean(),
    }


def train_vae(frames: np.ndarray, template: np.ndarray, faces: np.ndarray, edges: np.ndarray, diffused: DiffusedBody,
              config: VAEConfig = VAEConfig(), validation: np.ndarray | None = None, collision: bool = True) -> tuple[GarmentVAE, dict]:
    """Train on canonical frames (N, V, 3); returns the model and a record (losses, validation
    errors, wall time). ``collision=False`` leaves eq. 6.16 out (the ablation of thesis fig. 6.4)."""
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    V = len(template)
    basis = harmonic_basis(V, edges, config.basis)
    model = GarmentVAE(template, basis, config)
    L = laplacian_operator(V, edges)
    sdf = CanonicalSDF(diffused)
    data = torch.as_tensor(np.asarray(frames, np.float32))
    opt = torch.optim.Adam(model.parameters(), lr=config.lr)
    total = config.steps_reconstruction + config.steps_collision
    t0 = time.perf_counter()
    history = []
    for step in range(total):
        second = step >= config.steps_reconstruction
        ramp = min(1.0, (step - config.steps_reconstruction) / max(config.steps_collision / 2, 1)) if second else 0.0
        kl_w = config.kl_weight * (min(1.0, step / max(config.steps_reconstruction / 2, 1)))
        col_w = config.collision_weight * ramp if collision else 0.0
        for g in opt.param_groups:
            g["lr"] = config.lr_final if second else config.lr
        X = data[torch.as_tensor(rng.integers(0, len(data), config.batch))]
        t = vae_losses(model, X, L, sdf, config.random_batch)
        loss = t["rec"] + config.lap_weight * t["laplacian"] + col_w * (t["collision_data"] + t["collision_random"]) + kl_w * t["kl"]
        opt.zero_grad()
        loss.backward()
        opt.step()
        if step % 250 == 0 or step == total - 1:
            row = {"step": step, **{k: float(v.detach()) for k, v in t.items()}}
            history.append(row)
            log.info("step %d: %s", step, json.dumps({k: round(v, 7) for k, v in row.items()}))
    record = {"config": asdict(config), "collision": collision, "train_wall_s": round(time.perf_counter() - t0, 1),
              "frames": int(len(data)), "history": history, "metrics": evaluate_vae(model, data.numpy(), sdf, validation)}
    return model.eval(), record


@torch.no_grad()
def evaluate_vae(model: GarmentVAE, train: np.ndarray, sdf: CanonicalSDF, validation: np.ndarray | None = None,
                 samples: int = 256, seed: int = 1) -> dict:
    """Reconstruction error (mean and p99 per vertex, mm) on the training and validation frames
    (through the latent mean), and the share of vertices inside the canonical body of decoded
    random latents z ~ N(0, I) and of the data itself."""
    model.eval()
    out = {}
    for name, X in (("train", train), ("validation", validation)):
        if X is None or len(X) == 0:
            continue
        Xt = torch.as_tensor(np.asarray(X, np.float32))
        Y, _, _ = model(Xt, sample=False)
        err = torch.linalg.norm(Y - Xt, dim=-1).numpy() * 1e3
        out[name] = {"frames": len(X), "mean_mm": float(err.mean()), "p99_mm": float(np.percentile(err, 99)),
                     "max_mm": float(err.max()), "inside_data": float((sdf(Xt) < 0).double().mean()),
                     "inside_reconstruction": float((sdf(Y) < 0).double().mean())}
    g = torch.Generator().manual_seed(seed)
    Yr = model.decoder(torch.randn(samples, model.config.latent, generator=g))
    d = sdf(Yr)
    out["random"] = {"samples": samples, "inside": float((d < 0).double().mean()),
                     "deepest_mm": float(-d.min()) * 1e3 if float(d.min()) < 0 else 0.0,
                     "samples_with_any_inside": float((d < 0).any(-1).double().mean())}
    return out


def export_decoder(model: GarmentVAE, path: Path, record: dict, tolerance_m: float = 1e-4) -> dict:
    """decoder.onnx: z (B, latent) float32 -> canonical_vertices (B, V, 3) float32 metres, with
    torch-onnxruntime parity on random latents (B = 1 and 7)."""
    import warnings

    import onnxruntime as ort

    from training.export_onnx import OPSET, _add_metadata, _record_metadata, _sha256

    dec = model.decoder.eval()
    latent = model.config.latent
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(dec, (torch.zeros(2, latent),), str(path), input_names=["z"], output_names=["canonical_vertices"],
                          opset_version=OPSET, dynamo=False, dynamic_axes={"z": {0: "B"}, "canonical_vertices": {0: "B"}})
    _add_metadata(path, _record_metadata({**record, "steps": len(record.get("history", []))}))
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(2)
    worst = 0.0
    for B in (1, 7):
        z = rng.standard_normal((B, latent)).astype(np.float32)
        (y,) = sess.run(None, {"z": z})
        with torch.no_grad():
            worst = max(worst, float(np.abs(y - dec(torch.as_tensor(z)).numpy()).max()))
    if not worst <= tolerance_m:
        raise RuntimeError(f"{path.name}: parity {worst:.3g} m exceeds {tolerance_m} m")
    return {"file": path.name, "sha256": _sha256(path), "bytes": path.stat().st_size, "opset": OPSET,
            "inputs": {"z": ["B", latent]}, "outputs": {"canonical_vertices": ["B", dec.output.num_vertices, 3]},
            "parity_max_abs_m": worst}


def load_canonical(paths: list[Path]) -> np.ndarray:
    """Canonical frames of ``training.projection`` outputs, concatenated: (N, V, 3) float32."""
    frames = []
    for p in paths:
        with np.load(p, allow_pickle=False) as f:
            frames.append(f["canonical"])
    return np.concatenate(frames) if frames else np.zeros((0, 0, 3), np.float32)


def metadata_record(record: dict) -> dict:
    """The fields of a training record that the ONNX file's metadata carries (``training.export_onnx._record_metadata``)."""
    return {"config": record["config"], "train_wall_s": record["train_wall_s"], "metrics": record["metrics"],
            "steps": len(record["history"])}


def main(argv: list[str] | None = None) -> None:
    from inference.garment import GarmentCatalog

    p = argparse.ArgumentParser(description="Train the canonical-space VAE of one garment (thesis eq. 6.13-6.16).")
    p.add_argument("--garment", required=True)
    p.add_argument("--train", nargs="+", type=Path, required=True, help="canonical frames (training.projection outputs) of training clips")
    p.add_argument("--validation", nargs="*", type=Path, default=[], help="canonical frames of the validation clip (reported only)")
    p.add_argument("--diffused", type=Path, default=DEFAULT_PATH)
    p.add_argument("--out-dir", type=Path, default=Path("build/vae"))
    p.add_argument("--no-collision", action="store_true", help="leave eq. 6.16 out (ablation)")
    p.add_argument("--steps", type=int, nargs=2, default=None, metavar=("RECONSTRUCTION", "COLLISION"))
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    torch.set_num_threads(max(torch.get_num_threads(), 1))
    asset = GarmentCatalog.load().get(args.garment)
    config = VAEConfig() if args.steps is None else VAEConfig(steps_reconstruction=args.steps[0], steps_collision=args.steps[1])
    train = load_canonical(args.train)
    # the template itself is a canonical garment (the rest drape on the canonical body)
    train = np.concatenate([train, asset.vertices[None].astype(np.float32)])
    model, record = train_vae(train, asset.vertices, asset.faces, asset.edges, DiffusedBody.load(args.diffused), config,
                              load_canonical(args.validation) if args.validation else None, collision=not args.no_collision)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    tag = f"{args.garment}{'_nocol' if args.no_collision else ''}"
    torch.save(model.state_dict(), args.out_dir / f"{tag}.pt")
    record["export"] = export_decoder(model, args.out_dir / f"{tag}_decoder.onnx", metadata_record(record))
    (args.out_dir / f"{tag}.json").write_text(json.dumps(record, indent=1))
    log.info("metrics: %s", json.dumps(record["metrics"]))


if __name__ == "__main__":
    main()
