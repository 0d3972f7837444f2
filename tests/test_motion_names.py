"""Bone-name maps: every variant onto the 31 cmu_mb bones, head-at-joint semantics."""
from __future__ import annotations

import numpy as np
import pytest

from inference.motion.names import CMU_MB_BONES, CMU_MB_PARENTS, NAME_MAPS, match_names, normalise_name
from inference.motion.skeleton import MotionFormatError

MAX_NAMES = (
    "Hips LHipJoint LeftHip LeftKnee LeftAnkle LeftToe RHipJoint RightHip RightKnee RightAnkle RightToe "
    "lowerback Chest Chest2 lowerneck Neck Head LeftCollar LeftShoulder LeftElbow LeftWrist lhand LFingers "
    "LThumb RightCollar RightShoulder RightElbow RightWrist rhand RFingers RThumb"
).split()
ASF_NAMES = (
    "root lhipjoint rhipjoint lowerback lfemur rfemur upperback ltibia rtibia thorax lfoot rfoot lowerneck "
    "lclavicle rclavicle ltoes rtoes upperneck lhumerus rhumerus head lradius rradius lwrist rwrist lhand "
    "lthumb rhand rthumb lfingers rfingers"
).split()
MIXAMO_NAMES = [
    "mixamorig:" + n
    for n in (
        "Hips Spine Spine1 Spine2 Neck Head HeadTop_End LeftShoulder LeftArm LeftForeArm LeftHand "
        "LeftHandThumb1 LeftHandIndex1 LeftHandIndex2 RightShoulder RightArm RightForeArm RightHand "
        "LeftUpLeg LeftLeg LeftFoot LeftToeBase LeftToe_End RightUpLeg RightLeg RightFoot RightToeBase"
    ).split()
]


def mapped(names, variant=None):
    v, index = match_names(names, variant)
    return v, {b: (names[i] if i >= 0 else None) for b, i in zip(CMU_MB_BONES, index)}


def test_cmu_mb_names_map_to_themselves():
    v, index = match_names(CMU_MB_BONES)
    assert v == "cmu_mb"
    np.testing.assert_array_equal(index, np.arange(31))
    assert len(CMU_MB_PARENTS) == 31 and all(p < j for j, p in enumerate(CMU_MB_PARENTS))


def test_3dsmax_joint_maps_to_the_bone_starting_there():
    v, m = mapped(MAX_NAMES)
    assert v == "cmu_3dsmax"
    assert m["LeftUpLeg"] == "LeftHip" and m["LeftLeg"] == "LeftKnee" and m["LeftFoot"] == "LeftAnkle"
    assert m["LeftShoulder"] == "LeftCollar" and m["LeftArm"] == "LeftShoulder"  # same name, other meaning
    assert m["Spine"] == "Chest" and m["Neck"] == "lowerneck" and m["Neck1"] == "Neck"
    assert None not in m.values() and len(set(m.values())) == 31


def test_asf_bones():
    v, m = mapped(ASF_NAMES)
    assert v == "asf"
    assert m["Hips"] == "root" and m["LeftUpLeg"] == "lfemur" and m["RightArm"] == "rhumerus"
    assert m["LeftHand"] == "lwrist" and m["LeftFingerBase"] == "lhand" and m["LThumb"] == "lthumb"
    assert None not in m.values()


def test_mixamo_prefix_and_missing_bones():
    assert normalise_name("mixamorig:LeftArm") == "leftarm"
    assert normalise_name("mixamorig1:Hips") == "hips"
    v, m = mapped(MIXAMO_NAMES)
    assert v == "mixamo"
    assert m["LowerBack"] == "mixamorig:Spine" and m["Spine1"] == "mixamorig:Spine2"
    assert m["LeftShoulder"] == "mixamorig:LeftShoulder" and m["LeftArm"] == "mixamorig:LeftArm"
    assert m["LThumb"] == "mixamorig:LeftHandThumb1" and m["LeftFingerBase"] == "mixamorig:LeftHandIndex1"
    for missing in ("LHipJoint", "RHipJoint", "Neck1", "RThumb", "RightFingerBase"):
        assert m[missing] is None


def test_every_map_names_only_cmu_mb_bones():
    for table in NAME_MAPS.values():
        assert set(table) <= set(CMU_MB_BONES)


def test_forced_variant_and_unknown_skeleton():
    v, _ = match_names(MAX_NAMES, "cmu_3dsmax")
    assert v == "cmu_3dsmax"
    with pytest.raises(MotionFormatError, match="lacks bones"):
        match_names(["root", "a", "b", "c"])
