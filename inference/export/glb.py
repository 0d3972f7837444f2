"""glTF 2.0 binary (.glb) export of a try-on sequence: garments as morph-target animation,
the body (optional) as a skinned mesh with a bone animation, all in one animation "tryon".

Conventions of the file (glTF 2.0): metres, **Y-up**, right-handed; Z-up input is rotated by
(x, y, z) -> (x, z, -y). UV v is flipped (glTF's origin is the texture's top-left).

Garments: glTF wants one UV per vertex, so positions are split at UV seams
(``split_uv_seams``). Frames are cut into chunks of at most ``max_targets_per_mesh`` morph
targets (WebGL2 guarantees only 256 texture-array layers, which three.js uses for morph
targets, one per target). Chunk c is one mesh whose base is its first frame s_c and whose
target k is frame s_c + 1 + k minus the base; its weights are animated one-hot per frame with
LINEAR interpolation, so players interpolate between frames. Consecutive chunks share their
boundary frame; a chunk is shown only over its own frames by a STEP animation of its node's
scale (0 = hidden), the usual glTF visibility trick.

Quantization (``quantize=True``, KHR_mesh_quantization): base positions and target deltas are
normalized SHORT (value / 32767), dequantized by the chunk node's translation o and uniform
scale S: p = o + S (q_base + sum_k w_k q_k) / 32767. Frames are rounded as whole frames
(q_k = round(frame) - q_base), so a frame's error is at most S / 65534 per component:
S is the chunk's largest |p - o| over all its frames (about half the garment's size plus its
motion within the chunk), e.g. 15 um for S = 1 m. Weights are normalized UNSIGNED_BYTE.

Normals: by default none are written; glTF then requires players to compute flat normals from
the morphed positions, which is correct on every frame. ``normals=True`` writes smooth vertex
normals (base + float deltas per target; normal deltas span [-2, 2] and cannot be stored as
normalized integers): +12 bytes per vertex per frame.

Body: one node per bone in the bone hierarchy under a "body_skeleton" node; the node TRS are
the first frame's pose so that a still view matches the garments' base; inverse bind matrices
are inv(rest_bone_poses) in Y-up. Influences are sorted by weight, so JOINTS_0/WEIGHTS_0 hold
the 4 largest (what three.js reads; it renormalises them) and JOINTS_1/WEIGHTS_1 the rest when
some vertex has more than 4: with both sets the file reproduces our LBS exactly.
``max_influences=4`` writes only the 4 largest, renormalised, so every player shows what
three.js shows.
"""
from __future__ import annotations

import json
import struct
from collections.abc import Sequence

import numpy as np

from inference.errors import InputValueError
from inference.export.tracks import BodyTrack, GarmentTrack, dense_skin_weights, rigid_inverse
from inference.mesh import vertex_normals
from inference.rotations import matrix_to_quaternion

# (x, y, z) Z-up -> (x, z, -y) Y-up, a rotation of -90 degrees about X.
ZUP_TO_YUP = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], np.float32)
ANIMATION_NAME = "tryon"
DEFAULT_MAX_TARGETS_PER_MESH = 128

_SNORM16 = 32767  # normalized SHORT: float = q / 32767
_UNORM16 = 65535
_UNORM8 = 255
_BYTE, _UNSIGNED_BYTE, _SHORT, _UNSIGNED_SHORT, _UNSIGNED_INT, _FLOAT = 5120, 5121, 5122, 5123, 5125, 5126
_COMPONENT_TYPES = {
    np.dtype(np.int8): _BYTE, np.dtype(np.uint8): _UNSIGNED_BYTE, np.dtype(np.int16): _SHORT,
    np.dtype(np.uint16): _UNSIGNED_SHORT, np.dtype(np.uint32): _UNSIGNED_INT, np.dtype(np.float32): _FLOAT,
}
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_ACCESSOR_TYPES = {1: "SCALAR", 2: "VEC2", 3: "VEC3", 4: "VEC4", 16: "MAT4"}
_GLB_MAGIC, _GLB_JSON, _GLB_BIN = 0x46546C67, 0x4E4F534A, 0x004E4942
_MIN_SCALE_M = 1e-6  # quantization scale floor for a garment that is a single point
_GARMENT_COLOR = [0.35, 0.45, 0.65, 1.0]
_BODY_COLOR = [0.80, 0.66, 0.58, 1.0]


def zup_to_yup(points: np.ndarray) -> np.ndarray:
    """Rotates Z-up points into glTF's Y-up axes: (x, y, z) -> (x, z, -y).

    points  : (..., 3) float, metres
    returns : (..., 3) float32, metres
    """
    p = np.asarray(points, dtype=np.float32)
    return np.stack([p[..., 0], p[..., 2], -p[..., 1]], axis=-1)


def zup_to_yup_transforms(matrices: np.ndarray) -> np.ndarray:
    """Conjugates 4x4 transforms into Y-up: C M C^T with C = ZUP_TO_YUP.

    matrices : (..., 4, 4) float
    returns  : (..., 4, 4) float64
    """
    C = np.eye(4)
    C[:3, :3] = ZUP_TO_YUP
    return C @ np.asarray(matrices, dtype=np.float64) @ C.T


def split_uv_seams(faces: np.ndarray, face_uvs: np.ndarray):
    """One glTF vertex per distinct (position, uv) corner pair.

    faces    : (F, 3) int, position indices
    face_uvs : (F, 3) int, uv indices
    returns  : vertex_map (N,) int64, the position index of each split vertex;
               uv_map (N,) int64, its uv index;
               faces_split (F, 3) int32, indices into the N split vertices.
    Split vertices are sorted by (position, uv) index, so unseamed meshes keep their order.
    """
    num_uvs = int(face_uvs.max()) + 1 if face_uvs.size else 1
    key = faces.ravel().astype(np.int64) * num_uvs + face_uvs.ravel()
    pairs, inverse = np.unique(key, return_inverse=True)
    return pairs // num_uvs, pairs % num_uvs, inverse.reshape(faces.shape).astype(np.int32)


def chunk_ranges(num_frames: int, max_targets: int) -> list[tuple[int, int]]:
    """Frame ranges [start, end] (inclusive) of the morph-target meshes of one garment.

    Chunk c has base frame start and end - start targets; consecutive chunks share a frame.
    """
    if num_frames == 1:
        return [(0, 0)]
    starts = range(0, num_frames - 1, max_targets)
    return [(s, min(s + max_targets, num_frames - 1)) for s in starts]


class _BinaryBuilder:
    """Collects buffer views and accessors of the single GLB buffer."""

    def __init__(self):
        self.parts: list[bytes] = []
        self.length = 0
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def view(self, data: np.ndarray, target: int | None = None, stride: int | None = None) -> int:
        raw = np.ascontiguousarray(data).tobytes()
        entry = {"buffer": 0, "byteOffset": self.length, "byteLength": len(raw)}
        if stride is not None:
            entry["byteStride"] = stride
        if target is not None:
            entry["target"] = target
        self.parts.append(raw)
        pad = -len(raw) % 4  # every view starts 4-byte aligned
        self.parts.append(b"\0" * pad)
        self.length += len(raw) + pad
        self.views.append(entry)
        return len(self.views) - 1

    def accessor(self, view: int, dtype, count: int, ncomp: int, byte_offset: int = 0,
                 normalized: bool = False, lo=None, hi=None) -> int:
        entry = {"bufferView": view, "componentType": _COMPONENT_TYPES[np.dtype(dtype)], "count": int(count),
                 "type": _ACCESSOR_TYPES[ncomp]}
        if byte_offset:
            entry["byteOffset"] = int(byte_offset)
        if normalized:
            entry["normalized"] = True
        if lo is not None:
            entry["min"] = np.asarray(lo).ravel().tolist()
            entry["max"] = np.asarray(hi).ravel().tolist()
        self.accessors.append(entry)
        return len(self.accessors) - 1

    def array(self, data: np.ndarray, target: int | None = None, normalized: bool = False, bounds: bool = False) -> int:
        """One tightly packed (count, ncomp) or (count,) array as its own view + accessor."""
        data = np.ascontiguousarray(data)
        ncomp = 1 if data.ndim == 1 else data.shape[1]
        flat = data.reshape(len(data), ncomp)
        lo, hi = (flat.min(axis=0), flat.max(axis=0)) if bounds else (None, None)
        return self.accessor(self.view(data, target), data.dtype, len(data), ncomp, normalized=normalized, lo=lo, hi=hi)

    def blob(self) -> bytes:
        return b"".join(self.parts)


class _AnimationBuilder:
    """Samplers and channels of the one animation, with a shared keyframe-time view."""

    def __init__(self, builder: _BinaryBuilder, num_frames: int, fps: float):
        self.b = builder
        self.times = (np.arange(num_frames, dtype=np.float64) / fps).astype(np.float32)  # (T,) seconds
        self.time_view = builder.view(self.times)
        self.samplers: list[dict] = []
        self.channels: list[dict] = []
        self._inputs: dict[tuple[int, int], int] = {}

    def frames_input(self, start: int, end: int) -> int:
        """Accessor of keyframe times t / fps for frames start..end (inclusive)."""
        key = (start, end)
        if key not in self._inputs:
            t = self.times[start:end + 1]
            self._inputs[key] = self.b.accessor(self.time_view, np.float32, len(t), 1, byte_offset=4 * start,
                                                lo=[float(t[0])], hi=[float(t[-1])])
        return self._inputs[key]

    def add(self, node: int, path: str, input_accessor: int, output_accessor: int, interpolation: str = "LINEAR"):
        self.samplers.append({"input": input_accessor, "output": output_accessor, "interpolation": interpolation})
        self.channels.append({"sampler": len(self.samplers) - 1, "target": {"node": node, "path": path}})


def _position_accessors(b: _BinaryBuilder, X: np.ndarray, quantize: bool):
    """Base + morph-target POSITION accessors of one chunk, and the node TRS that dequantizes them.

    X       : (L + 1, N, 3) float32, metres, Y-up: the base frame then the L target frames
    returns : base accessor, [L target accessors], node TRS dict, the node's uniform scale
    """
    L, N = X.shape[0] - 1, X.shape[1]
    if not quantize:
        base, deltas = np.ascontiguousarray(X[0]), X[1:] - X[0]
        base_acc = b.accessor(b.view(base, _ARRAY_BUFFER, stride=12), np.float32, N, 3,
                              lo=base.min(axis=0), hi=base.max(axis=0))
        if not L:
            return base_acc, [], {}, 1.0
        view = b.view(deltas, _ARRAY_BUFFER, stride=12)  # shared by L accessors: stride required
        lo, hi = deltas.min(axis=1), deltas.max(axis=1)  # (L, 3)
        targets = [b.accessor(view, np.float32, N, 3, byte_offset=k * N * 12, lo=lo[k], hi=hi[k]) for k in range(L)]
        return base_acc, targets, {}, 1.0
    Xd = X.astype(np.float64)
    origin = (Xd[0].min(axis=0) + Xd[0].max(axis=0)) / 2.0
    reach = max(np.abs(Xd - origin).max(), np.abs(Xd[1:] - Xd[0]).max() if L else 0.0)
    # 32767 / 32766 keeps q_k - q_base within [-32767, 32767] after rounding both.
    scale = float(np.float32(max(reach * _SNORM16 / (_SNORM16 - 1), _MIN_SCALE_M)))
    q = np.rint((Xd - origin) * (_SNORM16 / scale)).astype(np.int32)  # whole frames, rounded
    q[1:] -= q[0]  # target deltas, exact in integers
    q = np.clip(q, -_SNORM16, _SNORM16)
    packed = np.zeros((L + 1, N, 4), np.int16)  # VEC3 SHORT padded to the 4-byte vertex stride
    packed[..., :3] = q
    base_acc = b.accessor(b.view(packed[0], _ARRAY_BUFFER, stride=8), np.int16, N, 3, normalized=True,
                          lo=q[0].min(axis=0), hi=q[0].max(axis=0))
    targets = []
    if L:
        view = b.view(packed[1:], _ARRAY_BUFFER, stride=8)
        lo, hi = q[1:].min(axis=1), q[1:].max(axis=1)  # (L, 3)
        targets = [b.accessor(view, np.int16, N, 3, byte_offset=k * N * 8, normalized=True, lo=lo[k], hi=hi[k])
                   for k in range(L)]  # one accessor per morph target (JSON only)
    return base_acc, targets, {"translation": origin.tolist(), "scale": [scale] * 3}, scale


def _visibility_keys(chunk: int, num_chunks: int, start: int, end: int, times: np.ndarray, scale: float):
    """STEP keyframes of a chunk node's scale: `scale` on [t_start, t_end), 0 elsewhere.

    returns : times (K,) float32 seconds, scales (K, 3) float32
    """
    if chunk == 0:
        key_t, key_s = [times[0], times[end]], [scale, 0.0]
    elif chunk == num_chunks - 1:
        key_t, key_s = [times[0], times[start]], [0.0, scale]
    else:
        key_t, key_s = [times[0], times[start], times[end]], [0.0, scale, 0.0]
    return np.asarray(key_t, np.float32), np.repeat(np.asarray(key_s, np.float32)[:, None], 3, axis=1)


def _write_garment(g: GarmentTrack, b: _BinaryBuilder, anim: _AnimationBuilder | None, nodes: list, meshes: list,
                   material: int, quantize: bool, normals: bool, max_targets: int) -> int:
    """Adds one garment (a group node, one morph-target mesh + node per chunk, their animation).

    returns : the group node's index
    """
    if g.uvs is None:
        vertex_map, uv, faces = np.arange(g.vertices.shape[1]), None, g.faces
    else:
        vertex_map, uv_map, faces = split_uv_seams(g.faces, g.face_uvs)
        uv = g.uvs[uv_map]
    N = len(vertex_map)
    index_dtype = np.uint16 if N <= _UNORM16 else np.uint32  # 65535 is the primitive-restart value
    indices = b.array(faces.astype(index_dtype).ravel(), target=_ELEMENT_ARRAY_BUFFER)
    shared = {}  # attributes common to all chunks
    if uv is not None:
        uv_gl = np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=-1)  # glTF: origin at the top-left
        if quantize and uv_gl.min() >= 0.0 and uv_gl.max() <= 1.0:  # core glTF: normalized USHORT
            shared["TEXCOORD_0"] = b.array(np.rint(uv_gl * _UNORM16).astype(np.uint16), _ARRAY_BUFFER, normalized=True)
        else:
            shared["TEXCOORD_0"] = b.array(uv_gl.astype(np.float32), _ARRAY_BUFFER)

    frames = zup_to_yup(g.vertices)  # (T, V, 3)
    ranges = chunk_ranges(g.num_frames, max_targets)
    group = {"name": g.name, "children": []}
    if g.metadata:
        group["extras"] = g.metadata
    nodes.append(group)
    group_index = len(nodes) - 1
    for c, (start, end) in enumerate(ranges):  # a few chunks, each vectorised
        L = end - start
        base, targets, trs, scale = _position_accessors(b, frames[start:end + 1][:, vertex_map], quantize)
        attributes = {**shared, "POSITION": base}
        morphs = [{"POSITION": t} for t in targets]
        if normals:
            # Normals of the welded mesh (smooth across UV seams), split like the positions.
            n = vertex_normals(frames[start:end + 1], g.faces, fallback=(0.0, 1.0, 0.0))[:, vertex_map]  # glTF: unit normals
            attributes["NORMAL"] = b.accessor(b.view(n[0], _ARRAY_BUFFER, stride=12), np.float32, N, 3)
            if L:
                view = b.view(n[1:] - n[0], _ARRAY_BUFFER, stride=12)
                for k in range(L):
                    morphs[k]["NORMAL"] = b.accessor(view, np.float32, N, 3, byte_offset=k * N * 12)
        name = f"{g.name}_morph{c}"
        primitive = {"attributes": attributes, "indices": indices, "material": material, "mode": 4}
        mesh = {"name": name, "primitives": [primitive]}
        if L:
            primitive["targets"] = morphs
            mesh["extras"] = {"targetNames": [f"frame_{t:05d}" for t in range(start + 1, end + 1)]}
        meshes.append(mesh)
        node = {"name": name, "mesh": len(meshes) - 1, **trs}
        if c > 0:
            node["scale"] = [0.0, 0.0, 0.0]  # hidden until its frames come: a still view shows frame 0
        nodes.append(node)
        group["children"].append(len(nodes) - 1)
        if anim is None or L == 0:
            continue
        # Weights: keyframe 0 (frame start) is the base, keyframe k is one-hot on target k - 1.
        w = np.zeros((L + 1, L), np.float32)
        w[np.arange(1, L + 1), np.arange(L)] = 1.0
        if quantize:
            out = b.accessor(b.view((w * _UNORM8).astype(np.uint8).ravel()), np.uint8, w.size, 1, normalized=True)
        else:
            out = b.accessor(b.view(w.ravel()), np.float32, w.size, 1)
        anim.add(len(nodes) - 1, "weights", anim.frames_input(start, end), out)
        if len(ranges) > 1:
            key_t, key_s = _visibility_keys(c, len(ranges), start, end, anim.times, scale)
            times = b.accessor(b.view(key_t), np.float32, len(key_t), 1, lo=[float(key_t[0])], hi=[float(key_t[-1])])
            anim.add(len(nodes) - 1, "scale", times, b.accessor(b.view(key_s), np.float32, len(key_s), 3), "STEP")
    return group_index


def _skin_influences(body: BodyTrack, max_influences: int = 8):
    """Influences sorted by weight, 4 or 8 per vertex, renormalised so float32 rows sum to 1.

    max_influences : 8 keeps every influence (K <= 8); 4 keeps the 4 largest, renormalised
    returns        : joints (V, 4|8) uint8|uint16, weights (V, 4|8) float32
    """
    dense = dense_skin_weights(body.skin_indices, body.skin_weights, body.num_bones).astype(np.float64)
    used = int((dense > 0).sum(axis=1).max())
    k = 4 if used <= 4 or max_influences == 4 else 8
    if dense.shape[1] < k:  # fewer bones than slots: pad with zero-weight columns
        dense = np.pad(dense, ((0, 0), (0, k - dense.shape[1])))
    order = np.argsort(-dense, axis=1, kind="stable")
    joints = order[:, :k]
    weights = np.take_along_axis(dense, joints, axis=1)
    weights /= weights.sum(axis=1, keepdims=True)
    weights = weights.astype(np.float32)
    # Push the float32 rounding residual into the largest weight (validator: |sum - 1| small).
    weights[:, 0] += (1.0 - weights.astype(np.float64).sum(axis=1)).astype(np.float32)
    joints = np.where(weights > 0, joints, 0)  # unused slots: joint 0, weight 0
    return joints.astype(np.uint8 if body.num_bones <= 256 else np.uint16), weights


def _bone_local_trs(body: BodyTrack):
    """Node-local translation and rotation of each bone per frame, Y-up.

    local_tj = inv(world_t,parent(j)) @ world_tj; a root's parent is the identity.
    returns : translation (T, J, 3) float32 metres, rotation (T, J, 4) float32 quaternion (x, y, z, w),
              sign-continuous over time so that slerp takes the short way.
    """
    world = zup_to_yup_transforms(body.bone_poses)  # (T, J, 4, 4)
    parent_world = np.where((body.parents >= 0)[None, :, None, None], world[:, np.maximum(body.parents, 0)], np.eye(4))
    local = rigid_inverse(parent_world) @ world
    q = matrix_to_quaternion(local[..., :3, :3])  # (T, J, 4) as (w, x, y, z)
    # q and -q are the same rotation; flip so consecutive keyframes have q_t . q_{t-1} >= 0.
    flips = np.sign(np.einsum("tjk,tjk->tj", q[1:], q[:-1]))
    flips = np.concatenate([np.ones_like(q[:1, :, 0]), np.cumprod(np.where(flips == 0, 1.0, flips), axis=0)])
    q = q * flips[..., None]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return local[..., :3, 3].astype(np.float32), q[..., [1, 2, 3, 0]].astype(np.float32)


def _write_body(body: BodyTrack, b: _BinaryBuilder, anim: _AnimationBuilder | None, nodes: list, meshes: list,
                skins: list, material: int, max_influences: int) -> list[int]:
    """Adds the skinned body mesh, its skeleton and bone animation; returns the scene root nodes."""
    if body.uvs is None:
        vertex_map, uv, faces = np.arange(len(body.rest_vertices)), None, body.faces
    else:
        vertex_map, uv_map, faces = split_uv_seams(body.faces, body.face_uvs)
        uv = body.uvs[uv_map]
    N = len(vertex_map)
    positions = zup_to_yup(body.rest_vertices)[vertex_map]
    joints, weights = _skin_influences(body, max_influences)
    joints, weights = joints[vertex_map], weights[vertex_map]
    attributes = {"POSITION": b.array(positions, _ARRAY_BUFFER, bounds=True)}
    if uv is not None:
        attributes["TEXCOORD_0"] = b.array(np.stack([uv[:, 0], 1.0 - uv[:, 1]], -1).astype(np.float32), _ARRAY_BUFFER)
    for s in range(weights.shape[1] // 4):
        attributes[f"JOINTS_{s}"] = b.array(np.ascontiguousarray(joints[:, 4 * s:4 * s + 4]), _ARRAY_BUFFER)
        attributes[f"WEIGHTS_{s}"] = b.array(np.ascontiguousarray(weights[:, 4 * s:4 * s + 4]), _ARRAY_BUFFER)
    index_dtype = np.uint16 if N <= _UNORM16 else np.uint32
    primitive = {"attributes": attributes, "indices": b.array(faces.astype(index_dtype).ravel(), _ELEMENT_ARRAY_BUFFER),
                 "material": material, "mode": 4}
    meshes.append({"name": "body", "primitives": [primitive]})

    # glTF MAT4 is column-major: write each IBM transposed.
    ibm = rigid_inverse(zup_to_yup_transforms(body.rest_bone_poses))
    ibm_accessor = b.array(np.swapaxes(ibm, -1, -2).reshape(-1, 16).astype(np.float32))
    translation, rotation = _bone_local_trs(body)
    J = body.num_bones
    skeleton = len(nodes)
    first_joint = skeleton + 1
    nodes.append({"name": "body_skeleton", "children": (first_joint + np.flatnonzero(body.parents < 0)).tolist()})
    for j in range(J):  # one node per bone (JSON only)
        node = {"name": body.bone_names[j], "translation": translation[0, j].tolist(),
                "rotation": rotation[0, j].tolist()}
        children = np.flatnonzero(body.parents == j)
        if children.size:
            node["children"] = (first_joint + children).tolist()
        nodes.append(node)
    skins.append({"name": "body", "inverseBindMatrices": ibm_accessor,
                  "joints": list(range(first_joint, first_joint + J)), "skeleton": skeleton})
    nodes.append({"name": "body", "mesh": len(meshes) - 1, "skin": len(skins) - 1})
    if anim is not None:
        T = body.num_frames
        times = anim.frames_input(0, T - 1)
        t_view = b.view(np.ascontiguousarray(translation.transpose(1, 0, 2)))  # (J, T, 3)
        r_view = b.view(np.ascontiguousarray(rotation.transpose(1, 0, 2)))  # (J, T, 4)
        for j in range(J):
            t_out = b.accessor(t_view, np.float32, T, 3, byte_offset=j * T * 12)
            r_out = b.accessor(r_view, np.float32, T, 4, byte_offset=j * T * 16)
            anim.add(first_joint + j, "translation", times, t_out)
            anim.add(first_joint + j, "rotation", times, r_out)
    return [skeleton, len(nodes) - 1]


def _pack_glb(gltf: dict, blob: bytes) -> bytes:
    json_bytes = json.dumps(gltf, separators=(",", ":"), allow_nan=False).encode("utf-8")
    json_bytes += b" " * (-len(json_bytes) % 4)
    blob += b"\0" * (-len(blob) % 4)
    total = 12 + 8 + len(json_bytes) + 8 + len(blob)
    return b"".join([
        struct.pack("<III", _GLB_MAGIC, 2, total),
        struct.pack("<II", len(json_bytes), _GLB_JSON), json_bytes,
        struct.pack("<II", len(blob), _GLB_BIN), blob,
    ])


def write_glb(garments: Sequence[GarmentTrack], body: BodyTrack | None = None, fps: float = 30.0, *,
              quantize: bool = True, normals: bool = False, max_influences: int = 8,
              max_targets_per_mesh: int = DEFAULT_MAX_TARGETS_PER_MESH, metadata: dict | None = None) -> bytes:
    """A try-on sequence as glTF 2.0 binary: Y-up, metres, one animation named "tryon".

    garments             : GarmentTrack each with (T, V_i, 3) vertices, Z-up metres; same T for all
    body                 : BodyTrack with T frames, or None
    fps                  : frames per second; keyframe t is at t / fps seconds
    quantize             : KHR_mesh_quantization positions (error <= S / 65534 per component,
                           S ~ the garment's half-size plus its motion in a chunk) and 8-bit weights
    normals              : write smooth per-frame vertex normals (float; +12 B per vertex per frame)
    max_influences       : body influences per vertex, 8 (exact LBS; JOINTS_1/WEIGHTS_1 when needed) or
                           4 (the 4 largest, renormalised: what three.js plays, for every player alike)
    max_targets_per_mesh : frames per morph-target mesh (<= 256 plays on every WebGL2 device)
    metadata             : JSON-serialisable, stored in asset.extras
    returns              : the .glb file's bytes
    """
    if not garments and body is None:
        raise InputValueError("garments", "nothing to export: no garment and no body")
    if not np.isfinite(fps) or fps <= 0:
        raise InputValueError("fps", f"must be > 0, got {fps}")
    if max_influences not in (4, 8):
        raise InputValueError("max_influences", f"must be 4 or 8, got {max_influences}")
    if int(max_targets_per_mesh) < 1:
        raise InputValueError("max_targets_per_mesh", f"must be >= 1, got {max_targets_per_mesh}")
    frame_counts = {g.num_frames for g in garments} | ({body.num_frames} if body is not None else set())
    if len(frame_counts) != 1:
        raise InputValueError("garments", f"all tracks need the same number of frames, got {sorted(frame_counts)}")
    names = [g.name for g in garments]
    if len(set(names)) != len(names):
        raise InputValueError("garments", f"garment names must be unique, got {names}")
    T = frame_counts.pop()

    b = _BinaryBuilder()
    anim = _AnimationBuilder(b, T, float(fps)) if T > 1 else None
    nodes: list[dict] = []
    meshes: list[dict] = []
    skins: list[dict] = []
    materials = [
        {"name": "garment", "doubleSided": True,
         "pbrMetallicRoughness": {"baseColorFactor": _GARMENT_COLOR, "metallicFactor": 0.0, "roughnessFactor": 0.9}},
        {"name": "body",
         "pbrMetallicRoughness": {"baseColorFactor": _BODY_COLOR, "metallicFactor": 0.0, "roughnessFactor": 0.7}},
    ]
    roots = []
    if body is not None:
        roots += _write_body(body, b, anim, nodes, meshes, skins, 1, max_influences)
    for g in garments:
        roots.append(_write_garment(g, b, anim, nodes, meshes, 0, quantize, normals, int(max_targets_per_mesh)))

    asset = {"version": "2.0", "generator": "tryon inference.export.glb"}
    extras = {"units": "metres", "axes": "Y-up right-handed (glTF)", "fps": float(fps), "frames": T,
              "garments": names, **(metadata or {})}
    asset["extras"] = extras
    gltf = {"asset": asset, "scene": 0, "scenes": [{"name": "tryon", "nodes": roots}], "nodes": nodes,
            "meshes": meshes, "materials": materials}
    if skins:
        gltf["skins"] = skins
    if anim is not None and anim.channels:
        gltf["animations"] = [{"name": ANIMATION_NAME, "samplers": anim.samplers, "channels": anim.channels}]
    if quantize and garments:
        gltf["extensionsUsed"] = ["KHR_mesh_quantization"]
        gltf["extensionsRequired"] = ["KHR_mesh_quantization"]
    gltf["accessors"] = b.accessors
    gltf["bufferViews"] = b.views
    blob = b.blob()
    gltf["buffers"] = [{"byteLength": len(blob)}]
    try:
        return _pack_glb(gltf, blob)
    except (TypeError, ValueError) as exc:
        raise InputValueError("metadata", f"must be JSON-serialisable: {exc}") from exc
