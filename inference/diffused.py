"""The diffused body model and the canonical garment model (thesis ch. 6.3.1-6.3.2), in numpy.

Eq. 6.4-6.5 give, for any point p near the canonical body (the neutral adult in the rest
A-pose), skinning weights W~(p) (J,) and shape offsets B~s(p, beta) (3,) by averaging the body's
surface values over a Gaussian neighbourhood whose width is the distance to the body; plus the
signed distance SDF(p) to the canonical skin. ``training.assets.build_diffused_body`` stores, at
the nodes of two grids, the *kernel* of that average: skin vertices k_j and weights c_j with

    W~(node) = sum_j c_j W(k_j),      B~s(node, beta) = sum_j c_j (v_{k_j}(beta) - v_{k_j}(neutral))

so W~ is contracted once at load, B~s once per body (``offsets``), from the body's own rest
vertices: exact at the skin for every body. A point reads the fields by trilinear interpolation

    f(p) = sum over the 8 nodes c of the cell holding p of  prod_i (1 - |p_i - c_i| / h) f(c)

on the fine grid, which holds the band of nodes around the skin (``BandGrid``); a corner outside
the band takes the coarse grid's interpolation at that corner, so f is continuous everywhere.
Points beyond the box take the value at its face (clamped).

The canonical garment model (eq. 6.7-6.8, without pose correctives: anny has none):

    T_G(X, beta) = X + B~s(X, beta)
    M_G(X, beta, theta) = sum_j W~_j(X) T_j(beta, theta) T_G(X, beta)

with T_j the skinning transforms of the shaped body from its rest pose (``BodyModel.pose``).
X is the garment in the canonical space: unposed and deshaped, on the neutral body.

Units: metres. Shapes: batch first; points (..., 3).
"""
from __future__ import annotations

import json
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse

from inference import diffused_kernels as kernels
from inference.body import ASSETS_DIR
from inference.errors import InputShapeError

DEFAULT_PATH = ASSETS_DIR / "body" / "diffused.npz"
# Points interpolated at once: bounds the (points, 8, channels) gather (~24 channels: 6 MB).
POINT_BLOCK = 8192
# Bodies whose contracted offsets are kept (a request's body is contracted once).
OFFSET_CACHE = 8
CORNERS = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], np.int64)  # i-major


class Grid:
    """A regular grid (nodes ``dims`` (nx, ny, nz), spacing h, corner ``origin``) and, optionally,
    channels at its nodes (``table`` (nodes, C), i-major), read by trilinear interpolation (module
    docstring), clamped to the grid's box."""

    def __init__(self, origin: np.ndarray, spacing: float, dims, table: np.ndarray | None = None):
        self.origin = np.asarray(origin, np.float32)
        self.spacing = float(spacing)
        self.dims = np.array([int(d) for d in dims], np.int64)
        if len(self.dims) != 3 or self.dims.min() < 2:
            raise InputShapeError("dims", "(nx, ny, nz), n >= 2", tuple(self.dims))
        n = int(np.prod(self.dims))
        self.table = np.zeros((n, 0), np.float32) if table is None else np.ascontiguousarray(table, np.float32).reshape(n, -1)
        self.strides = np.array([self.dims[1] * self.dims[2], self.dims[2], 1], np.int64)
        self.corner_offsets = CORNERS @ self.strides

    @classmethod
    def from_fields(cls, origin: np.ndarray, spacing: float, fields: np.ndarray) -> "Grid":
        """A grid of fields (nx, ny, nz, C)."""
        if fields.ndim != 4:
            raise InputShapeError("fields", "(nx, ny, nz, C)", fields.shape)
        return cls(origin, spacing, fields.shape[:3], fields.reshape(-1, fields.shape[-1]))

    @property
    def channels(self) -> int:
        return int(self.table.shape[1])

    def cells(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each point's cell: its lowest node (N, 3) int64, the 8 corner nodes (N, 8) as flat
        ids (i-major) and their trilinear weights (N, 8) float32."""
        u = (np.asarray(points, np.float32).reshape(-1, 3) - self.origin) * np.float32(1.0 / self.spacing)
        u = np.clip(u, 0.0, (self.dims - 1).astype(np.float32))
        i0 = np.minimum(u.astype(np.int64), self.dims - 2)
        t = u - i0  # (N, 3) in [0, 1]
        a = np.stack([1.0 - t, t], 1)  # (N, 2, 3): the 1-D weights of the lower and upper node per axis
        w = (a[:, :, None, None, 0] * a[:, None, :, None, 1] * a[:, None, None, :, 2]).reshape(len(u), 8)
        return i0, (i0 @ self.strides)[:, None] + self.corner_offsets[None], w

    def interpolate(self, points: np.ndarray, table: np.ndarray | None = None) -> np.ndarray:
        """Trilinear interpolation at points (..., 3) of ``table`` (nodes, C) (default the grid's own) -> (..., C) float32."""
        table = self.table if table is None else table
        p = np.asarray(points, np.float32)
        _, idx, w = self.cells(p)
        rows = np.take(table, idx.ravel(), axis=0).reshape(idx.shape + (table.shape[1],))
        out = np.einsum("nc,ncd->nd", w, rows, optimize=True)
        return out.reshape(p.shape[:-1] + (table.shape[1],))


class BandGrid:
    """A fine grid whose nodes exist only on a band (``fine_nodes``: flat ids), over a coarse grid
    with every node, sharing one origin; tables are (n_fine, C) and (n_coarse, C). A point
    interpolates the fine cell holding it; a corner outside the band takes the coarse grid's
    trilinear value at that corner (continuous across the band's edge)."""

    def __init__(self, origin: np.ndarray, fine_spacing: float, fine_dims: np.ndarray, fine_nodes: np.ndarray,
                 coarse_spacing: float, coarse_dims: np.ndarray):
        origin = np.asarray(origin, np.float32)
        self.fine = Grid(origin, fine_spacing, fine_dims)
        self.coarse = Grid(origin, coarse_spacing, coarse_dims)
        self.row = np.full(int(np.prod(self.fine.dims)), -1, np.int32)  # fine flat id -> band row, -1 off the band
        self.row[np.asarray(fine_nodes, np.int64)] = np.arange(len(fine_nodes), dtype=np.int32)
        self.fine_count = len(fine_nodes)
        self.coarse_count = int(np.prod(self.coarse.dims))

    def _block(self, p: np.ndarray, fine: np.ndarray, coarse: np.ndarray) -> np.ndarray:
        i0, idx, w = self.fine.cells(p)
        rows = self.row[idx]  # (N, 8)
        vals = np.take(fine, np.maximum(rows, 0).ravel(), axis=0).reshape(rows.shape + (fine.shape[1],))
        off = rows < 0
        if off.any():
            n, c = np.nonzero(off)
            corner = self.fine.origin + self.fine.spacing * (i0[n] + CORNERS[c]).astype(np.float32)
            vals[n, c] = self.coarse.interpolate(corner, coarse)
        return np.einsum("nc,ncd->nd", w, vals, optimize=True)

    def operators(self, points: np.ndarray) -> tuple[scipy.sparse.csr_matrix, scipy.sparse.csr_matrix]:
        """The interpolation at points (N, 3) as two sparse matrices, P_fine (N, n_fine) and
        P_coarse (N, n_coarse): ``interpolate(points, fine, coarse) = P_fine fine + P_coarse coarse``
        (a corner off the band spread over the coarse cell holding it). For points read many
        times, or composed with the diffusion kernels (``DiffusedBody.shape_operator``)."""
        p = np.asarray(points, np.float32).reshape(-1, 3)
        i0, idx, w = self.fine.cells(p)
        rows = self.row[idx]
        on = rows >= 0
        n_on, c_on = np.nonzero(on)
        P_fine = scipy.sparse.csr_matrix((w[on], (n_on, rows[on])), shape=(len(p), self.fine_count))
        n_off, c_off = np.nonzero(~on)
        corner = self.fine.origin + self.fine.spacing * (i0[n_off] + CORNERS[c_off]).astype(np.float32)
        _, cidx, cw = self.coarse.cells(corner)
        vals = (w[n_off, c_off][:, None] * cw).ravel()
        P_coarse = scipy.sparse.csr_matrix((vals, (np.repeat(n_off, 8), cidx.ravel())), shape=(len(p), self.coarse_count))
        return P_fine, P_coarse

    def interpolate(self, points: np.ndarray, fine: np.ndarray, coarse: np.ndarray) -> np.ndarray:
        """The fields of ``fine`` (n_fine, C) and ``coarse`` (n_coarse, C) at points (..., 3) -> (..., C) float32
        (compiled: ``inference.diffused_kernels``)."""
        p = np.asarray(points, np.float32)
        flat = np.ascontiguousarray(p.reshape(-1, 3))
        out = kernels.band_interpolate(
            flat, self.fine.origin, np.float32(self.fine.spacing), np.float32(1.0 / self.fine.spacing), self.fine.dims, self.row,
            np.ascontiguousarray(fine, np.float32), np.float32(1.0 / self.coarse.spacing), self.coarse.dims,
            np.ascontiguousarray(coarse, np.float32))
        return out.reshape(p.shape[:-1] + (fine.shape[1],))

    def interpolate_pair(self, points: np.ndarray, fine: np.ndarray, coarse: np.ndarray, fine2: np.ndarray,
                         coarse2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``interpolate`` of two tables at the same points, (..., C) and (..., C2), in one pass
        (each bitwise its own ``interpolate``)."""
        p = np.asarray(points, np.float32)
        flat = np.ascontiguousarray(p.reshape(-1, 3))
        out, out2 = kernels.band_interpolate_pair(
            flat, self.fine.origin, np.float32(self.fine.spacing), np.float32(1.0 / self.fine.spacing), self.fine.dims, self.row,
            np.ascontiguousarray(fine, np.float32), np.float32(1.0 / self.coarse.spacing), self.coarse.dims,
            np.ascontiguousarray(coarse, np.float32), np.ascontiguousarray(fine2, np.float32), np.ascontiguousarray(coarse2, np.float32))
        return out.reshape(p.shape[:-1] + (fine.shape[1],)), out2.reshape(p.shape[:-1] + (fine2.shape[1],))

    def interpolate_numpy(self, points: np.ndarray, fine: np.ndarray, coarse: np.ndarray) -> np.ndarray:
        """``interpolate`` in numpy, POINT_BLOCK points at a time (the reference of the compiled one in the tests)."""
        p = np.asarray(points, np.float32)
        flat = p.reshape(-1, 3)
        out = np.empty((len(flat), fine.shape[1]), np.float32)
        for a in range(0, len(flat), POINT_BLOCK):
            out[a:a + POINT_BLOCK] = self._block(flat[a:a + POINT_BLOCK], fine, coarse)
        return out.reshape(p.shape[:-1] + (fine.shape[1],))


class Kernel:
    """One level's diffusion kernels: skin vertex ids (n, K) and weights (n, K), rows summing to 1,
    held as a sparse (n, V) matrix."""

    def __init__(self, index: np.ndarray, weight: np.ndarray, num_vertices: int):
        n, k = index.shape
        self.matrix = scipy.sparse.csr_matrix((np.asarray(weight, np.float32).ravel(), np.asarray(index, np.int64).ravel(),
                                               np.arange(0, n * k + 1, k)), shape=(n, num_vertices))

    def contract(self, values: np.ndarray) -> np.ndarray:
        """sum_j c_j values[k_j]: values (V, C) -> (n, C) float32."""
        return np.asarray(self.matrix @ np.asarray(values, np.float32), np.float32)


@dataclass(frozen=True)
class BodyOffsets:
    """B~s(., beta) of one body at both levels' nodes: fine (n_fine, 3), coarse (n_coarse, 3), metres."""

    fine: np.ndarray
    coarse: np.ndarray


class DiffusedBody:
    """W~, SDF and B~s of the canonical body (module docstring)."""

    def __init__(self, arrays: dict[str, np.ndarray], metadata: dict | None = None):
        a = arrays
        self.grid = BandGrid(a["origin"], float(a["fine_spacing"]), a["fine_dims"], a["fine_nodes"],
                             float(a["coarse_spacing"]), a["coarse_dims"])
        self.neutral_vertices = np.asarray(a["neutral_vertices"], np.float32)
        self.kernels = {lvl: Kernel(a[f"{lvl}_index"], a[f"{lvl}_weight"], len(self.neutral_vertices)) for lvl in ("fine", "coarse")}
        weights = np.asarray(a["vertex_weights"], np.float32)
        self.bones = weights.shape[1]
        # bones with no weight anywhere (fingers and toes, folded into hand and foot) are left out
        # of the tables; bone_index maps the kept ones back
        self.bone_index = np.flatnonzero(weights.max(0) > 0)
        # skin tables: W~ over the kept bones, then the SDF, as one gather
        self.skin = {lvl: np.ascontiguousarray(np.concatenate([k.contract(weights[:, self.bone_index]),
                                                               np.asarray(a[f"{lvl}_sdf"], np.float32)[:, None]], 1))
                     for lvl, k in self.kernels.items()}
        self.sdf_tables = {lvl: np.ascontiguousarray(t[:, -1:]) for lvl, t in self.skin.items()}
        self.metadata = metadata or {}
        self._offsets: OrderedDict[bytes, BodyOffsets] = OrderedDict()

    @classmethod
    def load(cls, path: Path | str = DEFAULT_PATH) -> "DiffusedBody":
        with np.load(path, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files if k != "metadata"}
            metadata = json.loads(str(f["metadata"])) if "metadata" in f.files else {}
        return cls(arrays, metadata)

    # ------------------------------------------------------------------ fields
    def _skin(self, points: np.ndarray) -> np.ndarray:
        """W~ over the kept bones and the SDF at points (..., 3) -> (..., K + 1), one gather."""
        return self.grid.interpolate(points, self.skin["fine"], self.skin["coarse"])

    def _full_weights(self, w: np.ndarray) -> np.ndarray:
        """Clamped, normalised rows over the kept bones (..., K) -> (..., J)."""
        w = np.maximum(w, 0.0)
        w /= np.maximum(w.sum(-1, keepdims=True), 1e-12)
        out = np.zeros(w.shape[:-1] + (self.bones,), np.float32)
        out[..., self.bone_index] = w
        return out

    def fields(self, points: np.ndarray) -> np.ndarray:
        """W~ over the kept bones (unnormalised) and the SDF at points (..., 3) -> (..., K + 1)
        float32, one gather: what ``pose`` reads (its ``fields``), its last channel ``sdf``'s value."""
        return self._skin(np.asarray(points, np.float32))

    def fields_and_offsets(self, points: np.ndarray, offsets: BodyOffsets) -> tuple[np.ndarray, np.ndarray]:
        """``fields`` and ``shape_offsets`` at points (..., 3) in one pass over the grids: (..., K + 1)
        and (..., 3) float32, each bitwise what its own call gives."""
        return self.grid.interpolate_pair(np.asarray(points, np.float32), self.skin["fine"], self.skin["coarse"], offsets.fine,
                                          offsets.coarse)

    def weights(self, points: np.ndarray) -> np.ndarray:
        """W~(p) (eq. 6.4): (..., 3) -> (..., J) float32, non-negative rows summing to 1."""
        return self._full_weights(self._skin(points)[..., :-1])

    def sdf(self, points: np.ndarray) -> np.ndarray:
        """Signed distance to the canonical skin (metres, negative inside): (..., 3) -> (...)."""
        return self.grid.interpolate(points, self.sdf_tables["fine"], self.sdf_tables["coarse"])[..., 0]

    def offsets(self, rest_vertices: np.ndarray) -> BodyOffsets:
        """B~s(., beta) at the nodes for a body with rest vertices (V, 3) (``BodyShape.rest_vertices[0]``),
        contracted once per body (the last ``OFFSET_CACHE`` bodies are kept)."""
        v = np.asarray(rest_vertices, np.float32)
        if v.shape != self.neutral_vertices.shape:
            raise InputShapeError("rest_vertices", str(self.neutral_vertices.shape), v.shape)
        key = v.tobytes()
        if key in self._offsets:
            self._offsets.move_to_end(key)
            return self._offsets[key]
        delta = v - self.neutral_vertices
        out = BodyOffsets(*(self.kernels[lvl].contract(delta) for lvl in ("fine", "coarse")))
        self._offsets[key] = out
        while len(self._offsets) > OFFSET_CACHE:
            self._offsets.popitem(last=False)
        return out

    def shape_operator(self, points: np.ndarray) -> scipy.sparse.csr_matrix:
        """B~s at fixed points (N, 3) as one sparse (N, V) matrix S over the body's vertices:
        B~s(points, beta) = S (v(beta) - v(neutral)) for any body (the interpolation composed with
        the kernels; about 100 entries a row). A static canonical garment reads its offsets with
        one product per body instead of contracting the grids (``CanonicalModels``)."""
        P_fine, P_coarse = self.grid.operators(points)
        return (P_fine @ self.kernels["fine"].matrix + P_coarse @ self.kernels["coarse"].matrix).tocsr()

    def shape_offsets(self, points: np.ndarray, offsets: BodyOffsets) -> np.ndarray:
        """B~s(p, beta) (eq. 6.5) at points (..., 3) -> (..., 3) metres."""
        return self.grid.interpolate(points, offsets.fine, offsets.coarse)

    def deshaped_to_shaped(self, X: np.ndarray, offsets: BodyOffsets) -> np.ndarray:
        """T_G(X, beta) = X + B~s(X, beta) (eq. 6.8): (..., 3) -> (..., 3) float32 metres."""
        X = np.asarray(X, np.float32)
        return X + self.shape_offsets(X, offsets)

    # ------------------------------------------------------------------ eq. 6.7
    def pose(self, X: np.ndarray, offsets: BodyOffsets, transforms: np.ndarray, fields: np.ndarray | None = None,
             shape_offsets: np.ndarray | None = None) -> np.ndarray:
        """M_G(X, beta, theta) (eq. 6.7) with W~ and B~s at each frame's own canonical points.

        X             : (T, V, 3) canonical garment per frame, metres
        offsets       : ``offsets(rest_vertices)`` of the body
        transforms    : (T, J, 4, 4) the body's skinning transforms per frame
        fields        : ``fields(X)`` if already read (``inference.canonical.push_fields``)
        shape_offsets : ``shape_offsets(X, offsets)`` (T, V, 3) if already read (the same)
        returns         (T, V, 3) float32 posed garment
        """
        X = np.asarray(X, np.float32)
        if X.ndim != 3 or X.shape[-1] != 3:
            raise InputShapeError("X", "(T, V, 3)", X.shape)
        if transforms.shape != (len(X), self.bones, 4, 4):
            raise InputShapeError("transforms", f"({len(X)}, {self.bones}, 4, 4)", transforms.shape)
        if fields is not None and fields.shape != X.shape[:2] + (len(self.bone_index) + 1,):
            raise InputShapeError("fields", f"{X.shape[:2] + (len(self.bone_index) + 1,)}", fields.shape)
        fields = np.ascontiguousarray(self._skin(X) if fields is None else fields, np.float32)  # W~ over the kept bones, then the SDF
        if shape_offsets is not None and shape_offsets.shape != X.shape:
            raise InputShapeError("shape_offsets", str(X.shape), shape_offsets.shape)
        shaped = np.ascontiguousarray(X + (self.shape_offsets(X, offsets) if shape_offsets is None else shape_offsets), np.float32)
        A = np.ascontiguousarray(np.asarray(transforms, np.float32)[:, self.bone_index, :3, :].reshape(len(X), -1, 12))  # (T, K, 12)
        out = np.empty(X.shape, np.float32)
        kernels.blend_pose(fields, shaped, A, out)  # clamped, normalised W~ blending the transforms (compiled)
        return out


def warm_up() -> None:
    """Compile this module's kernels (``inference.diffused_kernels``: the band interpolation, of one
    table and of two, and eq. 6.7's blend) or load numba's cache, on a 2-node grid, so that no request pays a first
    compilation: every process that drapes calls it at start-up."""
    grid = BandGrid(np.zeros(3, np.float32), 1.0, np.array([2, 2, 2]), np.arange(8), 2.0, np.array([2, 2, 2]))
    table = np.ones((8, 2), np.float32)
    fields = grid.interpolate(np.full((1, 3), 0.5, np.float32), table, table)
    grid.interpolate_pair(np.full((1, 3), 0.5, np.float32), table, table, table[:, :1], table[:, :1])
    out = np.empty((1, 1, 3), np.float32)
    kernels.blend_pose(fields[None], np.zeros((1, 1, 3), np.float32), np.zeros((1, 1, 12), np.float32), out)
