"""inference.fit_basis: the geodesic output basis of the fit regressor (module doc)."""
from __future__ import annotations

import numpy as np
import pytest

from inference.errors import InferenceInputError
from inference.fit_basis import farthest_nodes, geodesic_rbf_basis
from inference.garment import GarmentCatalog


@pytest.fixture(scope="module")
def tshirt():
    return GarmentCatalog.load().get("tshirt")


def _grid(n: int = 12, gap: float = 0.0):
    """Two n x n sheets 1 cm apart (in z), 1 cm spacing, as vertices and edges."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    sheet = np.stack([i.ravel() * 0.01, j.ravel() * 0.01, np.zeros(n * n)], 1)
    idx = np.arange(n * n).reshape(n, n)
    e = np.concatenate([np.stack([idx[:-1].ravel(), idx[1:].ravel()], 1), np.stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()], 1)])
    verts = np.concatenate([sheet, sheet + [0, 0, 0.01 + gap]])
    return verts, np.concatenate([e, e + n * n])


def test_rows_are_a_partition_of_unity_and_reproducible(tshirt):
    nodes, sigma = farthest_nodes(tshirt.vertices, tshirt.edges, 64)
    assert len(np.unique(nodes)) == 64 and 0.02 < sigma < 0.3
    phi = geodesic_rbf_basis(tshirt.vertices, tshirt.edges, nodes, sigma)
    assert phi.shape == (tshirt.num_vertices, 64) and phi.dtype == np.float32 and (phi >= 0).all()
    np.testing.assert_allclose(phi.sum(1), 1.0, atol=1e-5)
    # a node's own vertex leans on it most
    assert (phi[nodes, np.arange(64)] >= phi[nodes].max(1) - 1e-6).mean() > 0.95
    # rebuilt from the stored ids and sigma: the same basis (what the runtime does)
    again = geodesic_rbf_basis(tshirt.vertices.astype(np.float64), tshirt.edges, nodes.tolist(), float(sigma))
    np.testing.assert_allclose(again, phi, atol=1e-6)


def test_sheets_that_share_no_edge_share_no_node():
    """Distances run along the edges: two sheets 1 cm apart never mix, each gets nodes first."""
    verts, edges = _grid()
    nodes, sigma = farthest_nodes(verts, edges, 8)
    half = len(verts) // 2
    assert (nodes < half).any() and (nodes >= half).any()
    phi = geodesic_rbf_basis(verts, edges, nodes, sigma)
    top = nodes >= half
    assert phi[:half][:, top].max() == 0.0 and phi[half:][:, ~top].max() == 0.0


def test_smooth_fields_are_reproduced(tshirt):
    """A linear field over the template is fitted to within a millimetre by least squares."""
    nodes, sigma = farthest_nodes(tshirt.vertices, tshirt.edges, 256)
    phi = geodesic_rbf_basis(tshirt.vertices, tshirt.edges, nodes, sigma)
    field = 0.05 * (tshirt.vertices - tshirt.vertices.mean(0))  # a 5 % grading, metres
    coef, *_ = np.linalg.lstsq(phi, field, rcond=None)
    assert np.abs(phi @ coef - field).mean() < 1e-3


def test_bad_inputs_are_refused(tshirt):
    with pytest.raises(InferenceInputError):
        farthest_nodes(tshirt.vertices, tshirt.edges, 0)
    with pytest.raises(InferenceInputError):
        geodesic_rbf_basis(tshirt.vertices, tshirt.edges, np.array([tshirt.num_vertices]), 0.05)
    with pytest.raises(InferenceInputError):
        geodesic_rbf_basis(tshirt.vertices, tshirt.edges, np.array([0, 1]), -1.0)
    with pytest.raises(InferenceInputError):
        geodesic_rbf_basis(tshirt.vertices, np.array([[0, 10**7]]), np.array([0]), 0.05)
