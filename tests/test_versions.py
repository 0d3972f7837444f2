"""Versions from content: the drape ETag follows the bytes of the shipped asset files (a retrained
model changes it with no version string to bump), and the output names the files it read."""
from __future__ import annotations

import io
import json
import os

import numpy as np
import pytest

from tests.conftest import REPO_ROOT

REQUEST = {"motion": {"type": "clip", "clip": "a_pose", "duration_s": 0.03}, "garments": [{"id": "tshirt"}], "format": "npz",
           "options": {"include_body": False, "fit": "learned", "dynamics": "none", "lift_arms": False}}


def _linked_assets(tmp_path, changed: str | None = None):
    """A copy of assets/ made of symlinks, except ``changed``, a real copy with one byte flipped
    in the middle (inside the ONNX weights: the model still loads)."""
    src = REPO_ROOT / "assets"
    for path in src.rglob("*"):
        if not path.is_file():
            continue
        rel = path.relative_to(src).as_posix()
        dst = tmp_path / rel
        dst.parent.mkdir(parents=True, exist_ok=True)
        if rel == changed:
            data = bytearray(path.read_bytes())
            data[len(data) // 2] ^= 1
            dst.write_bytes(bytes(data))
        else:
            os.symlink(path, dst)
    return tmp_path


def _drape(settings, assets):
    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.runtime import Runtime

    s = settings.model_copy(update={"assets_dir": assets, "worker_mode": "thread", "workers": 1, "jobs_backend": "off"})
    with TestClient(create_app(s, Runtime.load(s)), raise_server_exceptions=False) as c:
        r = c.post("/v1/drape", json=REQUEST)
        assert r.status_code == 200, r.text
        again = c.post("/v1/drape", json=REQUEST, headers={"if-none-match": r.headers["etag"]})
        assert again.status_code == 304
        return r


@pytest.mark.parametrize("changed", ["models/tshirt/fit.onnx"])
def test_one_byte_of_a_model_file_changes_the_etag(tmp_path, settings, changed):
    same = _drape(settings, _linked_assets(tmp_path / "same"))
    flipped = _drape(settings, _linked_assets(tmp_path / "flipped", changed))
    assert same.headers["etag"] != flipped.headers["etag"]
    meta = [json.loads(str(np.load(io.BytesIO(r.content), allow_pickle=False)["metadata"])) for r in (same, flipped)]
    assert meta[0]["assets_sha256"] != meta[1]["assets_sha256"]
    files = [m["asset_files_sha256"] for m in meta]
    assert set(files[0]) == {"body/body.npz", "body/hm08_helpers.npz", "motions/a_pose.npz", "garments/tshirt/garment.npz", changed}
    assert files[0][changed] != files[1][changed]
    assert {k: v for k, v in files[0].items() if k != changed} == {k: v for k, v in files[1].items() if k != changed}


def test_the_digest_skips_what_a_drape_never_reads_and_flags_a_stale_manifest(tmp_path):
    from inference.asset_digest import AssetDigest

    shipped = AssetDigest.of(REPO_ROOT / "assets")
    assert "manifest.json" not in shipped.files and "models/defaults.json" not in shipped.files
    assert not any(p.endswith(".glb") for p in shipped.files) and "models/tshirt/wrinkle.onnx" in shipped.files
    assert shipped.differs_from_manifest(REPO_ROOT / "assets" / "manifest.json") == []  # the shipped manifest is current
    flipped = AssetDigest.of(_linked_assets(tmp_path, "garments/dress/garment.json"))
    assert flipped.differs_from_manifest(tmp_path / "manifest.json") == ["garments/dress/garment.json"]
    assert flipped.combined != shipped.combined
