"""Shape-aware arm correction: lift the arms out of the torso where LBS sinks them in.

A clip recorded on one body and retargeted to a heavier one keeps its bone orientations
(``inference.motion.retarget``), so arms that hung close to a slim actor's sides sink into a
heavy avatar's torso (01_01, heaviest adult: 154 skin vertices per frame inside another part on
average, up to 550). No garment can be outside the body there: cloth between arm and torso is
inside one or the other, and the guard cannot resolve it. This stage abducts each upper arm
about its shoulder joint, per frame, until its skin clears the torso and thighs by ``margin_m``:

    depth  = max_a max(0, -(a - c_a) . n_c)       a: arm skin point, c_a: its nearest torso
                                                  point (within ``reach_m``, a projects onto
                                                  it: tangential offset < ``tangent_m``), n_c:
                                                  the outward normal there
    d      = the depth-weighted mean of those n_c  (the direction the arm must move)
    r      = a* - s                                (deepest point a*, shoulder joint s)
    k      = r x d / |r x d|,  theta = (depth + margin) / |r x d|      (small-angle step)
    W_arm <- R(k, theta) W_arm                    (world rotation about s; children follow)

repeated ``iterations`` times on the re-posed arm (only frames that still need it), each step
capped and widened to a centred moving maximum over time within each motion segment (a frame
never gets less than it needs; neighbours do not snap). In the pose contract of
``inference.body`` a world rotation Q of bone c is the local change D_c <- A^T Q A D_c with
A = W_parent R_parent^T R_c (the bone's world rotation at D = I).

Reported on the test clip 01_01 (no constant is chosen there; lifted at 30 fps, every 8th frame, with
``inference.metrics.self_intersecting_vertices``), skin vertices inside another part per frame,
mean: neutral 63.8 -> 33.0, heaviest adult 153.8 -> 17.9, lightest 13.7 -> 13.7 (untouched);
abduction mean / max: neutral 2.9° / 14.3°, heaviest 15.7° / 34.4°, lightest 0°.

Points: the torso and arm skin vertices thinned to one per ``TORSO_VOXEL_M`` / ``ARM_VOXEL_M``
cell in the rest pose; normals are the rest normals rotated by the blended skinning transform.
Each arm point's nearest torso point comes from a grid of the frame's torso points
(``inference.repair_kernels.frame_knn``, the answers of a KD-tree per frame); the depths, the
direction and the step are one compiled pass (``inference.motion.arm_kernels``). Cost (one thread,
30-frame windows of the ``dance`` clip, three bodies, session 39's machine): 0.24-0.28 ms per frame
(0.57-0.66 with a KD-tree per frame), 0.57-0.66 for a 1-frame request, plus ~11 ms of per-body
set-up (``ArmLifter``, cached per body shape by ``arm_lifter``). On session 43's slower machine,
the service's requests (default body, ``dance``): 0.72 ms a frame of 30, 2.4 ms for 1 frame, of
which the nearest torso points take 0.42 ms a frame.
Units: metres, radians.
"""
from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Sequence

import numpy as np

from inference.body import BodyModel, BodyShape, linear_blend_skinning, skin_points_and_normals
from inference.mesh import vertex_normals
from inference.motion.arm_kernels import arm_steps, rotate_bone, window_argmax
from inference.repair_kernels import frame_knn

# Bones of each arm chain (shoulder joint = head of the first) and of the body they must clear.
ARM_CHAINS = (
    ("LeftArm", "LeftForeArm", "LeftHand", "LThumb", "LeftFingerBase", "LeftHandFinger1"),
    ("RightArm", "RightForeArm", "RightHand", "RThumb", "RightFingerBase", "RightHandFinger1"),
)
TORSO_BONES = ("Hips", "LowerBack", "Spine", "Spine1", "LHipJoint", "RHipJoint", "LeftUpLeg", "RightUpLeg")
# Skin vertices with at least this much weight on a bone set belong to it (the shoulder blend,
# half arm and half torso, belongs to neither: it cannot leave the torso).
_MEMBER_WEIGHT = 0.95
# Clearance the arm skin keeps from the torso, metres: room for two garment surfaces between them
# (a sleeve and the torso of a shirt, 2 mm guard margin each, plus the cloth). Chosen on the
# validation clip 02_02 (`python tools/arm_margin_validation.py`: retarget T-shirt, every 2nd
# frame, clean inside % after the guard for no lift / 5 / 10 / 15 mm): heaviest adult
# 1.094 / 0.071 / 0.048 / 0.037, neutral 0.098 / 0.017 / 0.010 / 0.004, for a mean abduction of
# 19.3 / 20.6 / 21.6 deg (heaviest) and 5.3 / 7.0 / 8.5 deg (neutral): each 5 mm past 10 buys
# less and lifts the arms further from the clip. (01_01, reported only: heaviest 0.114 / 0.075 /
# 0.054 for 5 / 10 / 15 mm.)
DEFAULT_MARGIN_M = 0.010
# A torso point farther than this from an arm point does not judge it.
DEFAULT_REACH_M = 0.08
# ... nor one the arm point does not project onto (tangential offset larger than this): in the
# armpit the nearest torso point lies across a concave crease and its plane misjudges.
DEFAULT_TANGENT_M = 0.015
# Rest-pose thinning of the torso points (their planes judge: anny's mean edge, ~1.2 cm) and of
# the arm points (they only sample the depth). Arm cells on the validation clip 02_02
# (`python tools/arm_voxel_validation.py`): 2 cm against 1 cm keeps about half the arm points and
# changes the abduction by 0.13-0.22 deg on average (neutral, heaviest; up to 5.5 deg in a single
# frame); 3 cm changes it by 0.19-0.22 deg with a third of the points.
TORSO_VOXEL_M = 0.012
ARM_VOXEL_M = 0.02
# Largest abduction per iteration and in total, radians.
_STEP_CAP = 0.25
_TOTAL_CAP = 0.6
# Frames on each side of the centred moving maximum of each step.
SMOOTH_FRAMES = 2


def _members(body: BodyModel, bones: Sequence[str], rest: np.ndarray, voxel_m: float) -> np.ndarray:
    """Vertex ids with >= _MEMBER_WEIGHT on ``bones``, one per ``voxel_m`` cell of the rest pose."""
    ids = [body.bone_names.index(b) for b in bones if b in body.bone_names]
    v = np.flatnonzero(body.dense_weights[:, ids].sum(1) >= _MEMBER_WEIGHT)
    cell = np.floor(rest[v] / voxel_m).astype(np.int64)
    return np.sort(v[np.unique(cell, axis=0, return_index=True)[1]])


def _skin(body: BodyModel, ids: np.ndarray, rest: np.ndarray, normals: np.ndarray, transforms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Posed points (T, n, 3) and unit normals (T, n, 3) of the vertices ``ids``."""
    p, n = skin_points_and_normals(rest[None, ids], normals[None, ids], body.dense_weights[ids], transforms[None])
    return p[0], n[0]


class ArmLifter:
    """The per-body set-up of ``lift_arms`` (rest normals, thinned torso and arm points), reusable
    for many motions of one body (training draws many windows per bank shape)."""

    def __init__(self, body: BodyModel, shape: BodyShape):
        self.body, self.shape = body, shape
        self.rest = shape.rest_vertices[0]
        self.rest_normals = vertex_normals(self.rest, body.faces)
        self.torso = _members(body, TORSO_BONES, self.rest, TORSO_VOXEL_M)
        self.arms = [(body.bone_names.index(chain[0]), _members(body, chain, self.rest, ARM_VOXEL_M)) for chain in ARM_CHAINS]

    def lift(
        self,
        rotations: np.ndarray,
        translation: np.ndarray,
        segments: Sequence[int] | None = None,
        *,
        margin_m: float = DEFAULT_MARGIN_M,
        reach_m: float = DEFAULT_REACH_M,
        tangent_m: float = DEFAULT_TANGENT_M,
        iterations: int = 3,
        poses: bool = False,
    ) -> tuple[np.ndarray, ...]:
        """``lift_arms`` for this body (same arguments and results); ``poses``: also the bone poses
        and skinning transforms of the lifted motion (1, T, J, 4, 4) float32, ``BodyModel.pose``'s
        (each frame posed again after its last change), so that the caller need not pose it again."""
        body, shape, rest, rest_n = self.body, self.shape, self.rest, self.rest_normals
        rotations = np.array(rotations, np.float32)
        translation = np.asarray(translation, np.float32)
        T = rotations.shape[0]
        segments = [T] if segments is None else [int(n) for n in segments]
        W, transforms = body.pose(shape.rest_bone_poses, rotations[None], translation[None])
        tp, tn = _skin(body, self.torso, rest, rest_n, transforms[0])  # the torso does not move with the arms
        angles = np.zeros((T, 2), np.float32)
        # The two arms iterate side by side: an arm's chain and its skin do not depend on the other
        # arm's bones, so this is the left arm's iterations then the right's, with one forward
        # kinematics per iteration for both.
        active = [np.arange(T) for _ in self.arms]
        for _ in range(max(int(iterations), 1)):
            moved = []
            for side, (bone, arm) in enumerate(self.arms):
                if not len(active[side]):
                    continue
                a = active[side]
                ap = linear_blend_skinning(rest[None, arm], body.dense_weights[arm], transforms[:, a])[0]
                step, axes = _steps(tp, tn, ap, W[0, a, bone, :3, 3], a, T, margin_m, reach_m, tangent_m)
                if not step.any():
                    active[side] = a[:0]
                    continue
                src = _window_argmax(step, segments)  # a frame never gets less than its neighbours need
                axes = np.where((step > 0)[:, None], axes, axes[src])
                step = np.minimum(step[src], _TOTAL_CAP - angles[:, side])
                a = active[side] = np.flatnonzero(step > 0)
                if not len(a):
                    continue
                angles[a, side] += step[a]
                rotations[a, bone] = _rotate_bone(body, shape, W[0, a], rotations[a, bone], bone, axes[a], step[a])
                moved.append(a)
            if not moved:
                break
            u = moved[0] if len(moved) == 1 else np.union1d(*moved)
            Wa, Ta = body.pose(shape.rest_bone_poses, rotations[None, u], translation[None, u])
            W[0, u], transforms[0, u] = Wa[0], Ta[0]
        return (rotations, angles, W, transforms) if poses else (rotations, angles)


def lift_arms(
    body: BodyModel,
    shape: BodyShape,
    rotations: np.ndarray,
    translation: np.ndarray,
    segments: Sequence[int] | None = None,
    **kwargs,
) -> tuple[np.ndarray, np.ndarray]:
    """Abduct the upper arms out of the torso (module docstring).

    shape       : one body (``body.shape`` of a single phenotype vector)
    rotations   : (T, J, 3) axis-angle, radians (``inference.body`` pose contract)
    translation : (T, 3) metres
    segments    : frame counts of independent motions concatenated along T (smoothing stays
                  inside each); default one motion
    kwargs      : margin_m, reach_m, tangent_m (metres), iterations (``ArmLifter.lift``)
    returns     : corrected rotations (T, J, 3) float32 and the abduction (T, 2) radians of the
                  (left, right) arm
    """
    return arm_lifter(body, shape).lift(rotations, translation, segments, **kwargs)


# ArmLifter set-ups kept per body shape (~0.4 MB each; ~11 ms saved per request of a known body).
LIFTER_CACHE_SIZE = 16
_lifters: OrderedDict[tuple[int, bytes], ArmLifter] = OrderedDict()
_lifters_lock = threading.Lock()


def arm_lifter(body: BodyModel, shape: BodyShape) -> ArmLifter:
    """The ``ArmLifter`` of this body shape, from a small LRU cache keyed by its phenotypes."""
    key = (id(body), np.ascontiguousarray(shape.phenotypes, np.float32).tobytes())
    with _lifters_lock:
        hit = _lifters.get(key)
        if hit is not None and hit.body is body:
            _lifters.move_to_end(key)
            return hit
    lifter = ArmLifter(body, shape)
    with _lifters_lock:
        _lifters[key] = lifter
        while len(_lifters) > LIFTER_CACHE_SIZE:
            _lifters.popitem(last=False)
    return lifter


def _nearest_torso(tp: np.ndarray, ap: np.ndarray, active: np.ndarray, reach_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The nearest torso point of each arm point in its own frame, searched within ``reach_m``:
    indices (A * n,) into tp's points (0 where none) and whether one was found (A * n,) bool, for
    the arm points ``ap`` (A, n, 3) of the ``active`` frames (A,) and the torso points tp (T, m, 3)
    float32. A grid per frame of the torso points near its arm points, cells of the reach
    (``inference.repair_kernels.frame_knn``, exact): the answers of a KD-tree of each frame's torso
    points with ``distance_upper_bound``, without building one per frame; the kernel of ``_steps``
    drops those at the reach or beyond."""
    A, n = ap.shape[:2]
    q = np.ascontiguousarray(ap.reshape(-1, 3), np.float64)  # float32 points, exactly
    # boxed and searched a micrometre past the reach, cells a little wider (the 27 around a point's own
    # cover it): a point not found has no torso point within the reach
    nn, found = frame_knn(np.ascontiguousarray(tp, np.float32), np.asarray(active, np.int64), np.arange(A + 1, dtype=np.int64) * n, q,
                          np.arange(tp.shape[1], dtype=np.int64), 1, reach_m + 1e-6, reach_m + 2e-6, reach_m + 1e-6)
    return np.where(found, nn[:, 0], 0), found


def _steps(tp, tn, ap, shoulder, active, T, margin_m, reach_m, tangent_m) -> tuple[np.ndarray, np.ndarray]:
    """One abduction step per frame (module docstring): angle (T,) radians (0 where the arm is
    clear) and unit axis (T, 3), for the arm points ``ap`` (A, n, 3) of the ``active`` frames
    (A,), their shoulder joints (A, 3) and the torso points/normals tp, tn (T, m, 3). Per frame:
    depth = -(a - c) . n where the arm point a lies within the reach of its nearest torso point c
    and projects near it (|a - c|^2 - depth^2 < tangent_m^2), else 0; the direction d is the sum of
    the positive depths times their normals, normalised; the lever k = (a* - s) x d at the deepest
    arm point a*; step = min((max depth + margin) / |k|, _STEP_CAP) where the max depth > 0 and
    |k| > 1 mm. Compiled (``arm_kernels.arm_steps``, the same float32 and float64 operations as the
    numpy form it replaced, bitwise: the service's 30-frame requests 0.64 -> 0.46 ms a frame, of
    which the nearest torso points take 0.42)."""
    step, axes = np.zeros(T), np.zeros((T, 3))
    near, found = _nearest_torso(tp, ap, active, reach_m)
    arm_steps(tp, tn, np.ascontiguousarray(ap, np.float32), np.ascontiguousarray(shoulder, np.float32), np.asarray(active, np.int64),
              near, found, margin_m, reach_m, tangent_m, _STEP_CAP, step, axes)
    return step, axes


def _window_argmax(x: np.ndarray, segments: Sequence[int]) -> np.ndarray:
    """Index of the largest x within SMOOTH_FRAMES frames of each frame, inside its segment (T,):
    the offsets -S..S in turn, a later one taking over only where strictly larger (compiled,
    ``arm_kernels.window_argmax``: numpy's 2 S + 1 shifted comparisons cost ~0.15 ms a call)."""
    seg = np.repeat(np.arange(len(segments)), segments)
    best = np.empty(len(x), np.int64)
    window_argmax(np.ascontiguousarray(x, np.float64), seg, SMOOTH_FRAMES, best)
    return best


def _rotate_bone(body: BodyModel, shape: BodyShape, W: np.ndarray, rot: np.ndarray, bone: int, axes: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Local axis-angle (n, 3) of ``bone`` after the world rotations R(axes, theta) about its head
    in frames with bone poses W (n, J, 4, 4): D <- A^T Q A D, A = W_parent R_parent^T R_bone
    (compiled: ``arm_kernels.rotate_bone``; numpy's conversions and products cost ~0.25 ms a call)."""
    R = shape.rest_bone_poses[0, :, :3, :3].astype(np.float64)
    parent = body.parents[bone]
    out = np.empty((len(rot), 3), np.float32)
    rotate_bone(np.ascontiguousarray(W[:, parent, :3, :3], np.float32), R[parent].T @ R[bone], np.ascontiguousarray(axes, np.float64),
                np.ascontiguousarray(theta, np.float64), np.ascontiguousarray(rot, np.float32), out)
    return out


def warm_up() -> None:
    """Compile the nearest-torso search, the step, the window maximum and the arm's new rotation (or
    load numba's cache) for a request's float32 points, so that no request pays a first compilation."""
    pts = np.zeros((1, 2, 3), np.float32)
    _steps(pts, pts, pts, pts[0, :1], np.zeros(1, np.int64), 1, DEFAULT_MARGIN_M, DEFAULT_REACH_M, DEFAULT_TANGENT_M)
    _window_argmax(np.zeros(1), [1])
    rotate_bone(np.tile(np.eye(3, dtype=np.float32), (1, 1, 1)), np.eye(3), np.ones((1, 3)), np.zeros(1), np.zeros((1, 3), np.float32),
                np.empty((1, 3), np.float32))
