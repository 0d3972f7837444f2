"""The output frame count is checked before any resampling or retargeting (audit D1): a tiny
request whose frame rates would build millions of frames is refused at once, naming the field."""
from __future__ import annotations

import time

import pytest

from inference.motion.resample import resample_times, resampled_frame_count


def test_resampled_frame_count_matches_resample_times():
    for n, fin, fout in [(1, 30, 30), (2, 30, 30), (86, 30, 60), (300, 120, 30), (7, 24, 30)]:
        assert resampled_frame_count(n, fin, fout) == len(resample_times(n, fin, fout))
    assert resampled_frame_count(2, 1e-300, 120) == 2**62  # saturates instead of overflowing
    with pytest.raises(ValueError):
        resampled_frame_count(2, 0.0, 30)


def _poses(fps: float, frames: int = 2) -> dict:
    return {"body": {}, "garments": [{"id": "tshirt"}], "format": "npz", "options": {"fps": 120, "include_body": False},
            "motion": {"type": "poses", "fps": fps, "rotations": [[[0.0, 0.0, 0.0]] * 31] * frames, "translation": [[0.0, 0.0, 1.0]] * frames}}


@pytest.mark.parametrize("fps", [1e-5, 1e-300])
def test_slow_poses_are_refused_before_resampling(client, fps):
    t0 = time.perf_counter()
    r = client.post("/v1/drape", json=_poses(fps))
    elapsed = time.perf_counter() - t0
    assert r.status_code == 422, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    assert "motion/fps" in r.text and "exceed the limit" in r.text
    assert elapsed < 5.0  # no multi-million-frame arrays were built (a generous bound, not a timing test)


def test_jobs_refuse_the_same_request_before_the_202(client):
    r = client.post("/v1/jobs", json=_poses(1e-5))
    assert r.status_code == 422, r.text


def test_slow_bvh_is_refused_before_retargeting(client):
    joint = "HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation\n End Site\n {\n  OFFSET 0 1 0\n }\n}\n"
    motion = "MOTION\nFrames: 40\nFrame Time: 10\n" + "0 0 0 0 0 0\n" * 40
    body = {"body": {}, "garments": [{"id": "tshirt"}], "options": {"fps": 120}, "motion": {"type": "bvh", "bvh": joint + motion}}
    r = client.post("/v1/drape", json=body)
    assert r.status_code == 422, r.text
    assert "exceed the limit" in r.text
