"""A compact output basis for the fit regressor R_G: normalised geodesic Gaussians over the garment.

R_G's output is smooth over the garment (a one-size garment stretched over a bigger body, riding
up), so it is written as displacements c_k (metres) at K nodes, spread over the mesh by

    Phi[v, k] = g_k(v) / sum_j g_j(v),   g_k(v) = exp(-d(v, n_k)^2 / (2 sigma^2)),
    R_G(beta)[v] = sum_k Phi[v, k] c_k(beta)                                       (V, 3)

with d the shortest-path length along the template's edges (scipy ``csgraph.dijkstra``; a
geodesic, so a sleeve and the torso beside it do not share a node), the nodes a farthest-point
sample of the vertices and sigma the sample's covering radius (the largest distance from a vertex
to its nearest node). The rows sum to 1: a constant displacement is reproduced exactly.

Why not the manifold harmonics of the wrinkle GRU's basis: the harmonics have to ship with the
model (128 x 5,148 float32 for a T-shirt: 2.6 MB of a 2.9 MB ``fit.onnx``); they cannot be
recomputed where they are used, because an eigensolver returns any rotation of a near-degenerate
eigenspace. Phi depends continuously on the template, the node ids and sigma, so the model ships
only those (``model.json``) and its MLP's weights. Measured on the T-shirt's shipped R_G (200
random adult bodies, least squares onto Phi; ``python tools/fit_basis_check.py projection``): K = 256, sigma = covering radius (4.2 cm) leaves
0.8 mm mean, 2.9 mm p99 of a 23 mm mean displacement; sigma = 0.5 / 1.5 / 2 radii or K = 128 /
192 leave more.

Units: metres. Shapes: vertices (V, 3), edges (E, 2), nodes (K,), Phi (V, K) float32.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from inference.errors import InputShapeError, InputValueError

# Gaussian tails beyond this many sigmas are cut to 0 (exp(-8) = 3e-4 of a node's weight).
CUTOFF_SIGMAS = 4.0


def edge_graph(vertices: np.ndarray, edges: np.ndarray) -> sp.csr_matrix:
    """The template's edges as a symmetric sparse matrix of their lengths, metres."""
    v = np.asarray(vertices, np.float64)
    e = np.asarray(edges, np.int64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise InputShapeError("vertices", "(V, 3)", v.shape)
    if e.ndim != 2 or e.shape[1] != 2:
        raise InputShapeError("edges", "(E, 2)", e.shape)
    if len(e) and (e.min() < 0 or e.max() >= len(v)):
        raise InputValueError("edges", f"vertex ids must lie in 0..{len(v) - 1}")
    w = np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1)
    return sp.coo_matrix((np.r_[w, w], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(len(v), len(v))).tocsr()


def farthest_nodes(vertices: np.ndarray, edges: np.ndarray, k: int) -> tuple[np.ndarray, float]:
    """k nodes by farthest-point sampling along the edges, from vertex 0 (each next node the vertex
    farthest from those chosen; a part the edges do not reach is infinitely far, so every connected
    part gets a node first), and the covering radius, metres: ((k,) int64, float)."""
    graph = edge_graph(vertices, edges)
    n = graph.shape[0]
    if not 1 <= k <= n:
        raise InputValueError("k", f"must lie in 1..{n}, got {k}")
    nodes = [0]
    nearest = dijkstra(graph, indices=0)
    for _ in range(k - 1):
        nodes.append(int(np.argmax(nearest)))
        nearest = np.minimum(nearest, dijkstra(graph, indices=nodes[-1]))
    return np.array(nodes, np.int64), float(nearest.max())


def geodesic_rbf_basis(vertices: np.ndarray, edges: np.ndarray, nodes: np.ndarray, sigma_m: float) -> np.ndarray:
    """Phi (V, K) float32 of the module doc: rows sum to 1."""
    nodes = np.asarray(nodes, np.int64)
    graph = edge_graph(vertices, edges)
    if nodes.ndim != 1 or not len(nodes):
        raise InputShapeError("nodes", "(K,), K >= 1", nodes.shape)
    if nodes.min() < 0 or nodes.max() >= graph.shape[0]:
        raise InputValueError("nodes", f"vertex ids must lie in 0..{graph.shape[0] - 1}")
    if not (np.isfinite(sigma_m) and sigma_m > 0):
        raise InputValueError("sigma_m", f"must be a positive length, got {sigma_m}")
    d = dijkstra(graph, indices=nodes, limit=CUTOFF_SIGMAS * sigma_m)  # (K, V), inf beyond the limit
    g = np.exp(-0.5 * (d.T / sigma_m) ** 2)  # (V, K)
    total = g.sum(1, keepdims=True)
    if not (total > 0).all():
        raise InputValueError("nodes", f"{int((total == 0).sum())} vertices have no node within {CUTOFF_SIGMAS} sigma")
    return (g / total).astype(np.float32)
