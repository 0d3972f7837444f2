"""The arm correction (inference.motion.self_contact): lifts the arms of heavy bodies out of the
torso, leaves slim bodies and every other bone alone, respects motion segments."""
import numpy as np
import pytest

from inference.body import BodyModel
from inference.metrics import self_intersecting_vertices
from inference.motion.clips import ClipLibrary, adapt_clip
from inference.motion.self_contact import ARM_CHAINS, lift_arms

HEAVY = np.ones(6, np.float32)
LIGHT = np.array([0.0, 0.77, 0.0, 0.0, 0.0, 0.0], np.float32)


@pytest.fixture(scope="module")
def body():
    return BodyModel.load()


def _motion(body, phenotypes, frames=48):
    shape = body.shape(phenotypes[None])
    rot, trans = adapt_clip(ClipLibrary().load("walk"), body, shape)
    return shape, rot[0, :frames], trans[0, :frames]


def _self_intersections(body, shape, rot, trans):
    _, transforms = body.pose(shape.rest_bone_poses, rot[None], trans[None])
    verts = body.skin(shape.rest_vertices, transforms)[0]
    return self_intersecting_vertices(verts, body.faces).sum(1)


def test_heavy_body_arms_leave_the_torso(body):
    shape, rot, trans = _motion(body, HEAVY)
    lifted, angles = lift_arms(body, shape, rot, trans)
    before = _self_intersections(body, shape, rot[::4], trans[::4])
    after = _self_intersections(body, shape, lifted[::4], trans[::4])
    assert angles.max() > np.radians(5)  # the heavy body's arms hang into its torso on this walk
    assert after.mean() < 0.5 * before.mean(), (before.mean(), after.mean())
    assert np.all(angles >= 0) and angles.max() <= 0.6 + 1e-6


def test_only_the_upper_arms_rotate(body):
    shape, rot, trans = _motion(body, HEAVY, 24)
    lifted, _ = lift_arms(body, shape, rot, trans)
    arms = [body.bone_names.index(chain[0]) for chain in ARM_CHAINS]
    others = np.setdiff1d(np.arange(body.num_bones), arms)
    np.testing.assert_array_equal(lifted[:, others], rot[:, others])
    assert np.abs(lifted[:, arms] - rot[:, arms]).max() > 1e-3
    assert np.isfinite(lifted).all() and lifted.dtype == np.float32


def test_slim_body_is_left_alone(body):
    shape, rot, trans = _motion(body, LIGHT, 24)
    lifted, angles = lift_arms(body, shape, rot, trans)
    assert angles.max() == 0.0
    np.testing.assert_array_equal(lifted, rot)


def test_segments_are_independent(body):
    # two motions concatenated (cross-request batching) give each one's own correction
    shape, rot, trans = _motion(body, HEAVY, 40)
    a, _ = lift_arms(body, shape, rot[:17], trans[:17])
    b, _ = lift_arms(body, shape, rot[17:], trans[17:])
    both, _ = lift_arms(body, shape, rot, trans, segments=[17, 23])
    np.testing.assert_allclose(both, np.concatenate([a, b]), atol=1e-6)


def test_pipeline_poses_the_lifted_arms(body):
    from inference.garment import GarmentCatalog
    from inference.pipeline import DrapeOptions, PoseSequence, drape

    shape, rot, trans = _motion(body, HEAVY, 12)
    motion = PoseSequence(rot, trans, 30.0)
    tshirt = [GarmentCatalog.load().get("tshirt")]
    base = DrapeOptions(fit="retarget", dynamics="none", guard=False)
    off = drape(body, shape, motion, tshirt, DrapeOptions(fit="retarget", dynamics="none", guard=False, lift_arms=False))
    on = drape(body, shape, motion, tshirt, base)
    lifted, _ = lift_arms(body, shape, rot, trans)
    expected, _ = body.pose(shape.rest_bone_poses, lifted[None], trans[None])
    np.testing.assert_allclose(on.bone_poses, expected[0], atol=1e-6)
    assert np.abs(on.bone_poses - off.bone_poses).max() > 1e-3
    assert "arms" in on.timings_ms and "arms" not in off.timings_ms


def test_lifter_cache_reuses_the_body_set_up(body):
    from inference.motion.self_contact import ArmLifter, arm_lifter

    shape, rot, trans = _motion(body, HEAVY, 8)
    first = arm_lifter(body, shape)
    assert arm_lifter(body, body.shape(HEAVY[None])) is first  # same phenotypes, same set-up
    assert arm_lifter(body, body.shape(LIGHT[None])) is not first
    np.testing.assert_array_equal(first.lift(rot, trans)[0], ArmLifter(body, shape).lift(rot, trans)[0])


def test_nearest_torso_point_is_the_kd_trees_within_the_reach():
    import numba
    from scipy.spatial import cKDTree

    from inference.motion import self_contact
    from inference.motion.arm_kernels import arm_steps
    from inference.repair_kernels import frame_knn

    rng = np.random.default_rng(5)
    torso = rng.uniform(-0.2, 0.2, (3, 400, 3)).astype(np.float32)
    arm = rng.uniform(-0.3, 0.3, (4, 150, 3)).astype(np.float32)
    frames = np.array([2, 0, 2, 1], np.int64)
    near, found = self_contact._nearest_torso(torso, arm, frames, 0.05)
    near, found = near.reshape(4, 150), found.reshape(4, 150)
    for a, t in enumerate(frames):
        d, i = cKDTree(torso[t]).query(arm[a], k=1, distance_upper_bound=0.05)
        # found: the nearest of all, or none within the reach (the step's kernel drops those beyond it)
        within = found[a] & (np.linalg.norm(arm[a].astype(np.float64) - torso[t, near[a]], axis=1) < 0.05)
        np.testing.assert_array_equal(within, np.isfinite(d))
        np.testing.assert_array_equal(near[a][within], i[within])
    assert found.mean() > 0.2 and (~found).mean() > 0.2  # both cases are exercised
    self_contact.warm_up()  # a worker's start-up compiles the signatures a request uses
    assert numba.typeof(torso) in [sig[0] for sig in frame_knn.signatures]
    assert numba.typeof(torso) in [sig[0] for sig in arm_steps.signatures]


def _steps_numpy(tp, tn, ap, shoulder, active, T, margin_m, reach_m, tangent_m):
    """The arm step of the module doc in numpy, from a KD-tree per frame (the compiled one's reference)."""
    from scipy.spatial import cKDTree

    from inference.motion.self_contact import _STEP_CAP

    step, axes = np.zeros(T), np.zeros((T, 3))
    dist = np.stack([cKDTree(tp[t]).query(a, k=1, distance_upper_bound=reach_m)[0] for t, a in zip(active, ap)])
    near = np.stack([cKDTree(tp[t]).query(a, k=1, distance_upper_bound=reach_m)[1] for t, a in zip(active, ap)])
    ok = np.isfinite(dist)
    near = np.where(ok, near, 0)
    c, n = tp[active[:, None], near], tn[active[:, None], near]
    depth = -np.einsum("tic,tic->ti", ap - c, n)
    depth = np.where(ok & (np.where(ok, dist, 0.0) ** 2 - depth**2 < tangent_m**2), depth, 0.0)
    dirn = np.einsum("ti,tic->tc", np.maximum(depth, 0.0), n)
    dirn /= np.maximum(np.linalg.norm(dirn, axis=-1, keepdims=True), 1e-12)
    k = np.cross(ap[np.arange(len(active)), np.argmax(depth, axis=1)] - shoulder, dirn)
    lever = np.linalg.norm(k, axis=-1)
    need = (depth.max(axis=1) > 0) & (lever > 1e-3)
    step[active[need]] = np.minimum((depth.max(axis=1)[need] + margin_m) / lever[need], _STEP_CAP)
    axes[active[need]] = k[need] / lever[need, None]
    return step, axes


def test_compiled_arm_step_is_the_numpy_one(body):
    from inference.body import linear_blend_skinning
    from inference.motion import self_contact

    # a heavy body's walk: real torso normals and arms sunk into the torso, every frame and both arms
    shape, rot, trans = _motion(body, HEAVY, 24)
    lifter = self_contact.ArmLifter(body, shape)
    W, transforms = body.pose(shape.rest_bone_poses, rot[None], trans[None])
    tp, tn = self_contact._skin(body, lifter.torso, lifter.rest, lifter.rest_normals, transforms[0])
    active = np.arange(0, 24, 2)
    stepped = 0
    for bone, arm in lifter.arms:
        ap = linear_blend_skinning(lifter.rest[None, arm], body.dense_weights[arm], transforms[:, active])[0]
        args = (tp, tn, ap, W[0, active, bone, :3, 3], active, 24, 0.01, 0.08, 0.015)
        step, axes = self_contact._steps(*args)
        ref_step, ref_axes = _steps_numpy(*args)
        np.testing.assert_allclose(step, ref_step, rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(axes, ref_axes, rtol=1e-5, atol=1e-6)
        assert not step[1::2].any()  # only the active frames
        stepped += int((step > 0).sum())
    assert stepped >= 12  # the heavy body's arms need lifting in most of these frames


def test_the_lifts_poses_are_the_lifted_motions(body):
    # ``lift(poses=True)``: the bone poses and transforms it kept while re-posing the moved frames
    # are BodyModel.pose's of the lifted motion, bit for bit (the pipeline poses no more), on a
    # heavy body whose arms move in some frames and iterations and not in others, two segments
    from inference.motion.self_contact import arm_lifter

    shape, rot, trans = _motion(body, 0.5 * HEAVY, 30)
    lifted, angles, W, T = arm_lifter(body, shape).lift(rot, trans, [11, 19], poses=True)
    assert (angles > 0).any() and (angles == 0).any()
    W2, T2 = body.pose(shape.rest_bone_poses, lifted[None], trans[None])
    assert np.array_equal(W, W2) and np.array_equal(T, T2)


def test_the_window_maximum_is_numpys_shifted_comparisons():
    from inference.motion.self_contact import SMOOTH_FRAMES, _window_argmax

    rng = np.random.default_rng(2)
    x = np.round(rng.random(40), 1)  # ties
    x[5:9] = 0.0
    segments = [7, 1, 20, 12]
    seg = np.repeat(np.arange(len(segments)), segments)
    best = np.arange(len(x))
    for off in range(-SMOOTH_FRAMES, SMOOTH_FRAMES + 1):
        j = np.clip(np.arange(len(x)) + off, 0, len(x) - 1)
        best = np.where((seg[j] == seg) & (x[j] > x[best]), j, best)
    got = _window_argmax(x, segments)
    assert np.array_equal(got, best) and (got != np.arange(len(x))).any()
