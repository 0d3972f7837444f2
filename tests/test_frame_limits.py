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


def test_jobs_count_bvh_and_amc_frames_from_their_headers_before_the_202(client, settings):
    """A BVH that declares more frames than a job may have (and an AMC with too many frame lines)
    is refused before the 202, not after minutes in the queue."""
    frames = settings.job_max_frames * 2 + 1
    bvh = ("HIERARCHY\nROOT Hips\n{\n  OFFSET 0 0 0\n  CHANNELS 3 Xrotation Yrotation Zrotation\n  End Site\n  {\n    OFFSET 0 1 0\n  }\n}\n"
           f"MOTION\nFrames: {frames}\nFrame Time: 0.0333333\n" + "0 0 0\n" * 3)
    body = {"garments": [{"id": "tshirt"}], "format": "npz", "options": {"include_body": False}}
    r = client.post("/v1/jobs", json={**body, "motion": {"type": "bvh", "bvh": bvh}})
    assert r.status_code == 422 and r.json()["errors"][0]["pointer"] == "/motion/bvh" and "exceed the limit" in r.text, r.text
    amc = ":FULLY-SPECIFIED\n:DEGREES\n" + "".join(f"{i}\nroot 0 0 0 0 0 0\n" for i in range(1, frames + 1))
    r = client.post("/v1/jobs", json={**body, "motion": {"type": "asf_amc", "asf": ":version 1.10\n", "amc": amc, "fps": 30.0}})
    assert r.status_code == 422 and r.json()["errors"][0]["pointer"] == "/motion/amc", r.text
    assert client.get("/readyz").json()["queue_depth"] == 0


def test_header_frame_counts():
    from inference.motion.asfamc import amc_frames
    from inference.motion.bvh import bvh_frames

    assert bvh_frames("HIERARCHY\nMOTION\nFrames: 12\nFrame Time: 0.008333\n1 2 3\n") == (12, 1 / 0.008333)
    assert bvh_frames("HIERARCHY\nno motion") is None
    assert amc_frames(":DEGREES\n1\nroot 0 0 0\n2\nroot 1 1 1\n") == 2
