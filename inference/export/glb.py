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

Normals (``normals=True``, the default): smooth per-frame vertex normals of the welded mesh
(split at UV seams like the positions), as morph targets beside the positions. Quantized, the
base normal is normalized SHORT (unit to ~3e-5) and each target's delta normalized BYTE
(delta / 127, KHR_mesh_quantization): 4 bytes per vertex per frame, an angle error under 0.5
degree after the player renormalises (glTF requires it after morphing). A BYTE delta holds
[-1, 1] per component: a normal that turns more than ~60 degrees from its chunk's base frame
(a garment turning with a dancer; a vertex in a fold whose normal flips) would be clipped, so a
chunk where more than ``NORMAL_CLIP_SHARE`` of the vertex-frames would clip is halved, down to
``NORMAL_MIN_CHUNK`` targets (``split_for_normals``), and one that still would keeps float
deltas (exact). At most that share of a byte chunk's vertex-frames is clipped (fold vertices).
Unquantized, normals are float (+12 bytes per vertex per frame). ``normals=False``
leaves them out: players then compute flat normals from the morphed positions.

Materials: one per garment, from its ``GarmentTrack.appearance`` (linear base colour, roughness,
optional sheen, ``KHR_materials_sheen``), metallic 0; the body's skin tone otherwise.

Floor: with ``floor_z`` (the height of the floor in the input's Z-up metres: the rest body's
soles), the garments and the skeleton hang under one root node "tryon" lifted by -floor_z (the
skinned body's own node stays a scene root, as glTF requires; its joints carry it), so the
model stands on y = 0 as viewers and DCC tools expect. The scene's extras record ``fps``, ``frame_start`` and
``frame_end`` (what ``tools/blender_import.py`` applies to a Blender scene).

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
from inference.export import meshopt
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
_SNORM8 = 127
_NORMAL_DELTA_MAX = 1.0  # a BYTE-normalized delta holds [-1, 1]
# Normal chunks: split while more than this share of vertex-frames would clip, down to this many
# targets; a chunk that still clips more keeps float deltas (exact, 3x the bytes).
NORMAL_CLIP_SHARE = 0.02
NORMAL_MIN_CHUNK = 8
_BYTE, _UNSIGNED_BYTE, _SHORT, _UNSIGNED_SHORT, _UNSIGNED_INT, _FLOAT = 5120, 5121, 5122, 5123, 5125, 5126
_COMPONENT_TYPES = {
    np.dtype(np.int8): _BYTE, np.dtype(np.uint8): _UNSIGNED_BYTE, np.dtype(np.int16): _SHORT,
    np.dtype(np.uint16): _UNSIGNED_SHORT, np.dtype(np.uint32): _UNSIGNED_INT, np.dtype(np.float32): _FLOAT,
}
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_ACCESSOR_TYPES = {1: "SCALAR", 2: "VEC2", 3: "VEC3", 4: "VEC4", 16: "MAT4"}
_GLB_MAGIC, _GLB_JSON, _GLB_BIN = 0x46546C67, 0x4E4F534A, 0x004E4942
_MIN_SCALE_M = 1e-6  # quantization scale floor for a garment that is a single point
# Appearance (glTF PBR, linear base colour): garments carry their own (``GarmentTrack.appearance``).
DEFAULT_APPEARANCE = {"base_color": [0.098, 0.162, 0.319], "roughness": 0.8}
BODY_APPEARANCE = {"base_color": [0.604, 0.402, 0.296], "roughness": 0.6}


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


def clipped_share(normals: np.ndarray) -> float:
    """Share of a chunk's target normals (frames 1..L of (L + 1, N, 3)) whose delta from the base
    frame 0 leaves [-1, 1] in some component: what BYTE-normalized deltas would clip."""
    if len(normals) < 2:
        return 0.0
    return float((np.abs(normals[1:] - normals[0]).max(axis=-1) > _NORMAL_DELTA_MAX).mean())


def local_chunk(X: np.ndarray, normals: np.ndarray | None, rotate: bool):
    """A chunk's frames in its node's moving frame: x' = R_k^T (x - c_k) + c_0 and n' = R_k^T n,
    with R_k = ``chunk_rotations`` and c_k the frame's centroid; the node then carries
    x = c_k + R_k (x' - c_0) (``node_motion``).

    X : (L + 1, N, 3) ; normals : (L + 1, N, 3) or None
    returns X', normals', (R (L + 1, 3, 3), c (L + 1, 3)) or None when not rotated
    """
    if not rotate or len(X) < 2:
        return X, normals, None
    X = np.asarray(X, np.float32)
    R = chunk_rotations(X)
    c = X.mean(axis=1, dtype=np.float64)  # (L + 1, 3)
    R32 = R.astype(np.float32)
    # row vectors: (x - c) R = (R^T (x - c))^T; float32 (~1e-7 m, far under the quantization step)
    local = np.matmul(X - c[:, None].astype(np.float32), R32) + c[0].astype(np.float32)
    if normals is not None:
        normals = np.matmul(np.asarray(normals, np.float32), R32)
    return local, normals, (R, c)


def node_motion(motion: tuple[np.ndarray, np.ndarray], origin) -> tuple[np.ndarray, np.ndarray]:
    """Keyframed translation (L + 1, 3) and rotation (L + 1, 4 xyzw) of a chunk node whose mesh
    (``local_chunk`` frames) is offset by ``origin`` (the dequantization translation, or 0):
    x = c_k + R_k (x' - c_0) = [c_k + R_k (origin - c_0)] + R_k (x' - origin)."""
    R, c = motion
    translation = c + np.einsum("kij,j->ki", R, np.asarray(origin, np.float64) - c[0])
    return translation.astype(np.float32), keyframe_quaternions(R)


def split_for_normals(ranges: list[tuple[int, int]], X: np.ndarray, normals: np.ndarray, rotate: bool = True) -> list[tuple[int, int]]:
    """Halve every chunk of more than ``NORMAL_MIN_CHUNK`` targets whose BYTE normal deltas (in
    its turning frame, ``local_chunk``) would clip more than ``NORMAL_CLIP_SHARE`` of its
    vertex-frames.

    ranges : chunk_ranges output ; X, normals : (T, N, 3) positions and unit normals
    returns the refined ranges
    """
    out: list[tuple[int, int]] = []
    stack = list(reversed(ranges))
    while stack:  # a loop over chunks, each test vectorised over its frames and vertices
        s, e = stack.pop()
        if e - s > NORMAL_MIN_CHUNK and clipped_share(local_chunk(X[s:e + 1], normals[s:e + 1], rotate)[1]) > NORMAL_CLIP_SHARE:
            m = (s + e) // 2
            stack += [(m, e), (s, m)]
        else:
            out.append((s, e))
    return out


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


def _position_accessors(b: _BinaryBuilder, X: np.ndarray, quantize: bool, pivot: bool = False):
    """Base + morph-target POSITION accessors of one chunk, and the node TRS that dequantizes them.

    X       : (L + 1, N, 3) float32, metres, Y-up: the base frame then the L target frames
    pivot   : float positions relative to the base frame's bounding-box centre, the node's
              translation (quantized positions always are)
    returns : base accessor, [L target accessors], node TRS dict, the node's uniform scale
    """
    L, N = X.shape[0] - 1, X.shape[1]
    if not quantize:
        trs = {}
        if pivot:  # positions relative to the node's translation, the pivot it turns about
            origin = (X[0].min(axis=0) + X[0].max(axis=0)) / 2.0
            X = X - origin
            trs = {"translation": origin.astype(np.float64).tolist()}
        base, deltas = np.ascontiguousarray(X[0], np.float32), (X[1:] - X[0]).astype(np.float32)
        base_acc = b.accessor(b.view(base, _ARRAY_BUFFER, stride=12), np.float32, N, 3,
                              lo=base.min(axis=0), hi=base.max(axis=0))
        if not L:
            return base_acc, [], trs, 1.0
        view = b.view(deltas, _ARRAY_BUFFER, stride=12)  # shared by L accessors: stride required
        lo, hi = deltas.min(axis=1), deltas.max(axis=1)  # (L, 3)
        targets = [b.accessor(view, np.float32, N, 3, byte_offset=k * N * 12, lo=lo[k], hi=hi[k]) for k in range(L)]
        return base_acc, targets, trs, 1.0
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


def keyframe_quaternions(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (T, ..., 3, 3) over keyframes -> glTF quaternions (T, ..., 4) as (x, y, z, w)
    float32, each on the hemisphere of the previous keyframe's (q and -q are the same rotation;
    players slerp the shorter way only when consecutive keys have q_t . q_{t-1} >= 0)."""
    q = matrix_to_quaternion(R)  # (w, x, y, z)
    flips = np.sign(np.einsum("t...k,t...k->t...", q[1:], q[:-1]))
    flips = np.concatenate([np.ones_like(q[:1, ..., 0]), np.cumprod(np.where(flips == 0, 1.0, flips), axis=0)])
    q = q * flips[..., None]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return q[..., [1, 2, 3, 0]].astype(np.float32)


def chunk_rotations(X: np.ndarray) -> np.ndarray:
    """Best-fit rotations R_k taking a chunk's base frame to each of its frames (Kabsch):
    R_k = argmin_R sum_v |R (x_0v - c_0) - (x_kv - c_k)|^2, with c the frames' centroids.

    X : (L + 1, N, 3) positions ; returns (L + 1, 3, 3) float64 (R_0 = I)
    """
    Xd = np.asarray(X, np.float64)
    A = Xd[0] - Xd[0].mean(axis=0)
    B = Xd - Xd.mean(axis=1, keepdims=True)
    H = np.matmul(A.T[None], B)  # (L + 1, 3, 3) sum_v a_v b_v^T
    U, _, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, -1, -2)
    d = np.sign(np.linalg.det(V @ np.swapaxes(U, -1, -2)))
    D = np.broadcast_to(np.eye(3), H.shape).copy()
    D[:, 2, 2] = np.where(d == 0, 1.0, d)  # no reflections
    return V @ D @ np.swapaxes(U, -1, -2)


def _normal_accessors(b: _BinaryBuilder, n: np.ndarray, quantize: bool, byte_deltas: bool = True):
    """Base + morph-target NORMAL accessors of one chunk.

    n           : (L + 1, N, 3) float32 unit normals, Y-up: the base frame then the L target frames
    quantize    : normalized SHORT base (else float)
    byte_deltas : with quantize, normalized BYTE deltas (clipped to [-1, 1]); else float deltas
    returns     : base accessor, [L target accessors]
    """
    L, N = n.shape[0] - 1, n.shape[1]
    if not quantize:
        base = b.accessor(b.view(n[0], _ARRAY_BUFFER, stride=12), np.float32, N, 3)
        view = b.view(n[1:] - n[0], _ARRAY_BUFFER, stride=12) if L else None
        return base, [b.accessor(view, np.float32, N, 3, byte_offset=k * N * 12) for k in range(L)]
    q0 = np.zeros((N, 4), np.int16)  # VEC3 SHORT padded to the 4-byte vertex stride
    q0[:, :3] = np.rint(n[0] * _SNORM16)
    base = b.accessor(b.view(q0, _ARRAY_BUFFER, stride=8), np.int16, N, 3, normalized=True)
    if not L:
        return base, []
    if not byte_deltas:
        d = np.ascontiguousarray(n[1:] - q0[None, :, :3] / _SNORM16, np.float32)
        view = b.view(d, _ARRAY_BUFFER, stride=12)
        return base, [b.accessor(view, np.float32, N, 3, byte_offset=k * N * 12) for k in range(L)]
    dq = np.zeros((L, N, 4), np.int8)  # VEC3 BYTE padded to 4 bytes
    dq[..., :3] = np.clip(np.rint((n[1:] - q0[None, :, :3] / _SNORM16) * _SNORM8), -_SNORM8, _SNORM8)
    view = b.view(dq, _ARRAY_BUFFER, stride=4)
    return base, [b.accessor(view, np.int8, N, 3, byte_offset=k * N * 4, normalized=True) for k in range(L)]


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

    frames = zup_to_yup(g.vertices)[:, vertex_map]  # (T, N, 3), split at the UV seams
    ranges = chunk_ranges(g.num_frames, max_targets)
    rotate = anim is not None  # chunk nodes turn with the garment (keyframed rotation)
    frame_normals = None
    if normals:
        # Normals of the welded mesh (smooth across UV seams), split like the positions.
        frame_normals = vertex_normals(zup_to_yup(g.vertices), g.faces, fallback=(0.0, 1.0, 0.0))[:, vertex_map]
        if quantize:
            ranges = split_for_normals(ranges, frames, frame_normals, rotate)
    group = {"name": g.name, "children": []}
    if g.metadata:
        group["extras"] = g.metadata
    nodes.append(group)
    group_index = len(nodes) - 1
    for c, (start, end) in enumerate(ranges):  # a few chunks, each vectorised
        L = end - start
        X, chunk_normals, motion = local_chunk(frames[start:end + 1], None if frame_normals is None else frame_normals[start:end + 1], rotate)
        base, targets, trs, scale = _position_accessors(b, X, quantize, pivot=motion is not None)
        attributes = {**shared, "POSITION": base}
        morphs = [{"POSITION": t} for t in targets]
        if chunk_normals is not None:
            byte_deltas = clipped_share(chunk_normals) <= NORMAL_CLIP_SHARE
            attributes["NORMAL"], normal_targets = _normal_accessors(b, chunk_normals, quantize, byte_deltas)
            for k, t in enumerate(normal_targets):
                morphs[k]["NORMAL"] = t
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
        if motion is not None:
            t_keys, q_keys = node_motion(motion, trs.get("translation", [0.0, 0.0, 0.0]))
            frames_in = anim.frames_input(start, end)
            anim.add(len(nodes) - 1, "translation", frames_in, b.accessor(b.view(t_keys), np.float32, len(t_keys), 3))
            anim.add(len(nodes) - 1, "rotation", frames_in, b.accessor(b.view(q_keys), np.float32, len(q_keys), 4))
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
    return local[..., :3, 3].astype(np.float32), keyframe_quaternions(local[..., :3, :3])


def _write_body(body: BodyTrack, b: _BinaryBuilder, anim: _AnimationBuilder | None, nodes: list, meshes: list,
                skins: list, material: int, max_influences: int, normals: bool, quantize: bool) -> list[int]:
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
    if normals:  # rest normals: players skin them with the positions
        n = vertex_normals(zup_to_yup(body.rest_vertices), body.faces, fallback=(0.0, 1.0, 0.0))[vertex_map]
        attributes["NORMAL"] = _normal_accessors(b, n[None], quantize)[0]
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


def _material(name: str, appearance: dict, double_sided: bool) -> dict:
    """A glTF PBR material from an appearance: base_color (3,) linear RGB, roughness, optional
    sheen_color (3,) + sheen_roughness (KHR_materials_sheen: cloth's grazing-angle highlight).
    Metallic is 0: cloth and skin are dielectrics."""
    m = {"name": name, "pbrMetallicRoughness": {
        "baseColorFactor": [float(c) for c in appearance["base_color"]] + [1.0],
        "metallicFactor": 0.0, "roughnessFactor": float(appearance.get("roughness", 0.8))}}
    if double_sided:
        m["doubleSided"] = True  # open surfaces: the inside shows at hems and sleeves
    if "sheen_color" in appearance:
        m["extensions"] = {"KHR_materials_sheen": {"sheenColorFactor": [float(c) for c in appearance["sheen_color"]],
                                                   "sheenRoughnessFactor": float(appearance.get("sheen_roughness", 0.5))}}
    return m


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
              quantize: bool = True, normals: bool = True, max_influences: int = 8,
              max_targets_per_mesh: int = DEFAULT_MAX_TARGETS_PER_MESH, metadata: dict | None = None,
              floor_z: float | None = None, compression: str = "none") -> bytes:
    """A try-on sequence as glTF 2.0 binary: Y-up, metres, one animation named "tryon".

    garments             : GarmentTrack each with (T, V_i, 3) vertices, Z-up metres; same T for all
    body                 : BodyTrack with T frames, or None
    fps                  : frames per second; keyframe t is at t / fps seconds
    quantize             : KHR_mesh_quantization positions (error <= S / 65534 per component,
                           S ~ the garment's half-size plus its motion in a chunk) and 8-bit weights
    normals              : smooth per-frame vertex normals (quantized: +4 B per vertex per frame; float: +12 B)
    max_influences       : body influences per vertex, 8 (exact LBS; JOINTS_1/WEIGHTS_1 when needed) or
                           4 (the 4 largest, renormalised: what three.js plays, for every player alike)
    max_targets_per_mesh : frames per morph-target mesh (<= 256 plays on every WebGL2 device)
    metadata             : JSON-serialisable, stored in asset.extras
    floor_z              : height of the floor in the input (Z-up metres), lifted to y = 0; None: as is
    compression          : 'none' or 'meshopt' (EXT_meshopt_compression, ``inference.export.meshopt``)
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
    materials: list[dict] = []
    roots = []
    if body is not None:
        materials.append(_material("body", BODY_APPEARANCE, double_sided=False))
        roots += _write_body(body, b, anim, nodes, meshes, skins, 0, max_influences, normals, quantize)
    for g in garments:
        materials.append(_material(g.name, g.appearance or DEFAULT_APPEARANCE, double_sided=True))
        roots.append(_write_garment(g, b, anim, nodes, meshes, len(materials) - 1, quantize, normals, int(max_targets_per_mesh)))
    if floor_z is not None:
        # a skinned mesh's node stays a scene root (glTF ignores its parents' transforms): its
        # skeleton, under the lifted root, carries it up
        skinned = [r for r in roots if "skin" in nodes[r]]
        nodes.append({"name": "tryon", "translation": [0.0, -float(floor_z), 0.0], "children": [r for r in roots if r not in skinned]})
        roots = [len(nodes) - 1] + skinned
    scene = {"name": "tryon", "nodes": roots,
             "extras": {"fps": float(fps), "frame_start": 0, "frame_end": T - 1, "frames": T}}

    asset = {"version": "2.0", "generator": "tryon inference.export.glb"}
    extras = {"units": "metres", "axes": "Y-up right-handed (glTF)", "fps": float(fps), "frames": T,
              "garments": names, **(metadata or {})}
    asset["extras"] = extras
    gltf = {"asset": asset, "scene": 0, "scenes": [scene], "nodes": nodes, "meshes": meshes, "materials": materials}
    if skins:
        gltf["skins"] = skins
    if anim is not None and anim.channels:
        gltf["animations"] = [{"name": ANIMATION_NAME, "samplers": anim.samplers, "channels": anim.channels}]
    used = sorted({e for m in materials for e in m.get("extensions", {})})
    if quantize and (garments or normals):
        used.append("KHR_mesh_quantization")
        gltf["extensionsRequired"] = ["KHR_mesh_quantization"]
    if used:
        gltf["extensionsUsed"] = used
    gltf["accessors"] = b.accessors
    gltf["bufferViews"] = b.views
    blob = b.blob()
    gltf["buffers"] = [{"byteLength": len(blob)}]
    if compression == "meshopt":
        if not meshopt.available():
            raise InputValueError("/options/compression", "meshopt compression is not installed on this server "
                                                         "(pip install meshoptimizer, the 'compress' extra)")
        gltf, blob = meshopt.compress(gltf, blob)
    elif compression != "none":
        raise InputValueError("/options/compression", f"must be 'none' or 'meshopt', got {compression!r}")
    try:
        return _pack_glb(gltf, blob)
    except (TypeError, ValueError) as exc:
        raise InputValueError("metadata", f"must be JSON-serialisable: {exc}") from exc
