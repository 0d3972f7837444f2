"""The strain limit (inference/strain.py) and its place after the learned canonical model."""
from __future__ import annotations

import numpy as np
import pytest

from inference.strain import StrainLimit


def grid(n: int = 12, h: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """A flat n x n vertex grid with spacing h (m) and its edges (rows, columns, one diagonal)."""
    ij = np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), -1).reshape(-1, 2)
    verts = np.concatenate([ij * h, np.zeros((len(ij), 1))], 1).astype(np.float32)
    idx = np.arange(n * n).reshape(n, n)
    edges = np.concatenate([np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], 1),
                            np.stack([idx[:-1, :].ravel(), idx[1:, :].ravel()], 1),
                            np.stack([idx[:-1, :-1].ravel(), idx[1:, 1:].ravel()], 1)])
    return verts, edges


def ratios(limit: StrainLimit, X: np.ndarray) -> np.ndarray:
    return np.linalg.norm(X[:, limit.edges[:, 1]] - X[:, limit.edges[:, 0]], axis=-1) / limit.rest


def squeezed(rest: np.ndarray, factor: float) -> np.ndarray:
    """The grid with its middle third squeezed along x by ``factor`` (the rest of it shifted to stay attached)."""
    x = rest[:, 0].astype(np.float64)
    lo, hi = np.quantile(x, [1 / 3, 2 / 3])
    mapped = np.where(x < lo, x, np.where(x > hi, lo + (hi - lo) * factor + (x - hi), lo + (x - lo) * factor))
    out = rest.copy()
    out[:, 0] = mapped
    return out


def test_compressed_edges_are_pushed_back_towards_the_ratio_and_nothing_else_moves():
    rest, edges = grid()
    limit = StrainLimit.from_mesh(rest, edges)
    X = np.stack([squeezed(rest, 0.5), squeezed(rest, 0.7), rest + np.float32(0.01)])  # the last frame: moved, not compressed
    before = ratios(limit, X)
    out = limit(X, min_ratio=0.8, iterations=5)
    after = ratios(limit, out)
    assert out.dtype == np.float32 and out.shape == X.shape and np.isfinite(out).all()
    assert after[:2].min() > before[:2].min() + 0.1  # the squeezed frames' shortest edges lengthen
    np.testing.assert_array_equal(out[2], X[2])  # a frame with no edge below the ratio is left as it is
    # the same as the plain Jacobi iteration that measures every edge every time
    for iterations in (1, 5, 40):
        np.testing.assert_allclose(limit(X, 0.8, iterations), dense_jacobi(limit, X, 0.8, iterations), atol=2e-6)


def dense_jacobi(limit: StrainLimit, X: np.ndarray, ratio: float, iterations: int, max_ratio: float = np.inf) -> np.ndarray:
    """The module docstring's iteration, every edge of every frame each time, one frame at a time."""
    out = np.array(X, np.float64)
    i, j = limit.edges[:, 0], limit.edges[:, 1]
    for Y in out:
        for _ in range(iterations):
            d = Y[j] - Y[i]
            length = np.linalg.norm(d, axis=-1)
            deficit = np.where(length < ratio * limit.rest, ratio * limit.rest - length,
                               np.minimum(max_ratio * limit.rest - length, 0.0))
            on = (deficit != 0) & (length > 1e-9)
            c = d * np.where(on, 0.5 * deficit / np.maximum(length, 1e-9), 0.0)[:, None]
            move, count = np.zeros_like(Y), np.zeros(len(Y))
            np.add.at(move, j, c)
            np.add.at(move, i, -c)
            np.add.at(count, j, on)
            np.add.at(count, i, on)
            Y += move / np.maximum(count, 1.0)[:, None]
    return out


def stretched(rest: np.ndarray, factor: float) -> np.ndarray:
    """The grid with its middle third stretched along x by ``factor``."""
    return squeezed(rest, factor)


def test_stretched_edges_are_pulled_back_towards_the_max_ratio():
    rest, edges = grid()
    limit = StrainLimit.from_mesh(rest, edges, max_ratio=1.5)
    X = np.stack([stretched(rest, 2.5), stretched(rest, 1.2)])  # the second: within the limit
    out = limit(X, iterations=5)
    assert ratios(limit, out)[0].max() < ratios(limit, X)[0].max() - 0.2
    np.testing.assert_array_equal(out[1], X[1])
    for iterations in (1, 5, 40):
        np.testing.assert_allclose(limit(X, 0.8, iterations), dense_jacobi(limit, X, 0.8, iterations, 1.5), atol=2e-6)
    converged = limit(X, iterations=400)
    assert ratios(limit, converged)[0].max() < 1.5 + 0.01


def test_the_limit_never_moves_a_mesh_whose_edges_are_all_long_enough():
    rest, edges = grid()
    limit = StrainLimit.from_mesh(rest, edges)
    stretched = (rest * np.float32(1.3))[None]
    np.testing.assert_array_equal(limit(stretched), stretched)


def test_frames_are_limited_independently_of_the_batch_they_come_in():
    rest, edges = grid()
    limit = StrainLimit.from_mesh(rest, edges)
    X = np.stack([squeezed(rest, 0.5), squeezed(rest, 0.9), squeezed(rest, 0.6)])
    together = limit(X)
    for b in range(len(X)):
        np.testing.assert_allclose(limit(X[b:b + 1])[0], together[b], atol=1e-7)


def heavy_walk(garment: str, frames: int):
    """The body model, a garment asset, the heaviest adult and the first ``frames`` of the walk."""
    from inference.body import BodyModel
    from inference.garment import GarmentCatalog
    from inference.motion.clips import ClipLibrary
    from inference.pipeline import PoseSequence

    body = BodyModel.load()
    clip = ClipLibrary().load("walk")
    motion = PoseSequence(clip.rotations[:frames], clip.translation[:frames], clip.fps)
    return body, GarmentCatalog.load().get(garment), body.shape(np.ones((1, 6), np.float32)), motion


def test_the_shipped_learned_canonical_tshirt_keeps_its_short_edges(tmp_path):
    """The pipeline's learned canonical T-shirt has the limit after eq. 6.7: its shortest 1 % of
    edges are longer than the decoded and posed frames' (which the limit alone changes), and
    its shape hardly moves."""
    from inference.canonical import CanonicalModels
    from inference.motion.descriptor import motion_descriptor
    from inference.pipeline import DrapeOptions, drape

    canonical = CanonicalModels()
    if not canonical.available("tshirt"):
        pytest.skip("no learned canonical T-shirt shipped")
    body, asset, shape, motion = heavy_walk("tshirt", 6)
    options = DrapeOptions(fit="canonical", dynamics="learned", lift_arms=False, collisions="off")
    r = drape(body, shape, motion, [asset], options, canonical=canonical)
    assert "strain" in r.timings_ms
    limited = r.garments[0].vertices
    # the same frames without the limit: eq. 6.7 at the decoded points
    gamma = motion_descriptor(motion.rotations[None], motion.translation[None], motion.fps)
    X, _ = canonical.frames(asset, shape.phenotypes, gamma, [motion.num_frames])
    _, T = body.pose(shape.rest_bone_poses, motion.rotations[None], motion.translation[None])
    d = canonical.diffused
    raw = d.pose(X, d.offsets(shape.rest_vertices[0]), T[0])
    limit = canonical.strain_limit(asset)
    p1_raw, p1_limited = np.percentile(ratios(limit, raw), 1), np.percentile(ratios(limit, limited), 1)
    assert p1_limited > p1_raw + 0.03, (p1_raw, p1_limited)
    assert np.linalg.norm(limited - raw, axis=-1).mean() < 1e-3


def test_a_static_canonical_garment_gets_the_limit_after_its_skinning(monkeypatch):
    """fit 'canonical' without dynamics: the template's canonical form through eq. 6.7 squeezes
    the crew-neck tee under the arms on the heavy body; the limit lengthens its shortest edges
    and leaves the rest of it in place."""
    from inference.canonical import CanonicalModels
    from inference.pipeline import DrapeOptions, drape

    canonical = CanonicalModels()
    body, asset, shape, motion = heavy_walk("crewtee", 4)
    options = DrapeOptions(fit="canonical", dynamics="none", lift_arms=False, collisions="off")
    r = drape(body, shape, motion, [asset], options, canonical=canonical)
    assert "strain" in r.timings_ms
    limit = canonical.strain_limit(asset)
    # the same drape with the limit switched off
    monkeypatch.setattr(CanonicalModels, "strain_limit", lambda self, g: (lambda X: X))
    raw = drape(body, shape, motion, [asset], options, canonical=canonical).garments[0].vertices
    limited = r.garments[0].vertices
    assert ratios(limit, raw).min() < 0.7  # there is something to limit
    assert np.percentile(ratios(limit, limited), 1) > np.percentile(ratios(limit, raw), 1) + 0.02
    assert np.linalg.norm(limited - raw, axis=-1).mean() < 1e-3


def test_a_garment_limit_takes_its_category_ratio():
    """The bottoms' limit is MIN_RATIO_BY_CATEGORY's (chosen on validation), the dress's stretch
    limit and the bottoms' MAX_RATIO_BY_CATEGORY's; the others' MIN_RATIO and no stretch limit."""
    from inference.garment import GarmentCatalog
    from inference.strain import MAX_RATIO_BY_CATEGORY, MIN_RATIO, MIN_RATIO_BY_CATEGORY

    catalog = GarmentCatalog.load()
    trousers, tshirt = StrainLimit.for_garment(catalog.get("trousers")), StrainLimit.for_garment(catalog.get("tshirt"))
    dress = StrainLimit.for_garment(catalog.get("dress"))
    assert trousers.min_ratio == MIN_RATIO_BY_CATEGORY["bottom"] > MIN_RATIO == tshirt.min_ratio
    assert dress.max_ratio == MAX_RATIO_BY_CATEGORY["dress"] < np.inf == tshirt.max_ratio
    assert trousers.max_ratio == MAX_RATIO_BY_CATEGORY["bottom"] < np.inf
    rest, edges = grid()
    X = squeezed(rest, 0.5)[None]
    for ratio in (0.8, 0.85):
        limited = StrainLimit.from_mesh(rest, edges, ratio)(X, iterations=200)
        lengths = np.linalg.norm(limited[0, edges[:, 1]] - limited[0, edges[:, 0]], axis=-1)
        rest_len = np.linalg.norm(rest[edges[:, 1]] - rest[edges[:, 0]], axis=-1)
        assert (lengths / rest_len).min() > ratio - 0.01


def _full_jacobi(X, edges, rest, min_ratio, max_ratio, iterations):
    """The strain limit's Jacobi iteration evaluating every edge every time (the reference of the
    compiled kernel, which evaluates only the edges at moved vertices after a frame's first pass)."""
    X = X.copy()
    for b in range(X.shape[0]):
        for _ in range(iterations):
            move = np.zeros((X.shape[1], 3))
            count = np.zeros(X.shape[1], np.int64)
            active = 0
            for e, (i, j) in enumerate(edges):
                d = X[b, j].astype(np.float64) - X[b, i]
                length = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
                deficit = min_ratio * np.float64(rest[e]) - length
                if deficit <= 0.0:
                    deficit = min(max_ratio * np.float64(rest[e]) - length, 0.0)
                if deficit != 0.0 and length > 1e-9:
                    s = 0.5 * deficit / length
                    for k in range(3):  # one coordinate at a time, in the kernel's order
                        move[j, k] += s * d[k]
                    for k in range(3):
                        move[i, k] -= s * d[k]
                    count[i] += 1
                    count[j] += 1
                    active += 1
            if active == 0:
                break
            touched = count > 0
            X[b, touched] = (X[b, touched] + move[touched] / count[touched, None]).astype(np.float32)
    return X


@pytest.mark.parametrize("ratios_", [(0.8, np.inf), (0.0, 1.05), (0.9, 1.1)])
def test_the_kernel_equals_the_full_iteration_that_evaluates_every_edge(ratios_):
    # a grid crumpled here and stretched there, over three frames: the same vertices, bitwise
    from inference.strain_kernels import limit_in_place

    rest, edges = grid(10)
    rng = np.random.default_rng(4)
    X = np.stack([squeezed(rest, 0.5), rest * np.float32(1.2), rest + rng.normal(0, 0.003, rest.shape)]).astype(np.float32)
    rest_len = np.linalg.norm(rest[edges[:, 1]] - rest[edges[:, 0]], axis=-1).astype(np.float32)
    got = X.copy()
    limit_in_place(got, edges.astype(np.int64), rest_len, float(ratios_[0]), float(ratios_[1]), 5)
    want = _full_jacobi(X, edges, rest_len, float(ratios_[0]), float(ratios_[1]), 5)
    assert (got != X).any()
    np.testing.assert_array_equal(got, want)
