"""Bundled clips: index and files agree, loader, unknown ids, adaptation to other bodies."""
from __future__ import annotations

import functools
import json

import numpy as np
import pytest

from inference import rotations as rot
from inference.body import BodyModel, NEUTRAL_PHENOTYPES
from inference.errors import UnknownAssetError
from inference.motion.clips import DEFAULT_ASSETS_DIR, ClipLibrary, adapt_clip, load_clip, read_index
from inference.motion.descriptor import DESCRIPTOR_SIZE, motion_descriptor
from inference.motion.retarget import foot_heights, target_leg_length

REQUIRED = {"walk", "run", "jump", "dance", "a_pose", "turntable", "01_01"}


@functools.lru_cache(maxsize=1)
def body_model():
    return BodyModel.load()


def test_index_lists_the_required_clips_and_matches_the_files():
    entries = read_index()
    assert REQUIRED <= {e["id"] for e in entries}
    for e in entries:
        path = DEFAULT_ASSETS_DIR / "motions" / e["file"]
        assert path.stat().st_size < 400_000, e["id"]  # a few hundred KB at most
        c = load_clip(e["id"])
        assert c.rotations.shape == (e["frames"], 31, 3) and c.rotations.dtype == np.float32
        assert c.translation.shape == (e["frames"], 3) and c.translation.dtype == np.float32
        assert c.fps == e["fps"] == 30.0
        assert e["duration_s"] == pytest.approx((e["frames"] - 1) / 30.0, abs=1e-3)
        assert np.all(np.isfinite(c.rotations)) and np.all(np.isfinite(c.translation))
        assert e["licence"] and e["description"] and e["title"] and e["source"]
        assert e["test_only"] == (e["id"] == "01_01")
        np.testing.assert_allclose(c.phenotypes, NEUTRAL_PHENOTYPES)
    readme = (DEFAULT_ASSETS_DIR / "motions" / "README.md").read_text()
    assert "mocap.cs.cmu.edu" in readme and "NSF EIA-0196217" in readme
    index = json.loads((DEFAULT_ASSETS_DIR / "motions" / "index.json").read_text())
    assert "NSF EIA-0196217" in index["acknowledgement"]


def test_unknown_clip_ids_are_refused():
    for bad in ("nope", "../body/body", "walk.npz", ""):
        with pytest.raises(UnknownAssetError):
            load_clip(bad)
    lib = ClipLibrary()
    with pytest.raises(UnknownAssetError):
        lib.summary("nope")
    assert "01_01" in lib.ids() and "01_01" not in lib.ids(include_test_only=False)
    assert lib.summary("walk") == {
        k: v for k, v in next(e for e in read_index() if e["id"] == "walk").items() if k in ClipLibrary.SUMMARY_KEYS
    }
    assert lib.load("walk") is lib.load("walk")


def test_synthetic_clips():
    a = load_clip("a_pose")
    assert np.all(a.rotations == 0) and a.num_frames == 30
    assert np.allclose(a.translation[:, :2], 0) and np.ptp(a.translation[:, 2]) == 0
    body = body_model()
    shape = body.shape(NEUTRAL_PHENOTYPES[None])
    low = foot_heights(body, shape, a.rotations[None], a.translation[None])[0]
    np.testing.assert_allclose(low, 0.0, atol=1e-5)  # standing on z = 0
    t = load_clip("turntable")
    assert t.duration_s == pytest.approx(119 / 30)
    assert np.all(t.rotations[:, 1:] == 0)
    R = rot.axis_angle_to_matrix(t.rotations[:, 0].astype(np.float64))
    yaw = np.unwrap(np.arctan2(R[:, 1, 0], R[:, 0, 0]))
    np.testing.assert_allclose(np.diff(yaw), 2 * np.pi / 120, atol=1e-6)  # one turn, counter-clockwise
    np.testing.assert_allclose(R[:, 2, 2], 1.0, atol=1e-6)  # about the vertical only


@pytest.mark.parametrize("clip_id", ["walk", "jump"])
def test_adapt_clip_to_other_bodies(clip_id):
    body = body_model()
    clip = load_clip(clip_id)
    phen = np.stack([NEUTRAL_PHENOTYPES, [1, 1, 1, 1, 1, 1], [0, 0.77, 0, 0, 0, 0]]).astype(np.float32)
    shape = body.shape(phen)
    rotations, translation = adapt_clip(clip, body, shape)
    assert rotations.shape == (3, clip.num_frames, 31, 3) and translation.shape == (3, clip.num_frames, 3)
    assert rotations.dtype == np.float32 and translation.dtype == np.float32
    np.testing.assert_array_equal(rotations[1], clip.rotations)
    # The clip's own (neutral) body gets the stored clip back.
    np.testing.assert_allclose(translation[0], clip.translation, atol=1e-5)
    # Horizontal path scaled by the leg-length ratio.
    for b in (1, 2):
        ratio = target_leg_length(shape, b) / clip.leg_length_m
        np.testing.assert_allclose(translation[b, :, :2], ratio * clip.translation[:, :2], atol=1e-5)
    # Every body stands on z = 0: never below, touching it, and in contact as often as the
    # stored clip (within 2 cm).
    low = foot_heights(body, shape, rotations, translation)
    assert low.min() > -1e-4
    np.testing.assert_allclose(low.min(axis=1), 0.0, atol=1e-3)
    contact = np.mean(low < 0.02, axis=1)
    assert np.all(contact >= contact[0] - 0.15), contact
    # The descriptor runs on the adapted clips (training and inference share it).
    gamma = motion_descriptor(rotations, translation, clip.fps)
    assert gamma.shape == (3, clip.num_frames, DESCRIPTOR_SIZE) and np.all(np.isfinite(gamma))
