"""NPZ export of a try-on sequence: plain float32/int32 arrays + a JSON metadata string.

Axes and units as the anny body model: metres, Z-up right-handed (no conversion, unlike glb).
Every array loads with ``np.load(io.BytesIO(data), allow_pickle=False)``:

  garment_{i}_vertices : (T, V_i, 3) float32, metres, posed per frame
  garment_{i}_faces    : (F_i, 3) int32
  garment_{i}_uvs      : (Vt_i, 2) float32, OBJ convention (v up)       [when the garment has UVs]
  garment_{i}_face_uvs : (F_i, 3) int32, indices into garment_{i}_uvs   [when the garment has UVs]
  body_vertices        : (T, Vb, 3) float32, metres, posed by LBS       [when a body is given]
  body_faces           : (Fb, 3) int32                                  [when a body is given]
  body_uvs, body_face_uvs                                               [when the body has UVs]
  fps                  : () float32, frames per second
  metadata             : () unicode, JSON: format, units, axes, fps, num_frames, garments (index,
                         name and each garment's metadata, in order), has_body, and the caller's
                         metadata (model versions, request id, ...)

Uncompressed by default (``np.savez``): zip deflate saves little on float vertex data (12 % on
noisy vertices, 17 % on the posed body, 38 % on a smooth synthetic garment) and is 40-100x slower
(300 frames, 5k-vertex garment: ~10 ms vs ~0.7 s; bench/bench_export.py);
``compress=True`` switches to ``np.savez_compressed``.
"""
from __future__ import annotations

import io
import json
from collections.abc import Sequence

import numpy as np

from inference.errors import InputValueError
from inference.export.tracks import BodyTrack, GarmentTrack, pose_body_vertices

FORMAT = "tryon-npz"
FORMAT_VERSION = 1
UNITS = "metres"
AXES = "Z-up right-handed, as the anny body model"
UV_CONVENTION = "OBJ: origin at the texture's bottom-left, v up"
_RESERVED = ("format", "format_version", "units", "axes", "uv_convention", "fps", "num_frames", "garments", "has_body")


def write_npz(garments: Sequence[GarmentTrack], body: BodyTrack | None = None, fps: float = 30.0,
              metadata: dict | None = None, *, compress: bool = False) -> bytes:
    """A try-on sequence as an .npz archive (keys in the module docstring).

    garments : GarmentTrack each with (T, V_i, 3) vertices, Z-up metres; same T for all
    body     : BodyTrack with T frames, or None; written posed (LBS), not as a rig
    fps      : frames per second
    metadata : JSON-serialisable dict merged into the metadata JSON (model versions, ids);
               its keys must not be one of the reserved ones listed in ``_RESERVED``
    compress : zip deflate (12-38 % smaller, 40-100x slower)
    returns  : the .npz file's bytes
    """
    if not garments and body is None:
        raise InputValueError("garments", "nothing to export: no garment and no body")
    if not np.isfinite(fps) or fps <= 0:
        raise InputValueError("fps", f"must be > 0, got {fps}")
    frame_counts = {g.num_frames for g in garments} | ({body.num_frames} if body is not None else set())
    if len(frame_counts) != 1:
        raise InputValueError("garments", f"all tracks need the same number of frames, got {sorted(frame_counts)}")
    clash = sorted(set(metadata or {}) & set(_RESERVED))
    if clash:
        raise InputValueError("metadata", f"reserved keys cannot be overridden: {clash}")

    arrays: dict[str, np.ndarray] = {}
    for i, g in enumerate(garments):
        arrays[f"garment_{i}_vertices"] = g.vertices
        arrays[f"garment_{i}_faces"] = g.faces
        if g.uvs is not None:
            arrays[f"garment_{i}_uvs"] = g.uvs
            arrays[f"garment_{i}_face_uvs"] = g.face_uvs
    if body is not None:
        arrays["body_vertices"] = pose_body_vertices(body)
        arrays["body_faces"] = body.faces
        if body.uvs is not None:
            arrays["body_uvs"] = body.uvs
            arrays["body_face_uvs"] = body.face_uvs
    arrays["fps"] = np.array(fps, np.float32)
    info = {
        "format": FORMAT, "format_version": FORMAT_VERSION, "units": UNITS, "axes": AXES,
        "uv_convention": UV_CONVENTION, "fps": float(fps), "num_frames": frame_counts.pop(),
        "garments": [{"index": i, "name": g.name, **g.metadata} for i, g in enumerate(garments)],
        "has_body": body is not None, **(metadata or {}),
    }
    try:
        arrays["metadata"] = np.array(json.dumps(info, allow_nan=False))  # 0-d '<U' array, no pickle
    except (TypeError, ValueError) as exc:
        raise InputValueError("metadata", f"must be JSON-serialisable: {exc}") from exc
    out = io.BytesIO()
    (np.savez_compressed if compress else np.savez)(out, **arrays)
    return out.getvalue()


def read_npz(data: bytes) -> dict:
    """Loads what ``write_npz`` wrote, without pickle.

    returns : {key: array} for every array, except "fps" (float) and "metadata" (dict, parsed JSON)
    """
    with np.load(io.BytesIO(data), allow_pickle=False) as npz:
        out = {key: npz[key] for key in npz.files}
    out["fps"] = float(out["fps"])
    out["metadata"] = json.loads(str(out["metadata"]))
    return out
