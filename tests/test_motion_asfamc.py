"""ASF/AMC parser: real CMU files, a hand-computed frame, malformed input."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from inference.motion.asfamc import load_asf_amc, parse_amc, parse_asf
from inference.motion.skeleton import CMU_UNIT_M, MotionFormatError

MOCAP = Path(__file__).resolve().parents[1] / "training" / "sources" / "mocap"
needs_mocap = pytest.mark.skipif(not MOCAP.exists(), reason="training/sources/mocap missing")

TINY_ASF = """\
# a two-bone leg
:version 1.10
:name tiny
:units
  mass 1.0
  length 0.45
  angle deg
:documentation
  hand-written
:root
   order TX TY TZ RX RY RZ
   axis XYZ
   position 0 0 0
   orientation 0 0 0
:bonedata
  begin
     id 1
     name lfemur
     direction 0 -1 0
     length 10
     axis 0 0 {femur_axis_z}  XYZ
    dof rx ry rz
    limits (-160.0 20.0)
           (-70.0 70.0)
           (-60.0 70.0)
  end
  begin
     id 2
     name ltibia
     direction 0 -1 0
     length 10
     axis 0 0 {tibia_axis_z}  XYZ
    dof rx
    limits (-10.0 170.0)
  end
:hierarchy
  begin
    root lfemur
    lfemur ltibia
  end
"""


def tiny_asf(femur_axis_z=0, tibia_axis_z=0):
    return parse_asf(TINY_ASF.format(femur_axis_z=femur_axis_z, tibia_axis_z=tibia_axis_z))


def amc(*frames):
    """AMC text; each frame is (root 6 values, lfemur 3, ltibia 1)."""
    lines = ["#!OML:ASF tiny.asf", ":FULLY-SPECIFIED", ":DEGREES"]
    for i, (root, femur, tibia) in enumerate(frames, start=1):
        lines += [str(i), "root " + " ".join(map(str, root)), "lfemur " + " ".join(map(str, femur)), f"ltibia {tibia}"]
    return "\n".join(lines) + "\n"


def tails(m):
    return m.world_heads() + np.einsum("tjab,jb->tja", m.rotation_deltas(), m.rest_tails - m.rest_heads)


def test_skeleton_units_and_rest_pose():
    s = tiny_asf()
    u = 0.0254 / 0.45
    assert s.unit_scale == pytest.approx(u) == pytest.approx(CMU_UNIT_M)
    assert s.names == ("root", "lfemur", "ltibia")
    assert list(s.parents) == [-1, 0, 1]
    assert s.dofs == (("tx", "ty", "tz", "rx", "ry", "rz"), ("rx", "ry", "rz"), ("rx",))
    np.testing.assert_allclose(s.heads, [[0, 0, 0], [0, 0, 0], [0, -10 * u, 0]], atol=1e-12)
    np.testing.assert_allclose(s.tails[2], [0, -20 * u, 0], atol=1e-12)


def test_hand_computed_frame_identity_axes():
    u = CMU_UNIT_M
    # root at (1, 2, 3) units turned 90 deg about X; femur still; knee flexed 90 deg (rx).
    m = parse_amc(amc(([1, 2, 3, 90, 0, 0], [0, 0, 0], 90)), tiny_asf())
    assert m.num_frames == 1 and m.fps == 120.0
    h, t = m.world_heads()[0], tails(m)[0]
    root = np.array([1.0, 2.0, 3.0]) * u
    np.testing.assert_allclose(h[0], root, atol=1e-12)
    # Rx(90): (0, -1, 0) -> (0, 0, -1). Femur: root + 10u (0, 0, -1).
    np.testing.assert_allclose(h[2], root + [0, 0, -10 * u], atol=1e-9)
    # Tibia: Rx(90) Rx(90) (0, -1, 0) = (0, 1, 0).
    np.testing.assert_allclose(t[2], h[2] + [0, 10 * u, 0], atol=1e-9)


def test_hand_computed_frame_with_axis_frame():
    """L = C M C^-1 with C = Rz(20): the knee flexes about the tilted bone's own x axis."""
    u = CMU_UNIT_M
    m = parse_amc(amc(([0, 0, 0, 0, 0, 0], [0, 0, 0], 90)), tiny_asf(20, 20))
    h, t = m.world_heads()[0], tails(m)[0]
    # By hand: Rz(-20)(0,-1,0) = (-0.34202, -0.93969, 0); Rx(90) -> (-0.34202, 0, -0.93969);
    # Rz(20) -> (-0.34202 cos20, -0.34202 sin20, -0.93969) = (-0.32139, -0.11698, -0.93969).
    np.testing.assert_allclose((t[2] - h[2]) / (10 * u), [-0.32139, -0.11698, -0.93969], atol=1e-5)
    # The bone's frame in the world: dR C, with C = Rz(20) at rest.
    c, s = np.cos(np.radians(20)), np.sin(np.radians(20))
    np.testing.assert_allclose(m.rest_rotations[2], [[c, -s, 0], [s, c, 0], [0, 0, 1]], atol=1e-12)


def test_dof_order_is_applied_first_listed_first():
    # femur rx=90 then rz=90 (M = Rz Rx): (0,-1,0) -Rx-> (0,0,-1) -Rz-> (0,0,-1)
    m = parse_amc(amc(([0] * 6, [90, 0, 90], 0)), tiny_asf())
    t = tails(m)[0]
    np.testing.assert_allclose(t[1] - m.world_heads()[0, 1], [0, 0, -10 * CMU_UNIT_M], atol=1e-9)


@needs_mocap
def test_real_cmu_walk():
    m = load_asf_amc(MOCAP / "cmu-asfamc" / "02" / "02.asf", MOCAP / "cmu-asfamc" / "02" / "02_01.amc")
    assert m.num_joints == 31 and m.num_frames == 343 and m.fps == 120.0
    heads = m.world_heads()
    feet = [m.index(n) for n in ("lfoot", "ltoes", "rfoot", "rtoes")]
    hip_height = heads[:, 0, 1] - heads[:, feet, 1].min(axis=1)
    assert 0.85 < np.median(hip_height) < 1.0  # metres
    walked = m.root_positions[-1] - m.root_positions[0]
    assert np.hypot(walked[0], walked[2]) > 2.0  # walks over 2 m in 2.9 s
    # Bone lengths are preserved by the rotations.
    femur = np.linalg.norm(heads[:, m.index("ltibia")] - heads[:, m.index("lfemur")], axis=-1)
    np.testing.assert_allclose(femur, 7.59371 * CMU_UNIT_M, rtol=1e-9)


GOOD_AMC = amc(([0] * 6, [0, 0, 0], 0), ([0] * 6, [1, 2, 3], 4))


@pytest.mark.parametrize(
    "text, match",
    [
        ("", "no frames"),
        ("root 0 0 0 0 0 0\n", "expected a frame number"),
        (GOOD_AMC.replace("lfemur 1 2 3", "lfemur 1 2"), r"lfemur.*needs 3 numbers, got 2"),
        (GOOD_AMC.replace("lfemur 1 2 3", "lfemur 1 2 x"), "expected numbers"),
        (GOOD_AMC.replace("lfemur 1 2 3", "lfemur 1 2 inf"), "non-finite"),
        (GOOD_AMC.replace("lfemur 1 2 3", "rfemur 1 2 3"), "unknown bone 'rfemur'"),
        (GOOD_AMC.replace("ltibia 4", "ltibia 4\nltibia 4"), "listed twice"),
        (GOOD_AMC.replace("\nltibia 4", ""), r"lacks bones \['ltibia'\]"),
        (GOOD_AMC.replace("\n2\n", "\n5\n"), "frame number 5, expected 2"),
    ],
)
def test_malformed_amc(text, match):
    with pytest.raises(MotionFormatError, match=match):
        parse_amc(text, tiny_asf())


def test_amc_frame_limit():
    with pytest.raises(MotionFormatError, match="limit of 1 frames"):
        parse_amc(GOOD_AMC, tiny_asf(), max_frames=1)


@pytest.mark.parametrize(
    "edit, match",
    [
        (("  end\n  begin\n     id 2", "  begin\n     id 2"), "inside a bone block"),
        (("direction 0 -1 0\n     length 10\n     axis 0 0 0  XYZ\n    dof rx\n", "direction 0 -1 0\n     axis 0 0 0  XYZ\n    dof rx\n"), "no 'length'"),
        (("dof rx ry rz", "dof rx ry qq"), "dof must be"),
        (("axis 0 0 0  XYZ\n    dof rx\n", "axis 0 0 0  XYQ\n    dof rx\n"), "permutation of XYZ"),
        (("lfemur ltibia\n", "lfemur ltibia shin\n"), "unknown bone 'shin'"),
        (("    lfemur ltibia\n", ""), "not reachable"),
        (("order TX TY TZ RX RY RZ", "order TX TY TZ RX RY QZ"), "root order"),
        (("length 0.45", "length -1"), "positive"),
        (("direction 0 -1 0\n     length 10\n     axis 0 0 0  XYZ\n    dof rx\n", "direction 0 -1 zero\n     length 10\n     axis 0 0 0  XYZ\n    dof rx\n"), "expected numbers"),
    ],
)
def test_malformed_asf(edit, match):
    text = TINY_ASF.format(femur_axis_z=0, tibia_axis_z=0)
    old, new = edit
    assert old in text
    with pytest.raises(MotionFormatError, match=match):
        parse_asf(text.replace(old, new, 1))


def test_truncated_asf():
    text = TINY_ASF.format(femur_axis_z=0, tibia_axis_z=0)
    with pytest.raises(MotionFormatError, match="not closed"):
        parse_asf(text[: text.index("  end")])


def test_garbage_amc_is_refused_quickly():
    import time

    t0 = time.perf_counter()
    with pytest.raises(MotionFormatError):
        parse_amc("1\n" + "lfemur 1 2 3\n" * 10 + "x" * 4_000_000, tiny_asf())
    with pytest.raises(MotionFormatError):
        parse_asf("\x00" * 1_000_000)
    assert time.perf_counter() - t0 < 2.0
