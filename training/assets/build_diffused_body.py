"""Build the diffused body model (thesis ch. 6.3.1, eq. 6.4-6.5) as sparse diffusion kernels on two grids.

    python -m training.assets.build_diffused_body [--fine 0.015] [--coarse 0.05] [--samples 32] [--out assets/body/diffused.npz]

For every node p of a grid around the canonical body (the neutral adult in the rest A-pose, the
body every garment template is made on), with d(p) the distance from p to the skin:

    W~(p)        = 1/N sum_n W(phi(p + d(p) e_n))                      (eq. 6.4)
    B~s(p, beta) = 1/N sum_n B_s(phi(p + d(p) e_n), beta)              (eq. 6.5)

phi the closest point on the skin (barycentric interpolation of the vertex values), e_n a fixed
set of N standard-normal 3-vectors (a deterministic quadrature of q ~ N(p, d I): the same set at
every node, so the fields are continuous in p; at the surface they equal the body's values).

Both fields are linear in the skin's vertex values, so a node stores the *kernel*, not the
values: the skin vertices k_j and weights c_j (summing to 1) with value(p) = sum_j c_j value(k_j)
(the N samples' barycentric weights / N, merged per vertex, the K largest kept and renormalised).
One kernel serves W~ (the body's skinning weights, contracted once at load) and B~s for any body
(its rest vertices minus the neutral ones, contracted once per body): the offsets are exact at the
skin for every anny body (no truncated shape basis), and a node costs K (index, weight) pairs
instead of 3 x 51 basis values. Also the signed distance to the canonical skin (negative inside;
sign from the fast winding number).

Two grids share one origin: a fine one on the band of nodes with -``BAND_IN_M`` <= sdf <=
``BAND_OUT_M`` (where garments are: the catalog's templates lie 4 mm - 13 cm from the skin, and the
offsets change over centimetres there: across an arm, the growth of its two sides points in
opposite directions), and a coarse one over the whole box (the far field: a swinging hem, the
inside of the body). ``inference.diffused`` reads them.

anny has no pose correctives B_p, so eq. 6.6 is left out (M_G = W(X + B~s(X, beta), ...)).
Finger and toe weights are folded into the hand and foot (as the garments' own weights,
``build_garments.FOLDED_BONES``).

Arrays: ``origin`` (3,) m; per level L in (coarse, fine): ``L_spacing`` () m, ``L_dims`` (3,)
nodes, ``L_index`` (n, K) uint16 skin vertices, ``L_weight`` (n, K) float16, ``L_sdf`` (n,) float16
m; ``fine_nodes`` (n_f,) int32 flat ids of the band's nodes in the fine grid (the coarse grid
stores every node, i-major); ``neutral_vertices`` (V, 3) float32 m (the canonical body's rest
vertices, the reference of B_s); ``vertex_weights`` (V, J) float16, the folded skinning weights;
``metadata`` (JSON).
"""
from __future__ import annotations

import argparse
import json
import logging
import multiprocessing
import time
from pathlib import Path

import numpy as np

from inference.body import NEUTRAL_PHENOTYPES, BodyModel
from inference.diffused import DEFAULT_PATH
from training.assets.build_garments import FOLDED_BONES
from training.assets.garments_fit import barycentric, fold_into_parents, largest_component_faces

log = logging.getLogger(__name__)

BUILD_COMMAND = "python -m training.assets.build_diffused_body"
MARGIN_M = 0.25  # the box reaches this far beyond the body's rest bounding box
BAND_OUT_M = 0.10  # the fine band: nodes up to this far outside the skin ...
BAND_IN_M = 0.03  # ... and this deep inside it
FINE_K = 12  # kernel entries kept per fine node
COARSE_K = 24  # per coarse node (far nodes average over a wider patch of skin)


def gaussian_directions(n: int, seed: int = 0) -> np.ndarray:
    """N fixed standard-normal 3-vectors e_n, symmetrised (+e and -e) so their mean is 0."""
    e = np.random.default_rng(seed).standard_normal((n // 2, 3))
    return np.concatenate([e, -e])


class _Surface:
    """The canonical skin (module-level for the worker pool)."""

    vertices: np.ndarray
    faces: np.ndarray
    directions: np.ndarray
    k: int


_S = _Surface()


def signed_distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Signed distance (n,) to the skin, metres, negative inside (fast winding number sign)."""
    import igl

    return igl.signed_distance(np.asarray(points, np.float64), vertices, faces, sign_type=igl.SIGNED_DISTANCE_TYPE_FAST_WINDING_NUMBER)[0]


def top_k(rows: np.ndarray, ids: np.ndarray, weights: np.ndarray, n_rows: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Sparse kernel entries (row, vertex id, weight), duplicates allowed -> per row the k
    largest merged weights, renormalised to sum 1: ids (n_rows, k) int64 (0-padded), weights
    (n_rows, k) float64 (0 where padded)."""
    key = rows.astype(np.int64) * (int(ids.max()) + 1) + ids
    uniq, inv = np.unique(key, return_inverse=True)
    w = np.bincount(inv, weights=weights)
    r, v = np.divmod(uniq, int(ids.max()) + 1)
    order = np.lexsort((-w, r))  # by row, heaviest first
    r, v, w = r[order], v[order], w[order]
    start = np.searchsorted(r, np.arange(n_rows))
    rank = np.arange(len(r)) - start[r]
    keep = rank < k
    out_i = np.zeros((n_rows, k), np.int64)
    out_w = np.zeros((n_rows, k), np.float64)
    out_i[r[keep], rank[keep]] = v[keep]
    out_w[r[keep], rank[keep]] = w[keep]
    out_w /= out_w.sum(1, keepdims=True)
    return out_i, out_w


def _kernel_block(nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """eq. 6.4-6.5 kernels and the signed distance at nodes (n, 3)."""
    import igl

    V, F, E = _S.vertices, _S.faces, _S.directions
    sdf = signed_distance(nodes, V, F)
    q = (nodes[:, None, :] + np.abs(sdf)[:, None, None] * E[None]).reshape(-1, 3)
    _, face, c = igl.point_mesh_squared_distance(q, V, F)
    tri = F[face]
    bc = np.clip(barycentric(c, V[tri]), 0.0, 1.0)
    bc /= bc.sum(1, keepdims=True)
    rows = np.repeat(np.arange(len(nodes)), len(E) * 3)
    idx, w = top_k(rows, tri.ravel(), bc.ravel() / len(E), len(nodes), _S.k)
    return idx, w, sdf


def kernels(nodes: np.ndarray, vertices: np.ndarray, faces: np.ndarray, directions: np.ndarray, k: int,
            workers: int = 2, block: int = 4096) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Kernels (ids (n, k), weights (n, k)) and signed distances (n,) at ``nodes`` (n, 3)."""
    _S.vertices, _S.faces, _S.directions, _S.k = vertices, faces, directions, k
    blocks = [nodes[i:i + block] for i in range(0, len(nodes), block)]
    if workers <= 1:
        parts = [_kernel_block(b) for b in blocks]
    else:
        with multiprocessing.get_context("fork").Pool(workers) as pool:
            parts = pool.map(_kernel_block, blocks)
    return tuple(np.concatenate(x) for x in zip(*parts))


def grid_dims(extent: np.ndarray, spacing_m: float) -> np.ndarray:
    """Nodes per axis of a grid with ``spacing_m`` covering ``extent`` (3,) metres from its origin."""
    return np.ceil(extent / spacing_m).astype(np.int64) + 1


def grid_nodes(origin: np.ndarray, dims: np.ndarray, spacing_m: float, flat: np.ndarray | None = None) -> np.ndarray:
    """Positions (n, 3) of the grid's nodes (all, i-major, or the flat ids ``flat``)."""
    if flat is None:
        flat = np.arange(int(np.prod(dims)))
    ijk = np.stack(np.unravel_index(flat, tuple(int(d) for d in dims)), -1)
    return origin + spacing_m * ijk


def build(fine_m: float = 0.015, coarse_m: float = 0.05, samples: int = 32, workers: int = 2) -> tuple[dict[str, np.ndarray], dict]:
    """The diffused body arrays (module docstring) and a build report."""
    from inference.diffused import Grid

    t0 = time.perf_counter()
    body = BodyModel.load()
    V = body.shape(NEUTRAL_PHENOTYPES[None]).rest_vertices[0].astype(np.float64)
    F = largest_component_faces(body.faces, len(V)).astype(np.int64)
    fold = np.array([body.bone_names.index(n) for n in FOLDED_BONES])
    weights = fold_into_parents(body.dense_weights, body.parents, fold)
    directions = gaussian_directions(samples)
    origin = V.min(0) - MARGIN_M
    extent = V.max(0) + MARGIN_M - origin

    c_dims = grid_dims(extent, coarse_m)
    c_nodes = grid_nodes(origin, c_dims, coarse_m)
    log.info("coarse grid %s = %d nodes at %.3f m", tuple(c_dims), len(c_nodes), coarse_m)
    c_idx, c_w, c_sdf = kernels(c_nodes, V, F, directions, COARSE_K, workers)

    # the band: fine nodes whose coarse-interpolated sdf is near the band, then their exact sdf
    f_dims = grid_dims(extent, fine_m)
    coarse_sdf = Grid(origin, coarse_m, c_dims, c_sdf[:, None])
    flat = np.arange(int(np.prod(f_dims)))
    centre, half = 0.5 * (BAND_OUT_M - BAND_IN_M), 0.5 * (BAND_OUT_M + BAND_IN_M) + coarse_m
    chunks = [flat[i:i + (1 << 20)] for i in range(0, len(flat), 1 << 20)]
    near = np.concatenate([c[np.abs(coarse_sdf.interpolate(grid_nodes(origin, f_dims, fine_m, c))[:, 0] - centre) <= half] for c in chunks])
    sdf_near = signed_distance(grid_nodes(origin, f_dims, fine_m, near), V, F)
    band = near[(sdf_near >= -BAND_IN_M) & (sdf_near <= BAND_OUT_M)]
    log.info("fine grid %s at %.3f m: %d band nodes", tuple(f_dims), fine_m, len(band))
    f_idx, f_w, f_sdf = kernels(grid_nodes(origin, f_dims, fine_m, band), V, F, directions, FINE_K, workers)

    arrays = {
        "origin": origin.astype(np.float64),
        "coarse_spacing": np.float64(coarse_m), "coarse_dims": c_dims, "coarse_index": c_idx.astype(np.uint16),
        "coarse_weight": c_w.astype(np.float16), "coarse_sdf": c_sdf.astype(np.float16),
        "fine_spacing": np.float64(fine_m), "fine_dims": f_dims, "fine_nodes": band.astype(np.int32),
        "fine_index": f_idx.astype(np.uint16), "fine_weight": f_w.astype(np.float16), "fine_sdf": f_sdf.astype(np.float16),
        "neutral_vertices": V.astype(np.float32), "vertex_weights": weights.astype(np.float16),
    }
    report = {
        "command": BUILD_COMMAND, "fine_spacing_m": fine_m, "coarse_spacing_m": coarse_m, "fine_dims": f_dims.tolist(),
        "coarse_dims": c_dims.tolist(), "band_nodes": int(len(band)), "band_m": [-BAND_IN_M, BAND_OUT_M],
        "kernel_entries": {"fine": FINE_K, "coarse": COARSE_K}, "samples": samples, "bones": body.num_bones,
        "folded_bones": list(FOLDED_BONES), "seconds": round(time.perf_counter() - t0, 1),
    }
    return arrays, report


def main(argv: list[str] | None = None) -> None:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--fine", type=float, default=0.015, help="spacing of the band's grid, metres")
    ap.add_argument("--coarse", type=float, default=0.05, help="spacing of the whole box's grid, metres")
    ap.add_argument("--samples", type=int, default=32, help="Gaussian samples per node (N of eq. 6.4)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=DEFAULT_PATH)
    args = ap.parse_args(argv)
    arrays, report = build(args.fine, args.coarse, args.samples, args.workers)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(args.out, metadata=np.array(json.dumps(report)), **arrays)
    report["bytes"] = args.out.stat().st_size
    log.info("wrote %s: %s", args.out, json.dumps(report))


if __name__ == "__main__":
    main()
