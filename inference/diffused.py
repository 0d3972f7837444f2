"""The diffused body model and the canonical garment model (thesis ch. 6.3.1-6.3.2), in numpy.

Eq. 6.4-6.5 give, for any point p near the canonical body (the neutral adult in the rest
A-pose), skinning weights W~(p) (J,) and shape offsets B~s(p, beta) (3,) by averaging the body's
surface values over a Gaussian neighbourhood whose width is the distance to the body; plus the
signed distance SDF(p) to the canonical skin. ``training.assets.build_diffused_body`` samples
them on a regular grid; this module reads them by trilinear interpolation:

    f(p) = sum over the 8 nodes c of the cell holding p of  prod_i (1 - |p_i - c_i| / h) f(c)

(clamped to the grid's box: a point beyond it takes the value at the box's face).

The canonical garment model (eq. 6.7-6.8, without pose correctives: anny has none):

    T_G(X, beta) = X + B~s(X, beta),   B~s(X, beta) = sum_k a_k(beta) U~_k(X),  a = (c(beta) - c_n) A
    M_G(X, beta, theta) = sum_j W~_j(X) T_j(beta, theta) T_G(X, beta)

with c the body's blendshape coefficients, c_n the neutral body's, and T_j the skinning
transforms of the shaped body from its rest pose (``BodyModel.pose``). X is the garment in the
canonical space: unposed and deshaped, on the neutral body.

Units: metres. Shapes: batch first; points (..., 3).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from inference.body import ASSETS_DIR, linear_blend_skinning
from inference.errors import InputShapeError

DEFAULT_PATH = ASSETS_DIR / "body" / "diffused.npz"


class Grid:
    """Channels sampled on a regular grid (nodes (nx, ny, nz), spacing h, corner ``origin``),
    read by trilinear interpolation (module docstring), clamped to the grid's box."""

    def __init__(self, origin: np.ndarray, spacing: float, fields: np.ndarray):
        if fields.ndim != 4 or min(fields.shape[:3]) < 2:
            raise InputShapeError("fields", "(nx, ny, nz, C), n >= 2", fields.shape)
        self.origin = np.asarray(origin, np.float32)
        self.spacing = float(spacing)
        self.dims = np.array(fields.shape[:3], np.int64)
        # (nodes, C) float32: numpy's float16 -> float32 conversion of the gathered rows costs
        # more than the gather itself (measured 6.4 against 1.8 ms for 5k points x 32 channels)
        self.table = np.ascontiguousarray(fields.reshape(-1, fields.shape[-1]), dtype=np.float32)
        self.strides = np.array([self.dims[1] * self.dims[2], self.dims[2], 1], np.int64)
        corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], np.int64)
        self._corner_offsets = corners @ self.strides  # the 8 corners of a cell as flat node offsets, i-major
        self._tables: dict[tuple, np.ndarray] = {}

    @property
    def channels(self) -> int:
        return int(self.table.shape[1])

    def cells(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The 8 corner nodes (N, 8) int64 of each point's cell and their trilinear weights (N, 8) float32."""
        u = (np.asarray(points, np.float32).reshape(-1, 3) - self.origin) * np.float32(1.0 / self.spacing)
        u = np.clip(u, 0.0, (self.dims - 1).astype(np.float32))
        i0 = np.minimum(u.astype(np.int64), self.dims - 2)
        t = u - i0  # (N, 3) in [0, 1]
        base = i0[:, 0] * self.strides[0] + i0[:, 1] * self.strides[1] + i0[:, 2]
        a = np.stack([1.0 - t, t], 1)  # (N, 2, 3): the 1-D weights of the lower and upper node per axis
        w = (a[:, :, None, None, 0] * a[:, None, :, None, 1] * a[:, None, None, :, 2]).reshape(len(u), 8)
        return base[:, None] + self._corner_offsets[None], w

    def _channel_table(self, channels: slice) -> np.ndarray:
        """A contiguous copy of some channels, kept (np.take would copy a strided view per call)."""
        key = channels.indices(self.channels)
        if key not in self._tables:
            self._tables[key] = np.ascontiguousarray(self.table[:, channels])
        return self._tables[key]

    def interpolate(self, points: np.ndarray, channels: slice = slice(None)) -> np.ndarray:
        """Trilinear interpolation at points (..., 3) -> (..., C') float32."""
        p = np.asarray(points, np.float32)
        idx, w = self.cells(p)
        table = self.table if channels == slice(None) else self._channel_table(channels)
        rows = np.take(table, idx.ravel(), axis=0).reshape(idx.shape + (table.shape[1],))  # (N, 8, C')
        out = np.einsum("nc,ncd->nd", w, rows, optimize=True)
        return out.reshape(p.shape[:-1] + (out.shape[-1],))


@dataclass(frozen=True)
class DiffusedSample:
    """The diffused fields at points (..., 3): weights (..., J) rows summing to 1, shape basis
    (..., r, 3) metres per unit coefficient, sdf (...) metres (negative inside the canonical body)."""

    weights: np.ndarray
    shape_basis: np.ndarray
    sdf: np.ndarray


class DiffusedBody:
    """W~ and SDF on one grid, the shape basis U~_k on a coarser one; see the module docstring."""

    def __init__(self, skin: Grid, shape: Grid, shape_map: np.ndarray, neutral_coeffs: np.ndarray, metadata: dict | None = None):
        self.bones = skin.channels - 1
        # the bones whose W~ is zero everywhere (fingers and toes, folded into hand and foot) are
        # dropped from the table: the lookup reads the others and the SDF, bone_index maps them back
        self.bone_index = np.flatnonzero(np.abs(skin.table[:, : self.bones]).max(0) > 0)
        skin.table = np.ascontiguousarray(skin.table[:, np.append(self.bone_index, self.bones)])
        self.skin_grid, self.shape_grid = skin, shape
        self.shape_map = np.asarray(shape_map, np.float32)
        self.neutral_coeffs = np.asarray(neutral_coeffs, np.float64)
        self.components = self.shape_map.shape[1]
        if shape.channels != 3 * self.components:
            raise InputShapeError("shape_fields", f"(mx, my, mz, {3 * self.components})", tuple(shape.dims) + (shape.channels,))
        self.metadata = metadata or {}

    @classmethod
    def load(cls, path: Path | str = DEFAULT_PATH) -> "DiffusedBody":
        with np.load(path, allow_pickle=False) as f:
            return cls(Grid(f["origin"], float(f["spacing"]), f["fields"]), Grid(f["origin"], float(f["shape_spacing"]), f["shape_fields"]),
                       f["shape_map"], f["neutral_coeffs"], json.loads(str(f["metadata"])))

    def _full_weights(self, w: np.ndarray) -> np.ndarray:
        """Clamped, normalised rows of the kept bones (..., K) -> (..., J)."""
        w = np.maximum(w, 0.0)
        w /= np.maximum(w.sum(-1, keepdims=True), 1e-12)
        out = np.zeros(w.shape[:-1] + (self.bones,), np.float32)
        out[..., self.bone_index] = w
        return out

    def weights(self, points: np.ndarray) -> np.ndarray:
        """W~(p) (eq. 6.4): (..., 3) -> (..., J) float32, non-negative rows summing to 1."""
        return self._full_weights(self.skin_grid.interpolate(points)[..., :-1])

    def sdf(self, points: np.ndarray) -> np.ndarray:
        """Signed distance to the canonical skin (metres, negative inside): (..., 3) -> (...)."""
        return self.skin_grid.interpolate(points, slice(-1, None))[..., 0]

    def sample(self, points: np.ndarray) -> DiffusedSample:
        """W~, U~ and SDF at points (..., 3)."""
        skin = self.skin_grid.interpolate(points)
        w = self._full_weights(skin[..., :-1])
        basis = self.shape_grid.interpolate(points)
        return DiffusedSample(weights=w, shape_basis=basis.reshape(basis.shape[:-1] + (self.components, 3)), sdf=skin[..., -1])

    def shape_coefficients(self, body_coeffs: np.ndarray) -> np.ndarray:
        """a(beta) = (c(beta) - c_n) A: (B, 135) blendshape coefficients -> (B, r) float32."""
        c = np.asarray(body_coeffs, np.float64)
        return ((c - self.neutral_coeffs) @ self.shape_map.astype(np.float64)).astype(np.float32)

    def shape_offsets(self, points: np.ndarray, body_coeffs: np.ndarray) -> np.ndarray:
        """B~s(p, beta) (eq. 6.5): points (B, V, 3), body_coeffs (B, 135) -> offsets (B, V, 3) metres."""
        basis = self.shape_grid.interpolate(points)  # (B, V, 3r)
        basis = basis.reshape(basis.shape[:-1] + (self.components, 3))
        return np.einsum("bvkc,bk->bvc", basis, self.shape_coefficients(body_coeffs), optimize=True)

    def deshaped_to_shaped(self, X: np.ndarray, body_coeffs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """T_G(X, beta) = X + B~s(X, beta) (eq. 6.8) and W~(X) (eq. 6.4).

        X : (B, V, 3) canonical garment ; body_coeffs : (B, 135) the bodies' blendshape coefficients
        returns the shaped rest garment (B, V, 3) float32 metres and its weights (B, V, J) float32
        """
        X = np.asarray(X, np.float32)
        if X.ndim != 3 or X.shape[-1] != 3:
            raise InputShapeError("X", "(B, V, 3)", X.shape)
        return X + self.shape_offsets(X, body_coeffs), self.weights(X)

    def offset_grid(self, body_coeffs: np.ndarray) -> Grid:
        """B~s(., beta) of one body as a 3-channel grid: the basis contracted with a(beta) once
        per body, sum_k a_k U~_k(node), so a lookup reads 3 channels instead of 3 r.
        body_coeffs : (135,) or (1, 135)."""
        a = self.shape_coefficients(np.asarray(body_coeffs, np.float64).reshape(1, -1))[0]
        table = self.shape_grid.table.reshape(len(self.shape_grid.table), self.components, 3)
        fields = np.einsum("nkc,k->nc", table, a, optimize=True).reshape(tuple(self.shape_grid.dims) + (3,))
        return Grid(self.shape_grid.origin, self.shape_grid.spacing, fields)

    def pose(self, X: np.ndarray, offsets: Grid, transforms: np.ndarray) -> np.ndarray:
        """M_G(X, beta, theta) (eq. 6.7) with W~ and B~s at each frame's own canonical points.

        X          : (T, V, 3) canonical garment per frame, metres
        offsets    : ``offset_grid(beta)``
        transforms : (T, J, 4, 4) the body's skinning transforms per frame
        returns      (T, V, 3) float32 posed garment
        """
        X = np.asarray(X, np.float32)
        if X.ndim != 3 or X.shape[-1] != 3:
            raise InputShapeError("X", "(T, V, 3)", X.shape)
        if transforms.shape != (len(X), self.bones, 4, 4):
            raise InputShapeError("transforms", f"({len(X)}, {self.bones}, 4, 4)", transforms.shape)
        w = np.maximum(self.skin_grid.interpolate(X, slice(0, -1)), 0.0)  # (T, V, K) over the kept bones
        w /= np.maximum(w.sum(-1, keepdims=True), 1e-12)
        shaped = X + offsets.interpolate(X)
        A = np.matmul(w, np.asarray(transforms, np.float32)[:, self.bone_index, :3, :].reshape(len(X), -1, 12))  # (T, V, 12)
        A = A.reshape(X.shape[:2] + (3, 4))
        return np.einsum("tvab,tvb->tva", A[..., :3], shaped, optimize=True) + A[..., 3]

    def fields_at(self, points: np.ndarray, body_coeffs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """W~ (V, J) and B~s(., beta) (V, 3) at one set of points (V, 3): the skinning attributes
        of a request's garment frozen at one canonical shape (``pose_frozen``); the shape basis is
        read at the points and contracted there (V x 3 r), not over the whole grid."""
        p = np.asarray(points, np.float32)
        a = self.shape_coefficients(np.asarray(body_coeffs, np.float64).reshape(1, -1))[0]
        basis = self.shape_grid.interpolate(p).reshape(len(p), self.components, 3)
        return self.weights(p), np.einsum("vkc,k->vc", basis, a, optimize=True)

    def pose_frozen(self, X: np.ndarray, weights: np.ndarray, offsets: np.ndarray, transforms: np.ndarray) -> np.ndarray:
        """eq. 6.7 with W~ and B~s frozen at one canonical shape X_bar (``fields_at(X_bar)``):
        sum_j W~_j(X_bar) T_j (X_t + B~s(X_bar, beta)) for every frame t. Differs from ``pose``
        by the change of the fields between X_bar and X_t (measured in docs/benchmarks.md).

        X : (T, V, 3) ; weights : (V, J) ; offsets : (V, 3) ; transforms (T, J, 4, 4) -> (T, V, 3) float32
        """
        X = np.asarray(X, np.float32)
        if X.ndim != 3 or X.shape[1:] != offsets.shape or weights.shape != (X.shape[1], self.bones):
            raise InputShapeError("X", f"(T, {len(offsets)}, 3) with weights ({len(offsets)}, {self.bones})", X.shape)
        return linear_blend_skinning((X + offsets)[None], weights, np.asarray(transforms, np.float32)[None])[0]
