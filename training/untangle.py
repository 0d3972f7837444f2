"""The exact local untangling operator of thesis ch. 7.3.2 (eq. 7.6) and its training samples.

At a point x, N layered garments (layer i + 1 outside layer i) give signed distances f*_i (> 0
outside the layer's surface) and covariant values h*_i (< 0 away from the openings, where a layer
is a closed wall; >= 0 in the volume that extends an opening, where other layers may pass). The
operator returns the closest field values without a tangle:

    f = O(f*, h*) = argmin_f |f - f*|^2 + sum_{i<j} H(f_i, h*_i, f_j, h*_j),                 (7.6)
    H = inf  if f_i < 0, h*_i < 0, f_j > 0, h*_j < 0  (x inside layer i but outside layer j > i)

Only the active layers (h* < 0) are constrained; the others keep f = f*. Over the active layers,
in order, a feasible f has no negative value before a positive one, so it is split at some k:
f_i >= 0 for the first k and f_i <= 0 for the rest (x lies between layers k and k + 1). For a
split, the closest such f clamps each value to its side, at the cost

    C(k) = sum_{i <= k} min(f*_i, 0)^2 + sum_{i > k} max(f*_i, 0)^2,

and the operator takes the split of least cost (the first one on a tie): O(N) per point with
prefix sums, where Buffet et al. solve a more general problem in O(N^3). This is the ground
truth the learned untangler is fitted to (eq. 7.7); it is garment-agnostic.

Samples (§7.5): f* ~ U(-0.2, 1.5), h* ~ U(-1, 1) per layer, N = 7 slots; an outfit with fewer
layers sets h* = 1 (inactive) in the unused ones.

Units: the fields' (metres for f; h is unitless). Shapes: (..., N), layers last, inner first.
"""
from __future__ import annotations

import numpy as np

from inference.errors import InputShapeError

# Layer slots of the learned operator (thesis: "more than enough for common outfits").
MAX_LAYERS = 7
F_RANGE = (-0.2, 1.5)
H_RANGE = (-1.0, 1.0)


def untangle_exact(f_star: np.ndarray, h_star: np.ndarray) -> np.ndarray:
    """O(f*, h*) of eq. 7.6 (module doc): (..., N) float -> (..., N) float64."""
    f = np.asarray(f_star, np.float64)
    h = np.asarray(h_star, np.float64)
    if f.shape != h.shape or f.ndim < 1:
        raise InputShapeError("h_star", str(f.shape), h.shape)
    active = h < 0.0
    # cost of putting layer i outside the point (f_i >= 0) or inside it (f_i <= 0); 0 if inactive
    up = np.where(active, np.minimum(f, 0.0) ** 2, 0.0)
    down = np.where(active, np.maximum(f, 0.0) ** 2, 0.0)
    zeros = np.zeros(f.shape[:-1] + (1,))
    # C(k) for k = 0..N: the first k layers above zero, the rest below
    cost = np.concatenate([zeros, np.cumsum(up, -1)], -1) + np.concatenate([np.cumsum(down[..., ::-1], -1)[..., ::-1], zeros], -1)
    k = np.argmin(cost, -1)[..., None]
    first = np.arange(f.shape[-1]) < k
    return np.where(active, np.where(first, np.maximum(f, 0.0), np.minimum(f, 0.0)), f)


def tangled(f: np.ndarray, h: np.ndarray) -> np.ndarray:
    """(...,) bool: some active pair i < j has f_i < 0 and f_j > 0 (H = inf)."""
    f, h = np.asarray(f), np.asarray(h)
    active = h < 0.0
    inside = active & (f < 0.0)
    outside = active & (f > 0.0)
    # a negative before a positive: the running "any inside so far" meets an outside after it
    before = np.concatenate([np.zeros(f.shape[:-1] + (1,), bool), np.logical_or.accumulate(inside, -1)[..., :-1]], -1)
    return np.any(before & outside, -1)


def sample_untangling(n: int, rng: np.random.Generator, layers: int = MAX_LAYERS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """n training samples (§7.5): f* (n, layers), h* (n, layers) and f = O(f*, h*), float32."""
    f_star = rng.uniform(*F_RANGE, (n, layers))
    h_star = rng.uniform(*H_RANGE, (n, layers))
    return f_star.astype(np.float32), h_star.astype(np.float32), untangle_exact(f_star, h_star).astype(np.float32)
