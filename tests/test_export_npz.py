"""npz export: round trip without pickle, keys/dtypes/shapes, metadata JSON, posed body."""
from __future__ import annotations

import io
import json

import numpy as np
import pytest

from inference.errors import InputValueError
from inference.export.npz import AXES, read_npz, write_npz
from inference.export.tracks import BodyTrack, GarmentTrack, pose_body_vertices
from tests.test_export_glb import make_body, make_garment


def test_round_trip_keys_dtypes_shapes():
    T = 12
    tube = make_garment(T, "tube")
    plain = GarmentTrack("plain", tube.vertices[:, :10] + 1.0, np.array([[0, 1, 2], [2, 3, 4]]))  # no UVs
    body = make_body(T, num_bones=6, influences=8, uv=True)
    data = write_npz([tube, plain], body, fps=25.0, metadata={"model_versions": {"wrinkle": "1.2.0"}})

    with np.load(io.BytesIO(data), allow_pickle=False) as npz:  # what any client does
        files = set(npz.files)
        arrays = {k: npz[k] for k in npz.files}
    assert files == {
        "garment_0_vertices", "garment_0_faces", "garment_0_uvs", "garment_0_face_uvs",
        "garment_1_vertices", "garment_1_faces",
        "body_vertices", "body_faces", "body_uvs", "body_face_uvs", "fps", "metadata",
    }
    V = tube.vertices.shape[1]
    expected = {
        "garment_0_vertices": (np.float32, (T, V, 3)), "garment_0_faces": (np.int32, tube.faces.shape),
        "garment_0_uvs": (np.float32, tube.uvs.shape), "garment_0_face_uvs": (np.int32, tube.faces.shape),
        "garment_1_vertices": (np.float32, (T, 10, 3)), "garment_1_faces": (np.int32, (2, 3)),
        "body_vertices": (np.float32, (T, len(body.rest_vertices), 3)), "body_faces": (np.int32, body.faces.shape),
        "fps": (np.float32, ()),
    }
    for key, (dtype, shape) in expected.items():
        assert arrays[key].dtype == dtype, key
        assert arrays[key].shape == shape, key
    assert arrays["metadata"].shape == () and arrays["metadata"].dtype.kind == "U"

    out = read_npz(data)
    np.testing.assert_array_equal(out["garment_0_vertices"], tube.vertices)
    np.testing.assert_array_equal(out["garment_0_faces"], tube.faces)
    np.testing.assert_array_equal(out["garment_0_uvs"], tube.uvs)
    np.testing.assert_array_equal(out["garment_1_vertices"], plain.vertices)
    np.testing.assert_array_equal(out["body_vertices"], pose_body_vertices(body))
    assert out["fps"] == 25.0

    meta = out["metadata"]
    assert meta["units"] == "metres" and meta["axes"] == AXES and "Z-up" in meta["axes"]
    assert meta["fps"] == 25.0 and meta["num_frames"] == T and meta["has_body"] is True
    assert [g["name"] for g in meta["garments"]] == ["tube", "plain"]
    assert [g["index"] for g in meta["garments"]] == [0, 1]
    assert meta["garments"][0]["id"] == "tube" and meta["garments"][0]["size"] == "M"
    assert meta["model_versions"] == {"wrinkle": "1.2.0"}
    json.dumps(meta)


def test_compressed_round_trip_is_equal():
    g = make_garment(5)
    a, b = read_npz(write_npz([g])), read_npz(write_npz([g], compress=True))
    assert a.keys() == b.keys()
    for key in a:
        if key != "metadata":
            np.testing.assert_array_equal(a[key], b[key])
    assert "body_vertices" not in a and a["metadata"]["has_body"] is False


def test_body_vertices_hand_computed():
    # Two bones; bone 1 (head at x = 1) turns 90 degrees about Z in frame 1.
    # Vertex (2, 0, 0) weighted 0.5/0.5: bone 0 keeps it, bone 1 moves it to (1, 1, 0).
    rest = np.tile(np.eye(4, dtype=np.float32), (2, 1, 1))
    rest[1, 0, 3] = 1.0
    poses = np.tile(rest, (2, 1, 1, 1))
    poses[1, 1, :3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    body = BodyTrack(np.array([[2.0, 0, 0], [0, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]]),
                     np.array([[0, 1], [0, 1], [0, 1]]), np.array([[0.5, 0.5], [1, 0], [1, 0]], np.float32),
                     np.array([-1, 0]), ["root", "arm"], rest, poses)
    out = read_npz(write_npz([], body))
    np.testing.assert_allclose(out["body_vertices"][0], body.rest_vertices, atol=1e-7)
    np.testing.assert_allclose(out["body_vertices"][1, 0], [1.5, 0.5, 0.0], atol=1e-7)


def test_pose_body_vertices_matches_naive_lbs():
    body = make_body(70, num_bones=6, influences=5)  # 70 frames: several frame blocks
    fast = pose_body_vertices(body)
    X = body.bone_poses.astype(np.float64) @ np.linalg.inv(body.rest_bone_poses.astype(np.float64))
    v = np.concatenate([body.rest_vertices, np.ones((len(body.rest_vertices), 1))], 1)
    naive = np.zeros(fast.shape)
    for k in range(body.skin_indices.shape[1]):  # posed v = sum_k w_vk X[t, j_vk] v
        M = X[:, body.skin_indices[:, k]]  # (T, V, 4, 4)
        naive += body.skin_weights[None, :, k, None] * np.einsum("tvij,vj->tvi", M, v)[..., :3]
    np.testing.assert_allclose(fast, naive, atol=1e-5)


def test_rejects_bad_inputs():
    g = make_garment(4)
    with pytest.raises(InputValueError, match="reserved"):
        write_npz([g], metadata={"units": "inches"})
    with pytest.raises(InputValueError, match="JSON"):
        write_npz([g], metadata={"bad": object()})
    with pytest.raises(InputValueError, match="same number of frames"):
        write_npz([g, make_garment(5, "other")])
    with pytest.raises(InputValueError, match="NaN"):
        GarmentTrack("nan", np.full((2, 3, 3), np.nan, np.float32), np.array([[0, 1, 2]]))
    with pytest.raises(InputValueError, match="indices"):
        GarmentTrack("oob", np.zeros((2, 3, 3), np.float32), np.array([[0, 1, 3]]))
