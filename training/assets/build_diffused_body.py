"""Build the diffused body model (thesis ch. 6.3.1, eq. 6.4-6.5) as precomputed 3-D grids.

    python -m training.assets.build_diffused_body [--spacing 0.02] [--samples 48] [--out assets/body/diffused.npz]

For every node p of a regular grid around the canonical body (the neutral adult in the rest
A-pose, the body every garment template is made on), with d(p) the distance from p to the skin:

    W~(p)       = 1/N sum_n W(phi(p + d(p) e_n))                      (eq. 6.4)
    B~s(p, beta) = 1/N sum_n B_s(phi(p + d(p) e_n), beta)             (eq. 6.5)

phi the closest point on the skin (barycentric interpolation of the vertex values), e_n a fixed
set of N standard-normal 3-vectors (a deterministic quadrature of q ~ N(p, d I): the same set at
every node, so the fields are continuous in p, and at the surface they equal the body's values).
Also the signed distance to the canonical skin (negative inside; sign from the fast winding number).

anny has no pose correctives B_p, so eq. 6.6 is left out (M_G = W(X + B~s(X, beta), ...)).

Shape blendshapes are stored in a compressed basis: over adult phenotypes the offsets of the
body from the neutral one, delta(beta) = (c(beta) - c_n) S (S the (135, V, 3) skin basis), are
exactly a linear image of the 135 coefficients; their principal directions U_k (r of them, the
residual bounded below) are diffused, and B~s(p, beta) = sum_k a_k(beta) U~_k(p) with
a(beta) = (c(beta) - c_n) A, A (135, r). Finger and toe weights are folded into the hand and foot
(as the garments' own weights, ``build_garments.FOLDED_BONES``).

Arrays (``inference.diffused.DiffusedBody`` reads them): ``origin`` (3,) m, the corner of both
grids; ``spacing`` () m and ``fields`` (nx, ny, nz, J + 1) float16: J weights and the sdf (m);
``shape_spacing`` () m and ``shape_fields`` (mx, my, mz, 3 r) float16: the diffused basis U~_k,
component-major (metres per unit coefficient; a coarser grid: the offsets vary slowly);
``shape_map`` (135, r) float32, ``neutral_coeffs`` (135,) float64, ``metadata`` (JSON).
"""
from __future__ import annotations

import argparse
import json
import logging
import multiprocessing
import time
from pathlib import Path

import numpy as np

from inference.body import NEUTRAL_PHENOTYPES, PHENOTYPE_RANGES, BodyModel
from inference.diffused import DEFAULT_PATH
from training.assets.build_garments import FOLDED_BONES
from training.assets.garments_fit import barycentric, fold_into_parents, largest_component_faces

log = logging.getLogger(__name__)

BUILD_COMMAND = "python -m training.assets.build_diffused_body"
MARGIN_M = 0.25  # the grid reaches this far beyond the body's rest bounding box
SHAPE_SAMPLES = 4096  # adult phenotypes sampled to find the shape basis
SHAPE_RESIDUAL_M = 5e-3  # largest vertex error of the truncated shape basis over the checked samples
CHECK_SAMPLES = 1024  # the first of them (the box's corners first) checked for that error


def adult_phenotypes(n: int, seed: int = 0) -> np.ndarray:
    """(64 + n, 6) phenotypes: the adult box's 64 corners, then n uniform in it."""
    lo = np.array([PHENOTYPE_RANGES[k][0] for k in PHENOTYPE_RANGES], np.float32)
    hi = np.array([PHENOTYPE_RANGES[k][1] for k in PHENOTYPE_RANGES], np.float32)
    u = np.random.default_rng(seed).uniform(size=(n, 6)).astype(np.float32)
    corners = np.array(np.meshgrid(*[[0.0, 1.0]] * 6, indexing="ij")).reshape(6, -1).T.astype(np.float32)
    return lo + np.concatenate([corners, u]) * (hi - lo)


def shape_basis(body: BodyModel, residual_m: float = SHAPE_RESIDUAL_M, samples: int = SHAPE_SAMPLES) -> tuple[np.ndarray, np.ndarray, dict]:
    """Principal shape offsets of the adult bodies from the neutral one.

    delta = D S with D = c(beta) - c_n (M, 135) and S^T = Q R (thin QR), so delta = (D R^T) Q^T and
    the SVD D R^T = U s W^T gives delta's principal directions Q W exactly. Keeps the fewest r whose
    reconstruction error of every sampled body is <= residual_m at every vertex.
    returns basis (r, V, 3) float64 (metres per unit coefficient, the coefficient of a sampled body
    has unit RMS), shape_map A (135, r) with a = (c - c_n) A, and a report.
    """
    c_n = body.coefficients(NEUTRAL_PHENOTYPES[None])[0]
    D = body.coefficients(adult_phenotypes(samples)) - c_n
    S = body.blendshapes.astype(np.float64).reshape(len(body.blendshapes), -1)  # (135, 3V)
    Q, R = np.linalg.qr(S.T)
    U, s, Wt = np.linalg.svd(D @ R.T, full_matrices=False)
    scale = s / np.sqrt(len(D))  # RMS coefficient 1
    QW = Q @ Wt.T  # (3V, 135) principal directions
    check = (U * s)[: min(len(D), CHECK_SAMPLES)]  # truncation residual of body m: check[m, r:] QW[:, r:]^T

    def worst(r: int) -> float:
        err = (check[:, r:] @ QW[:, r:].T).reshape(len(check), -1, 3)
        return float(np.linalg.norm(err, axis=-1).max())

    lo, hi = 1, len(s)  # fewest r with worst(r) <= residual_m, by bisection (worst falls with r)
    while lo < hi:
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if worst(mid) <= residual_m else (mid + 1, hi)
    r = lo
    basis = QW[:, :r].T * scale[:r, None]  # (r, 3V)
    A = R.T @ Wt[:r].T / scale[:r]  # (135, r)
    worst_r = worst(r) if r < len(s) else 0.0
    report = {"components": r, "residual_max_m": worst_r, "checked_samples": len(check), "samples": len(D), "largest_offset_m": float(np.linalg.norm((D @ S).reshape(len(D), -1, 3), axis=-1).max())}
    return basis.reshape(r, -1, 3), A, report


def gaussian_directions(n: int, seed: int = 0) -> np.ndarray:
    """N fixed standard-normal 3-vectors e_n, symmetrised (+e and -e) so their mean is 0."""
    e = np.random.default_rng(seed).standard_normal((n // 2, 3))
    return np.concatenate([e, -e])


class _Surface:
    """The canonical skin and the per-vertex values to diffuse (module-level for the worker pool)."""

    vertices: np.ndarray
    faces: np.ndarray
    values: np.ndarray  # (V, C - 1)
    directions: np.ndarray


_S = _Surface()


def _diffuse_block(nodes: np.ndarray) -> np.ndarray:
    """Diffused values and signed distance at grid nodes (n, 3) -> (n, C) float64."""
    import igl

    V, F = _S.vertices, _S.faces
    sdf = igl.signed_distance(nodes, V, F, sign_type=igl.SIGNED_DISTANCE_TYPE_FAST_WINDING_NUMBER)[0]
    d = np.abs(sdf)
    q = (nodes[:, None, :] + d[:, None, None] * _S.directions[None]).reshape(-1, 3)
    _, face, c = igl.point_mesh_squared_distance(q, V, F)
    tri = F[face]
    bc = np.clip(barycentric(c, V[tri]), 0.0, 1.0)
    bc /= bc.sum(1, keepdims=True)
    vals = np.einsum("nk,nkc->nc", bc, _S.values[tri]).reshape(len(nodes), len(_S.directions), -1).mean(1)
    return np.concatenate([vals, sdf[:, None]], 1)


def diffuse(nodes: np.ndarray, vertices: np.ndarray, faces: np.ndarray, values: np.ndarray, directions: np.ndarray,
            workers: int = 2, block: int = 2048) -> np.ndarray:
    """eq. 6.4-6.5 at ``nodes`` (n, 3) for surface ``values`` (V, C') on the mesh; plus the SDF.
    returns (n, C' + 1) float64."""
    _S.vertices, _S.faces, _S.values, _S.directions = vertices, faces, values, directions
    blocks = [nodes[i:i + block] for i in range(0, len(nodes), block)]
    if workers <= 1:
        return np.concatenate([_diffuse_block(b) for b in blocks])
    with multiprocessing.get_context("fork").Pool(workers) as pool:
        return np.concatenate(pool.map(_diffuse_block, blocks))


def grid_nodes(lo: np.ndarray, hi: np.ndarray, spacing_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Nodes (n, 3) of the regular grid from lo with ``spacing_m`` covering [lo, hi], and its dims (3,)."""
    dims = np.ceil((hi - lo) / spacing_m).astype(int) + 1
    axes = [lo[i] + spacing_m * np.arange(dims[i]) for i in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3), dims


def build(spacing_m: float = 0.02, shape_spacing_m: float = 0.04, samples: int = 48, workers: int = 2,
          residual_m: float = SHAPE_RESIDUAL_M) -> tuple[dict[str, np.ndarray], dict]:
    """The diffused body arrays (module docstring) and a build report."""
    t0 = time.perf_counter()
    body = BodyModel.load()
    neutral = body.shape(NEUTRAL_PHENOTYPES[None])
    V = neutral.rest_vertices[0].astype(np.float64)
    F = largest_component_faces(body.faces, len(V)).astype(np.int64)
    fold = np.array([body.bone_names.index(n) for n in FOLDED_BONES])
    weights = fold_into_parents(body.dense_weights, body.parents, fold)
    basis, A, shape_report = shape_basis(body, residual_m)
    r = len(basis)
    directions = gaussian_directions(samples)
    lo, hi = V.min(0) - MARGIN_M, V.max(0) + MARGIN_M

    nodes, dims = grid_nodes(lo, hi, spacing_m)
    log.info("skin grid %s = %d nodes at %.3f m, %d samples each", tuple(dims), len(nodes), spacing_m, samples)
    skin = diffuse(nodes, V, F, weights, directions, workers)
    J = body.num_bones
    skin[:, :J] /= skin[:, :J].sum(1, keepdims=True)
    shape_nodes, shape_dims = grid_nodes(lo, hi, shape_spacing_m)
    log.info("shape grid %s = %d nodes at %.3f m, %d components", tuple(shape_dims), len(shape_nodes), shape_spacing_m, r)
    shape = diffuse(shape_nodes, V, F, basis.transpose(1, 0, 2).reshape(len(V), 3 * r), directions, workers)[:, :-1]
    arrays = {
        "origin": lo.astype(np.float64),
        "spacing": np.float64(spacing_m),
        "fields": skin.reshape(*dims, J + 1).astype(np.float16),
        "shape_spacing": np.float64(shape_spacing_m),
        "shape_fields": shape.reshape(*shape_dims, 3 * r).astype(np.float16),
        "shape_map": A.astype(np.float32),
        "neutral_coeffs": body.coefficients(NEUTRAL_PHENOTYPES[None])[0],
    }
    report = {
        "command": BUILD_COMMAND, "spacing_m": spacing_m, "shape_spacing_m": shape_spacing_m, "grid": [int(x) for x in dims],
        "shape_grid": [int(x) for x in shape_dims], "samples": samples, "bones": J, "shape": shape_report,
        "folded_bones": list(FOLDED_BONES), "seconds": round(time.perf_counter() - t0, 1),
    }
    return arrays, report


def main(argv: list[str] | None = None) -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--spacing", type=float, default=0.02, help="grid spacing, metres")
    ap.add_argument("--shape-spacing", type=float, default=0.04, help="spacing of the shape-offset grid, metres")
    ap.add_argument("--residual", type=float, default=SHAPE_RESIDUAL_M, help="largest vertex error of the shape basis, metres")
    ap.add_argument("--samples", type=int, default=48, help="Gaussian samples per node (N of eq. 6.4)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=DEFAULT_PATH)
    args = ap.parse_args(argv)
    arrays, report = build(args.spacing, args.shape_spacing, args.samples, args.workers, args.residual)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.out, metadata=np.array(json.dumps(report)), **arrays)
    report["bytes"] = args.out.stat().st_size
    log.info("wrote %s: %s", args.out, json.dumps(report))


if __name__ == "__main__":
    main()
