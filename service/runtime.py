"""What the service holds in memory (body model, garment catalog and each garment's default
method, clips, learned models) and the drape work, by way of the inference entry points.

A request is translated into inference inputs here (``inference.motion.importer``: the motion on
the body within the frame limits; the garments, options and methods), run by
``inference.batch.drape_many`` (compatible requests merged into one pipeline call) or, for a
job, ``inference.pipeline.drape_chunks``, and encoded as glb or npz. No array maths here. This
runs inside the worker pool (service/pool.py), never on the event loop.
"""
from __future__ import annotations

import json
import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Callable

from inference import body as body_model
from inference import diffused, layers, repair, strain, winding
from inference.guard import nearest, push_kernels
from inference.motion import self_contact
from inference.asset_digest import AssetDigest
from inference.batch import DrapeJob, concatenate_results, drape_many
from inference.body import NEUTRAL_PHENOTYPES, PHENOTYPE_LABELS, BodyModel, BodyShape
from inference.canonical import MODEL_FILE as CANONICAL_MODEL_FILE
from inference.canonical import CanonicalModels
from inference.defaults import DEFAULTS_FILE, DefaultMethods, Method, resolve_methods
from inference.errors import InputValueError
from inference.export import BodyTrack, GarmentTrack, write_glb, write_npz
from inference.garment import GarmentAsset, GarmentCatalog
from inference.learned import LearnedModels
from inference.motion.clips import ClipLibrary
from inference.motion.importer import AsfAmcSpec, BvhSpec, ClipSpec, MotionImporter, MotionLimits, MotionSpec, PosesSpec, shape_of
from inference.pipeline import DrapeOptions, DrapeResult, PoseSequence, drape_chunks, without_root_travel
from service import allocator
from service.bodies import BodyService
from service.config import Settings
from service.errors import ProblemDetail, problem_from_exception
from service.schemas import AsfAmcMotion, BvhMotion, ClipMotion, DrapeRequest, PoseMotion

log = logging.getLogger(__name__)

# The code's algorithm versions (bumped when a stage's maths changes). The asset files' versions
# (trained models, body, garments, clips) come from their content: ``Runtime.assets``.
MODEL_VERSIONS = {
    "body": "anny-0.6.2-cmu_mb",
    "fit": "mhclo-retarget",
    "canonical": "diffused-canonical-v2",  # fit 'canonical': the diffused body (assets/body/diffused.npz), thesis ch. 6; v2: + the compression limit (inference/strain.py)
    "canonical_dynamics": "canonical-vae-gru-v2",  # fit 'canonical' + dynamics 'learned': regressor + VAE decoder (canonical.json); v2: + the compression limit (inference/strain.py)
    "dynamics": "none",
    "learned_fit": "snug-fit-v3",  # fit 'learned' (assets/models/<garment>/fit.onnx)
    "learned_canonical": "snug-fit-v3+diffused-canonical-v2",  # fit 'learned-canonical': fit.onnx's garment posed by the diffused body
    "learned_dynamics": "snug-gru-v6",  # dynamics 'learned' (wrinkle.onnx); v6: the wider output basis (every garment)
    "guard": "plane-push-v5",  # v4: closest-triangle check after the push (options.collisions 'check' and 'exact'); v5: an outfit's learned canonical garment planned on its static form (session 46)
    "guard_plain": "plane-push-v4",  # options.collisions 'push': the push alone (v3: farther limbs; v4: as guard v5)
    "repair": "winding-repair-v5",  # options.collisions 'exact', the default (inference/repair.py); v2: the outermost layer 2 mm off the skin; v3: inner layers kept under the outer ones; v4: the targets' skin normals in float64 (moves within 0.5 um of v3); v5: inner layers kept under the outer moves, sides held across frames, neighbours kept together, an inner layer's far look within 5 cm (sessions 40-47)
    "layers": "anchor-sink-v3",  # outfits of several garments, collisions not 'off' (inference/layers.py); v3: step (b) keeps the gap, a height over the skin; the rim looked past farther (session 48)
    "arms": "shoulder-lift-v2",  # options.lift_arms, the default (inference/motion/self_contact.py); v2: 10 mm clearance
}


def used_model_versions(options, methods: Mapping[str, Method]) -> dict[str, str | dict[str, str]]:
    """The versions of the models a request ran (its output metadata): body, arms, guard and
    repair from its options; fit and dynamics per garment id from ``methods``, the method each
    garment ran (``MODEL_VERSIONS``; 'none' for a stage that did not run)."""
    fit = {"canonical": MODEL_VERSIONS["canonical"], "learned-canonical": MODEL_VERSIONS["learned_canonical"],
           "learned": MODEL_VERSIONS["learned_fit"], "retarget": MODEL_VERSIONS["fit"], "none": "none"}
    dynamics = {"learned": MODEL_VERSIONS["learned_dynamics"], "none": "none"}
    # as inference.pipeline.drape: a lone canonical garment skips the guard's pushes and always
    # has the final exact stage
    canonical = all(m.canonical for m in methods.values())
    guard = len(methods) > 1 or not canonical
    def dyn(m):
        return MODEL_VERSIONS["canonical_dynamics"] if (m.fit, m.dynamics) == ("canonical", "learned") else dynamics[m.dynamics]

    def blend(m, name):  # a method blended into its beyond-range one: both, with their weights
        if m.beyond is None:
            return name(m)
        return f"{name(m.own)} x{1.0 - m.beyond_weight:.3f} + {name(m.beyond)} x{m.beyond_weight:.3f}"

    return {"body": MODEL_VERSIONS["body"], "arms": MODEL_VERSIONS["arms"] if options.lift_arms else "none",
            "fit": {gid: blend(m, lambda x: fit[x.fit]) for gid, m in methods.items()},
            "dynamics": {gid: blend(m, dyn) for gid, m in methods.items()},
            "guard": (MODEL_VERSIONS["guard"] if options.guard_check else MODEL_VERSIONS["guard_plain"]) if options.guard and guard else "none",
            "repair": MODEL_VERSIONS["repair"] if options.guard and (options.guard_exact or canonical) else "none",
            "layers": MODEL_VERSIONS["layers"] if options.guard and len(methods) > 1 else "none"}


@dataclass(frozen=True)
class RequestLimits:
    """Per-request limits: the synchronous route's, or the (larger) job route's."""

    max_frames: int
    max_total_vertices: int
    max_garments: int
    max_source_frames: int
    max_bvh_bytes: int

    @classmethod
    def drape(cls, s: Settings) -> "RequestLimits":
        return cls(s.max_frames, s.max_total_vertices, s.max_garments, s.max_source_frames, s.max_bvh_bytes)

    @classmethod
    def job(cls, s: Settings) -> "RequestLimits":
        return cls(s.job_max_frames, s.job_max_total_vertices, s.max_garments, s.max_source_frames, s.max_bvh_bytes)

    @property
    def motion(self) -> MotionLimits:
        return MotionLimits(self.max_frames, self.max_source_frames, self.max_bvh_bytes)


@dataclass
class DrapeOutput:
    payload: bytes
    headers: dict[str, str]
    timings_ms: dict[str, float] = field(default_factory=dict)
    model_versions: dict[str, str | dict[str, str]] = field(default_factory=dict)  # ``used_model_versions`` of the request


@dataclass
class PreparedDrape:
    """A validated request turned into pipeline inputs."""

    request: DrapeRequest
    shape: BodyShape
    motion: PoseSequence
    assets: list[GarmentAsset]  # layer order
    options: DrapeOptions
    methods: list[Method]  # per asset: the request's fit / dynamics, else the garment's default
    t0: float  # perf_counter at the start of the work (for the total time)


class Runtime:
    def __init__(self, settings: Settings, body: BodyModel, catalog: GarmentCatalog, clips: ClipLibrary, defaults: DefaultMethods,
                 models: LearnedModels | None = None, assets: AssetDigest | None = None, canonical: CanonicalModels | None = None):
        self.settings = settings
        self.body = body
        self.catalog = catalog
        self.clips = clips
        self.defaults = defaults  # each garment's default method (assets/models/defaults.json)
        self.models = models or LearnedModels(settings.assets_dir / "models")
        # the diffused body and the canonical models of fit 'canonical' (thesis ch. 6)
        self.canonical = canonical or CanonicalModels(settings.assets_dir / "body" / "diffused.npz", settings.assets_dir / "models")
        self.assets = assets or AssetDigest.of(settings.assets_dir)  # content versions: cache keys, ETags, metadata
        self.neutral_shape: BodyShape = body.shape(NEUTRAL_PHENOTYPES[None])
        self.motions = MotionImporter(body, clips)
        self._bodies: BodyService | None = None

    @property
    def bodies(self) -> BodyService:
        """Body fits and measurements (built on first use: only workers measure)."""
        if self._bodies is None:
            self._bodies = BodyService(self.body)
        return self._bodies

    @classmethod
    def load(cls, settings: Settings, learned: bool = True) -> "Runtime":
        """Every asset, and (``learned``) every learned model's ONNX session: a process that drapes
        loads them all at start-up; the API process of a process pool, which never drapes,
        passes False."""
        t0 = time.perf_counter()
        catalog = GarmentCatalog.load(settings.assets_dir)
        # a bad defaults file (unknown garment or mode, a garment without one) stops the start-up here
        defaults = DefaultMethods.load(settings.assets_dir / DEFAULTS_FILE, catalog.ids())
        body = BodyModel.load(settings.assets_dir / "body")
        clips = ClipLibrary(settings.assets_dir)
        models = LearnedModels(settings.assets_dir / "models")
        loaded = models.load_all(catalog.ids()) if learned else []  # no request waits for a session; a broken file stops the start
        canonical = CanonicalModels(settings.assets_dir / "body" / "diffused.npz", settings.assets_dir / "models")
        if learned:
            loaded += [f"{g} (canonical)" for g in canonical.load_all(catalog.ids())]
            allocator.keep_freed_memory()  # a request's arrays reuse the last one's pages (service.allocator)
            winding.warm_up()  # the exact inside test's compiled kernels, before the first request
            repair.warm_up()  # the final stage's
            layers.warm_up()  # and the layer stage's
            strain.warm_up()  # and the compression limit's (learned canonical garments)
            nearest.warm_up()  # and the guard's per-frame nearest body vertices
            push_kernels.warm_up()  # and its plane push and collider planes
            self_contact.warm_up()  # and the arm lift's nearest torso points, step and window maximum
            diffused.warm_up()  # and the diffused body's interpolation and eq. 6.7's blend
            body_model.warm_up()  # and the forward kinematics
        runtime = cls(settings, body, catalog, clips, defaults, models, AssetDigest.of(settings.assets_dir), canonical)
        log.info("loaded assets in %.2f s (learned models: %s; assets sha256 %s)", time.perf_counter() - t0, ", ".join(loaded) or "none",
                 runtime.assets.combined[:16])
        return runtime

    # ------------------------------------------------------------------ request -> inference inputs
    @staticmethod
    def motion_spec(request: DrapeRequest) -> MotionSpec:
        m = request.motion
        if isinstance(m, ClipMotion):
            return ClipSpec(m.clip, m.start_s, m.duration_s)
        if isinstance(m, PoseMotion):
            return PosesSpec(m.rotations, m.translation, m.fps)
        if isinstance(m, BvhMotion):
            return BvhSpec(m.bvh, m.units)
        assert isinstance(m, AsfAmcMotion)
        return AsfAmcSpec(m.asf, m.amc, m.fps, m.units)

    def output_frames(self, request: DrapeRequest, limits: RequestLimits | None = None) -> int | None:
        """The number of frames the request's drape will have, from the request alone
        (``MotionImporter.output_frames``; None for a BVH without a readable MOTION header)."""
        limits = limits or RequestLimits.drape(self.settings)
        return self.motions.output_frames(self.motion_spec(request), request.options.fps, limits.motion)

    def check_request(self, request: DrapeRequest, limits: RequestLimits | None = None) -> list[GarmentAsset]:
        """The request's garments in its order, which is the layer order, innermost first (a shirt
        listed before trousers is tucked into them; the catalog's ``layer`` is only the usual
        place); raises a 422 input error for unknown garment or clip ids, duplicates, too many.
        Cheap, so the API checks it before accepting a job."""
        limits = limits or RequestLimits.drape(self.settings)
        ids = [g.id for g in request.garments]
        if len(ids) > limits.max_garments:
            raise InputValueError("/garments", f"at most {limits.max_garments} garments per request")
        if len(set(ids)) != len(ids):
            raise InputValueError("/garments", "a garment is listed twice")
        assets = []
        for i, gid in enumerate(ids):
            if gid not in self.catalog.ids():
                raise InputValueError(f"/garments/{i}/id", f"unknown garment {gid!r}; see GET /v1/garments")
            assets.append(self.catalog.get(gid))
        self.motions.check(self.motion_spec(request), request.options.fps, limits.motion)  # unknown clip, pose frame count
        return assets

    def prepare(self, request: DrapeRequest, limits: RequestLimits | None = None) -> PreparedDrape:
        """Validate the request against the catalog and the limits; import its motion."""
        t0 = time.perf_counter()
        limits = limits or RequestLimits.drape(self.settings)
        assets = self.check_request(request, limits)
        shape = shape_of(self.body, request.body.phenotypes.model_dump())
        motion = self.motions.import_motion(self.motion_spec(request), shape, request.options.fps, limits.motion)
        o = request.options
        per_frame = sum(a.num_vertices for a in assets) + (self.body.num_vertices if o.include_body else 0)
        if motion.num_frames * per_frame > limits.max_total_vertices:
            raise InputValueError(
                "", f"{motion.num_frames} frames x {per_frame} vertices exceed the limit of {limits.max_total_vertices} vertices per request"
            )
        options = o  # the request's options are the pipeline's (inference.options.DrapeOptions)
        methods = resolve_methods([a.id for a in assets], o.fit, o.dynamics, self.defaults,
                                  beyond=lambda i: self.canonical.beyond_weight(next(a for a in assets if a.id == i), shape.phenotypes),
                                  outfit=len(assets) > 1)
        return PreparedDrape(request, shape, motion, assets, options, methods, t0)

    def drape_batch(self, prepared: list[PreparedDrape]) -> list[DrapeResult]:
        """Run the pipeline for several prepared requests (``inference.batch.drape_many``: those
        with the same body, garments, resolved methods and options share one call)."""
        jobs = [DrapeJob(p.shape, p.motion, p.assets, p.options, p.methods) for p in prepared]
        return drape_many(self.body, jobs, neutral=self.neutral_shape, models=self.models, defaults=self.defaults, canonical=self.canonical)

    def export(self, p: PreparedDrape, result: DrapeResult) -> DrapeOutput:
        """Encode one request's result as glb or npz."""
        request, shape, motion, o = p.request, p.shape, p.motion, p.request.options
        t_export = time.perf_counter()
        if request.motion.in_place:  # (the export poses the body from the bones: its skinned frames are not shifted)
            result = without_root_travel(replace(result, body_vertices=None))
        # what each garment ran (its resolved method), not the request's options (null: the default)
        versions = used_model_versions(o, {g.asset.id: g.method for g in result.garments})
        metadata = {
            "frames": motion.num_frames,
            "phenotypes": dict(zip(PHENOTYPE_LABELS, shape.phenotypes[0].tolist())),
            "model_versions": versions, "options": o.model_dump(), "in_place": request.motion.in_place,
            "assets_sha256": self.assets.combined, "asset_files_sha256": self.used_files(p, result),
        }
        tracks = [
            GarmentTrack(name=g.asset.id, vertices=g.vertices, faces=g.asset.faces, uvs=g.asset.uvs, face_uvs=g.asset.face_uvs,
                         metadata={"layer": g.asset.layer, "category": g.asset.category, "fit": g.method.fit, "dynamics": g.method.dynamics,
                                   **({} if g.method.beyond is None else {"beyond_range": {"fit": g.method.beyond.fit, "dynamics": g.method.beyond.dynamics,
                                                                                           "weight": g.method.beyond_weight}})},
                         appearance=g.asset.appearance)
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
            # the rest body's soles on the floor (y = 0)
            payload = write_glb(tracks, body_track, motion.fps, metadata=metadata, floor_z=float(shape.rest_vertices[0, :, 2].min()),
                                normals=o.normals, compression=o.compression)
        else:
            payload = write_npz(tracks, body_track, motion.fps, metadata=metadata)
        timings = {**result.timings_ms, "export": (time.perf_counter() - t_export) * 1e3, "total": (time.perf_counter() - p.t0) * 1e3}
        log.info("drape %s frames=%d %s", [a.id for a in p.assets], motion.num_frames, json.dumps({k: round(v, 1) for k, v in timings.items()}))
        headers = {
            "X-Frames": str(motion.num_frames),
            "Server-Timing": ", ".join(f"{k};dur={v:.1f}" for k, v in timings.items()),
        }
        return DrapeOutput(payload=payload, headers=headers, timings_ms=timings, model_versions=versions)

    def used_files(self, p: PreparedDrape, result: DrapeResult) -> dict[str, str]:
        """The asset files this drape read, with the first 16 hex digits of their SHA-256."""
        files = ["body/body.npz", "body/hm08_helpers.npz"]
        if isinstance(p.request.motion, ClipMotion):
            files.append(f"motions/{p.request.motion.clip}.npz")
        if any(g.method.canonical for g in result.garments):
            files.append("body/diffused.npz")
        for g in result.garments:
            files.append(f"garments/{g.asset.id}/garment.npz")
            if any(f in ("learned", "learned-canonical") for f in g.method.fits):
                files.append(f"models/{g.asset.id}/{self.models.get(g.asset.id).meta['fit']['file']}")
            if g.method.dynamics == "learned" and g.method.fit == "canonical":
                meta = self.canonical.learned(g.asset.id).meta
                files += [f"models/{g.asset.id}/{f}" for f in (CANONICAL_MODEL_FILE, meta["regressor"]["file"], meta["decoder"]["file"])]
            elif g.method.dynamics == "learned":
                files.append(f"models/{g.asset.id}/{self.models.get(g.asset.id).meta['wrinkle']['file']}")
        return {f: self.assets.short(f) for f in files}

    def run_drape(self, request: DrapeRequest) -> DrapeOutput:
        """One request, synchronously (raises the runtime's input errors)."""
        p = self.prepare(request)
        return self.export(p, self.drape_batch([p])[0])

    def run_batch(self, requests: list[DrapeRequest]) -> list[DrapeOutput | ProblemDetail]:
        """A batch from the scheduler: one outcome per request, never an exception (a bad request
        answers its own problem; the others still run)."""
        outcomes: list[DrapeOutput | ProblemDetail | None] = [None] * len(requests)
        prepared, index = [], []
        for i, r in enumerate(requests):
            try:
                prepared.append(self.prepare(r))
                index.append(i)
            except Exception as exc:  # noqa: BLE001 - every failure becomes this request's problem
                outcomes[i] = _problem(exc)
        try:
            results = self.drape_batch(prepared)
        except Exception:  # noqa: BLE001 - one bad member must not fail the batch: run them alone
            results = []
            for p in prepared:
                try:
                    results.append(self.drape_batch([p])[0])
                except Exception as exc:  # noqa: BLE001
                    results.append(exc)
        for i, p, r in zip(index, prepared, results):
            try:
                outcomes[i] = _problem(r) if isinstance(r, Exception) else self.export(p, r)
            except Exception as exc:  # noqa: BLE001
                outcomes[i] = _problem(exc)
        return outcomes  # type: ignore[return-value]

    def run_job(self, request: DrapeRequest, progress: Callable[[int, int], bool] | None = None) -> DrapeOutput | None:
        """A long request in chunks of ``job_chunk_frames`` frames (``inference.pipeline.drape_chunks``:
        the arm lift and the motion descriptor over the whole motion, the wrinkle GRU's state
        carried across chunks, so the result is the unchunked drape's); ``progress(done, total)``
        is called before the first chunk and after each, and returns True to cancel (then the
        result is None)."""
        p = self.prepare(request, RequestLimits.job(self.settings))
        total = p.motion.num_frames
        if progress is not None and progress(0, total):
            return None
        parts = []
        for done, part in drape_chunks(self.body, p.shape, p.motion, p.assets, p.options, self.settings.job_chunk_frames,
                                       neutral=self.neutral_shape, models=self.models, defaults=self.defaults, canonical=self.canonical):
            parts.append(part)
            if progress is not None and progress(done, total):
                return None
        return self.export(p, concatenate_results(parts, p.motion.fps))


def _problem(exc: BaseException) -> ProblemDetail:
    problem = problem_from_exception(exc)
    if problem.status >= 500:
        log.error("drape failed", exc_info=exc)
    return problem
