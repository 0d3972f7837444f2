"""BVH parser: real CMU files, a hand-computed tiny file, channel orders vs scipy, malformed input."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from inference.motion.bvh import infer_unit_scale, load_bvh, parse_bvh
from inference.motion.skeleton import CMU_UNIT_M, MAX_JOINTS, MotionFormatError

MOCAP = Path(__file__).resolve().parents[1] / "training" / "sources" / "mocap"
needs_mocap = pytest.mark.skipif(not MOCAP.exists(), reason="training/sources/mocap missing")


def make_bvh(joints, frames, frame_time=1 / 30) -> str:
    """BVH text from [(name, parent_index, offset (3,), channels [...], end_site (3,) or None)].

    frames : (T, sum of channels) values in file order (joints in list order = depth-first).
    """
    children = {i: [k for k, j in enumerate(joints) if j[1] == i] for i in range(len(joints))}
    out = ["HIERARCHY"]

    def emit(i, depth):
        name, parent, offset, channels, end = joints[i]
        pad = "  " * depth
        out.append(f"{pad}{'ROOT' if parent < 0 else 'JOINT'} {name}")
        out.append(pad + "{")
        out.append(f"{pad}  OFFSET {offset[0]} {offset[1]} {offset[2]}")
        out.append(f"{pad}  CHANNELS {len(channels)} {' '.join(channels)}")
        for c in children[i]:
            emit(c, depth + 1)
        if end is not None:
            out.append(f"{pad}  End Site")
            out.append(pad + "  {")
            out.append(f"{pad}    OFFSET {end[0]} {end[1]} {end[2]}")
            out.append(pad + "  }")
        out.append(pad + "}")

    emit(0, 0)
    frames = np.atleast_2d(frames)
    out += ["MOTION", f"Frames: {len(frames)}", f"Frame Time: {frame_time:.6f}"]
    out += [" ".join(f"{v:.6f}" for v in row) for row in frames]
    return "\n".join(out) + "\n"


POS = ["Xposition", "Yposition", "Zposition"]
TINY = [
    ("Hips", -1, (0, 0, 0), POS + ["Zrotation", "Xrotation", "Yrotation"], None),
    ("Chest", 0, (0, 10, 0), ["Zrotation", "Xrotation", "Yrotation"], (0, 5, 0)),
    ("Leg", 0, (2, 0, 0), ["Xrotation", "Zrotation"], (0, -8, 0)),
]


def tail_positions(m):
    """(T, J, 3) bone ends per frame: head + dR (rest_tail - rest_head)."""
    return m.world_heads() + np.einsum("tjab,jb->tja", m.rotation_deltas(), m.rest_tails - m.rest_heads)


def test_tiny_bvh_forward_kinematics_by_hand():
    frames = np.array([
        [0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0],
        # root at (100, 200, 300) cm turned 90 deg about Z; Chest Z=0 X=90; Leg X=0 Z=90
        [100, 200, 300, 90, 0, 0, 0, 90, 0, 0, 90],
    ], float)  # fmt: skip
    m = parse_bvh(make_bvh(TINY, frames, 0.5), unit_scale=0.01)
    assert m.names == ("Hips", "Chest", "Leg")
    assert list(m.parents) == [-1, 0, 0]
    assert m.fps == pytest.approx(2.0)
    assert m.up_axis == "y"
    np.testing.assert_allclose(m.rest_heads, [[0, 0, 0], [0, 0.1, 0], [0.02, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(m.rest_tails, [[0, 0, 0], [0, 0.15, 0], [0.02, -0.08, 0]], atol=1e-12)
    heads, tails = m.world_heads(), tail_positions(m)
    np.testing.assert_allclose(heads[0], m.rest_heads, atol=1e-12)
    # Rz(90) maps x -> y, y -> -x.
    root = np.array([1.0, 2.0, 3.0])
    np.testing.assert_allclose(heads[1, 0], root, atol=1e-9)
    np.testing.assert_allclose(heads[1, 1], root + [-0.1, 0, 0], atol=1e-9)  # Rz(90) (0, .1, 0)
    np.testing.assert_allclose(heads[1, 2], root + [0, 0.02, 0], atol=1e-9)  # Rz(90) (.02, 0, 0)
    # Chest end: Rz(90) Rx(90) (0, .05, 0) = Rz(90) (0, 0, .05) = (0, 0, .05)
    np.testing.assert_allclose(tails[1, 1], heads[1, 1] + [0, 0, 0.05], atol=1e-9)
    # Leg end: Rz(90) [Rx(0) Rz(90)] (0, -.08, 0) = Rz(180) (0, -.08, 0) = (0, .08, 0)
    np.testing.assert_allclose(tails[1, 2], heads[1, 2] + [0, 0.08, 0], atol=1e-9)


@pytest.mark.parametrize("order", ["ZYX", "ZXY", "XYZ", "YXZ", "YZX", "XZY"])
def test_channel_orders_match_scipy_intrinsic(order):
    rng = np.random.default_rng(len(order) + ord(order[0]))
    angles = np.round(rng.uniform(-170, 170, size=(5, 3)), 6)  # as written to the file
    joints = [("Root", -1, (0, 0, 0), [f"{a}rotation" for a in order], (0, 1, 0))]
    m = parse_bvh(make_bvh(joints, angles), unit_scale=1.0)
    expected = Rotation.from_euler(order.upper(), angles, degrees=True).as_matrix()  # intrinsic
    np.testing.assert_allclose(m.world_rotations[:, 0], expected, atol=1e-9)


def test_units_inferred_from_skeleton_height():
    assert infer_unit_scale(1.7) == 1.0
    assert infer_unit_scale(30.0) == pytest.approx(CMU_UNIT_M)
    assert infer_unit_scale(67.0) == pytest.approx(0.0254)
    assert infer_unit_scale(170.0) == pytest.approx(0.01)
    for bad in (0.1, 6.0, 1000.0):
        with pytest.raises(MotionFormatError):
            infer_unit_scale(bad)


@needs_mocap
def test_cmu_units_and_metres_files_agree():
    cmu = load_bvh(MOCAP / "bvh" / "131_01.bvh")  # units inferred: CMU
    metres = load_bvh(MOCAP / "bvh" / "scaled_131_01.bvh")
    assert cmu.num_joints == metres.num_joints == 31
    assert cmu.fps == pytest.approx(120.0, rel=1e-4)
    assert cmu.num_frames == 994 and metres.num_frames == 995
    np.testing.assert_allclose(cmu.rest_heads, metres.rest_heads, atol=2e-4)
    np.testing.assert_allclose(cmu.root_positions[:100], metres.root_positions[:100], atol=2e-4)
    np.testing.assert_allclose(cmu.world_rotations[:100], metres.world_rotations[:100], atol=1e-4)
    # Standing at frame 0: hips ~0.95 m above the lowest joint.
    heads = cmu.world_heads()[0]
    assert 0.85 < heads[0, 1] - heads[:, 1].min() < 1.0
    assert cmu.names[cmu.parents[cmu.index("LeftKnee")]] == "LeftHip"


@needs_mocap
def test_real_file_parses_fast():
    t0 = time.perf_counter()
    m = load_bvh(MOCAP / "bvh" / "scaled_131_03.bvh")
    assert time.perf_counter() - t0 < 2.0
    assert m.world_rotations.shape == (1248, 31, 3, 3)
    assert np.all(np.isfinite(m.world_rotations))


GOOD = make_bvh(TINY, np.zeros((3, 11)))


@pytest.mark.parametrize(
    "text, match",
    [
        ("", "MOTION"),
        ("HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n", "MOTION"),  # truncated hierarchy
        (GOOD.rsplit("\n", 2)[0] + "\n", "truncated"),  # a frame line missing
        (GOOD.replace("Frames: 3", "Frames: 5"), "truncated"),
        (GOOD.replace("Frames: 3", "Frames: 2"), "more frame lines"),
        (GOOD.replace("OFFSET 0 10 0", "OFFSET 0 ten 0"), "expected a number"),
        (GOOD[: GOOD.rindex("0.000000")] + "abc\n", "expected a number"),
        (GOOD[: GOOD.rindex("0.000000")] + "nan\n", "not finite|non-finite"),
        (GOOD.replace("CHANNELS 3 Zrotation", "CHANNELS 4 Zrotation"), "channel name"),
        (GOOD.replace("CHANNELS 2 Xrotation", "CHANNELS 2 Wrotation"), "channel name"),
        (GOOD.replace("CHANNELS 2 Xrotation Zrotation", "CHANNELS 2 Xrotation Xrotation"), "repeated"),
        (GOOD.replace("CHANNELS 6", "CHANNELS 7"), "channel count"),
        (GOOD.replace("Frame Time: 0.033333", "Frame Time: 0"), "frame time"),
        (GOOD.replace("Frames: 3", "Frames: -3"), "frame count"),
        (GOOD.replace("HIERARCHY", "HIERARCHIE"), "HIERARCHY"),
        (GOOD.replace("MOTION", "}\nMOTION", 1), "after the ROOT block|unexpected"),
        (GOOD.replace("MOTION", "ROOT Other\n{\nOFFSET 0 0 0\nCHANNELS 0\n}\nMOTION", 1), "one ROOT"),
        ("\x00\x01garbage\nMOTION\n", "HIERARCHY"),
    ],
)
def test_malformed_bvh_raises_motion_format_error(text, match):
    with pytest.raises(MotionFormatError, match=match):
        parse_bvh(text, unit_scale=0.01)


def test_error_messages_carry_line_numbers():
    bad = GOOD.replace("OFFSET 0 10 0", "OFFSET 0 ten 0")
    line = bad.splitlines().index(next(ln for ln in bad.splitlines() if "ten" in ln)) + 1
    with pytest.raises(MotionFormatError, match=f"line {line}:"):
        parse_bvh(bad)


def test_wrong_value_count_in_a_frame_line():
    lines = GOOD.splitlines()
    lines[-2] = lines[-2] + " 0.0"
    with pytest.raises(MotionFormatError, match=r"frame 2 has 12 values, expected 11"):
        parse_bvh("\n".join(lines), unit_scale=0.01)


def test_too_many_joints_refused_quickly():
    joints = [("Root", -1, (0, 0, 0), POS, None)]
    joints += [(f"J{i}", 0, (0, 1, 0), [], (0, 1, 0)) for i in range(MAX_JOINTS + 10)]
    text = make_bvh(joints, np.zeros((1, 3)))
    t0 = time.perf_counter()
    with pytest.raises(MotionFormatError, match=f"more than {MAX_JOINTS} joints"):
        parse_bvh(text, unit_scale=1.0)
    assert time.perf_counter() - t0 < 1.0


def test_frame_limit_is_checked_before_reading_frames():
    huge = GOOD.replace("Frames: 3", "Frames: 1000000000000")
    with pytest.raises(MotionFormatError, match="more than the limit"):
        parse_bvh(huge, unit_scale=0.01, max_frames=1000)
    with pytest.raises(MotionFormatError, match="more than the limit 2"):
        parse_bvh(GOOD, unit_scale=0.01, max_frames=2)


def test_motion_format_error_is_a_value_error():
    with pytest.raises(ValueError):
        parse_bvh("not a bvh")


@pytest.mark.parametrize(
    "text",
    [
        "x " * 2_000_000,  # 4 MB without structure
        "HIERARCHY\nROOT a\n{\n" + "junk " * 500_000 + "\nMOTION\n",
        GOOD.replace("Frames: 3", "Frames: 99999") + "\n" * 10,  # declared far more frames than lines
    ],
)
def test_garbage_is_refused_quickly(text):
    t0 = time.perf_counter()
    with pytest.raises(MotionFormatError):
        parse_bvh(text, unit_scale=0.01)
    assert time.perf_counter() - t0 < 2.0
