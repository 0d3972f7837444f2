"""The exact local untangling operator (thesis eq. 7.6; inference/untangle.py) and its samples."""
import itertools

import numpy as np
import pytest

from inference.errors import InputShapeError
from inference.untangle import tangled, untangle_exact
from training.untangle import sample_untangling


def _brute_force(f, h):
    """The closest point of the union of the feasible closed orthants: every sign pattern of the
    active layers without an inside (<= 0) layer below an outside (>= 0) one, reached by clamping;
    the least squared distance wins."""
    best, best_cost = None, np.inf
    act = np.flatnonzero(h < 0)
    for signs in itertools.product((1, -1), repeat=len(act)):
        # infeasible: an inner active layer forced negative below an outer one forced positive
        if any(signs[a] < 0 and signs[b] > 0 for a in range(len(act)) for b in range(a + 1, len(act))):
            continue
        g = f.astype(np.float64).copy()
        for s, i in zip(signs, act):
            g[i] = max(g[i], 0.0) if s > 0 else min(g[i], 0.0)
        cost = float(((g - f) ** 2).sum())
        if cost < best_cost - 1e-15:
            best, best_cost = g, cost
    return best, best_cost


def test_equals_the_brute_force_projection_and_leaves_nothing_tangled():
    rng = np.random.default_rng(0)
    for n_layers in (1, 2, 3, 5, 7):
        f_star, h_star, f = sample_untangling(400, rng, n_layers)
        assert not tangled(f, h_star).any()
        if n_layers >= 3:  # the samples do exercise the operator
            assert tangled(f_star, h_star).mean() > 0.02
        for a, hh, got in zip(f_star, h_star, f):
            want, cost = _brute_force(a, hh)
            # the same minimum (a tie between splits may pick another of the equally close points)
            got_cost = float(((got.astype(np.float64) - a.astype(np.float64)) ** 2).sum())
            assert abs(got_cost - cost) <= 1e-6 * max(cost, 1e-6), (a, hh, got, want)


def test_untangled_input_and_inactive_layers_are_left_alone():
    rng = np.random.default_rng(1)
    f_star, h_star, f = sample_untangling(2000, rng)
    free = ~tangled(f_star, h_star)
    np.testing.assert_array_equal(f[free], f_star[free])
    np.testing.assert_array_equal(f[h_star >= 0], f_star[h_star >= 0])
    np.testing.assert_allclose(untangle_exact(f, h_star), f)  # a projection: idempotent


def test_the_order_of_the_layers_decides():
    # x inside the shirt (layer 0) and outside the jacket (layer 1): one of them moves to x
    f, h = np.array([-0.01, 0.03]), np.array([-1.0, -1.0])
    np.testing.assert_allclose(untangle_exact(f, h), [0.0, 0.03])  # the shirt, 1 cm, is cheaper to move
    np.testing.assert_allclose(untangle_exact(f[::-1], h), [0.03, -0.01])  # jacket under shirt: no tangle here
    # near an opening of the jacket (h >= 0) the shirt may pass: nothing moves
    np.testing.assert_allclose(untangle_exact(f, np.array([-1.0, 0.5])), f)


def test_shapes_are_checked():
    with pytest.raises(InputShapeError):
        untangle_exact(np.zeros((4, 3)), np.zeros((4, 2)))
