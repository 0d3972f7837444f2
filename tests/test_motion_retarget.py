"""Retargeting onto the cmu_mb body, and the issue's acceptance test.

"The retargeted walk is a walk: the test checks for no NaN, feet reaching the ground, and bone
directions within a few degrees of the source."
"""
from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest

from inference.body import BodyModel, NEUTRAL_PHENOTYPES
from inference.motion.asfamc import load_asf_amc
from inference.motion.bvh import load_bvh, parse_bvh
from inference.motion.names import CMU_MB_BONES
from inference.motion.retarget import FORWARD, foot_heights, retarget, target_leg_length
from tests.test_motion_bvh import make_bvh

MOCAP = Path(__file__).resolve().parents[1] / "training" / "sources" / "mocap"
needs_mocap = pytest.mark.skipif(not MOCAP.exists(), reason="training/sources/mocap missing")

# Adult extremes (age within [0.77, 1]).
BODIES = {
    "neutral": NEUTRAL_PHENOTYPES,
    "big_old_male": np.array([1, 1, 1, 1, 1, 1], np.float32),
    "small_young_female": np.array([0, 0.77, 0, 0, 0, 0], np.float32),
}
# cmu_mb bone -> (ASF joint at its head, ASF joint at its tail or None for the bone's own end).
ASF_BONES = {
    "LeftUpLeg": ("lfemur", "ltibia"), "LeftLeg": ("ltibia", "lfoot"), "LeftFoot": ("lfoot", "ltoes"),
    "RightUpLeg": ("rfemur", "rtibia"), "RightLeg": ("rtibia", "rfoot"), "RightFoot": ("rfoot", "rtoes"),
    "LeftArm": ("lhumerus", "lradius"), "LeftForeArm": ("lradius", "lwrist"),
    "RightArm": ("rhumerus", "rradius"), "RightForeArm": ("rradius", "rwrist"),
    "LowerBack": ("lowerback", "upperback"), "Spine": ("upperback", "thorax"), "Spine1": ("thorax", "lowerneck"),
    "Neck": ("lowerneck", "upperneck"), "Neck1": ("upperneck", "head"), "Head": ("head", None),
}  # fmt: skip
MAX_BONES = {
    "LeftUpLeg": ("LeftHip", "LeftKnee"), "LeftLeg": ("LeftKnee", "LeftAnkle"), "LeftFoot": ("LeftAnkle", "LeftToe"),
    "RightUpLeg": ("RightHip", "RightKnee"), "RightLeg": ("RightKnee", "RightAnkle"),
    "LeftArm": ("LeftShoulder", "LeftElbow"), "LeftForeArm": ("LeftElbow", "LeftWrist"),
    "RightArm": ("RightShoulder", "RightElbow"), "RightForeArm": ("RightElbow", "RightWrist"),
    "LowerBack": ("lowerback", "Chest"), "Spine": ("Chest", "Chest2"), "Neck1": ("Neck", "Head"),
}  # fmt: skip
TOLERANCE_DEG = 3.0


@functools.lru_cache(maxsize=1)
def body_model():
    return BodyModel.load()


@functools.lru_cache(maxsize=4)
def shape_of(name):
    return body_model().shape(BODIES[name][None])


@functools.lru_cache(maxsize=1)
def walk():
    return load_asf_amc(MOCAP / "cmu-asfamc" / "02" / "02.asf", MOCAP / "cmu-asfamc" / "02" / "02_01.amc")


def posed_bone_directions(body, shape, result):
    """(T, 31, 3) unit head->tail directions of the posed target bones."""
    W, _ = body.pose(shape.rest_bone_poses, result.rotations[None], result.translation[None])
    P = shape.rest_bone_poses[0].astype(np.float64)
    rest_vec = np.einsum("jba,jb->ja", P[:, :3, :3], shape.bone_tails[0] - shape.bone_heads[0])  # in bone frame
    d = np.einsum("tjab,jb->tja", W[0, :, :, :3, :3].astype(np.float64), rest_vec)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def source_bone_directions(source, result, pairs):
    """{bone: (T, 3) unit source directions in the body frame}, from the source's own FK."""
    heads = source.world_heads() @ result.source_frame.T
    dR = source.rotation_deltas()
    out = {}
    for bone, (a, b) in pairs.items():
        i = source.index(a)
        if b is None:
            d = np.einsum("tab,b->ta", dR[:, i], source.rest_tails[i] - source.rest_heads[i]) @ result.source_frame.T
        else:
            d = heads[:, source.index(b)] - heads[:, i]
        out[bone] = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return out


def angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, -1), -1.0, 1.0)))


def lowest_skin_point(body, shape, rotations, translation):
    """(T,) lowest z of the whole posed skin (independent of retarget.foot_vertices)."""
    _, transforms = body.pose(shape.rest_bone_poses, rotations[None], translation[None])
    return body.skin(shape.rest_vertices, transforms)[0, ..., 2].min(axis=-1)


@needs_mocap
@pytest.mark.parametrize("body_name", list(BODIES))
def test_retargeted_walk_is_a_walk(body_name):
    body, shape, source = body_model(), shape_of(body_name), walk()

    # Bone directions at the source's own frame rate (no resampling), every frame.
    r = retarget(source, body, shape, fps=None)
    assert r.variant == "asf"
    assert r.rotations.shape == (343, 31, 3) and r.translation.shape == (343, 3)
    assert r.rotations.dtype == np.float32 and r.translation.dtype == np.float32
    assert np.all(np.isfinite(r.rotations)) and np.all(np.isfinite(r.translation))
    target = posed_bone_directions(body, shape, r)
    for bone, d in source_bone_directions(source, r, ASF_BONES).items():
        err = angle_deg(target[:, CMU_MB_BONES.index(bone)], d)
        assert err.max() < TOLERANCE_DEG, f"{bone}: {err.max():.2f} deg"

    # Feet on the ground at 30 fps: the lowest skin point is within 2 cm of z = 0 in most frames
    # (a walk always has a foot down) and never below -1 cm.
    r30 = retarget(source, body, shape, fps=30.0)
    assert len(r30.rotations) == 86 and r30.fps == 30.0
    low = lowest_skin_point(body, shape, r30.rotations, r30.translation)
    assert low.min() > -0.01
    assert np.mean(np.abs(low) < 0.02) > 0.8, np.round(low, 3)
    assert np.mean(np.abs(low) < 0.03) > 0.95

    # It walks forward: > 2 m in 2.8 s, on average along the body's forward (-Y), starting
    # facing it; the hip height bobs but stays near standing height.
    travel = r30.translation[-1, :2] - r30.translation[0, :2]
    assert np.linalg.norm(travel) > 2.0 * target_leg_length(shape) / target_leg_length(shape_of("neutral"))
    assert angle_deg(np.append(travel / np.linalg.norm(travel), 0.0), FORWARD) < 20.0
    hips_z = shape.bone_heads[0, 0, 2] + r30.translation[:, 2]  # above the ground z = 0
    standing = shape.bone_heads[0, 0, 2] - shape.rest_vertices[0, :, 2].min()
    assert np.all(np.abs(hips_z - standing) < 0.1 * standing)


@needs_mocap
def test_walk_starts_facing_forward():
    body, shape = body_model(), shape_of("neutral")
    r = retarget(walk(), body, shape, fps=30.0)
    W, _ = body.pose(shape.rest_bone_poses, r.rotations[None, :15], r.translation[None, :15])
    facing = W[0, :, 0, :3, :3] @ FORWARD  # root forward over the first 0.5 s
    mean = facing[:, :2].mean(0)
    assert angle_deg(np.append(mean / np.linalg.norm(mean), 0.0), FORWARD) < 1.0


@needs_mocap
def test_131_bvh_3dsmax_names():
    body, shape = body_model(), shape_of("neutral")
    source = load_bvh(MOCAP / "bvh" / "scaled_131_03.bvh")
    r = retarget(source, body, shape, fps=None)
    assert r.variant == "cmu_3dsmax"
    assert np.all(np.isfinite(r.rotations)) and np.all(np.isfinite(r.translation))
    target = posed_bone_directions(body, shape, r)
    for bone, d in source_bone_directions(source, r, MAX_BONES).items():
        err = angle_deg(target[:, CMU_MB_BONES.index(bone)], d)
        assert err.max() < TOLERANCE_DEG, f"{bone}: {err.max():.2f} deg"
    low = foot_heights(body, shape, r.rotations[None, ::4], r.translation[None, ::4])[0]
    assert low.min() > -0.01 and np.mean(low < 0.03) > 0.8


def mixamo_bvh(T=12):
    """A Mixamo-named BVH in centimetres, T-pose rest, Y-up facing +Z; left arm lowers, left knee bends."""
    P = ["Xposition", "Yposition", "Zposition", "Zrotation", "Xrotation", "Yrotation"]
    R = ["Zrotation", "Xrotation", "Yrotation"]
    m = "mixamorig:"
    joints = [
        (m + "Hips", -1, (0, 100, 0), P, None),
        (m + "Spine", 0, (0, 10, -1), R, None),
        (m + "Spine1", 1, (0, 12, 0), R, None),
        (m + "Spine2", 2, (0, 13, 0), R, None),
        (m + "Neck", 3, (0, 15, 1), R, None),
        (m + "Head", 4, (0, 10, 1), R, (0, 18, 0)),
        (m + "LeftShoulder", 3, (6, 11, 0), R, None),
        (m + "LeftArm", 6, (12, 0, 0), R, None),
        (m + "LeftForeArm", 7, (28, 0, 0), R, None),
        (m + "LeftHand", 8, (26, 0, 0), R, (9, 0, 0)),
        (m + "RightShoulder", 3, (-6, 11, 0), R, None),
        (m + "RightArm", 10, (-12, 0, 0), R, None),
        (m + "RightForeArm", 11, (-28, 0, 0), R, None),
        (m + "RightHand", 12, (-26, 0, 0), R, (-9, 0, 0)),
        (m + "LeftUpLeg", 0, (9, -5, 0), R, None),
        (m + "LeftLeg", 14, (0, -44, 0), R, None),
        (m + "LeftFoot", 15, (0, -43, 0), R, None),
        (m + "LeftToeBase", 16, (0, -7, 13), R, (0, 0, 6)),
        (m + "RightUpLeg", 0, (-9, -5, 0), R, None),
        (m + "RightLeg", 18, (0, -44, 0), R, None),
        (m + "RightFoot", 19, (0, -43, 0), R, None),
        (m + "RightToeBase", 20, (0, -7, 13), R, (0, 0, 6)),
    ]
    frames = np.zeros((T, 6 + 3 * (len(joints) - 1)))
    frames[:, 1] = 100.0  # hips height, cm
    frames[:, 2] = np.linspace(0, 30, T)  # walks 30 cm along +Z (its forward)
    s = np.linspace(0, 1, T)
    col = {j[0]: 6 + 3 * (i - 1) for i, j in enumerate(joints) if i > 0}
    frames[:, col[m + "LeftArm"] + 0] = -70 * s  # Zrotation: lower the left arm
    frames[:, col[m + "LeftLeg"] + 1] = 60 * s  # Xrotation: bend the left knee
    return make_bvh(joints, frames, 1 / 30)


def test_mixamo_bvh_retargets():
    body, shape = body_model(), shape_of("neutral")
    source = parse_bvh(mixamo_bvh())  # centimetres, inferred
    assert source.rest_heads[0, 1] == pytest.approx(1.0)
    r = retarget(source, body, shape, fps=None)
    assert r.variant == "mixamo"
    assert np.all(np.isfinite(r.rotations)) and np.all(np.isfinite(r.translation))
    pairs = {
        "LeftArm": ("mixamorig:LeftArm", "mixamorig:LeftForeArm"), "LeftForeArm": ("mixamorig:LeftForeArm", "mixamorig:LeftHand"),
        "LeftUpLeg": ("mixamorig:LeftUpLeg", "mixamorig:LeftLeg"), "LeftLeg": ("mixamorig:LeftLeg", "mixamorig:LeftFoot"),
        "RightLeg": ("mixamorig:RightLeg", "mixamorig:RightFoot"), "Spine": ("mixamorig:Spine1", "mixamorig:Spine2"),
    }  # fmt: skip
    target = posed_bone_directions(body, shape, r)
    for bone, d in source_bone_directions(source, r, pairs).items():
        assert angle_deg(target[:, CMU_MB_BONES.index(bone)], d).max() < TOLERANCE_DEG, bone
    # Bones with no Mixamo source keep their rest pose relative to their parent.
    for bone in ("LHipJoint", "RHipJoint", "Neck1", "LThumb", "LeftHandFinger1"):
        np.testing.assert_allclose(r.rotations[:, CMU_MB_BONES.index(bone)], 0.0, atol=1e-5)
    # Left arm ends lowered 70 deg from horizontal; the knee bent 60 deg.
    arm = target[-1, CMU_MB_BONES.index("LeftArm")]
    assert np.degrees(np.arcsin(-arm[2])) == pytest.approx(70.0, abs=TOLERANCE_DEG)
    thigh, shin = target[-1, CMU_MB_BONES.index("LeftUpLeg")], target[-1, CMU_MB_BONES.index("LeftLeg")]
    assert angle_deg(thigh, shin) == pytest.approx(60.0, abs=TOLERANCE_DEG)
    # Moves 0.3 m (scaled by leg length ratio) along its forward, which is the body's -Y.
    travel = r.translation[-1] - r.translation[0]
    scale = target_leg_length(shape) / 0.87
    np.testing.assert_allclose(travel[:2], [0.0, -0.3 * scale], atol=0.01)


def test_source_in_its_rest_pose_gives_the_target_rest_directions_of_the_source():
    """A CMU-like source standing in its rest pose: the target's legs point straight down."""
    body, shape = body_model(), shape_of("neutral")
    source = parse_bvh(mixamo_bvh(T=1))
    r = retarget(source, body, shape, fps=None, grounded=False)
    target = posed_bone_directions(body, shape, r)[0]
    for bone in ("LeftLeg", "RightLeg"):
        np.testing.assert_allclose(target[CMU_MB_BONES.index(bone)], [0, 0, -1], atol=1e-5)
    np.testing.assert_allclose(target[CMU_MB_BONES.index("LeftArm")], [1, 0, 0], atol=1e-5)  # T-pose
