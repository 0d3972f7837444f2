"""Learned garment models at runtime (onnxruntime, no torch): R_G and R_L of thesis eq. 4.2.

    T_c(beta, gamma_1..t) = retarget_fit(beta) + R_G(beta) + R_L(beta, gamma_1..t)   (eq. 4.2)

R_G (``fit.onnx``) is a residual on the ``.mhclo`` retarget fit (``GarmentAsset.retarget_fit``);
R_L (``wrinkle.onnx``) is the SNUG wrinkle GRU over the motion descriptor gamma
(``inference.motion.descriptor``), one ORT call for a whole sequence, with its GRU state in and
out so that a long sequence can be processed in chunks. Both are trained by
``training.train_fit`` / ``training.train_wrinkle`` and exported by ``training.export_onnx`` to
``assets/models/<garment_id>/{fit.onnx, wrinkle.onnx, model.json}``.

A ``fit.onnx`` may answer the coefficients of a geodesic output basis instead of displacements
(``model.json``'s ``fit.basis``: node ids and sigma, ``inference.fit_basis``): the basis is rebuilt
here from the garment's template, once per load, and R_G = Phi @ coefficients. A garment may ship
R_G alone (``"wrinkle": null``): its dynamics 'learned' is then only the canonical model's.

``LearnedModels`` is the registry the pipeline uses: each garment's models are loaded on first
use, once; a garment without models raises ``MissingModelError``.
"""
from __future__ import annotations

import json
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort

from inference.body import ASSETS_DIR
from inference.errors import InputShapeError, InputValueError, UnknownAssetError
from inference.fit_basis import geodesic_rbf_basis
from inference.garment import GarmentAsset

MODELS_DIR = ASSETS_DIR / "models"


class MissingModelError(UnknownAssetError):
    """A learned fit or dynamics mode was asked for a garment that ships no learned models."""


def ort_session(path: Path, threads: int) -> ort.InferenceSession:
    """A CPU onnxruntime session of ``threads`` intra-op threads, quiet logs."""
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.log_severity_level = 3
    return ort.InferenceSession(str(path), sess_options=opts, providers=["CPUExecutionProvider"])


@dataclass
class LearnedGarment:
    """The ONNX fit and wrinkle models of one garment.

    meta : model.json (training config, metrics, input/output shapes)
    fit_basis : (V, K) float32, the geodesic basis the fit's coefficients multiply (None: fit.onnx
                answers displacements)
    wrinkle_session : None where the garment ships R_G alone
    """

    garment_id: str
    meta: dict
    fit_session: ort.InferenceSession
    wrinkle_session: ort.InferenceSession | None
    fit_basis: np.ndarray | None = None

    @classmethod
    def load(cls, directory: Path | str, threads: int = 1, garment: GarmentAsset | None = None) -> "LearnedGarment":
        """Load ``directory/{model.json, fit.onnx[, wrinkle.onnx]}``; ``garment`` (a
        ``GarmentAsset``) is needed where the fit ships a geodesic basis to rebuild."""
        directory = Path(directory)
        meta_path = directory / "model.json"
        if not meta_path.exists():
            raise MissingModelError("garment", f"no learned models for garment {directory.name!r} ({meta_path} is missing)")
        meta = json.loads(meta_path.read_text())
        basis = meta["fit"].get("basis")
        phi = None
        if basis is not None:
            if basis.get("kind") != "geodesic" or garment is None:
                raise ValueError(f"{meta_path}: fit basis {basis.get('kind')!r} needs 'geodesic' and the garment's template")
            phi = geodesic_rbf_basis(garment.vertices, garment.edges, np.asarray(basis["nodes"], np.int64), float(basis["sigma_m"]))
            if phi.shape != (int(meta["vertices"]), int(meta["fit"]["basis_size"])):
                raise ValueError(f"{meta_path}: basis {phi.shape} against {meta['vertices']} vertices, {meta['fit']['basis_size']} nodes")
        return cls(
            garment_id=str(meta["garment"]),
            meta=meta,
            fit_session=ort_session(directory / meta["fit"]["file"], threads),
            wrinkle_session=ort_session(directory / meta["wrinkle"]["file"], threads) if meta.get("wrinkle") else None,
            fit_basis=phi,
        )

    @property
    def has_wrinkles(self) -> bool:
        """Whether the garment ships R_L (wrinkle.onnx)."""
        return self.wrinkle_session is not None

    @property
    def num_vertices(self) -> int:
        return int(self.meta["vertices"])

    @property
    def descriptor_size(self) -> int:
        if self.wrinkle_session is None:
            raise MissingModelError("/options/dynamics", f"garment {self.garment_id!r} ships no wrinkle model (R_L)")
        return int(self.meta["wrinkle"]["descriptor_size"])

    @property
    def state_shape(self) -> tuple[int, int]:
        """(L, H): GRU layers and hidden size; the state is (L, B, H)."""
        return int(self.meta["wrinkle"]["gru_layers"]), int(self.meta["wrinkle"]["gru_hidden"])

    @staticmethod
    def _phenotypes(phenotypes: np.ndarray) -> np.ndarray:
        p = np.ascontiguousarray(phenotypes, np.float32)
        if p.ndim != 2 or p.shape[1] != 6:
            raise InputShapeError("phenotypes", "(B, 6)", p.shape)
        if not np.isfinite(p).all():
            raise InputValueError("phenotypes", "must be finite")
        return p

    def fit(self, phenotypes: np.ndarray) -> np.ndarray:
        """R_G: fit displacements on top of the retarget fit.

        phenotypes : (B, 6) float32, PHENOTYPE_LABELS order, in the adult box
        returns    : (B, V, 3) float32 metres (add to ``GarmentAsset.retarget_fit``)
        """
        (out,) = self.fit_session.run(None, {"phenotypes": self._phenotypes(phenotypes)})
        if self.fit_basis is not None:  # (B, K, 3) coefficients: one GEMM (V, K) @ (K, 3B)
            B, K = out.shape[:2]
            out = (self.fit_basis @ out.transpose(1, 0, 2).reshape(K, 3 * B)).reshape(-1, B, 3).transpose(1, 0, 2)
        return np.ascontiguousarray(out, np.float32)

    def wrinkles(self, phenotypes: np.ndarray, gamma: np.ndarray, h0: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """R_L over a whole sequence in one call.

        phenotypes : (B, 6) float32
        gamma      : (B, T, F) float32 motion descriptor (inference.motion.descriptor, 30 fps)
        h0         : (L, B, H) float32 GRU state from the previous chunk, or None (zeros: the
                     start of a sequence)
        returns    : displacements (B, T, V, 3) float32 metres (unposed, added to the fit) and
                     the final state hT (L, B, H)
        """
        if self.wrinkle_session is None:
            raise MissingModelError("/options/dynamics", f"garment {self.garment_id!r} ships no wrinkle model (R_L); "
                                                         "use dynamics='none', or fit='canonical' where it has a canonical model")
        p = self._phenotypes(phenotypes)
        g = np.ascontiguousarray(gamma, np.float32)
        B, F = p.shape[0], self.descriptor_size
        if g.ndim != 3 or g.shape[0] != B or g.shape[2] != F:
            raise InputShapeError("gamma", f"({B}, T, {F})", g.shape)
        L, H = self.state_shape
        if h0 is None:
            h0 = np.zeros((L, B, H), np.float32)
        h0 = np.ascontiguousarray(h0, np.float32)
        if h0.shape != (L, B, H):
            raise InputShapeError("h0", f"({L}, {B}, {H})", h0.shape)
        if g.shape[1] == 0:
            return np.zeros((B, 0, self.num_vertices, 3), np.float32), h0
        delta, h_t = self.wrinkle_session.run(None, {"phenotypes": p, "gamma": g, "h0": h0})
        return delta, h_t


class LearnedModels:
    """Registry of learned garment models under ``models_dir/<garment_id>/``: loaded lazily,
    once per garment (thread-safe), shared by every request."""

    def __init__(self, models_dir: Path | str = MODELS_DIR, threads: int = 1, garments_dir: Path | str | None = None):
        self.models_dir = Path(models_dir)
        self.garments_dir = Path(garments_dir) if garments_dir is not None else self.models_dir.parent / "garments"
        self.threads = threads
        self._loaded: dict[str, LearnedGarment] = {}
        self._lock = threading.Lock()

    def available(self, garment_id: str) -> bool:
        """Whether ``garment_id`` ships learned models (without loading them)."""
        return (self.models_dir / garment_id / "model.json").exists()

    def load_all(self, garment_ids) -> list[str]:
        """Load every listed garment that ships learned models now (a service's start-up, so that
        no request pays for it and a broken model stops the start); the ids loaded."""
        loaded = [g for g in garment_ids if self.available(g)]
        for g in loaded:
            self.get(g)
        return loaded

    def get(self, garment_id: str, field: str = "garment") -> LearnedGarment:
        """The garment's models; ``MissingModelError`` (naming ``field``) if it has none."""
        with self._lock:
            if garment_id not in self._loaded:
                if not self.available(garment_id):
                    raise MissingModelError(field, f"garment {garment_id!r} has no learned models (assets/models/{garment_id}/); "
                                                       "use fit='retarget' and dynamics='none'")
                self._loaded[garment_id] = LearnedGarment.load(self.models_dir / garment_id, self.threads, self._garment(garment_id))
            return self._loaded[garment_id]

    def _garment(self, garment_id: str) -> GarmentAsset | None:
        """The garment's asset where its fit ships a geodesic basis (rebuilt from the template), else None."""
        meta = json.loads((self.models_dir / garment_id / "model.json").read_text())
        return GarmentAsset.load(self.garments_dir / garment_id) if meta["fit"].get("basis") else None


_DEFAULT: LearnedModels | None = None


def default_models() -> LearnedModels:
    """The process-wide registry over the repository's ``assets/models``."""
    global _DEFAULT
    if _DEFAULT is None:
        _DEFAULT = LearnedModels()
    return _DEFAULT
