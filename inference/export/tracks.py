"""What the exporters write: animated garment and body tracks, checked on construction.

Axes and units of every array here: metres, world axes **Z-up** right-handed, as the anny
body model (``inference.body``). The writers convert to their own conventions (glTF: Y-up).
UVs follow OBJ: corners are indexed separately from positions (``face_uvs``), so a position
on a UV seam has several UVs, and v runs upwards (origin at the texture's bottom-left).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np

from inference.body import linear_blend_skinning
from inference.errors import InputShapeError, InputValueError

MAX_INFLUENCES = 8  # skinning influences per vertex the exporters accept (glTF: 2 sets of 4)
_RIGID_TOL = 1e-3  # max |R^T R - I| entry for a bone pose to count as rigid
_WEIGHT_SUM_TOL = 1e-3  # max |sum_k w_vk - 1| accepted for skinning weights


def _as_array(name: str, value, dtype) -> np.ndarray:
    a = np.ascontiguousarray(value, dtype=dtype)
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        raise InputValueError(name, "contains NaN or inf")
    return a


def _check_faces(name: str, faces: np.ndarray, count: int) -> None:
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise InputShapeError(name, "(F, 3)", faces.shape)
    if faces.size and (faces.min() < 0 or faces.max() >= count):
        raise InputValueError(name, f"indices must lie in [0, {count}), got [{faces.min()}, {faces.max()}]")


def _check_uvs(prefix: str, uvs, face_uvs, faces: np.ndarray):
    """Returns (uvs (Vt, 2) float32, face_uvs (F, 3) int32) or (None, None)."""
    if (uvs is None) != (face_uvs is None):
        raise InputValueError(f"{prefix}.uvs", "uvs and face_uvs must be given together")
    if uvs is None:
        return None, None
    uvs = _as_array(f"{prefix}.uvs", uvs, np.float32)
    face_uvs = _as_array(f"{prefix}.face_uvs", face_uvs, np.int32)
    if uvs.ndim != 2 or uvs.shape[1] != 2:
        raise InputShapeError(f"{prefix}.uvs", "(Vt, 2)", uvs.shape)
    if face_uvs.shape != faces.shape:
        raise InputShapeError(f"{prefix}.face_uvs", f"{faces.shape}", face_uvs.shape)
    _check_faces(f"{prefix}.face_uvs", face_uvs, len(uvs))
    return uvs, face_uvs


def _check_json(name: str, value) -> None:
    try:
        json.dumps(value, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise InputValueError(name, f"must be JSON-serialisable: {exc}") from exc


@dataclass(frozen=True)
class GarmentTrack:
    """One garment's vertices over a sequence.

    name     : str, unique within an export
    vertices : (T, V, 3) float32, metres, Z-up world axes, posed per frame
    faces    : (F, 3) int32, indices into the V welded vertices
    uvs      : (Vt, 2) float32 or None, OBJ convention (v up)
    face_uvs : (F, 3) int32 or None, indices into uvs, one per face corner
    metadata : dict, JSON-serialisable (garment id, size, layer, ...)
    appearance : dict or None, the garment's look (``garment.json`` "appearance": base_color
               (3,) linear RGB 0-1, roughness 0-1, optional sheen_color, sheen_roughness)
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray | None = None
    face_uvs: np.ndarray | None = None
    metadata: dict = field(default_factory=dict)
    appearance: dict | None = None

    def __post_init__(self):
        p = f"garment[{self.name!r}]"
        if not isinstance(self.name, str) or not self.name:
            raise InputValueError("garment.name", "must be a non-empty string")
        vertices = _as_array(f"{p}.vertices", self.vertices, np.float32)
        if vertices.ndim != 3 or vertices.shape[2] != 3 or vertices.shape[0] < 1:
            raise InputShapeError(f"{p}.vertices", "(T, V, 3) with T >= 1", vertices.shape)
        faces = _as_array(f"{p}.faces", self.faces, np.int32)
        _check_faces(f"{p}.faces", faces, vertices.shape[1])
        uvs, face_uvs = _check_uvs(p, self.uvs, self.face_uvs, faces)
        _check_json(f"{p}.metadata", self.metadata)
        if self.appearance is not None:
            _check_appearance(f"{p}.appearance", self.appearance)
        for key, value in (("vertices", vertices), ("faces", faces), ("uvs", uvs), ("face_uvs", face_uvs)):
            object.__setattr__(self, key, value)

    @property
    def num_frames(self) -> int:
        return self.vertices.shape[0]


def _check_appearance(field_name: str, appearance: dict) -> None:
    colours = [appearance.get("base_color")] + ([appearance["sheen_color"]] if "sheen_color" in appearance else [])
    for c in colours:
        c = np.asarray(c, np.float64)
        if c.shape != (3,) or not np.all(np.isfinite(c)) or c.min() < 0 or c.max() > 1:
            raise InputValueError(field_name, "colours must be 3 linear RGB values in [0, 1]")
    for key in ("roughness", "sheen_roughness"):
        v = appearance.get(key, 0.5)
        if not (isinstance(v, (int, float)) and 0.0 <= v <= 1.0):
            raise InputValueError(field_name, f"{key} must be in [0, 1]")


@dataclass(frozen=True)
class BodyTrack:
    """A skinned body and its bone animation over a sequence.

    rest_vertices   : (V, 3) float32, metres, Z-up, the shaped body in its rest pose
    faces           : (F, 3) int32
    skin_indices    : (V, K) int32, bone indices, K <= 8
    skin_weights    : (V, K) float32, >= 0, rows sum to 1
    parents         : (J,) int32, -1 for a root, parents listed before their children
    bone_names      : list[str] of length J
    rest_bone_poses : (J, 4, 4) float32, each bone's rigid world frame in the rest pose
    bone_poses      : (T, J, 4, 4) float32, each bone's rigid world frame per frame
    uvs, face_uvs   : as GarmentTrack, optional

    Linear blend skinning (thesis eq. 4.3):
    posed v = sum_j w_vj (bone_poses[t, j] @ inv(rest_bone_poses[j])) v.
    """

    rest_vertices: np.ndarray
    faces: np.ndarray
    skin_indices: np.ndarray
    skin_weights: np.ndarray
    parents: np.ndarray
    bone_names: list
    rest_bone_poses: np.ndarray
    bone_poses: np.ndarray
    uvs: np.ndarray | None = None
    face_uvs: np.ndarray | None = None

    def __post_init__(self):
        rest = _as_array("body.rest_vertices", self.rest_vertices, np.float32)
        if rest.ndim != 2 or rest.shape[1] != 3:
            raise InputShapeError("body.rest_vertices", "(V, 3)", rest.shape)
        V = rest.shape[0]
        faces = _as_array("body.faces", self.faces, np.int32)
        _check_faces("body.faces", faces, V)
        uvs, face_uvs = _check_uvs("body", self.uvs, self.face_uvs, faces)

        parents = _as_array("body.parents", self.parents, np.int32)
        if parents.ndim != 1 or parents.size < 1:
            raise InputShapeError("body.parents", "(J,)", parents.shape)
        J = parents.size
        if np.any((parents != -1) & ((parents < 0) | (parents >= np.arange(J)))):
            raise InputValueError("body.parents", "each parent must be -1 or an earlier bone")
        names = [str(n) for n in self.bone_names]
        if len(names) != J:
            raise InputShapeError("body.bone_names", f"({J},)", (len(names),))

        idx = _as_array("body.skin_indices", self.skin_indices, np.int32)
        w = _as_array("body.skin_weights", self.skin_weights, np.float32)
        if idx.ndim != 2 or idx.shape[0] != V or not 1 <= idx.shape[1] <= MAX_INFLUENCES:
            raise InputShapeError("body.skin_indices", f"({V}, K) with 1 <= K <= {MAX_INFLUENCES}", idx.shape)
        if w.shape != idx.shape:
            raise InputShapeError("body.skin_weights", f"{idx.shape}", w.shape)
        if idx.min() < 0 or idx.max() >= J:
            raise InputValueError("body.skin_indices", f"bone indices must lie in [0, {J})")
        if w.min() < 0:
            raise InputValueError("body.skin_weights", "weights must be >= 0")
        sums = w.sum(axis=1, dtype=np.float64)
        if np.abs(sums - 1.0).max() > _WEIGHT_SUM_TOL:
            worst = sums[np.argmax(np.abs(sums - 1.0))]
            raise InputValueError("body.skin_weights", f"rows must sum to 1 (worst {worst:.6f})")

        rest_poses = _as_array("body.rest_bone_poses", self.rest_bone_poses, np.float32)
        if rest_poses.shape != (J, 4, 4):
            raise InputShapeError("body.rest_bone_poses", f"({J}, 4, 4)", rest_poses.shape)
        poses = _as_array("body.bone_poses", self.bone_poses, np.float32)
        if poses.ndim != 4 or poses.shape[1:] != (J, 4, 4) or poses.shape[0] < 1:
            raise InputShapeError("body.bone_poses", f"(T, {J}, 4, 4)", poses.shape)
        for name, m in (("body.rest_bone_poses", rest_poses), ("body.bone_poses", poses)):
            R = m[..., :3, :3].astype(np.float64)
            err = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max()
            if err > _RIGID_TOL or np.abs(m[..., 3, :] - [0, 0, 0, 1]).max() > 0:
                raise InputValueError(name, f"bone frames must be rigid [R | t; 0 0 0 1] (|R^T R - I| = {err:.2e})")

        for key, value in (
            ("rest_vertices", rest), ("faces", faces), ("uvs", uvs), ("face_uvs", face_uvs),
            ("skin_indices", idx), ("skin_weights", w), ("parents", parents), ("bone_names", names),
            ("rest_bone_poses", rest_poses), ("bone_poses", poses),
        ):
            object.__setattr__(self, key, value)

    @property
    def num_frames(self) -> int:
        return self.bone_poses.shape[0]

    @property
    def num_bones(self) -> int:
        return self.parents.size


def dense_skin_weights(skin_indices: np.ndarray, skin_weights: np.ndarray, num_bones: int) -> np.ndarray:
    """Sparse (V, K) influences -> dense (V, J) weights; repeated bone indices are summed.

    skin_indices : (V, K) int, bone indices
    skin_weights : (V, K) float32
    returns      : (V, J) float32
    """
    V = skin_indices.shape[0]
    flat = (np.arange(V)[:, None] * num_bones + skin_indices).ravel()
    dense = np.bincount(flat, weights=skin_weights.ravel().astype(np.float64), minlength=V * num_bones)
    return dense.reshape(V, num_bones).astype(np.float32)


def rigid_inverse(M: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms [R | t; 0 0 0 1] -> [R^T | -R^T t; 0 0 0 1] (exact last row).

    M       : (..., 4, 4) float
    returns : (..., 4, 4) same dtype
    """
    out = np.zeros_like(M)
    Rt = np.swapaxes(M[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, M[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def skinning_transforms(body: BodyTrack) -> np.ndarray:
    """Bone transforms relative to the rest pose, X_tj = bone_poses[t, j] @ inv(rest_bone_poses[j]).

    returns : (T, J, 4, 4) float32
    """
    inv = rigid_inverse(body.rest_bone_poses.astype(np.float64))
    return (body.bone_poses.astype(np.float64) @ inv).astype(np.float32)


def pose_body_vertices(body: BodyTrack) -> np.ndarray:
    """The body posed per frame by linear blend skinning, thesis eq. 4.3
    (``inference.body.linear_blend_skinning`` with the track's dense weights).

    returns : (T, V, 3) float32, metres, Z-up
    """
    W = dense_skin_weights(body.skin_indices, body.skin_weights, body.num_bones)  # (V, J)
    X = skinning_transforms(body)  # (T, J, 4, 4)
    return linear_blend_skinning(np.asarray(body.rest_vertices, np.float32)[None], W, X[None])[0]
