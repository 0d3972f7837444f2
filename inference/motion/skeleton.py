"""The common source-motion representation every parser (BVH, ASF/AMC) produces.

A source skeleton is a tree of J joints. Joint j is the *head* of the bone that joint j's
rotation moves (BVH joint = bone starting at that joint; ASF bone = its head is the parent
bone's tail). Everything is in metres, in the source's own world axes (``up_axis`` says which
of them is vertical); the retargeter converts to the service's Z-up world.

Rotations: matrices act on column vectors. ``rest_rotations[j]`` is joint j's frame in the
world at rest (identity for BVH, the ASF ``axis`` frame C for ASF); ``world_rotations[t, j]``
is the same frame at frame t. The world-space rotation change of joint j is
``dR_j(t) = world_rotations[t, j] @ rest_rotations[j].T``, and forward kinematics is
``head_c(t) = head_j(t) + dR_j(t) @ (rest_heads[c] - rest_heads[j])`` for every child c of j.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from inference.errors import InferenceInputError

MAX_JOINTS = 256
DEFAULT_MAX_FRAMES = 100_000

# Metres per unit of the CMU mocap data: ASF `length 0.45` = 1/0.45 inch per unit; the
# cgspeed BVH conversion uses the same units (131_01.bvh root x 5.2300 = 0.295202 m in
# scaled_131_01.bvh: ratio 0.056444).
CMU_UNIT_M = 0.0254 / 0.45


class MotionFormatError(InferenceInputError):
    """Malformed or unsupported motion input (BVH, ASF/AMC text, pose arrays); a ValueError.

    ``field`` names the request field (default "motion") for the service's problem+json.
    """

    def __init__(self, message: str, field: str = "motion"):
        super().__init__(field, message)


@dataclass(frozen=True)
class SourceMotion:
    """A parsed source motion, metres, source world axes.

    names           : J joint names, as in the file
    parents         : (J,) int64, parent index, -1 for the root (joint 0); parents[j] < j
    rest_heads      : (J, 3) float64, metres, joint positions in the rest (offset/bind) pose
    rest_tails      : (J, 3) float64, metres, bone ends at rest: the end site (leaf joints), the
                      single child's head, or the ASF bone end; equal to the head where the
                      bone is undefined (several children)
    rest_rotations  : (J, 3, 3) float64, joint frames in the world at rest
    world_rotations : (T, J, 3, 3) float64, joint frames in the world per frame
    root_positions  : (T, 3) float64, metres, root joint position per frame
    fps             : frames per second
    up_axis         : "y" or "z", the source world's vertical axis (+)
    """

    names: tuple[str, ...]
    parents: np.ndarray
    rest_heads: np.ndarray
    rest_tails: np.ndarray
    rest_rotations: np.ndarray
    world_rotations: np.ndarray
    root_positions: np.ndarray
    fps: float
    up_axis: str = "y"

    @property
    def num_frames(self) -> int:
        return int(self.world_rotations.shape[0])

    @property
    def num_joints(self) -> int:
        return len(self.names)

    def index(self, name: str) -> int:
        return self.names.index(name)

    def frames(self, start: int, stop: int | None = None) -> "SourceMotion":
        """The same motion restricted to frames [start, stop)."""
        sl = slice(start, stop)
        if len(range(*sl.indices(self.num_frames))) == 0:
            raise ValueError(f"frames [{start}, {stop}) select nothing of {self.num_frames}")
        return replace(self, world_rotations=self.world_rotations[sl], root_positions=self.root_positions[sl])

    def rotation_deltas(self) -> np.ndarray:
        """(T, J, 3, 3) world rotation change from rest, dR_j(t) = R_j(t) R_j(rest)^T."""
        return self.world_rotations @ np.swapaxes(self.rest_rotations, -1, -2)

    def world_heads(self) -> np.ndarray:
        """(T, J, 3) metres, joint positions per frame (forward kinematics, see module doc)."""
        dR = self.rotation_deltas()
        heads = np.empty((self.num_frames, self.num_joints, 3))
        heads[:, 0] = self.root_positions
        for j in range(1, self.num_joints):  # loop over joints, vectorised over frames
            p = self.parents[j]
            heads[:, j] = heads[:, p] + dR[:, p] @ (self.rest_heads[j] - self.rest_heads[p])
        return heads


def euler_to_matrix(angles_rad: np.ndarray, axes: str) -> np.ndarray:
    """Rotation matrices from intrinsic Euler angles, the first listed axis outermost.

    angles_rad : (..., k) radians, one angle per axis letter
    axes       : k letters from "XYZ" (e.g. "ZYX"); returns R_axes[0] @ R_axes[1] @ ...
    returns    : (..., 3, 3) float64

    This is the BVH channel convention (``Zrotation Yrotation Xrotation`` -> Rz Ry Rx) and,
    read backwards, the ASF one (``axis ... XYZ`` / ``dof rx ry rz`` -> Rz Ry Rx).
    """
    angles_rad = np.asarray(angles_rad, dtype=np.float64)
    if angles_rad.shape[-1] != len(axes):
        raise ValueError(f"expected {len(axes)} angles for axes {axes!r}, got {angles_rad.shape[-1]}")
    R = np.broadcast_to(np.eye(3), angles_rad.shape[:-1] + (3, 3)).copy()
    for k, axis in enumerate(axes.upper()):
        R = R @ _axis_rotation(angles_rad[..., k], axis)
    return R


def _axis_rotation(a: np.ndarray, axis: str) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    if axis == "X":
        m = [o, z, z, z, c, -s, z, s, c]
    elif axis == "Y":
        m = [c, z, s, z, o, z, -s, z, c]
    elif axis == "Z":
        m = [c, -s, z, s, c, z, z, z, o]
    else:
        raise ValueError(f"unknown rotation axis {axis!r}")
    return np.stack(m, -1).reshape(a.shape + (3, 3))
