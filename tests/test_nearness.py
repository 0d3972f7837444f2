"""``inference.nearness``: the exact "some point nearer than r" test."""
from __future__ import annotations

import numpy as np

from inference.nearness import first_per_cell, within


def test_within_equals_the_distance_matrix_whatever_the_cell():
    rng = np.random.default_rng(7)
    points = rng.uniform(-0.3, 0.3, (500, 3)).astype(np.float32)
    queries = rng.uniform(-0.8, 0.8, (3000, 3)).astype(np.float32)
    d = np.sqrt(((queries[:, None].astype(np.float64) - points[None]) ** 2).sum(-1)).min(1)
    for cell in (0.01, 0.05, 0.2):
        got = within(points, queries, 0.15, cell)
        np.testing.assert_array_equal(got, d < 0.15)
    assert 0.1 < (d < 0.15).mean() < 0.9  # both answers are exercised
    assert not within(points[:0], queries, 0.15, 0.05).any() and within(points, queries[:0], 0.15, 0.05).shape == (0,)


def test_first_per_cell_keeps_the_lowest_index_of_each_cell():
    x = np.array([[0.01, 0, 0], [0.5, 0, 0], [0.02, 0.01, 0], [0.51, 0.02, 0.03], [-0.01, 0, 0]], np.float32)
    assert sorted(first_per_cell(x, 0.1).tolist()) == [0, 1, 4]
