"""What the service holds in memory (body model, garment catalog, clips) and the drape job.

Requests are turned into pipeline inputs here (motion import, retargeting, resampling, frame
limits), run in worker threads with bounded concurrency and a bounded wait queue, and encoded
as glb or npz.
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass

import anyio
import numpy as np

from inference.body import NEUTRAL_PHENOTYPES, PHENOTYPE_LABELS, BodyModel, BodyShape
from inference.errors import InputValueError
from inference.export import BodyTrack, GarmentTrack, write_glb, write_npz
from inference.garment import GarmentCatalog
from inference.motion.bvh import parse_bvh
from inference.motion.clips import ClipLibrary, adapt_clip
from inference.motion.resample import resample_motion
from inference.motion.retarget import retarget
from inference.pipeline import DrapeOptions, PoseSequence, drape
from service.config import Settings
from service.errors import ProblemException
from service.schemas import BvhMotion, ClipMotion, DrapeRequest, PoseMotion

log = logging.getLogger(__name__)

# metres per BVH unit for the request's `units` (None: infer from the skeleton's size)
BVH_UNITS = {"auto": None, "metres": 1.0, "centimetres": 0.01, "inches": 0.0254, "cmu": 0.0254 / 0.45}
MODEL_VERSIONS = {"body": "anny-0.6.2-cmu_mb", "fit": "mhclo-retarget", "dynamics": "none", "guard": "plane-push-v1"}


@dataclass
class DrapeOutput:
    payload: bytes
    headers: dict[str, str]


class Runtime:
    def __init__(self, settings: Settings, body: BodyModel, catalog: GarmentCatalog, clips: ClipLibrary):
        self.settings = settings
        self.body = body
        self.catalog = catalog
        self.clips = clips
        self.neutral_shape: BodyShape = body.shape(NEUTRAL_PHENOTYPES[None])
        self._limiter = anyio.CapacityLimiter(settings.max_concurrent_drapes)
        self._waiting = 0

    @classmethod
    def load(cls, settings: Settings) -> "Runtime":
        t0 = time.perf_counter()
        body = BodyModel.load(settings.assets_dir / "body")
        catalog = GarmentCatalog.load(settings.assets_dir)
        clips = ClipLibrary(settings.assets_dir)
        runtime = cls(settings, body, catalog, clips)
        log.info("loaded assets in %.2f s", time.perf_counter() - t0)
        return runtime

    # ------------------------------------------------------------------ request -> pipeline
    def _phenotypes(self, request: DrapeRequest) -> np.ndarray:
        p = request.body.phenotypes
        return np.array([getattr(p, name) for name in PHENOTYPE_LABELS], np.float32)

    def _motion(self, request: DrapeRequest, shape: BodyShape) -> PoseSequence:
        """The request's motion on this body, at the requested fps, within the frame limit."""
        m, fps = request.motion, request.options.fps
        s = self.settings
        if isinstance(m, ClipMotion):
            clip = self.clips.load(m.clip)
            start = int(round(m.start_s * clip.fps))
            if start >= clip.num_frames:
                raise InputValueError("/body/motion/start_s", f"the clip lasts {clip.duration_s:.2f} s")
            stop = clip.num_frames
            if m.duration_s is not None:
                stop = min(stop, start + int(round(m.duration_s * clip.fps)) + 1)
            rotations, translation = adapt_clip(clip, self.body, shape)
            rotations, translation = rotations[0, start:stop], translation[0, start:stop]
            rotations, translation = resample_motion(rotations, translation, clip.fps, fps)
            if m.duration_s is None:  # to the end of the clip, within the limit
                rotations, translation = rotations[: s.max_frames], translation[: s.max_frames]
        elif isinstance(m, PoseMotion):
            if len(m.rotations) != len(m.translation):
                raise InputValueError("/body/motion/translation", f"{len(m.translation)} frames, rotations have {len(m.rotations)}")
            if len(m.rotations) > s.max_source_frames:
                raise InputValueError("/body/motion/rotations", f"at most {s.max_source_frames} frames")
            rotations = np.asarray(m.rotations, np.float32)
            translation = np.asarray(m.translation, np.float32)
            if np.abs(rotations).max() > 1e3 or np.abs(translation).max() > 1e4:
                raise InputValueError("/body/motion", "rotations must be within 1000 rad and translations within 10 km")
            rotations, translation = resample_motion(rotations, translation, m.fps, fps)
        else:
            assert isinstance(m, BvhMotion)
            if len(m.bvh.encode()) > s.max_bvh_bytes:
                raise InputValueError("/body/motion/bvh", f"BVH text exceeds {s.max_bvh_bytes} bytes")
            source = parse_bvh(m.bvh, unit_scale=BVH_UNITS[m.units], max_frames=s.max_source_frames)
            result = retarget(source, self.body, shape, fps=fps)
            rotations, translation = result.rotations, result.translation
        if len(rotations) > s.max_frames:
            raise InputValueError("/body/motion", f"{len(rotations)} frames at {fps:g} fps exceed the limit of {s.max_frames}; shorten the motion or lower options.fps")
        return PoseSequence(np.ascontiguousarray(rotations, np.float32), np.ascontiguousarray(translation, np.float32), fps)

    def run_drape(self, request: DrapeRequest) -> DrapeOutput:
        """The whole request, synchronously (called in a worker thread)."""
        t0 = time.perf_counter()
        ids = [g.id for g in request.garments]
        if len(ids) > self.settings.max_garments:
            raise InputValueError("/body/garments", f"at most {self.settings.max_garments} garments per request")
        if len(set(ids)) != len(ids):
            raise InputValueError("/body/garments", "a garment is listed twice")
        assets = []
        for i, gid in enumerate(ids):
            if gid not in self.catalog.ids():
                raise InputValueError(f"/body/garments/{i}/id", f"unknown garment {gid!r}; see GET /v1/garments")
            assets.append(self.catalog.get(gid))
        # Layer order: the catalog's default layer, then the request's order (stable).
        assets = [a for _, _, a in sorted((a.layer, i, a) for i, a in enumerate(assets))] if len(assets) > 1 else assets

        shape = self.body.shape(self._phenotypes(request)[None])
        motion = self._motion(request, shape)
        o = request.options
        options = DrapeOptions(fit=o.fit, dynamics=o.dynamics, guard=o.guard, margin_m=o.margin_m, layer_gap_m=o.layer_gap_m, include_body=o.include_body)
        result = drape(self.body, shape, motion, assets, options, neutral=self.neutral_shape)

        t_export = time.perf_counter()
        metadata = {
            "frames": motion.num_frames,
            "phenotypes": dict(zip(PHENOTYPE_LABELS, map(float, shape.phenotypes[0]))),
            "model_versions": MODEL_VERSIONS, "options": o.model_dump(),
        }
        tracks = [
            GarmentTrack(name=g.asset.id, vertices=g.vertices, faces=g.asset.faces, uvs=g.asset.uvs, face_uvs=g.asset.face_uvs,
                         metadata={"layer": g.asset.layer, "category": g.asset.category})
            for g in result.garments
        ]
        body_track = None
        if o.include_body:
            body_track = BodyTrack(
                rest_vertices=shape.rest_vertices[0], faces=self.body.faces, skin_indices=self.body.skin_indices,
                skin_weights=self.body.skin_weights, parents=self.body.parents, bone_names=self.body.bone_names,
                rest_bone_poses=shape.rest_bone_poses[0], bone_poses=result.bone_poses, uvs=self.body.uvs, face_uvs=self.body.face_uvs,
            )
        if request.format == "glb":  # (the npz writer records units, axes, fps and garments itself)
            metadata.update(units="metres, seconds", axes="Y-up (glTF)", garments=[g.asset.id for g in result.garments], fps=motion.fps)
            payload = write_glb(tracks, body_track, motion.fps, metadata=metadata)
        else:
            payload = write_npz(tracks, body_track, motion.fps, metadata=metadata)
        timings = {**result.timings_ms, "export": (time.perf_counter() - t_export) * 1e3, "total": (time.perf_counter() - t0) * 1e3}
        log.info("drape %s frames=%d %s", ids, motion.num_frames, json.dumps({k: round(v, 1) for k, v in timings.items()}))
        headers = {
            "X-Frames": str(motion.num_frames),
            "Server-Timing": ", ".join(f"{k};dur={v:.1f}" for k, v in timings.items()),
        }
        return DrapeOutput(payload=payload, headers=headers)

    async def drape(self, request: DrapeRequest) -> DrapeOutput:
        """Run a drape in a worker thread; 503 when too many requests already wait for one."""
        if self._limiter.borrowed_tokens >= self._limiter.total_tokens and self._waiting >= self.settings.max_waiting_drapes:
            raise ProblemException(503, "Busy", "too many drape requests in flight; retry later", headers={"Retry-After": "1"})
        self._waiting += 1
        try:
            await self._limiter.acquire()
        finally:
            self._waiting -= 1
        try:
            return await anyio.to_thread.run_sync(self.run_drape, request)
        finally:
            self._limiter.release()
