"""The headless renderer (training.render) and the contact sheet's layout (training.contact_sheet)."""
from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest

from training.contact_sheet import SheetRow, facing_yaw_rad, moment_indices, render_sheet
from training.render import (AMBIENT, RenderInputError, camera_axes, encode_png, rasterize, render, tile, write_png)

RGB = (0.2, 0.4, 0.6)
UPRIGHT = np.array([[-1.0, 0.0, -1.0], [1.0, 0.0, -1.0], [0.0, 0.0, 1.0]])  # in the XZ plane, facing the front camera
ONE_TRI = np.array([[0, 1, 2]])


def _u8(rgb) -> np.ndarray:
    return np.round(np.asarray(rgb) * 255).astype(np.uint8)


def test_camera_axes_hand_checked():
    front = camera_axes("front")
    np.testing.assert_allclose(front, [[1, 0, 0], [0, 0, 1], [0, 1, 0]], atol=1e-12)  # right +X, up +Z, looking +Y
    np.testing.assert_allclose(camera_axes("back"), [[-1, 0, 0], [0, 0, 1], [0, -1, 0]], atol=1e-12)
    np.testing.assert_allclose(camera_axes("front", np.pi / 2), camera_axes("left"), atol=1e-12)
    with pytest.raises(RenderInputError):
        camera_axes("top")


def test_front_view_faces_the_body():
    """The body asset's toes point to -Y and its left is +X: 'front' sees the toes nearer than the
    ankles, and the body's left arm on the image's right."""
    from inference.body import NEUTRAL_PHENOTYPES, BodyModel

    body = BodyModel.load()
    heads = body.shape(NEUTRAL_PHENOTYPES[None]).bone_heads[0]
    axes = camera_axes("front")
    toe, ankle = heads[body.bone_names.index("LeftToeBase")], heads[body.bone_names.index("LeftFoot")]
    assert toe @ axes[2] < ankle @ axes[2] - 0.05
    assert heads[body.bone_names.index("LeftArm")] @ axes[0] > 0.1 > -0.1 > heads[body.bone_names.index("RightArm")] @ axes[0]


def test_single_triangle_centre_and_corners():
    image = render([(UPRIGHT, ONE_TRI, RGB)], "front", (32, 48))
    assert image.shape == (48, 32, 3) and image.dtype == np.uint8
    np.testing.assert_array_equal(image[24, 16], _u8(RGB))  # normal along the view: fully lit
    for corner in (image[0, 0], image[0, -1], image[-1, 0], image[-1, -1]):
        np.testing.assert_array_equal(corner, [255, 255, 255])


def test_lambert_two_sided_hand_checked():
    """A triangle turned 60 degrees away from the camera: |cos 60| = 0.5, lit ambient + (1 - ambient) 0.5,
    whichever way its winding faces."""
    c, s = np.cos(np.pi / 3), np.sin(np.pi / 3)
    turned = UPRIGHT @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]]).T  # about +Z
    expected = _u8(np.asarray(RGB) * (AMBIENT + (1 - AMBIENT) * 0.5))
    for faces in (ONE_TRI, ONE_TRI[:, ::-1]):
        image = render([(turned, faces, RGB)], "front", (32, 48))
        np.testing.assert_array_equal(image[24, 16], expected)


def test_zbuffer_nearer_triangle_wins_in_any_order():
    near = (UPRIGHT, ONE_TRI, (1.0, 0.0, 0.0))
    far = (UPRIGHT * [1.5, 1, 1.5] + [0, 1.0, 0], ONE_TRI, (0.0, 0.0, 1.0))  # larger, behind (+Y)
    for meshes in ([near, far], [far, near]):
        front = render(meshes, "front", (40, 40))
        np.testing.assert_array_equal(front[22, 20], [255, 0, 0])
        back = render(meshes, "back", (40, 40))
        np.testing.assert_array_equal(back[22, 20], [0, 0, 255])


def test_rasterize_square_has_no_cracks():
    """Two triangles sharing a diagonal over pixel centres 1.5 .. 4.5: each of the 16 pixels drawn once."""
    xy = np.array([[1.0, 1.0], [5.0, 1.0], [5.0, 5.0], [1.0, 5.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    face_id, zbuf = rasterize(xy, np.array([1.0, 1.0, 2.0, 2.0]), faces, (8, 6))
    inside = face_id >= 0
    assert inside.sum() == 16 and inside[1:5, 1:5].all()
    assert set(np.unique(face_id[inside])) == {0, 1}
    np.testing.assert_allclose(zbuf[1, 1:5], 1.0 + np.array([0.5, 0.5, 0.5, 0.5]) / 4)  # z interpolated along y
    assert np.isinf(zbuf[~inside]).all()


def test_front_and_back_are_mirrored():
    """An asymmetric flat mesh: the back view is the front view mirrored left-right (same scale);
    an asymmetric solid (tetrahedron): the silhouettes are mirrored, the images are not symmetric."""
    flat = np.array([[-0.3, 0.0, -1.0], [1.1, 0.0, -0.7], [0.2, 0.0, 1.3], [0.9, 0.0, 1.0]])
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    front = render([(flat, faces, RGB)], "front", (40, 60), px_per_m=15.3)
    back = render([(flat, faces, RGB)], "back", (40, 60), px_per_m=15.3)
    np.testing.assert_array_equal(back, front[:, ::-1])
    assert not np.array_equal(front, front[:, ::-1])

    tet = np.array([[0.0, 0.0, 0.0], [1.0, 0.1, 0.0], [0.2, 1.0, 0.1], [0.3, 0.2, 1.2]])
    tet_faces = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    f = render([(tet, tet_faces, RGB)], "front", (40, 60), px_per_m=30.7)
    b = render([(tet, tet_faces, RGB)], "back", (40, 60), px_per_m=30.7)
    np.testing.assert_array_equal((f != 255).any(-1), (b != 255).any(-1)[:, ::-1])
    assert not np.array_equal(f, f[:, ::-1])


def test_render_rejects_bad_meshes():
    with pytest.raises(RenderInputError):
        render([], "front")
    with pytest.raises(RenderInputError):
        render([(UPRIGHT[:, :2], ONE_TRI, RGB)], "front")
    with pytest.raises(RenderInputError):
        render([(UPRIGHT, ONE_TRI + 1, RGB)], "front")


def _random_image(h: int = 7, w: int = 5) -> np.ndarray:
    return np.random.default_rng(0).integers(0, 256, (h, w, 3), dtype=np.uint8)


def test_encode_png_round_trip_without_pillow():
    image = _random_image()
    data = encode_png(image)
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    length, tag = struct.unpack(">I4s", data[8:16])
    assert (length, tag) == (13, b"IHDR")
    w, h, depth, colour = struct.unpack(">IIBB", data[16:26])
    assert (w, h, depth, colour) == (5, 7, 8, 2)
    (idat_len,) = struct.unpack(">I", data[33:37])
    assert data[37:41] == b"IDAT" and data.endswith(b"IEND\xaeB`\x82")
    raw = np.frombuffer(zlib.decompress(data[41:41 + idat_len]), np.uint8).reshape(7, 1 + 5 * 3)
    assert (raw[:, 0] == 0).all()
    np.testing.assert_array_equal(raw[:, 1:].reshape(7, 5, 3), image)


def test_write_png_round_trip(tmp_path):
    image = _random_image()
    path = write_png(tmp_path / "sub" / "x.png", image)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert struct.unpack(">II", path.read_bytes()[16:24]) == (5, 7)
    Image = pytest.importorskip("PIL.Image")
    np.testing.assert_array_equal(np.asarray(Image.open(path).convert("RGB")), image)
    flat = np.zeros((6, 4, 3), np.uint8)
    flat[:, 2:] = (200, 100, 50)  # two colours: the palette keeps them exactly
    np.testing.assert_array_equal(np.asarray(Image.open(write_png(tmp_path / "p.png", flat, palette=True)).convert("RGB")), flat)


def test_tile_layout():
    images = [np.full((4, 6, 3), 10 * k, np.uint8) for k in range(5)]
    sheet = tile(images, 2, 3)
    assert sheet.shape == (8, 18, 3)
    np.testing.assert_array_equal(sheet[4:8, 6:12], images[4])  # row-major: image 4 at row 1, column 1
    assert (sheet[4:8, 12:18] == 255).all()  # the missing cell is background
    with pytest.raises(RenderInputError):
        tile(images, 2, 2)
    pytest.importorskip("PIL")
    assert tile(images, 2, 3, labels=list("abcde")).shape == (8, 18, 3)
    assert tile(images, 2, 3, title="t").shape[0] > 8


def test_render_sheet_layout_rows_bodies_columns_moment_view():
    """2 bodies x 2 moments x (front, back) on tiny meshes: a (2 H, 4 W) sheet, tiles in that order."""
    tet = np.array([[0.0, 0.0, 0.0], [1.0, 0.1, 0.0], [0.2, 1.0, 0.1], [0.3, 0.2, 1.2]])
    tet_faces = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    shirt = UPRIGHT * 0.3 + [0.3, -0.5, 0.5]  # in front of the body
    rows = [SheetRow(name, np.array([3, 9]), 30.0, np.stack([tet * s, tet * s]), [np.stack([shirt, shirt])], np.zeros(2))
            for name, s in (("a", 1.0), ("b", 1.5))]
    W, H = 16, 24
    sheet, seconds = render_sheet(rows, tet_faces, [ONE_TRI], (W, H), supersample=1)
    assert sheet.shape[1:] == (4 * W, 3) and sheet.shape[0] == 2 * H
    assert seconds >= 0
    # the same scale everywhere: body b (1.5x) covers more pixels than body a in the same view
    ink = lambda r, c: int((sheet[r * H:(r + 1) * H, c * W:(c + 1) * W] != 255).any(-1).sum())
    assert ink(1, 0) > ink(0, 0)


def test_moment_indices_and_facing_yaw():
    np.testing.assert_array_equal(moment_indices(688, 3), [137, 344, 550])
    np.testing.assert_array_equal(moment_indices(2, 3), [0, 1])
    np.testing.assert_array_equal(moment_indices(11, 1), [5])
    np.testing.assert_array_equal(moment_indices(4, 3), [0, 2, 3])  # 20-80 % of 4 frames holds only 2
    rest = np.random.default_rng(1).normal(size=(50, 3))
    angles = np.array([0.0, 0.7, -2.5, np.pi - 0.01])
    c, s = np.cos(angles), np.sin(angles)
    R = np.stack([np.stack([c, -s, 0 * c], -1), np.stack([s, c, 0 * c], -1), np.broadcast_to([0.0, 0.0, 1.0], (4, 3))], -2)
    posed = np.einsum("tij,nj->tni", R, rest) + [0.4, -2.0, 0.1]
    np.testing.assert_allclose(facing_yaw_rad(rest, posed), angles, atol=1e-9)


def test_rasterize_matches_a_naive_loop():
    """Random overlapping triangles: the chunked rasteriser against a per-pixel, per-triangle loop."""
    rng = np.random.default_rng(2)
    W, H, F = 24, 16, 30
    xy = rng.uniform([-4, -4], [W + 4, H + 4], (3 * F, 2))
    depth = rng.uniform(0, 1, 3 * F)
    faces = np.arange(3 * F).reshape(F, 3)
    face_id, zbuf = rasterize(xy, depth, faces, (W, H))
    naive_id, naive_z = np.full((H, W), -1), np.full((H, W), np.inf)
    for y in range(H):
        for x in range(W):
            for f, (i, j, k) in enumerate(faces):
                a, b, c = xy[i], xy[j], xy[k]
                d = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
                q = (x + 0.5 - a[0], y + 0.5 - a[1])
                u = (q[0] * (c[1] - a[1]) - q[1] * (c[0] - a[0])) / d
                v = ((b[0] - a[0]) * q[1] - (b[1] - a[1]) * q[0]) / d
                z = depth[i] + u * (depth[j] - depth[i]) + v * (depth[k] - depth[i])
                if u >= 0 and v >= 0 and u + v <= 1 and z < naive_z[y, x]:
                    naive_id[y, x], naive_z[y, x] = f, z
    np.testing.assert_array_equal(face_id, naive_id)
    np.testing.assert_allclose(zbuf, naive_z)
