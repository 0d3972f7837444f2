"""Fitting a garment template to the neutral body: collision relaxation and skinning weights.

Thesis ch. 4.3.1: the garment is pre-positioned once on the template body and relaxed into a
collision-free state, then smoothed (rho) to give the template T_c-bar. Here the pre-position
is the MakeHuman ``.mhclo`` placement; the relaxation pushes every vertex that is inside the
body, or closer than a margin, out along the closest-point direction, alternating with Taubin
smoothing of the *correction field* (so the garment's own folds and seams stay as modelled).
Thesis ch. 4.2.1: W_c from the closest body triangle's interpolated skinning weights.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from inference.mesh import face_normals
from inference.metrics import inside_mask
from training.assets.garments_mesh import quad_components, unique_edges, vertex_adjacency


def body_inside_mask(points: np.ndarray, body_vertices: np.ndarray, body_faces: np.ndarray) -> np.ndarray:
    """Exact inside test against the closed skin mesh (generalised winding number > 0.5).

    points        : (N, 3) metres
    body_vertices : (Vb, 3) metres ; body_faces : (Fb, 3), closed and outward oriented
    returns       : (N,) bool
    """
    return np.asarray(inside_mask(np.asarray(points)[None], np.asarray(body_vertices)[None], body_faces), bool)[0]


def closest_points(points: np.ndarray, body_vertices: np.ndarray, body_faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest point on the body surface: distance (N,) metres, face index (N,), point (N, 3)."""
    import igl

    d2, face, c = igl.point_mesh_squared_distance(
        np.asarray(points, np.float64), np.asarray(body_vertices, np.float64), np.asarray(body_faces, np.int64)
    )
    return np.sqrt(d2), face, c


def largest_component_faces(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Faces (F', 3) of the largest connected component (the skin without eyes etc.)."""
    lab = quad_components(faces, n_vertices)[faces[:, 0]]
    big = np.argmax(np.bincount(lab))
    return faces[lab == big]


def push_out(points: np.ndarray, body_vertices: np.ndarray, body_faces: np.ndarray, margin_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Move points that are inside the body or within ``margin_m`` of it to ``margin_m`` outside.

    The target is closest surface point + margin along (point -> surface) for inside points
    and (surface -> point) for outside ones; the face normal where they coincide.
    points : (N, 3) metres ; returns (new points (N, 3), moved mask (N,))
    """
    dist, face, c = closest_points(points, body_vertices, body_faces)
    inside = body_inside_mask(points, body_vertices, body_faces)
    move = inside | (dist < margin_m)
    d = np.where(inside[:, None], c - points, points - c)
    n = np.linalg.norm(d, axis=1, keepdims=True)
    fn = face_normals(body_vertices, np.asarray(body_faces), dtype=np.float64)[face]
    direction = np.where(n > 1e-7, d / np.maximum(n, 1e-12), fn)
    out = np.where(move[:, None], c + margin_m * direction, points)
    return out, move


def uniform_laplacian(faces: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """Row-normalised graph Laplacian L = mean(neighbours) - I, (V, V)."""
    A = vertex_adjacency(faces, n_vertices)
    deg = np.asarray(A.sum(1)).ravel()
    return sp.csr_matrix(sp.diags(1.0 / np.maximum(deg, 1)) @ A - sp.identity(n_vertices))


def taubin_smooth(field: np.ndarray, laplacian: sp.csr_matrix, steps: int, lam: float = 0.5, mu: float = -0.53, mask: np.ndarray | None = None) -> np.ndarray:
    """Taubin lambda/mu smoothing (no shrinkage) of a per-vertex field (V, C); only ``mask`` rows move."""
    x = np.asarray(field, np.float64).copy()
    m = np.ones(len(x), bool) if mask is None else mask
    for _ in range(steps):
        for f in (lam, mu):
            x[m] += f * (laplacian @ x)[m]
    return x


def restore_edge_lengths(x: np.ndarray, edges: np.ndarray, rest_lengths: np.ndarray, iterations: int, stiffness: float = 0.5) -> np.ndarray:
    """Jacobi position-based-dynamics steps pulling edges (E, 2) toward their rest lengths (E,) metres.

    Each edge moves both ends by half its length error along itself, averaged over the edges of a
    vertex and scaled by ``stiffness``; x (V, 3) metres. A spring-only stand-in for the cloth
    simulation that relaxes the pre-positioned garment in the thesis (ch. 4.3.1).
    """
    x = np.asarray(x, np.float64).copy()
    count = np.bincount(edges.ravel(), minlength=len(x))[:, None]
    for _ in range(iterations):
        d = x[edges[:, 1]] - x[edges[:, 0]]
        length = np.linalg.norm(d, axis=1, keepdims=True)
        step = 0.5 * (length - rest_lengths[:, None]) / np.maximum(length, 1e-12) * d  # (E, 3)
        acc = np.zeros_like(x)
        np.add.at(acc, edges[:, 0], step)
        np.add.at(acc, edges[:, 1], -step)
        x += stiffness * acc / np.maximum(count, 1)
    return x


def relax_template(
    bound: np.ndarray,
    faces: np.ndarray,
    body_vertices: np.ndarray,
    body_faces: np.ndarray,
    margin_m: float,
    rounds: int = 8,
    smooth_steps: int = 4,
    edge_steps: int = 5,
) -> tuple[np.ndarray, dict]:
    """Collision-free template from the bound garment (thesis ch. 4.3.1, pre-position + relax + smooth).

    bound         : (V, 3) metres, the garment bound on the neutral body
    faces         : (F, 3) garment triangles
    body_vertices : (Vb, 3) metres, neutral body in rest pose ; body_faces : (Fb, 3) closed skin
    margin_m      : clearance every vertex gets from the skin, metres
    Rounds of: push out to the margin, then Taubin-smooth the correction (template - bound);
    then rounds of push-out and ``edge_steps`` edge-length restoring steps (rest lengths: the
    bound garment's); a last push-out guarantees the margin. Returns the template (V, 3) and a report dict
    (inside fraction before/after, mean/max correction in metres).
    """
    L = uniform_laplacian(faces, len(bound))
    x = np.asarray(bound, np.float64)
    report = {"inside_before": float(body_inside_mask(x, body_vertices, body_faces).mean())}
    correction = np.zeros_like(x)
    for _ in range(rounds):
        pushed, _ = push_out(x + correction, body_vertices, body_faces, margin_m)
        correction = taubin_smooth(pushed - x, L, smooth_steps)
    # the per-vertex projections squeeze narrow bands (cuffs, hems): let the edges relax back
    edges = unique_edges(faces)
    rest = np.linalg.norm(x[edges[:, 1]] - x[edges[:, 0]], axis=1)
    template = x + correction
    for _ in range(rounds):
        template, _ = push_out(template, body_vertices, body_faces, margin_m)
        template = restore_edge_lengths(template, edges, rest, edge_steps)
    template, _ = push_out(template, body_vertices, body_faces, margin_m)
    # a second pass catches points the last push moved into another body part (creases)
    template, _ = push_out(template, body_vertices, body_faces, margin_m)
    dist, _, _ = closest_points(template, body_vertices, body_faces)
    inside = body_inside_mask(template, body_vertices, body_faces)
    corr = np.linalg.norm(template - x, axis=1)
    report.update(
        inside_after=float(inside.mean()),
        inside_after_count=int(inside.sum()),
        min_clearance_m=float(dist[~inside].min()) if (~inside).any() else 0.0,
        correction_mean_m=float(corr.mean()),
        correction_max_m=float(corr.max()),
    )
    return template, report


def barycentric(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (N, 3) of points (N, 3) in triangles (N, 3, 3) (points on their planes)."""
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    v0, v1, v2 = b - a, c - a, points - a
    d00 = np.einsum("nc,nc->n", v0, v0)
    d01 = np.einsum("nc,nc->n", v0, v1)
    d11 = np.einsum("nc,nc->n", v1, v1)
    d20 = np.einsum("nc,nc->n", v2, v0)
    d21 = np.einsum("nc,nc->n", v2, v1)
    den = d00 * d11 - d01 * d01
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    return np.stack([1.0 - v - w, v, w], 1)


def project_skin_weights(points: np.ndarray, body_vertices: np.ndarray, body_faces: np.ndarray, body_weights: np.ndarray) -> np.ndarray:
    """W_c (thesis ch. 4.2.1): closest body triangle's skinning weights, barycentrically interpolated.

    points       : (V, 3) metres, the template ; body_vertices (Vb, 3) ; body_faces (Fb, 3)
    body_weights : (Vb, J) rows sum to 1 ; returns (V, J) float64, rows sum to 1
    """
    _, face, c = closest_points(points, body_vertices, body_faces)
    tri = body_faces[face]
    bc = np.clip(barycentric(c, np.asarray(body_vertices, np.float64)[tri]), 0.0, 1.0)
    bc /= bc.sum(1, keepdims=True)
    w = np.einsum("nk,nkj->nj", bc, body_weights[tri].astype(np.float64))
    return w / w.sum(1, keepdims=True)


def fold_into_parents(weights: np.ndarray, parents: np.ndarray, fold: np.ndarray) -> np.ndarray:
    """Move the weight of every bone in ``fold`` (indices) to its nearest ancestor not in ``fold``.

    Garments never cover fingers or toes, yet a cuff or hem near them picks up their weights
    from the closest triangle and would follow a curling thumb. weights (V, J) ; parents (J,)
    with parents[0] = -1 ; returns (V, J), rows unchanged in sum.
    """
    out = np.asarray(weights, np.float64).copy()
    folded = set(int(j) for j in fold)
    for j in sorted(folded):
        target = int(parents[j])
        while target in folded:
            target = int(parents[target])
        out[:, target] += out[:, j]
        out[:, j] = 0.0
    return out


def smooth_skirt_weights(
    weights: np.ndarray,
    faces: np.ndarray,
    heights: np.ndarray,
    skirt: np.ndarray,
    top_m: float,
    ramp_m: float,
    iterations: int,
) -> np.ndarray:
    """Diffuse skinning weights over a skirt so that it does not tear between the legs.

    Closest-triangle weights jump from the left thigh to the right one across the skirt's
    front and back centre lines. Here the weights of the ``skirt`` vertices are diffused over the
    garment's own mesh graph (``iterations`` Jacobi steps of w <- w + 0.5 L w, vertices outside
    the skirt held fixed), then blended with the original by height: unchanged above ``top_m``,
    fully diffused ``ramp_m`` below it (smoothstep), so the waist still follows the pelvis.

    weights : (V, J) rows sum to 1 ; faces (F, 3) ; heights (V,) metres (Z-up) ; skirt (V,) bool
    returns : (V, J) rows sum to 1
    """
    L = uniform_laplacian(faces, len(weights))
    w = np.asarray(weights, np.float64).copy()
    for _ in range(iterations):
        w[skirt] += 0.5 * (L @ w)[skirt]
    t = np.clip((top_m - heights) / ramp_m, 0.0, 1.0)
    alpha = (t * t * (3.0 - 2.0 * t))[:, None] * skirt[:, None]
    out = (1.0 - alpha) * weights + alpha * w
    out = np.clip(out, 0.0, None)
    return out / out.sum(1, keepdims=True)
