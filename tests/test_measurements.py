"""Body measurements (inference.measurements) and the body fit (inference.body_fit)."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import ConvexHull

from bench.body_fit import random_adults
from inference.body import NEUTRAL_PHENOTYPES, BodyModel
from inference.body_fit import GENDERS, TOLERANCE_M, BodyFitter
from inference.measurements import MEASUREMENTS, mesh_volume, slice_girths


@pytest.fixture(scope="module")
def fitter():
    return BodyFitter(BodyModel.load())


def test_girth_is_the_convex_hull_perimeter_of_the_slice(fitter):
    shape = fitter.body.shape(random_adults(3, seed=5))
    levels = fitter.measurer.measure(shape.rest_vertices, shape.bone_heads).levels  # chest, waist, hips
    girths = fitter.measurer.girths(shape.rest_vertices, levels)
    for b in range(3):
        for k, z in enumerate(levels[b]):
            exact = ConvexHull(fitter.measurer.slice_points(shape.rest_vertices[b], z)).area  # 2D: area is the perimeter
            assert girths[b, k] == pytest.approx(exact, abs=2e-4)


def test_a_cylinder_girth_and_a_box_volume():
    """On known solids: a vertical cylinder's girth is 2 pi r, a box's volume w d h."""
    cyl = trimesh.creation.cylinder(radius=0.15, height=1.0, sections=512)
    edges = np.asarray(cyl.edges_unique)
    g = slice_girths(np.asarray(cyl.vertices)[None], edges, np.array([[0.1, -0.3]]))
    np.testing.assert_allclose(g, 2 * np.pi * 0.15, rtol=1e-4)
    box = trimesh.creation.box((0.3, 0.2, 1.5))
    assert mesh_volume(np.asarray(box.vertices)[None], box.faces)[0] == pytest.approx(0.3 * 0.2 * 1.5)


def test_measurements_follow_the_body(fitter):
    """Taller bodies measure taller, heavier ones wider, the neutral adult as documented."""
    p = np.tile(NEUTRAL_PHENOTYPES, (3, 1))
    p[1, 4] = 0.9  # taller
    p[2, 3] = 0.9  # heavier
    m, mass = fitter.evaluate(p)
    h, c, w, hip, inseam = m.T
    assert h[1] > h[0] + 0.05 and inseam[1] > inseam[0] + 0.02
    assert w[2] > w[0] + 0.03 and hip[2] > hip[0] + 0.02 and mass[2] > mass[0] + 5
    assert 1.6 < h[0] < 2.0 and 0.35 < inseam[0] / h[0] < 0.55 and w[0] < c[0] and w[0] < hip[0]
    assert 50 < mass[0] < 90


def test_round_trip_within_a_centimetre(fitter):
    """Random adults: measure, fit from the measurements, measure the fit (the full 200-body run
    is bench.body_fit; numbers in docs/benchmarks.md)."""
    phenotypes = random_adults(6, seed=11)
    targets, mass = fitter.evaluate(phenotypes)
    for i in range(len(phenotypes)):
        fit = fitter.fit(targets[i])
        assert not fit.misses
        assert np.abs(fit.residuals).max() < TOLERANCE_M
        again, _ = fitter.evaluate(fit.phenotypes[None])
        np.testing.assert_allclose(again[0], fit.measurements, atol=1e-6)
    side = "female" if phenotypes[0, 0] >= 0.5 else "male"
    fit = fitter.fit(targets[0], weight_kg=float(mass[0]), gender=GENDERS[side])
    assert GENDERS[side][0] <= fit.phenotypes[0] <= GENDERS[side][1]
    assert fit.mass_residual_kg is not None


def test_impossible_measurements_are_named(fitter):
    fit = fitter.fit(np.array([1.80, 0.60, 1.50, 1.00, 0.85]))  # a 60 cm chest over a 150 cm waist
    assert {"chest", "waist"} <= set(fit.misses)
    assert set(fit.misses) <= set(MEASUREMENTS) | {"weight"}


def test_fit_refuses_non_finite(fitter):
    with pytest.raises(ValueError):
        fitter.fit(np.array([1.8, np.nan, 0.8, 1.0, 0.8]))
