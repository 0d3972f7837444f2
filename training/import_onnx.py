"""Rebuild ``fit.pt`` / ``wrinkle.pt`` training checkpoints from a shipped ``assets/models/<g>/``.

The checkpoints are build output (``build/models``, not committed); the ONNX files are what a
clean clone has. This module reads the weights back out of ``fit.onnx`` and ``wrinkle.onnx`` so
that training can continue from the shipped models (``train_wrinkle --init``) in a new checkout:
- fit.onnx: the initializers carry the torch names (``mlp.*``, ``head.*``, ``output.basis``).
- wrinkle.onnx: the exporter turned ``nn.GRU`` into one ONNX GRU op per layer, with inputs
  W (1, 3H, I), R (1, 3H, H), B (1, 6H) = [W_b, R_b] in gate order (z, r, h) and
  ``linear_before_reset = 1``, which is torch's GRU; torch stores (r, z, n), so the gate blocks
  are reordered back. The head is a MatMul by ``head.weight``^T.
- The output basis is stored pre-multiplied by ``OutputBasis``'s coefficient unit; the
  checkpoint's ``basis`` divides it back out, and the state dict keeps the exact ONNX buffer.
- The record comes from ``model.json`` (config, steps, wall time, metrics, git commit).

Every rebuilt model is checked against onnxruntime on random inputs (max abs difference <=
``training.export_onnx.PARITY_TOLERANCE_M``) before it is written.

Run: ``python -m training.import_onnx --garment tshirt longsleeve`` (writes
``build/models/<g>/{fit,wrinkle}.pt``; ``--models`` / ``--out`` choose other roots).
"""
from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch
from onnx import numpy_helper

from inference.fit_basis import geodesic_rbf_basis
from inference.garment import GarmentCatalog
from training.export_onnx import MODELS_DIR, PARITY_TOLERANCE_M, _random_phenotypes, _sha256
from training.models import FitRegressor, OutputBasis, WrinkleGRU
from training.train_fit import CHECKPOINT_DIR

log = logging.getLogger(__name__)


def _initializers(path: Path) -> tuple[onnx.ModelProto, dict[str, np.ndarray]]:
    model = onnx.load(str(path))
    return model, {t.name: numpy_helper.to_array(t).astype(np.float32) for t in model.graph.initializer}


def _record(entry: dict, kind: str, path: Path) -> dict:
    keep = ("config", "steps", "train_wall_s", "metrics", "git_commit", "training_frames", "output_basis")
    record = {k: entry[k] for k in keep if k in entry}
    record["model"] = kind
    record["imported_from"] = {"path": str(path), "sha256": _sha256(path)}
    return record


def _unscaled_basis(buffer: np.ndarray, basis_size: int) -> np.ndarray:
    """The checkpoint's (V, K) basis: the ONNX buffer divided by OutputBasis's coefficient unit."""
    if buffer.shape[1] != basis_size:
        raise ValueError(f"basis has {buffer.shape[1]} columns, model.json says {basis_size}")
    unit = OutputBasis(np.ones((1, 1), np.float32)).basis[0, 0].numpy()  # metres per coefficient
    return buffer / unit


def fit_checkpoint(model_dir: Path) -> dict:
    """The ``fit.pt`` dict (record, state_dict, basis, hidden, layers) of ``model_dir/fit.onnx``."""
    entry = json.loads((model_dir / "model.json").read_text())["fit"]
    path = model_dir / entry["file"]
    _, w = _initializers(path)
    spec, phi = entry.get("basis"), None
    if spec is not None:  # a geodesic basis: rebuilt from the template; the weights under "model.", float16 ones "_f16"
        asset = GarmentCatalog.load().get(model_dir.name)
        basis = geodesic_rbf_basis(asset.vertices, asset.edges, np.asarray(spec["nodes"]), spec["sigma_m"])
        w = {k.removeprefix("model.").removesuffix("_f16"): v for k, v in w.items()}
        w["output.basis"] = basis * OutputBasis(np.ones((1, 1), np.float32)).basis[0, 0].numpy()
        phi = basis
    else:
        basis = _unscaled_basis(w["output.basis"], entry["basis_size"])
    layers = sum(k.startswith("mlp.") and k.endswith(".weight") for k in w)  # one Linear per hidden layer
    hidden = int(w["mlp.0.weight"].shape[0])
    model = FitRegressor(basis, hidden, layers)
    model.load_state_dict({k: torch.as_tensor(v) for k, v in w.items() if k in model.state_dict()})
    _check_fit(model.eval(), path, phi)
    return {"record": _record(entry, "fit", path), "state_dict": model.state_dict(), "basis": basis, "basis_spec": spec,
            "hidden": hidden, "layers": layers}


def _gru_blocks(a: np.ndarray, H: int) -> np.ndarray:
    """ONNX gate order (z, r, h) -> torch's (r, z, n) along axis 0 (blocks of H rows)."""
    z, r, h = a[:H], a[H:2 * H], a[2 * H:3 * H]
    return np.concatenate([r, z, h])


def wrinkle_checkpoint(model_dir: Path) -> dict:
    """The ``wrinkle.pt`` dict (record, state_dict, basis, gamma stats, hidden, layers) of ``wrinkle.onnx``."""
    entry = json.loads((model_dir / "model.json").read_text())["wrinkle"]
    path = model_dir / entry["file"]
    graph, w = _initializers(path)
    grus = [n for n in graph.graph.node if n.op_type == "GRU"]
    H, L = entry["gru_hidden"], entry["gru_layers"]
    if len(grus) != L:
        raise ValueError(f"{path}: {len(grus)} GRU ops, model.json says {L} layers")
    basis = _unscaled_basis(w["output.basis"], entry["basis_size"])
    model = WrinkleGRU(basis, w["gamma_mean"], w["gamma_std"], H, L)
    state = {k: torch.as_tensor(w[k]) for k in ("gamma_mean", "gamma_std", "normalise.lo", "normalise.span", "output.basis", "head.bias")}
    head = [n for n in graph.graph.node if n.op_type == "MatMul" and n.input[1] in w and n.input[1] != "output.basis"]
    state["head.weight"] = torch.as_tensor(np.ascontiguousarray(w[head[0].input[1]].T))
    for k, node in enumerate(grus):
        attrs = {a.name: a.i for a in node.attribute}
        if attrs.get("linear_before_reset") != 1 or attrs.get("hidden_size") != H:
            raise ValueError(f"{path}: GRU {k} is not torch's GRU ({attrs})")
        W, R, B = (w[node.input[i]][0] for i in (1, 2, 3))
        state[f"gru.weight_ih_l{k}"] = torch.as_tensor(_gru_blocks(W, H))
        state[f"gru.weight_hh_l{k}"] = torch.as_tensor(_gru_blocks(R, H))
        state[f"gru.bias_ih_l{k}"] = torch.as_tensor(_gru_blocks(B[:3 * H], H))
        state[f"gru.bias_hh_l{k}"] = torch.as_tensor(_gru_blocks(B[3 * H:], H))
    model.load_state_dict(state)
    _check_wrinkle(model.eval(), path)
    return {"record": _record(entry, "wrinkle", path), "state_dict": model.state_dict(), "basis": basis,
            "gamma_mean": w["gamma_mean"], "gamma_std": w["gamma_std"], "hidden": H, "layers": L}


def _check(worst: float, path: Path) -> None:
    if not worst <= PARITY_TOLERANCE_M:
        raise RuntimeError(f"{path.name}: rebuilt torch model differs from onnxruntime by {worst:.3g} (> {PARITY_TOLERANCE_M})")
    log.info("%s: rebuilt, parity with onnxruntime %.2g", path.name, worst)


def _check_fit(model: FitRegressor, path: Path, phi: np.ndarray | None = None, seed: int = 0) -> None:
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    p = _random_phenotypes(4, np.random.default_rng(seed))
    (y,) = sess.run(None, {"phenotypes": p})
    if phi is not None:  # coefficients (B, K, 3) of the geodesic basis
        y = np.einsum("vk,bkc->bvc", phi, y)
    with torch.no_grad():
        _check(float(np.abs(y - model(torch.as_tensor(p)).numpy()).max()), path)


def _check_wrinkle(model: WrinkleGRU, path: Path, seed: int = 0) -> None:
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(seed)
    B, T, L, H = 2, 7, model.layers, model.hidden
    p = _random_phenotypes(B, rng)
    g = (model.gamma_mean.numpy() + model.gamma_std.numpy() * rng.standard_normal((B, T, model.descriptor_size))).astype(np.float32)
    h0 = (0.1 * rng.standard_normal((L, B, H))).astype(np.float32)
    y, hT = sess.run(None, {"phenotypes": p, "gamma": g, "h0": h0})
    with torch.no_grad():
        ry, rh = model(torch.as_tensor(p), torch.as_tensor(g), torch.as_tensor(h0))
    _check(max(float(np.abs(y - ry.numpy()).max()), float(np.abs(hT - rh.numpy()).max())), path)


def import_garment(garment: str, models: Path = MODELS_DIR, out: Path = CHECKPOINT_DIR) -> tuple[Path, Path]:
    """Write ``out/<garment>/{fit,wrinkle}.pt`` rebuilt from ``models/<garment>/``."""
    d = out / garment
    d.mkdir(parents=True, exist_ok=True)
    fit_path, wrinkle_path = d / "fit.pt", d / "wrinkle.pt"
    torch.save(fit_checkpoint(models / garment), fit_path)
    torch.save(wrinkle_checkpoint(models / garment), wrinkle_path)
    return fit_path, wrinkle_path


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description="Rebuild fit.pt / wrinkle.pt checkpoints from shipped ONNX models.")
    p.add_argument("--garment", nargs="+", required=True)
    p.add_argument("--models", type=Path, default=MODELS_DIR, help="root holding <garment>/{model.json,fit.onnx,wrinkle.onnx}")
    p.add_argument("--out", type=Path, default=CHECKPOINT_DIR, help="checkpoint root (train_fit/train_wrinkle --out)")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    for g in args.garment:
        for path in import_garment(g, args.models, args.out):
            log.info("wrote %s", path)


if __name__ == "__main__":
    main()
