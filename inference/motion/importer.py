"""A request's motion on a shaped body, at the requested frame rate, within the frame limits: the
one motion import that the service, the jobs and any other caller share.

Four kinds of input (``MotionSpec``): a bundled clip (retargeted by leg length, memoised per
body), an explicit pose sequence in the body model's pose contract, a BVH text, or a CMU ASF
skeleton with its AMC motion (both parsed and retargeted onto the body). The output frame count is known from the input before any work is
done (``MotionImporter.output_frames``) and refused past ``MotionLimits.max_frames`` before
resampling or retargeting. Errors are ``InputValueError`` naming the request field as an RFC 6901
pointer (``/motion/...``).

Units: radians, metres, seconds; arrays float32, frames first.
"""
from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from inference.body import PHENOTYPE_LABELS, BodyModel, BodyShape
from inference.errors import InputValueError
from inference.motion.asfamc import CMU_FPS, amc_frames, parse_amc, parse_asf
from inference.motion.bvh import bvh_frames, parse_bvh
from inference.motion.clips import ClipLibrary, adapt_clip
from inference.motion.resample import resample_motion, resampled_frame_count
from inference.motion.retarget import retarget
from inference.pipeline import PoseSequence

# metres per BVH unit for the request's `units` (None: infer from the skeleton's size)
BVH_UNITS = {"auto": None, "metres": 1.0, "centimetres": 0.01, "inches": 0.0254, "cmu": 0.0254 / 0.45}
CLIP_CACHE_ENTRIES = 64  # adapted clips kept per process (a 10 s clip is ~0.1 MB)
# Shaped bodies kept per process (~0.2 MB each): a shopper's body is draped again for every
# garment and motion, and the default neutral body serves most requests; ~1.2 ms a request saved.
SHAPE_CACHE_ENTRIES = 32


@dataclass(frozen=True)
class ClipSpec:
    clip: str
    start_s: float = 0.0
    duration_s: float | None = None  # None: to the end of the clip, within the frame limit


@dataclass(frozen=True)
class PosesSpec:
    rotations: Sequence  # (T, 31, 3) axis-angle per bone, radians
    translation: Sequence  # (T, 3) root displacement, metres, Z-up
    fps: float


@dataclass(frozen=True)
class BvhSpec:
    text: str
    units: str = "auto"  # a key of BVH_UNITS


@dataclass(frozen=True)
class AsfAmcSpec:
    asf: str  # the skeleton
    amc: str  # the motion
    fps: float = CMU_FPS  # AMC files carry no frame rate; CMU captured at 120
    units: str = "auto"  # a key of BVH_UNITS; auto: the ASF's own `length` (CMU: 0.45 in per unit)


MotionSpec = ClipSpec | PosesSpec | BvhSpec | AsfAmcSpec


@dataclass(frozen=True)
class MotionLimits:
    max_frames: int  # output frames, after resampling
    max_source_frames: int  # frames of an uploaded motion (poses, BVH)
    max_bvh_bytes: int  # BVH text, or ASF + AMC texts together


_shapes: OrderedDict[tuple[int, bytes], tuple[BodyModel, BodyShape]] = OrderedDict()
_shapes_lock = threading.Lock()


def shape_of(body: BodyModel, phenotypes: dict[str, float]) -> BodyShape:
    """The shaped body of one phenotype vector given by name (``PHENOTYPE_LABELS``), from a small
    LRU of the last ``SHAPE_CACHE_ENTRIES`` bodies (keyed by the float32 phenotypes; its arrays
    are read-only, shared by every request of that body)."""
    p = np.array([[phenotypes[name] for name in PHENOTYPE_LABELS]], np.float32)
    key = (id(body), p.tobytes())
    with _shapes_lock:
        hit = _shapes.get(key)
        if hit is not None and hit[0] is body:
            _shapes.move_to_end(key)
            return hit[1]
    shape = body.shape(p)
    for a in vars(shape).values():
        a.setflags(write=False)
    with _shapes_lock:
        _shapes[key] = (body, shape)
        while len(_shapes) > SHAPE_CACHE_ENTRIES:
            _shapes.popitem(last=False)
    return shape


class MotionImporter:
    """Motion import for one body model and clip library (thread-safe clip memo)."""

    def __init__(self, body: BodyModel, clips: ClipLibrary, cache_entries: int = CLIP_CACHE_ENTRIES):
        self.body, self.clips = body, clips
        self.cache_entries = cache_entries
        self._cache: OrderedDict = OrderedDict()
        self._lock = threading.Lock()

    # ------------------------------------------------------------------ from the input alone
    def _clip_window(self, spec: ClipSpec) -> tuple[int, int]:
        clip = self.clips.load(spec.clip)
        start = int(round(spec.start_s * clip.fps))
        if start >= clip.num_frames:
            raise InputValueError("/motion/start_s", f"the clip lasts {clip.duration_s:.2f} s")
        stop = clip.num_frames
        if spec.duration_s is not None:
            stop = min(stop, start + int(round(spec.duration_s * clip.fps)) + 1)
        return start, stop

    def output_frames(self, spec: MotionSpec, fps: float, limits: MotionLimits) -> int | None:
        """Frames of the imported motion at ``fps``, from the input alone (a clip to its end is
        cut at the limit; BVH from its MOTION header, AMC from its frame-number lines); None for
        an unknown clip or a BVH without a readable header (parsing will say why)."""
        if isinstance(spec, ClipSpec):
            if spec.clip not in self.clips.ids():
                return None
            clip = self.clips.load(spec.clip)
            start = int(round(spec.start_s * clip.fps))
            stop = clip.num_frames if spec.duration_s is None else min(clip.num_frames, start + int(round(spec.duration_s * clip.fps)) + 1)
            frames = resampled_frame_count(max(stop - start, 0), clip.fps, fps)
            return frames if spec.duration_s is not None else min(frames, limits.max_frames)
        if isinstance(spec, PosesSpec):
            return resampled_frame_count(len(spec.rotations), spec.fps, fps)
        if isinstance(spec, BvhSpec):
            header = bvh_frames(spec.text)
            return None if header is None else resampled_frame_count(header[0], header[1], fps)
        return resampled_frame_count(amc_frames(spec.amc), spec.fps, fps)

    def check(self, spec: MotionSpec, fps: float, limits: MotionLimits) -> None:
        """The cheap refusals, before any work (the job route's, before its 202): an unknown
        clip; a motion whose output frame count, from the input alone, exceeds the limit."""
        if isinstance(spec, ClipSpec) and spec.clip not in self.clips.ids():
            raise InputValueError("/motion/clip", f"unknown clip {spec.clip!r}; see GET /v1/motions")
        frames = self.output_frames(spec, fps, limits)
        if frames is not None:
            field = {ClipSpec: "/motion/duration_s", PosesSpec: "/motion/fps", BvhSpec: "/motion/bvh", AsfAmcSpec: "/motion/amc"}[type(spec)]
            check_frames(frames, fps, limits, field)

    # ------------------------------------------------------------------ import
    def import_motion(self, spec: MotionSpec, shape: BodyShape, fps: float, limits: MotionLimits) -> PoseSequence:
        """The motion on this body at ``fps`` (float32, contiguous)."""
        if isinstance(spec, ClipSpec):
            clip = self.clips.load(spec.clip)
            start, stop = self._clip_window(spec)
            if spec.duration_s is not None:
                check_frames(resampled_frame_count(stop - start, clip.fps, fps), fps, limits)
            rotations, translation = self._adapted_clip(spec.clip, clip, shape)
            rotations, translation = resample_motion(rotations[0, start:stop], translation[0, start:stop], clip.fps, fps)
            if spec.duration_s is None:  # to the end of the clip, within the limit
                rotations, translation = rotations[: limits.max_frames], translation[: limits.max_frames]
        elif isinstance(spec, PosesSpec):
            if len(spec.rotations) != len(spec.translation):
                raise InputValueError("/motion/translation", f"{len(spec.translation)} frames, rotations have {len(spec.rotations)}")
            if len(spec.rotations) > limits.max_source_frames:
                raise InputValueError("/motion/rotations", f"at most {limits.max_source_frames} frames")
            check_frames(resampled_frame_count(len(spec.rotations), spec.fps, fps), fps, limits, "/motion/fps")
            rotations = np.asarray(spec.rotations, np.float32)
            translation = np.asarray(spec.translation, np.float32)
            if np.abs(rotations).max() > 1e3 or np.abs(translation).max() > 1e4:
                raise InputValueError("/motion", "rotations must be within 1000 rad and translations within 10 km")
            rotations, translation = resample_motion(rotations, translation, spec.fps, fps)
        else:
            if isinstance(spec, BvhSpec):
                if len(spec.text.encode()) > limits.max_bvh_bytes:
                    raise InputValueError("/motion/bvh", f"BVH text exceeds {limits.max_bvh_bytes} bytes")
                source, field = parse_bvh(spec.text, unit_scale=BVH_UNITS[spec.units], max_frames=limits.max_source_frames), "/motion/bvh"
            else:
                if len(spec.asf.encode()) + len(spec.amc.encode()) > limits.max_bvh_bytes:
                    raise InputValueError("/motion/amc", f"ASF and AMC texts exceed {limits.max_bvh_bytes} bytes together")
                skeleton = parse_asf(spec.asf, unit_scale=BVH_UNITS[spec.units])
                source, field = parse_amc(spec.amc, skeleton, fps=spec.fps, max_frames=limits.max_source_frames), "/motion/amc"
            check_frames(resampled_frame_count(source.num_frames, source.fps, fps), fps, limits, field)
            result = retarget(source, self.body, shape, fps=fps)
            rotations, translation = result.rotations, result.translation
        check_frames(len(rotations), fps, limits)
        return PoseSequence(np.ascontiguousarray(rotations, np.float32), np.ascontiguousarray(translation, np.float32), fps)

    def _adapted_clip(self, clip_id: str, clip, shape: BodyShape) -> tuple[np.ndarray, np.ndarray]:
        """The whole clip adapted to this body (``adapt_clip``, ~0.1-0.4 s), memoised per
        (clip, phenotypes): a shopper's body tries many garments on the same clips."""
        key = (clip_id, tuple(shape.phenotypes[0].tolist()))
        with self._lock:
            hit = self._cache.get(key)
            if hit is not None:
                self._cache.move_to_end(key)
                return hit
        hit = adapt_clip(clip, self.body, shape)
        with self._lock:
            self._cache[key] = hit
            while len(self._cache) > self.cache_entries:
                self._cache.popitem(last=False)
        return hit


def check_frames(frames: int, fps: float, limits: MotionLimits, field: str = "/motion") -> None:
    """Refuse a motion whose output frame count (counted before any resampling or retargeting)
    exceeds the limit."""
    if frames > limits.max_frames:
        raise InputValueError(field, f"{frames} frames at {fps:g} fps exceed the limit of {limits.max_frames}; "
                                     "shorten the motion, lower options.fps or use POST /v1/jobs")
