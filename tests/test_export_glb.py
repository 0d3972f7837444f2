"""glb export: Khronos validator clean, Y-up, morph-target playback and skinning reproduce the input.

The file is parsed back with pygltflib (an independent reader) and played by a small glTF
player written here from the spec: keyframe sampling (LINEAR/STEP), node hierarchy, morph
targets, and skinning (joint matrix = global(joint) @ IBM).
"""
from __future__ import annotations

import json
import shutil
import subprocess
from dataclasses import replace
from pathlib import Path

import numpy as np
import pygltflib
import pytest

from inference.errors import InputValueError
from inference.export.glb import (ANIMATION_NAME, NORMAL_CLIP_SHARE, NORMAL_MIN_CHUNK, chunk_ranges, chunk_rotations, clipped_share, split_for_normals,
                                  split_uv_seams, write_glb, zup_to_yup)
from inference.mesh import vertex_normals
from inference.export.tracks import BodyTrack, GarmentTrack, pose_body_vertices
from inference.rotations import axis_angle_to_matrix, quaternion_to_matrix

REPO = Path(__file__).resolve().parents[1]
VALIDATOR_SCRIPT = REPO / "tools" / "validate_gltf.mjs"
# Quantization bound of the writer: S / 65534 per component with S <= ~1 m here; 0.5 mm is
# the product tolerance, the bound actually checked is computed from each chunk's scale.
QUANT_TOL_M = 5e-4
SKIN_TOL_M = 2e-5  # float32 LBS vs float32 glTF skinning of a ~1 m body
SHEEN = {"base_color": [0.5, 0.1, 0.1], "roughness": 0.75, "sheen_color": [0.3, 0.1, 0.1], "sheen_roughness": 0.5}


# ----------------------------------------------------------------------------- fixtures

def make_tube(n_around: int = 24, n_rows: int = 8, radius: float = 0.2, height: float = 0.5):
    """A UV-mapped open cylinder about Z with one UV seam (u = 0 and u = 1).

    returns : vertices (V, 3) float32, faces (F, 3), uvs (Vt, 2), face_uvs (F, 3)
    """
    a = np.arange(n_around) * 2 * np.pi / n_around
    z = np.linspace(0.8, 0.8 + height, n_rows)
    verts = np.stack([np.broadcast_to(radius * np.cos(a), (n_rows, n_around)),
                      np.broadcast_to(radius * np.sin(a), (n_rows, n_around)),
                      np.broadcast_to(z[:, None], (n_rows, n_around))], -1).reshape(-1, 3)
    u = np.arange(n_around + 1) / n_around
    v = np.linspace(0.0, 1.0, n_rows)
    uvs = np.stack(np.broadcast_arrays(u[None, :], v[:, None]), -1).reshape(-1, 2)
    r, c = np.meshgrid(np.arange(n_rows - 1), np.arange(n_around), indexing="ij")
    r, c = r.ravel(), c.ravel()
    p = lambda rr, cc: rr * n_around + cc % n_around  # noqa: E731
    t = lambda rr, cc: rr * (n_around + 1) + cc  # noqa: E731
    faces = np.concatenate([np.stack([p(r, c), p(r, c + 1), p(r + 1, c + 1)], -1),
                            np.stack([p(r, c), p(r + 1, c + 1), p(r + 1, c)], -1)])
    face_uvs = np.concatenate([np.stack([t(r, c), t(r, c + 1), t(r + 1, c + 1)], -1),
                               np.stack([t(r, c), t(r + 1, c + 1), t(r + 1, c)], -1)])
    return verts.astype(np.float32), faces, uvs.astype(np.float32), face_uvs


def make_garment(T: int, name: str = "tube", seed: int = 0, **tube) -> GarmentTrack:
    """The tube turning about Z, walking along +X and rippling radially."""
    verts, faces, uvs, face_uvs = make_tube(**tube)
    t = np.arange(T)[:, None, None] / 30.0
    R = axis_angle_to_matrix(np.stack([np.zeros(T), np.zeros(T), 0.9 * np.arange(T) / 30.0], -1))
    ripple = 1.0 + 0.05 * np.sin(8 * verts[None, :, 2:3] + 5 * t)
    frames = np.einsum("tij,tvj->tvi", R, verts[None] * np.concatenate([ripple, ripple, np.ones_like(ripple)], -1))
    frames = frames + np.stack([1.2 * t[..., 0], 0 * t[..., 0], 0.02 * np.sin(3 * t[..., 0])], -1)
    noise = np.random.default_rng(seed).normal(scale=1e-3, size=frames.shape)
    return GarmentTrack(name, (frames + noise).astype(np.float32), faces, uvs, face_uvs, {"id": name, "size": "M"})


def make_body(T: int, num_bones: int = 3, influences: int = 3, uv: bool = False, seed: int = 1) -> BodyTrack:
    """A vertical tube skinned to a bone tree (a chain, with bone 3+ branching from bone 1).

    Rest frames are rotated (not identity) so that axis conversions are exercised; the
    animation rotates every bone about a random axis and walks the root.
    """
    rng = np.random.default_rng(seed)
    verts, faces, uvs, face_uvs = make_tube(n_around=16, n_rows=12, radius=0.15, height=1.0)
    verts[:, 2] -= 0.8
    J = num_bones
    parents = np.array([-1, 0, 1] + [1] * (J - 3))[:J]
    heads = np.stack([0.05 * np.sin(np.arange(J)), np.zeros(J), np.linspace(0.0, 0.9, J)], -1)
    rest = np.tile(np.eye(4), (J, 1, 1))
    rest[:, :3, :3] = axis_angle_to_matrix(rng.normal(scale=0.5, size=(J, 3)))
    rest[:, :3, 3] = heads
    # FK: world_tj = world_t,parent (rest_parent^-1 rest_j) [R(theta_tj) | 0]
    theta = rng.normal(scale=0.4, size=(1, J, 3)) * np.sin(np.arange(T) / 7.0)[:, None, None]
    theta[:, 0] += np.linspace(0, 3.5, T)[:, None] * np.array([0.0, 0.0, 1.0])  # root turns > 180 deg
    D = np.tile(np.eye(4), (T, J, 1, 1))
    D[..., :3, :3] = axis_angle_to_matrix(theta)
    world = np.zeros((T, J, 4, 4))
    for j in range(J):  # J is tiny; a reference FK, not runtime code
        if parents[j] < 0:
            world[:, j] = rest[j] @ D[:, j]
            world[:, j, :3, 3] += np.stack([0.8 * np.arange(T) / 30.0, np.zeros(T), np.zeros(T)], -1)
        else:
            world[:, j] = world[:, parents[j]] @ np.linalg.inv(rest[parents[j]]) @ rest[j] @ D[:, j]
    d = np.linalg.norm(verts[:, None] - heads[None], axis=-1)  # (V, J)
    K = min(influences, J)
    idx = np.argsort(d, axis=1)[:, :K]
    w = np.exp(-np.take_along_axis(d, idx, 1) / 0.2)
    w /= w.sum(1, keepdims=True)
    return BodyTrack(verts, faces, idx, w.astype(np.float32), parents, [f"bone{j}" for j in range(J)],
                     rest.astype(np.float32), world.astype(np.float32),
                     uvs if uv else None, face_uvs if uv else None)


# ----------------------------------------------------------------------------- a tiny glTF player

_DTYPES = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


class Player:
    def __init__(self, data: bytes):
        self.gltf = pygltflib.GLTF2.load_from_bytes(data)
        self.blob = self.gltf.binary_blob()
        self.parent = {c: i for i, n in enumerate(self.gltf.nodes) for c in (n.children or [])}

    def accessor(self, index: int) -> np.ndarray:
        """Decoded (count, ncomp) float64 (normalized ints dequantized as the spec says)."""
        acc = self.gltf.accessors[index]
        view = self.gltf.bufferViews[acc.bufferView]
        dtype = np.dtype(_DTYPES[acc.componentType])
        ncomp = _NCOMP[acc.type]
        item = dtype.itemsize * ncomp
        stride = view.byteStride or item
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        assert start + (acc.count - 1) * stride + item <= (view.byteOffset or 0) + view.byteLength
        raw = np.frombuffer(self.blob, np.uint8, count=acc.count * stride - (stride - item), offset=start)
        raw = np.concatenate([raw, np.zeros(stride - item, np.uint8)]).reshape(acc.count, stride)[:, :item]
        out = np.ascontiguousarray(raw).view(dtype).reshape(acc.count, ncomp).astype(np.float64)
        if acc.normalized:
            info = np.iinfo(dtype)
            out = np.maximum(out / info.max, -1.0)
        return out

    def animation(self):
        (anim,) = self.gltf.animations
        return anim

    def sample(self, sampler, time: float) -> np.ndarray:
        """Value of an animation sampler at a time (LINEAR lerp / quaternion slerp, STEP)."""
        t = self.accessor(sampler.input)[:, 0]
        out = self.accessor(sampler.output)
        out = out.reshape(len(t), -1)
        if time <= t[0]:
            return out[0]
        if time >= t[-1]:
            return out[-1]
        k = np.searchsorted(t, time, side="right") - 1
        if sampler.interpolation == "STEP":
            return out[k]
        a = (time - t[k]) / (t[k + 1] - t[k])
        if out.shape[1] == 4 and "rotation" in self._paths_of(sampler):
            q0, q1 = out[k], out[k + 1]
            q1 = q1 if q0 @ q1 >= 0 else -q1
            q = (1 - a) * q0 + a * q1  # nlerp is enough for the close keyframes tested here
            return q / np.linalg.norm(q)
        return (1 - a) * out[k] + a * out[k + 1]

    def _paths_of(self, sampler):
        anim = self.animation()
        i = anim.samplers.index(sampler)
        return {c.target.path for c in anim.channels if c.sampler == i}

    def trs(self, node: int, time: float | None):
        n = self.gltf.nodes[node]
        tr = {"translation": np.array(n.translation or [0.0, 0, 0]), "rotation": np.array(n.rotation or [0.0, 0, 0, 1]),
              "scale": np.array(n.scale or [1.0, 1, 1]), "weights": None}
        if time is not None and self.gltf.animations:
            anim = self.animation()
            for c in anim.channels:
                if c.target.node == node:
                    tr[c.target.path] = self.sample(anim.samplers[c.sampler], time)
        return tr

    def local_matrix(self, node: int, time: float | None) -> np.ndarray:
        tr = self.trs(node, time)
        x, y, z, w = tr["rotation"]
        M = np.eye(4)
        M[:3, :3] = quaternion_to_matrix(np.array([w, x, y, z])) * tr["scale"][None, :]
        M[:3, 3] = tr["translation"]
        return M

    def world_matrix(self, node: int, time: float | None) -> np.ndarray:
        M = self.local_matrix(node, time)
        while node in self.parent:
            node = self.parent[node]
            M = self.local_matrix(node, time) @ M
        return M

    def node_index(self, name: str) -> int:
        return [n.name for n in self.gltf.nodes].index(name)

    def morphed_world_positions(self, node: int, time: float | None) -> np.ndarray:
        """Base + sum_k w_k target_k, then the node's world transform: (N, 3) metres."""
        prim = self.gltf.meshes[self.gltf.nodes[node].mesh].primitives[0]
        p = self.accessor(prim.attributes.POSITION)
        weights = self.trs(node, time)["weights"]
        if weights is not None:
            for k, w in enumerate(weights):
                if w != 0:
                    p = p + w * self.accessor(prim.targets[k]["POSITION"])
        M = self.world_matrix(node, time)
        return p @ M[:3, :3].T + M[:3, 3]

    def skinned_positions(self, node: int, time: float | None) -> np.ndarray:
        """glTF skinning: v' = sum_s sum_c w_sc (global(joint) @ IBM)[j_sc] v, (N, 3) metres."""
        n = self.gltf.nodes[node]
        skin = self.gltf.skins[n.skin]
        attrs = self.gltf.meshes[n.mesh].primitives[0].attributes
        p = self.accessor(attrs.POSITION)
        ibm = self.accessor(skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)  # column-major
        joint_mats = np.stack([self.world_matrix(j, time) for j in skin.joints]) @ ibm
        sets = [s for s in (0, 1) if getattr(attrs, f"JOINTS_{s}", None) is not None]
        joints = np.concatenate([self.accessor(getattr(attrs, f"JOINTS_{s}")) for s in sets], 1).astype(int)
        weights = np.concatenate([self.accessor(getattr(attrs, f"WEIGHTS_{s}")) for s in sets], 1)
        M = np.einsum("vk,vkij->vij", weights, joint_mats[joints])
        return np.einsum("vij,vj->vi", M[:, :3, :3], p) + M[:, :3, 3]


def garment_frame(player: Player, name: str, time: float):
    """Positions of the garment's visible chunk at a time (exactly one must be visible)."""
    group = player.gltf.nodes[player.node_index(name)]
    visible = [c for c in group.children if np.any(player.trs(c, time)["scale"] != 0)]
    assert len(visible) == 1, f"{len(visible)} chunks visible at t={time}"
    node = visible[0]
    M = player.world_matrix(node, time)
    return player.morphed_world_positions(node, time), abs(M[0, 0])


def expected_garment(g: GarmentTrack, t: float) -> np.ndarray:
    """Input frames (fractional t: linear blend), Y-up, split at seams like the writer."""
    vmap, _, _ = split_uv_seams(g.faces, g.face_uvs)
    k = int(np.floor(t))
    a = t - k
    v = g.vertices[k] if a == 0 else (1 - a) * g.vertices[k] + a * g.vertices[k + 1]
    return zup_to_yup(v)[vmap].astype(np.float64)


# ----------------------------------------------------------------------------- validator

def run_validator(data: bytes, tmp_path: Path) -> dict:
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed: the Khronos glTF validator runs on node (CI: npm ci)")
    if not (REPO / "node_modules" / "gltf-validator").is_dir():
        pytest.skip("node_modules/gltf-validator is missing: run `npm ci` at the repository root")
    path = tmp_path / "out.glb"
    path.write_bytes(data)
    proc = subprocess.run([node, str(VALIDATOR_SCRIPT), str(path)], capture_output=True, text=True, timeout=120)
    assert proc.returncode in (0, 1), proc.stderr
    report = json.loads(proc.stdout)
    assert (proc.returncode == 1) == (report["issues"]["numErrors"] > 0)
    return report


def issues(report: dict, severity: int) -> list[str]:
    return [f"{m['code']} {m.get('pointer', '')}: {m['message']}" for m in report["issues"]["messages"]
            if m["severity"] == severity]


@pytest.mark.parametrize(
    "case",
    [
        dict(T=300, body=None, quantize=True, normals=False),  # 3 morph chunks of <= 128 targets
        dict(T=300, body=None, quantize=True, normals=True),  # normals: chunks split as the tube turns
        dict(T=40, body=dict(num_bones=6, influences=8, uv=True), quantize=False, normals=True),
        dict(T=20, body=dict(num_bones=3, influences=3), quantize=True, normals=True, garments=2, floor_z=-0.8),
        dict(T=1, body=dict(num_bones=3, influences=2), quantize=True, normals=False),
        dict(T=1, body=dict(num_bones=3, influences=2), quantize=True, normals=True, appearance=True),
    ],
    ids=["garment-300f-quant", "garment-300f-normals", "body8-float-normals", "body3-2garments-floor", "single-frame",
         "single-frame-normals-sheen"],
)
def test_validator_reports_no_errors_or_warnings(case, tmp_path):
    garments = [make_garment(case["T"], name=f"g{i}", seed=i) for i in range(case.get("garments", 1))]
    if case.get("appearance"):
        garments = [replace(g, appearance=SHEEN) for g in garments]
    body = make_body(case["T"], **case["body"]) if case["body"] else None
    data = write_glb(garments, body, fps=30.0, quantize=case["quantize"], normals=case["normals"], floor_z=case.get("floor_z"))
    report = run_validator(data, tmp_path)
    assert issues(report, 0) == [], issues(report, 0)[:10]
    assert issues(report, 1) == [], issues(report, 1)[:10]  # warnings: none either
    info = report["info"]
    assert info["animationCount"] == (0 if case["T"] == 1 else 1)
    assert info["hasSkins"] == (body is not None)
    assert info["hasMorphTargets"] == (case["T"] > 1)


def test_validator_script_fails_on_errors(tmp_path):
    data = bytearray(write_glb([make_garment(3)], quantize=False))
    # Corrupt the first POSITION min: the validator must report ACCESSOR_MIN_MISMATCH and exit 1.
    player = Player(bytes(data))
    gltf = player.gltf
    acc = gltf.accessors[gltf.meshes[0].primitives[0].attributes.POSITION]
    acc.min = [m - 1.0 for m in acc.min]
    gltf.set_binary_blob(player.blob)
    path = tmp_path / "bad.glb"
    gltf.save_binary(str(path))
    report = run_validator(path.read_bytes(), tmp_path)
    assert "ACCESSOR_MIN_MISMATCH" in {m["code"] for m in report["issues"]["messages"]}


# ----------------------------------------------------------------------------- geometry and animation

def test_zup_to_yup_hand_computed():
    g = GarmentTrack("tri", np.array([[[1.0, 2.0, 3.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]]], np.float32),
                     np.array([[0, 1, 2]]))
    p = Player(write_glb([g], quantize=False))
    node = p.node_index("tri_morph0")
    np.testing.assert_array_equal(p.morphed_world_positions(node, None),
                                  [[1.0, 3.0, -2.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]])
    assert p.gltf.asset.extras["units"] == "metres"


def test_split_uv_seams():
    verts, faces, uvs, face_uvs = make_tube(n_around=6, n_rows=3)
    vmap, uvmap, fs = split_uv_seams(faces, face_uvs)
    assert len(vmap) == len(verts) + 3  # the seam column is doubled on each of the 3 rows
    # every split corner has the position and the uv of the original corner
    np.testing.assert_array_equal(vmap[fs], faces)
    np.testing.assert_array_equal(uvmap[fs], face_uvs)
    assert np.all(np.diff(vmap) >= 0)


def test_chunk_ranges_cover_all_frames_and_share_boundaries():
    assert chunk_ranges(1, 128) == [(0, 0)]
    assert chunk_ranges(300, 128) == [(0, 128), (128, 256), (256, 299)]
    assert chunk_ranges(129, 128) == [(0, 128)]


@pytest.mark.parametrize("quantize,normals", [(True, False), (False, False), (True, True)])
def test_garment_playback_matches_input(quantize, normals):
    T, fps = 300, 30.0
    g = make_garment(T)
    p = Player(write_glb([g], fps=fps, quantize=quantize, normals=normals))
    anim = p.animation()
    assert anim.name == ANIMATION_NAME
    group = p.gltf.nodes[p.node_index("tube")]
    assert len(group.children) == 3  # with normals too: the chunk nodes turn with the tube, the deltas stay small
    assert group.extras == {"id": "tube", "size": "M"}
    for c in group.children:
        prim = p.gltf.meshes[p.gltf.nodes[c].mesh].primitives[0]
        assert len(prim.targets) <= 128
    worst = 0.0
    # every frame at its keyframe time (as stored), and half-way between some frames
    times = p.accessor(anim.samplers[0].input)[:, 0]
    for t in [0, 1, 2, 64, 127, 128, 129, 200, 255, 256, 257, 298, 299]:
        got, scale = garment_frame(p, "tube", float(np.float32(t / fps)))
        # per-component quantization error in the chunk node's turning frame, rotated: x sqrt(3);
        # the node's keyframed translation is float32 (the tube walks 12 m: ulp ~1e-6 m)
        bound = np.sqrt(3) * scale / 65534 * 1.0001 + 4e-6 if quantize else 4e-6
        err = np.abs(got - expected_garment(g, t)).max()
        assert err <= bound, (t, err, bound)
        worst = max(worst, err)
    # Between keyframes a player slerps the chunk node's rotation and lerps its morphs: that is off
    # the linear blend of the two frames by about r d^2 / 8 (r ~0.2 m the tube's radius, d = 0.03 rad
    # its turn per frame: 2e-5 m, 5e-5 with the ripple)
    for t in [0.5, 127.5, 128.5, 298.5]:
        got, scale = garment_frame(p, "tube", t / fps)
        assert np.abs(got - expected_garment(g, t)).max() <= (np.sqrt(3) * scale / 65534 + 1e-4 if quantize else 1e-4)
    assert worst < (QUANT_TOL_M if quantize else 4e-6)
    assert times[0] == 0.0


def test_keyframes_are_frames_over_fps():
    T, fps = 50, 24.0
    p = Player(write_glb([make_garment(T)], make_body(T), fps=fps, normals=False))
    anim = p.animation()
    body_sampler = next(anim.samplers[c.sampler] for c in anim.channels if c.target.path == "rotation")
    times = p.accessor(body_sampler.input)[:, 0]
    np.testing.assert_allclose(times, np.arange(T) / fps, rtol=1e-7)
    weights = next(anim.samplers[c.sampler] for c in anim.channels if c.target.path == "weights")
    assert weights.interpolation == "LINEAR"
    assert len(p.accessor(weights.input)) == T  # 49 targets: one chunk
    out = p.accessor(weights.output).reshape(T, T - 1)
    np.testing.assert_array_equal(out[1:], np.eye(T - 1))
    np.testing.assert_array_equal(out[0], 0)


def test_uvs_are_flipped_to_gltf_convention():
    g = make_garment(2)
    p = Player(write_glb([g], quantize=True))
    prim = p.gltf.meshes[0].primitives[0]
    _, uvmap, _ = split_uv_seams(g.faces, g.face_uvs)
    uv = p.accessor(prim.attributes.TEXCOORD_0)
    np.testing.assert_allclose(uv[:, 0], g.uvs[uvmap, 0], atol=1 / 65535)
    np.testing.assert_allclose(uv[:, 1], 1.0 - g.uvs[uvmap, 1], atol=1 / 65535)


def test_vertex_normals_match_naive_sum_over_faces():
    g = make_garment(3, n_around=7, n_rows=4)
    fast = vertex_normals(g.vertices, g.faces)
    for t in range(3):
        naive = np.zeros((g.vertices.shape[1], 3))
        for f in g.faces:  # area-weighted: sum of the unnormalised face normals
            a, b, c = g.vertices[t, f].astype(np.float64)
            naive[f] += np.cross(b - a, c - a)
        naive /= np.linalg.norm(naive, axis=1, keepdims=True)
        np.testing.assert_allclose(fast[t], naive, atol=1e-6)
    lonely = np.concatenate([g.vertices, np.zeros((3, 1, 3), np.float32)], axis=1)  # a vertex on no face
    assert (vertex_normals(lonely, g.faces)[:, -1] == 0).all()
    assert (vertex_normals(lonely, g.faces, fallback=(0.0, 1.0, 0.0))[:, -1] == [0.0, 1.0, 0.0]).all()
    assert vertex_normals(lonely[None], g.faces).shape == (1,) + lonely.shape  # any leading axes


def test_normals_are_unit_and_follow_the_motion():
    g = make_garment(30)
    p = Player(write_glb([g], normals=True))
    node = p.node_index("tube_morph0")
    prim = p.gltf.meshes[p.gltf.nodes[node].mesh].primitives[0]
    n0 = p.accessor(prim.attributes.NORMAL)
    np.testing.assert_allclose(np.linalg.norm(n0, axis=1), 1.0, atol=1e-4)  # normalized SHORT
    # the tube's normals are radial: at frame 20 the garment turned by 0.6 rad about Z (Y in glTF)
    n20 = visible_normals(p, "tube", 20)
    pos20 = expected_garment(g, 20)
    radial = pos20 - pos20.mean(0)
    radial[:, 1] = 0
    cos = np.abs(np.sum(n20 * radial, 1)) / np.linalg.norm(radial, axis=1)
    assert np.median(cos) > 0.99


def visible_normals(p: Player, name: str, t: int, fps: float = 30.0) -> np.ndarray:
    """Decoded, renormalised normals of the garment's visible chunk at frame t (glTF Y-up)."""
    group = p.gltf.nodes[p.node_index(name)]
    time = float(np.float32(t / fps))
    (node,) = [c for c in group.children if np.any(p.trs(c, time)["scale"] != 0)]
    prim = p.gltf.meshes[p.gltf.nodes[node].mesh].primitives[0]
    n = p.accessor(prim.attributes.NORMAL)
    for k, w in enumerate(p.trs(node, time)["weights"] if prim.targets else []):
        if w != 0:
            n = n + w * p.accessor(prim.targets[k]["NORMAL"])
    n = n @ p.world_matrix(node, time)[:3, :3].T  # the node turns with the garment (uniform scale)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def test_quantized_normals_match_every_frame_of_a_turning_garment():
    """BYTE deltas hold [-1, 1]: chunks split so that a garment turning 0.9 rad/s keeps every
    frame's normals within half a degree of the input's."""
    T = 300
    g = make_garment(T)
    p = Player(write_glb([g]))
    vmap, _, _ = split_uv_seams(g.faces, g.face_uvs)
    expected = vertex_normals(zup_to_yup(g.vertices), g.faces)[:, vmap]
    worst = 0.0
    for t in range(0, T, 7):
        cos = np.sum(visible_normals(p, "tube", t) * expected[t], axis=1)
        worst = max(worst, float(np.degrees(np.arccos(np.clip(cos, -1, 1))).max()))
    assert worst < 0.5, worst


def test_split_for_normals_halves_only_where_needed():
    T, N = 65, 1000
    n = np.zeros((T, N, 3))
    n[..., 2] = 1.0
    X = np.random.default_rng(0).normal(size=(T, N, 3))
    assert split_for_normals([(0, 64)], X, n, rotate=False) == [(0, 64)]
    n[40:, :3, :] = [0.0, 0.0, -1.0]  # 3 of 1000 vertices flip (0.3 %: under NORMAL_CLIP_SHARE): kept, clipped
    assert split_for_normals([(0, 64)], X, n, rotate=False) == [(0, 64)]
    n = np.concatenate([n, n[-1:].repeat(64, axis=0)])  # 129 frames
    n[40:] = [0.0, 0.0, -1.0]  # all flip at frame 40: halved where it clips, down to NORMAL_MIN_CHUNK targets
    ranges = split_for_normals([(0, 128)], np.zeros((129, N, 3)), n, rotate=False)
    assert NORMAL_MIN_CHUNK == 8 and ranges == [(0, 32), (32, 40), (40, 48), (48, 64), (64, 128)]
    assert [clipped_share(n[s_:e + 1]) > NORMAL_CLIP_SHARE for s_, e in ranges] == [False, True, False, False, False]  # float deltas


def test_chunk_rotations_recover_a_turn():
    X0 = np.random.default_rng(1).normal(size=(50, 3))
    R = axis_angle_to_matrix(np.array([[0.0, 0.0, 0.0], [0.0, 1.2, 0.0], [0.3, -2.0, 0.5]]))
    X = np.einsum("kij,vj->kvi", R, X0) + np.array([[[0, 0, 0]], [[1.0, 2, 3]], [[-1.0, 0, 0.5]]])
    np.testing.assert_allclose(chunk_rotations(X), R, atol=1e-9)


def test_materials_floor_and_scene_frame_range():
    T = 12
    g = replace(make_garment(T), appearance=SHEEN)
    body = make_body(T)
    p = Player(write_glb([g], body, floor_z=-0.8))
    materials = {m.name: m for m in p.gltf.materials}
    tube = materials["tube"]
    assert tube.pbrMetallicRoughness.baseColorFactor == SHEEN["base_color"] + [1.0]
    assert tube.pbrMetallicRoughness.metallicFactor == 0.0 and tube.doubleSided
    assert tube.extensions["KHR_materials_sheen"]["sheenColorFactor"] == SHEEN["sheen_color"]
    assert materials["body"].pbrMetallicRoughness.metallicFactor == 0.0
    assert "KHR_materials_sheen" in p.gltf.extensionsUsed
    # one root lifts everything by 0.8 m: the garment's world positions are the input's + 0.8 in y
    root, skinned = p.gltf.scenes[0].nodes
    assert p.gltf.nodes[root].name == "tryon" and p.gltf.nodes[root].translation == [0.0, 0.8, 0.0]
    assert p.gltf.nodes[skinned].name == "body"  # a skinned mesh's node is a root; its skeleton is lifted
    lifted = p.skinned_positions(skinned, 0.0)
    plain = Player(write_glb([g], body))
    np.testing.assert_allclose(lifted, plain.skinned_positions(plain.node_index("body"), 0.0) + [0.0, 0.8, 0.0], atol=1e-5)
    got, _ = garment_frame(p, "tube", 0.0)
    np.testing.assert_allclose(got, expected_garment(g, 0) + [0.0, 0.8, 0.0], atol=QUANT_TOL_M)
    assert p.gltf.scenes[0].extras == {"fps": 30.0, "frame_start": 0, "frame_end": T - 1, "frames": T}
    body_prim = p.gltf.meshes[p.gltf.nodes[p.node_index("body")].mesh].primitives[0]
    n = p.accessor(body_prim.attributes.NORMAL)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-4)


def test_bad_appearance_is_refused():
    g = make_garment(2)
    with pytest.raises(InputValueError):
        replace(g, appearance={"base_color": [2.0, 0.0, 0.0]})


# ----------------------------------------------------------------------------- skinning

@pytest.mark.parametrize("influences,bones", [(3, 3), (8, 6)])
def test_skinning_reproduces_numpy_lbs(influences, bones):
    T = 40
    body = make_body(T, num_bones=bones, influences=influences, uv=True)
    p = Player(write_glb([], body, fps=30.0))
    node = p.node_index("body")
    attrs = p.gltf.meshes[p.gltf.nodes[node].mesh].primitives[0].attributes
    assert (getattr(attrs, "JOINTS_1", None) is not None) == (influences > 4)
    sets = [a for a in (attrs.WEIGHTS_0, getattr(attrs, "WEIGHTS_1", None)) if a is not None]
    w = np.concatenate([p.accessor(a) for a in sets], 1)
    assert np.all(np.diff(w, axis=1) <= 0)  # sorted: JOINTS_0 holds the 4 largest
    np.testing.assert_allclose(w.sum(1), 1.0, atol=2e-7)
    vmap, _, _ = split_uv_seams(body.faces, body.face_uvs)
    expected = zup_to_yup(pose_body_vertices(body))[:, vmap]
    times = p.accessor(p.animation().samplers[0].input)[:, 0]
    for t in [0, 1, 17, T - 1]:
        got = p.skinned_positions(node, float(times[t]))
        np.testing.assert_allclose(got, expected[t], atol=SKIN_TOL_M)
    # without the animation (a still view) the body shows frame 0, like the garments
    np.testing.assert_allclose(p.skinned_positions(node, None), expected[0], atol=SKIN_TOL_M)


def test_four_influences_keep_the_largest_renormalised():
    """max_influences=4: what three.js plays (it reads JOINTS_0/WEIGHTS_0 and renormalises)."""
    body = make_body(8, num_bones=6, influences=8)
    p = Player(write_glb([], body, max_influences=4))
    node = p.node_index("body")
    assert getattr(p.gltf.meshes[p.gltf.nodes[node].mesh].primitives[0].attributes, "JOINTS_1", None) is None
    order = np.argsort(-body.skin_weights, axis=1)[:, :4]
    w4 = np.take_along_axis(body.skin_weights, order, 1)
    pruned = BodyTrack(body.rest_vertices, body.faces, np.take_along_axis(body.skin_indices, order, 1),
                       w4 / w4.sum(1, keepdims=True), body.parents, body.bone_names, body.rest_bone_poses,
                       body.bone_poses)
    expected = zup_to_yup(pose_body_vertices(pruned))
    times = p.accessor(p.animation().samplers[0].input)[:, 0]
    np.testing.assert_allclose(p.skinned_positions(node, float(times[5])), expected[5], atol=SKIN_TOL_M)
    assert np.abs(expected[5] - zup_to_yup(pose_body_vertices(body))[5]).max() > 1e-3  # pruning matters here


def test_bone_rotations_are_continuous():
    body = make_body(60)
    p = Player(write_glb([], body))
    anim = p.animation()
    for c in anim.channels:
        if c.target.path == "rotation":
            q = p.accessor(anim.samplers[c.sampler].output)
            assert np.all(np.sum(q[1:] * q[:-1], 1) > 0)


def test_body_and_garments_share_one_animation():
    T = 10
    p = Player(write_glb([make_garment(T, "a"), make_garment(T, "b", seed=3)], make_body(T), fps=30.0))
    assert len(p.gltf.animations) == 1
    paths = {c.target.path for c in p.animation().channels}
    assert paths == {"weights", "translation", "rotation"}
    roots = p.gltf.scenes[0].nodes
    assert {p.gltf.nodes[r].name for r in roots} == {"a", "b", "body", "body_skeleton"}


# ----------------------------------------------------------------------------- inputs

def test_rejects_inconsistent_inputs():
    with pytest.raises(InputValueError, match="same number of frames"):
        write_glb([make_garment(5)], make_body(6))
    with pytest.raises(InputValueError, match="unique"):
        write_glb([make_garment(5), make_garment(5)])
    with pytest.raises(InputValueError, match="nothing to export"):
        write_glb([])
    with pytest.raises(InputValueError, match="fps"):
        write_glb([make_garment(5)], fps=0.0)
    with pytest.raises(InputValueError, match="max_influences"):
        write_glb([make_garment(5)], max_influences=6)
    body = make_body(3)
    poses = body.bone_poses.copy()
    poses[..., :3, :3] *= 1.1
    with pytest.raises(InputValueError, match="rigid"):
        BodyTrack(body.rest_vertices, body.faces, body.skin_indices, body.skin_weights, body.parents,
                  body.bone_names, body.rest_bone_poses, poses)


# ----------------------------------------------------------------------------- meshopt compression

def canonical_triangles(indices: np.ndarray) -> np.ndarray:
    """Each triangle's corners rotated to start at its smallest index (winding kept)."""
    tri = indices.reshape(-1, 3)
    k = np.argmin(tri, axis=1)
    return np.stack([tri[np.arange(len(tri)), (k + j) % 3] for j in range(3)], axis=1)


def test_meshopt_views_decode_to_the_uncompressed_file(tmp_path):
    """Every EXT_meshopt_compression view decodes (meshoptimizer's own decoder) to the bytes of the
    same view in the uncompressed file; the file is smaller and validator-clean."""
    meshoptimizer = pytest.importorskip("meshoptimizer")
    T = 40
    tracks = [make_garment(T, "a"), make_garment(T, "b", seed=3)], make_body(T, num_bones=6, influences=8, uv=True)
    plain = Player(write_glb(*tracks, floor_z=-0.8))
    data = write_glb(*tracks, floor_z=-0.8, compression="meshopt")
    packed = Player(data)
    assert len(data) < 0.8 * len(plain.blob)
    assert "EXT_meshopt_compression" in packed.gltf.extensionsRequired
    assert len(packed.gltf.bufferViews) == len(plain.gltf.bufferViews)
    compressed = 0
    for i, (v, ref) in enumerate(zip(packed.gltf.bufferViews, plain.gltf.bufferViews)):
        want = plain.blob[ref.byteOffset or 0:(ref.byteOffset or 0) + ref.byteLength]
        ext = (v.extensions or {}).get("EXT_meshopt_compression")
        if ext is None:
            got = packed.blob[v.byteOffset or 0:(v.byteOffset or 0) + v.byteLength]
        else:
            compressed += 1
            stream = packed.blob[ext["byteOffset"]:ext["byteOffset"] + ext["byteLength"]]
            if ext["mode"] == "TRIANGLES":  # the codec may rotate a triangle's corners (same winding)
                dtype = np.uint16 if ext["byteStride"] == 2 else np.uint32
                decoded = np.asarray(meshoptimizer.decode_index_buffer(ext["count"], ext["byteStride"], stream))
                got = np.frombuffer(decoded.tobytes()[:ext["count"] * ext["byteStride"]], dtype)  # raw bytes, whatever the array type
                got, want = (canonical_triangles(x).tobytes() for x in (got, np.frombuffer(want, dtype)))
            else:
                got = np.asarray(meshoptimizer.decode_vertex_buffer(ext["count"], ext["byteStride"], stream)).tobytes()
        assert got == want, i
    assert compressed > len(plain.gltf.bufferViews) // 2
    report = run_validator(data, tmp_path)
    assert issues(report, 0) == [] and issues(report, 1) == []


def test_unknown_compression_is_refused():
    with pytest.raises(InputValueError):
        write_glb([make_garment(2)], compression="draco")
