"""The newton reference (training.reference): the SNUG -> VBD material mapping, and three frames of
a small garment on the moving body on the CPU."""
import numpy as np
import pytest

pytest.importorskip("newton")

from inference.body import NEUTRAL_PHENOTYPES, BodyModel  # noqa: E402
from inference.garment import GarmentCatalog  # noqa: E402
from inference.metrics import inside_mask  # noqa: E402
from inference.pipeline import DrapeOptions, drape  # noqa: E402
from training.protocol import SMOKE, case_motion  # noqa: E402
from training.reference import ReferenceSettings, bending_stiffness_per_edge, lead_in_motion, simulate  # noqa: E402


def test_bending_stiffness_maps_snug_eq_5_10():
    # hinge of two right triangles with legs 1 m on the edge (2, 3) of length 1 m: a1 = a2 = 0.5 m^2
    rest = np.array([[0, 1, 0], [0, -1, 0], [0, 0, 0], [1, 0, 0]], np.float64)
    edges = np.array([[0, 1, 2, 3], [-1, 1, 2, 3]])
    ke = bending_stiffness_per_edge(rest, edges, k_bend=4.0)
    # SNUG: E = k l^2 / (4 (a1 + a2)) dtheta^2 / 2 = 1 * dtheta^2 / 2 ; newton: E = ke l dtheta^2 / 2
    np.testing.assert_allclose(ke, [1.0, 0.0])


def test_lead_in_starts_at_rest_and_reaches_the_first_pose():
    rot = np.full((4, 31, 3), 0.3, np.float32)
    trans = np.array([[0.0, 0.0, 1.0]] * 4, np.float32)
    r, t = lead_in_motion(rot, trans, 5)
    assert r.shape == (5, 31, 3) and np.all(r[0] == 0) and np.all(np.diff(r[:, 0, 0]) > 0) and r[-1, 0, 0] < 0.3
    np.testing.assert_array_equal(t, np.repeat(trans[:1], 5, 0))


@pytest.mark.timeout(600)
def test_three_frames_of_trousers_on_the_cpu():
    body, catalog = BodyModel.load(), GarmentCatalog.load()
    shape, motion, start = case_motion(body, SMOKE)
    settings = ReferenceSettings(lead_in_frames=0, settle_frames=0, device="cpu")
    asset = catalog.get("trousers")
    rot, trans = motion.rotations[start:], motion.translation[start:]
    result = simulate(asset, body, NEUTRAL_PHENOTYPES, rot, trans, motion.fps, settings)
    v = result.vertices
    assert v.shape == (SMOKE.frames, asset.num_vertices, 3) and np.isfinite(v).all()
    # the cloth follows the body: within a few cm of the skinned retarget, hardly inside the body
    base = drape(body, shape, type(motion)(rot, trans, motion.fps), [asset], DrapeOptions(fit="retarget", dynamics="none", lift_arms=False, guard=False))
    err = np.linalg.norm(v - base.garments[0].vertices, axis=-1).mean()
    assert err < 0.03
    assert inside_mask(v, result.body_vertices, body.faces).mean() < 0.01
    # and it moves: gravity and the body act between the frames
    assert np.abs(v[-1] - v[0]).max() > 1e-4
