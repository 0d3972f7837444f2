"""Export a garment's trained R_G and R_L to ONNX (opset 17), check parity, write model.json.

Writes ``assets/models/<garment>/``:
- ``fit.onnx``     phenotypes (B, 6) float32 -> fit_displacement (B, V, 3) float32, metres:
                   R_G, a residual on the .mhclo retarget fit (training.models.FitRegressor);
                   trained on the geodesic basis (``--basis geodesic``), it answers
                   fit_coefficients (B, K, 3) instead, and model.json's ``fit.basis`` holds
                   the node ids and sigma the runtime rebuilds the basis from
                   (``inference.fit_basis``): ~0.25 MB instead of ~3 MB
- ``wrinkle.onnx`` phenotypes (B, 6), gamma (B, T, F), h0 (L, B, H) -> wrinkle_displacement
                   (B, T, V, 3) metres, hT (L, B, H): R_L over a whole sequence in one call (the
                   ONNX GRU op); pass hT as the next chunk's h0 to process a long sequence in chunks
- ``model.json``   files, sha256, sizes, input/output names and shapes, parity, training config,
                   wall time and metrics (the same are in each ONNX file's metadata_props:
                   config, git_commit, train_wall_s, steps, metrics, exported_at)

Parity: torch vs onnxruntime on random inputs (several batch sizes and lengths), max abs
difference <= PARITY_TOLERANCE_M.

Run: ``python -m training.export_onnx --garment tshirt`` (after train_fit and train_wrinkle; a
garment with no wrinkle checkpoint exports its fit alone, ``"wrinkle": null``).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import logging
import time
import warnings
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch
from torch import nn

from inference.fit_basis import geodesic_rbf_basis
from inference.garment import GarmentAsset, GarmentCatalog
from training.datasets import REPO_ROOT
from training.manifest import git_commit
from training.models import FitRegressor, WrinkleGRU, phenotype_box
from training.train_fit import CHECKPOINT_DIR, load_fit
from training.train_wrinkle import load_wrinkle

log = logging.getLogger(__name__)

MODELS_DIR = REPO_ROOT / "assets" / "models"
OPSET = 17
PARITY_TOLERANCE_M = 1e-4  # max |torch - onnxruntime| displacement, metres
MODEL_FORMAT = 1
# ``half_weights``: the smallest weight tensor stored as float16 (biases and norms stay float32).
HALF_MIN_SIZE = 1024


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _random_phenotypes(n: int, rng: np.random.Generator) -> np.ndarray:
    lo, hi = phenotype_box()
    return (lo + rng.random((n, 6)).astype(np.float32) * (hi - lo)).astype(np.float32)


def _add_metadata(path: Path, meta: dict[str, str]) -> None:
    model = onnx.load(str(path))
    del model.metadata_props[:]
    for k, v in meta.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = k, v
    model.producer_name = "tryon training.export_onnx"
    onnx.checker.check_model(model)
    onnx.save(model, str(path))


def half_weights(path: Path, min_size: int = HALF_MIN_SIZE) -> None:
    """Store a model's float32 weights of at least ``min_size`` elements as float16, each followed by
    a Cast back to float32 (in place): half the file, the same float32 arithmetic (onnxruntime folds
    the casts when it loads the model); the weights are rounded to 11 significant bits."""
    from onnx import TensorProto, helper, numpy_helper

    model = onnx.load(str(path))
    graph = model.graph
    casts, halves = [], []
    for init in list(graph.initializer):
        a = numpy_helper.to_array(init)
        if a.dtype != np.float32 or a.size < min_size:
            continue
        halves.append(numpy_helper.from_array(a.astype(np.float16), init.name + "_f16"))
        casts.append(helper.make_node("Cast", [init.name + "_f16"], [init.name], to=TensorProto.FLOAT, name=init.name + "_cast"))
        graph.initializer.remove(init)
    graph.initializer.extend(halves)
    nodes = list(graph.node)
    del graph.node[:]
    graph.node.extend(casts + nodes)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))


def _record_metadata(record: dict) -> dict[str, str]:
    return {
        "config": json.dumps(record["config"]),
        "git_commit": str(record.get("git_commit", "unknown")),
        "train_wall_s": f"{record['train_wall_s']:.1f}",
        "steps": str(record["steps"]),
        "metrics": json.dumps(record["metrics"]),
        "exported_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "export_git_commit": git_commit(),
    }


class _FitCoefficients(nn.Module):
    """R_G up to its output basis: phenotypes (B, 6) -> coefficients (B, K, 3), metres."""

    def __init__(self, model: FitRegressor):
        super().__init__()
        self.model = model

    def forward(self, phenotypes: torch.Tensor) -> torch.Tensor:
        return self.model.coefficients(phenotypes)


def export_fit(model: FitRegressor, path: Path, record: dict, seed: int = 0, basis_spec: dict | None = None,
               asset: GarmentAsset | None = None) -> dict:
    """fit.onnx + parity (B = 1 and 5); returns the model.json entry.

    basis_spec None: the ONNX holds the output basis and answers displacements (B, V, 3). A
    geodesic basis (``inference.fit_basis``; its node ids and sigma in ``basis_spec``): the ONNX
    answers the coefficients (B, K, 3), its weights are stored as float16 where the parity allows,
    and the parity is taken after the runtime's own basis (rebuilt from ``asset``'s template)."""
    model = model.eval()
    graph, out_name = (model, "fit_displacement") if basis_spec is None else (_FitCoefficients(model), "fit_coefficients")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(graph, (torch.as_tensor(_random_phenotypes(2, np.random.default_rng(seed))),), str(path),
                          input_names=["phenotypes"], output_names=[out_name], opset_version=OPSET, dynamo=False,
                          dynamic_axes={"phenotypes": {0: "B"}, out_name: {0: "B"}})
    _add_metadata(path, _record_metadata(record))
    phi = None
    if basis_spec is not None:
        phi = geodesic_rbf_basis(asset.vertices, asset.edges, np.asarray(basis_spec["nodes"]), basis_spec["sigma_m"])

    def parity() -> float:
        sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        rng = np.random.default_rng(seed + 1)
        worst = 0.0
        for B in (1, 5):
            p = _random_phenotypes(B, rng)
            (y,) = sess.run(None, {"phenotypes": p})
            if phi is not None:
                y = np.einsum("vk,bkc->bvc", phi, y)
            with torch.no_grad():
                ref = model(torch.as_tensor(p)).numpy()
            worst = max(worst, float(np.abs(y - ref).max()))
        return worst

    if phi is not None:
        full = path.read_bytes()
        half_weights(path)
        if not parity() <= PARITY_TOLERANCE_M:  # float16 weights cost more than the tolerance: keep float32
            path.write_bytes(full)
    worst = parity()
    if not worst <= PARITY_TOLERANCE_M:
        raise RuntimeError(f"{path.name}: parity {worst:.3g} m exceeds {PARITY_TOLERANCE_M} m")
    V = model.output.num_vertices
    outputs = {"fit_displacement": ["B", V, 3]} if basis_spec is None else {"fit_coefficients": ["B", model.output.size, 3]}
    return {
        "file": path.name, "sha256": _sha256(path), "bytes": path.stat().st_size, "opset": OPSET,
        "inputs": {"phenotypes": ["B", 6]}, "outputs": outputs, **({"basis": basis_spec} if basis_spec is not None else {}),
        "parity_max_abs_m": worst, "basis_size": model.output.size,
        "config": record["config"], "steps": record["steps"], "train_wall_s": record["train_wall_s"],
        "metrics": record["metrics"], "git_commit": record.get("git_commit"),
    }


def export_wrinkle(model: WrinkleGRU, path: Path, record: dict, seed: int = 0) -> dict:
    """wrinkle.onnx + parity (several B, T; chunked state); returns the model.json entry."""
    model = model.eval()
    F, L, H = model.descriptor_size, model.layers, model.hidden
    rng = np.random.default_rng(seed)
    mean, std = model.gamma_mean.numpy(), model.gamma_std.numpy()

    def gamma(B: int, T: int) -> np.ndarray:
        return (mean + std * rng.standard_normal((B, T, F))).astype(np.float32)

    args = (torch.as_tensor(_random_phenotypes(2, rng)), torch.as_tensor(gamma(2, 4)), torch.zeros(L, 2, H))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the exporter's note on GRU batch sizes: h0 is an input here
        torch.onnx.export(model, args, str(path), input_names=["phenotypes", "gamma", "h0"],
                          output_names=["wrinkle_displacement", "hT"], opset_version=OPSET, dynamo=False,
                          dynamic_axes={"phenotypes": {0: "B"}, "gamma": {0: "B", 1: "T"}, "h0": {1: "B"},
                                        "wrinkle_displacement": {0: "B", 1: "T"}, "hT": {1: "B"}})
    _add_metadata(path, _record_metadata(record))
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    worst = 0.0
    for B, T in ((1, 1), (1, 9), (3, 5)):
        p, g = _random_phenotypes(B, rng), gamma(B, T)
        h0 = (0.1 * rng.standard_normal((L, B, H))).astype(np.float32)
        y, hT = sess.run(None, {"phenotypes": p, "gamma": g, "h0": h0})
        with torch.no_grad():
            ry, rh = model(torch.as_tensor(p), torch.as_tensor(g), torch.as_tensor(h0))
        worst = max(worst, float(np.abs(y - ry.numpy()).max()), float(np.abs(hT - rh.numpy()).max()))
    if not worst <= PARITY_TOLERANCE_M:
        raise RuntimeError(f"{path.name}: parity {worst:.3g} exceeds {PARITY_TOLERANCE_M}")
    return {
        "file": path.name, "sha256": _sha256(path), "bytes": path.stat().st_size, "opset": OPSET,
        "inputs": {"phenotypes": ["B", 6], "gamma": ["B", "T", F], "h0": [L, "B", H]},
        "outputs": {"wrinkle_displacement": ["B", "T", model.output.num_vertices, 3], "hT": [L, "B", H]},
        "parity_max_abs": worst, "basis_size": model.output.size, "gru_layers": L, "gru_hidden": H, "descriptor_size": F,
        "config": record["config"], "steps": record["steps"], "train_wall_s": record["train_wall_s"],
        "metrics": record["metrics"], "git_commit": record.get("git_commit"),
        "training_frames": record.get("training_frames"),
        **({"output_basis": record["output_basis"]} if "output_basis" in record else {}),
    }


def export_garment(garment: str, checkpoints: Path = CHECKPOINT_DIR, out_dir: Path = MODELS_DIR, smoke: bool = False) -> dict:
    """Export ``checkpoints/<garment>/{fit,wrinkle}.pt`` to ``out_dir/<garment>/``; returns model.json.
    A garment with no wrinkle checkpoint exports its fit alone (``"wrinkle": null``: fit 'learned'
    and 'learned-canonical' run, dynamics 'learned' outside the canonical space does not)."""
    suffix = "_smoke" if smoke else ""
    fit_path = checkpoints / garment / f"fit{suffix}.pt"
    fit, fit_record = load_fit(fit_path)
    basis_spec = torch.load(fit_path, weights_only=False).get("basis_spec")
    wrinkle_path = checkpoints / garment / f"wrinkle{suffix}.pt"
    wrinkle, wrinkle_record = load_wrinkle(wrinkle_path) if wrinkle_path.exists() else (None, None)
    if wrinkle is not None and fit.output.num_vertices != wrinkle.output.num_vertices:
        raise ValueError(f"{garment}: fit has {fit.output.num_vertices} vertices, wrinkle {wrinkle.output.num_vertices}")
    d = out_dir / garment
    d.mkdir(parents=True, exist_ok=True)
    asset = GarmentCatalog.load().get(garment) if basis_spec is not None else None
    if wrinkle is None:
        (d / "wrinkle.onnx").unlink(missing_ok=True)
    entry = {
        "format": MODEL_FORMAT,
        "garment": garment,
        "vertices": fit.output.num_vertices,
        "model": "thesis eq. 4.2: retarget_fit(beta) + R_G(beta) + R_L(beta, gamma_1..t), then LBS with the garment's skin weights"
                 + ("" if wrinkle is not None else " (R_G only: no R_L)"),
        "fit_mode": "retarget_residual",
        "units": "metres; phenotypes raw in the adult box; gamma = inference.motion.descriptor.motion_descriptor at the clip fps",
        "fps": 30.0,
        "smoke": smoke,
        "fit": export_fit(fit, d / "fit.onnx", fit_record, basis_spec=basis_spec, asset=asset),
        "wrinkle": export_wrinkle(wrinkle, d / "wrinkle.onnx", wrinkle_record) if wrinkle is not None else None,
        "exported_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "export_git_commit": git_commit(),
    }
    entry["bytes_total"] = entry["fit"]["bytes"] + (entry["wrinkle"]["bytes"] if wrinkle is not None else 0)
    (d / "model.json").write_text(json.dumps(entry, indent=1) + "\n")
    log.info("%s: fit.onnx %.2f MB (parity %.2g m)%s", garment, entry["fit"]["bytes"] / 1e6, entry["fit"]["parity_max_abs_m"],
             "" if wrinkle is None else f", wrinkle.onnx {entry['wrinkle']['bytes'] / 1e6:.1f} MB (parity {entry['wrinkle']['parity_max_abs']:.2g})")
    return entry


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description="Export a garment's trained fit and wrinkle models to ONNX.")
    p.add_argument("--garment", nargs="+", required=True)
    p.add_argument("--checkpoints", type=Path, default=CHECKPOINT_DIR)
    p.add_argument("--out", type=Path, default=MODELS_DIR)
    p.add_argument("--smoke", action="store_true", help="export the *_smoke.pt checkpoints")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    for g in args.garment:
        export_garment(g, args.checkpoints, args.out, args.smoke)


if __name__ == "__main__":
    main()
