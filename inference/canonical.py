"""The canonical-space garment model at runtime (thesis ch. 6.3.2), fit 'canonical'.

A garment X in the canonical space (unposed, deshaped: on the neutral body in its rest pose) is
shaped and posed by the diffused body (``inference.diffused``, eq. 6.7-6.8):

    M_G(X, beta, theta) = sum_j W~_j(X) T_j(beta, theta) (X + B~s(X, beta))

with W~ and B~s read at the garment's own canonical points, not fixed per vertex. The canonical
body is constant, so a garment outside it (SDF(X) >= margin, one lookup) stays outside the posed
body wherever the body's own deformation does not fold space onto itself (the armpit and the
crotch when the limbs close, the arms sunk into a heavy torso): there the final exact stage
(``inference.repair``) moves the few vertices it must.

X is the garment's template pushed out of the canonical body to ``margin_m`` (``push_out``: the
templates are made collision-free on the neutral body, 4 mm - 13 cm from its skin, so this moves
nothing on the shipped catalog; it guards a template added later).

Units: metres. Arrays: float32, batch axis first.
"""
from __future__ import annotations

import threading
from pathlib import Path

import numpy as np

from inference.diffused import DEFAULT_PATH, DiffusedBody
from inference.errors import InputShapeError
from inference.garment import GarmentAsset

# Central-difference step of the SDF gradient, metres (well inside the fine grid's 15 mm cells).
GRADIENT_STEP_M = 0.002
# Push iterations: the trilinear SDF is not exactly a distance, so a point is pushed again from
# where the last push left it (on points within 4 mm of the neutral skin, 3 passes left 4 %
# of them more than 0.5 mm short of the margin, at the head and toes; 6 passes left 0.25 %).
PUSH_STEPS = 6


def sdf_gradient(diffused: DiffusedBody, points: np.ndarray) -> np.ndarray:
    """Unit gradient (N, 3) of the canonical SDF at points (N, 3), by central differences."""
    h = np.float32(GRADIENT_STEP_M)
    e = np.eye(3, dtype=np.float32) * h
    probe = np.concatenate([points[:, None] + e[None], points[:, None] - e[None]], 1)  # (N, 6, 3)
    s = diffused.sdf(probe)
    g = (s[:, :3] - s[:, 3:]) / (2 * h)
    return g / np.maximum(np.linalg.norm(g, axis=-1, keepdims=True), 1e-12)


def push_out(diffused: DiffusedBody, X: np.ndarray, margin_m: float, steps: int = PUSH_STEPS) -> tuple[np.ndarray, int]:
    """Points with SDF(X) < margin moved along the SDF's gradient to SDF = margin:
    X' = X + (margin - SDF(X)) grad SDF / |grad SDF|, repeated ``steps`` times.

    X : (..., 3) canonical points, metres ; returns (X' float32 (..., 3), number of points moved)
    """
    X = np.array(X, np.float32, copy=True)
    if X.shape[-1] != 3:
        raise InputShapeError("X", "(..., 3)", X.shape)
    flat = X.reshape(-1, 3)
    moved = np.zeros(len(flat), bool)
    for _ in range(steps):
        s = diffused.sdf(flat)
        low = np.flatnonzero(s < margin_m)
        if not len(low):
            break
        moved[low] = True
        flat[low] += (margin_m - s[low])[:, None] * sdf_gradient(diffused, flat[low])
    return X, int(moved.sum())


class CanonicalModels:
    """The diffused body and each garment's canonical form, loaded once, shared by every request."""

    def __init__(self, diffused_path: Path | str = DEFAULT_PATH):
        self.diffused_path = Path(diffused_path)
        self._diffused: DiffusedBody | None = None
        self._templates: dict[str, np.ndarray] = {}
        self._lock = threading.Lock()

    @property
    def diffused(self) -> DiffusedBody:
        with self._lock:
            if self._diffused is None:
                self._diffused = DiffusedBody.load(self.diffused_path)
            return self._diffused

    def template(self, garment: GarmentAsset) -> np.ndarray:
        """X of the garment (V, 3) float32: its template pushed out of the canonical body to its
        collision margin (``material.collision_margin_m``)."""
        diffused = self.diffused
        with self._lock:
            if garment.id not in self._templates:
                margin = float(garment.material.get("collision_margin_m", 0.003))
                self._templates[garment.id] = push_out(diffused, garment.template, margin)[0]
            return self._templates[garment.id]

    def rest_fit(self, garment: GarmentAsset, rest_vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The garment shaped to a body in its rest pose, T_G(X, beta) = X + B~s(X, beta) (eq. 6.8),
        (V, 3) float32, and its skinning weights W~(X) (V, J) (eq. 6.4), X the canonical form.

        rest_vertices : (Vb, 3) the body's rest vertices (``BodyShape.rest_vertices[0]``)
        """
        X = self.template(garment)
        d = self.diffused
        return d.deshaped_to_shaped(X, d.offsets(rest_vertices)), d.weights(X)


_DEFAULT: CanonicalModels | None = None


def default_canonical() -> CanonicalModels:
    """The process-wide canonical models over the repository's assets."""
    global _DEFAULT
    if _DEFAULT is None:
        _DEFAULT = CanonicalModels()
    return _DEFAULT
