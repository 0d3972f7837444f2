"""Bone-name maps from source skeletons onto the service's 31-bone ``cmu_mb`` rig.

A source *joint* corresponds to the target *bone whose head is at that joint*: 3ds Max
``LeftHip`` (the hip joint) moves the thigh, so it maps to cmu_mb ``LeftUpLeg``; ASF bones are
named after the bone itself (``lfemur`` -> ``LeftUpLeg``). Each map gives, per target bone,
source names in order of preference (the first one present wins); target bones with no source
keep their rest orientation relative to their parent (identity local rotation).

Matching ignores case and a namespace prefix (``mixamorig:Hips``, ``mixamorig1:Hips``,
``Armature|Hips``...). :func:`match_names` picks the variant that matches the most source joints.
"""
from __future__ import annotations

import re

import numpy as np

from inference.motion.skeleton import MotionFormatError

CMU_MB_BONES: tuple[str, ...] = (
    "Hips", "LHipJoint", "LeftUpLeg", "LeftLeg", "LeftFoot", "LeftToeBase",
    "LowerBack", "Spine", "Spine1",
    "LeftShoulder", "LeftArm", "LeftForeArm", "LeftHand", "LThumb", "LeftFingerBase", "LeftHandFinger1",
    "Neck", "Neck1", "Head",
    "RightShoulder", "RightArm", "RightForeArm", "RightHand", "RThumb", "RightFingerBase", "RightHandFinger1",
    "RHipJoint", "RightUpLeg", "RightLeg", "RightFoot", "RightToeBase",
)  # fmt: skip
CMU_MB_PARENTS: tuple[int, ...] = (
    -1, 0, 1, 2, 3, 4, 0, 6, 7, 8, 9, 10, 11, 12, 12, 14, 8, 16, 17, 8, 19, 20, 21, 22, 22, 24, 0, 26, 27, 28, 29,
)  # fmt: skip


def _sided(table: dict[str, tuple[str, ...]]) -> dict[str, tuple[str, ...]]:
    """Expand '{S}' (Left/Right), '{s}' (l/r) and '{C}' (L/R) templates into both sides."""
    out: dict[str, tuple[str, ...]] = {}
    for target, sources in table.items():
        if "{" not in target:
            out[target] = sources
            continue
        for S, s, C in (("Left", "l", "L"), ("Right", "r", "R")):
            out[target.format(S=S, s=s, C=C)] = tuple(src.format(S=S, s=s, C=C) for src in sources)
    return out


# target cmu_mb bone -> source joint names (preference order), per naming variant.
NAME_MAPS: dict[str, dict[str, tuple[str, ...]]] = {
    # CMU MotionBuilder-friendly BVH (cgspeed) = the cmu_mb rig's own names.
    "cmu_mb": _sided({
        "Hips": ("Hips",), "LowerBack": ("LowerBack",), "Spine": ("Spine",), "Spine1": ("Spine1",),
        "Neck": ("Neck",), "Neck1": ("Neck1",), "Head": ("Head",),
        "{C}HipJoint": ("{C}HipJoint",), "{S}UpLeg": ("{S}UpLeg",), "{S}Leg": ("{S}Leg",),
        "{S}Foot": ("{S}Foot",), "{S}ToeBase": ("{S}ToeBase",),
        "{S}Shoulder": ("{S}Shoulder",), "{S}Arm": ("{S}Arm",), "{S}ForeArm": ("{S}ForeArm",),
        "{S}Hand": ("{S}Hand",), "{C}Thumb": ("{C}Thumb",), "{S}FingerBase": ("{S}FingerBase",),
        "{S}HandFinger1": ("{S}HandFinger1", "{S}HandIndex1"),
    }),
    # CMU 3ds Max-friendly BVH (cgspeed; /shared/data/mocap/bvh/131_*.bvh).
    "cmu_3dsmax": _sided({
        "Hips": ("Hips",), "LowerBack": ("lowerback",), "Spine": ("Chest",), "Spine1": ("Chest2",),
        "Neck": ("lowerneck",), "Neck1": ("Neck",), "Head": ("Head",),
        "{C}HipJoint": ("{C}HipJoint",), "{S}UpLeg": ("{S}Hip",), "{S}Leg": ("{S}Knee",),
        "{S}Foot": ("{S}Ankle",), "{S}ToeBase": ("{S}Toe",),
        "{S}Shoulder": ("{S}Collar",), "{S}Arm": ("{S}Shoulder",), "{S}ForeArm": ("{S}Elbow",),
        "{S}Hand": ("{S}Wrist",), "{C}Thumb": ("{C}Thumb",), "{S}FingerBase": ("{s}hand",),
        "{S}HandFinger1": ("{C}Fingers",),
    }),
    # CMU Acclaim ASF bone names.
    "asf": _sided({
        "Hips": ("root",), "LowerBack": ("lowerback",), "Spine": ("upperback",), "Spine1": ("thorax",),
        "Neck": ("lowerneck",), "Neck1": ("upperneck",), "Head": ("head",),
        "{C}HipJoint": ("{s}hipjoint",), "{S}UpLeg": ("{s}femur",), "{S}Leg": ("{s}tibia",),
        "{S}Foot": ("{s}foot",), "{S}ToeBase": ("{s}toes",),
        "{S}Shoulder": ("{s}clavicle",), "{S}Arm": ("{s}humerus",), "{S}ForeArm": ("{s}radius",),
        "{S}Hand": ("{s}wrist",), "{C}Thumb": ("{s}thumb",), "{S}FingerBase": ("{s}hand",),
        "{S}HandFinger1": ("{s}fingers",),
    }),
    # Mixamo (prefix mixamorig: stripped). Its Spine starts above the pelvis (= cmu_mb LowerBack),
    # it has no hip-joint or second neck bone (LHipJoint, RHipJoint, Neck1 stay at rest).
    "mixamo": _sided({
        "Hips": ("Hips",), "LowerBack": ("Spine",), "Spine": ("Spine1",), "Spine1": ("Spine2",),
        "Neck": ("Neck",), "Head": ("Head",),
        "{S}UpLeg": ("{S}UpLeg",), "{S}Leg": ("{S}Leg",), "{S}Foot": ("{S}Foot",),
        "{S}ToeBase": ("{S}ToeBase",),
        "{S}Shoulder": ("{S}Shoulder",), "{S}Arm": ("{S}Arm",), "{S}ForeArm": ("{S}ForeArm",),
        "{S}Hand": ("{S}Hand",), "{C}Thumb": ("{S}HandThumb1",),
        "{S}FingerBase": ("{S}HandMiddle1", "{S}HandIndex1"),
        "{S}HandFinger1": ("{S}HandMiddle2", "{S}HandIndex2"),
    }),
}

_PREFIX = re.compile(r"^.*[:|]")


def normalise_name(name: str) -> str:
    """Lower-case, without a namespace prefix ('mixamorig:LeftArm' -> 'leftarm')."""
    return _PREFIX.sub("", name).strip().lower()


def match_names(source_names: tuple[str, ...] | list[str], variant: str | None = None) -> tuple[str, np.ndarray]:
    """Map source joints onto the cmu_mb bones.

    source_names : J_src joint names as in the file
    variant      : a key of NAME_MAPS, or None to pick the one matching most source names
    returns      : (variant, source_index (31,) int64: the source joint of each cmu_mb bone,
                   -1 where the bone has no source)
    Raises MotionFormatError unless the hips and both thighs, shins and feet match.
    """
    lookup: dict[str, int] = {}
    for i, name in enumerate(source_names):
        lookup.setdefault(normalise_name(name), i)
    candidates = [variant] if variant is not None else list(NAME_MAPS)
    best: tuple[int, str, np.ndarray] | None = None
    for v in candidates:
        table = NAME_MAPS[v]
        index = np.full(len(CMU_MB_BONES), -1, dtype=np.int64)
        for b, bone in enumerate(CMU_MB_BONES):
            for src in table.get(bone, ()):
                if src.lower() in lookup:
                    index[b] = lookup[src.lower()]
                    break
        # Score: distinct source joints used (a name matched under another meaning scores too,
        # but the right variant matches more, e.g. 3ds Max 'LeftShoulder' vs MotionBuilder's).
        score = len(set(index[index >= 0].tolist()))
        if best is None or score > best[0]:
            best = (score, v, index)
    assert best is not None
    _, v, index = best
    essential = ("Hips", "LeftUpLeg", "RightUpLeg", "LeftLeg", "RightLeg", "LeftFoot", "RightFoot")
    missing = [b for b in essential if index[CMU_MB_BONES.index(b)] < 0]
    if missing:
        raise MotionFormatError(f"source skeleton ({v} names) lacks bones for {missing}; names: {list(source_names)[:40]}")
    return v, index
