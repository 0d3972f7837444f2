"""The drape pipeline: shape -> arms -> fit -> dynamics -> skin -> guard -> layers -> repair -> export.

Thesis eq. 4.2-4.3: T_c(beta, theta) = T_bar_c + R_G(beta) + R_L(beta, gamma_1..t), then
M_c = W(T_c, beta, theta, W_c), then the collision post-process of ch. 4.2.1. Each stage is a
function over batched float32 arrays. Each garment runs one fit and one dynamics method
(DrapeOptions; where the request names none, the garment's default, ``inference.defaults``); the
learned ones are ``inference.learned``'s fit MLP R_G and wrinkle GRU R_L (ONNX, trained
self-supervised with the SNUG losses):

- fit 'canonical' : the garment's canonical form X (thesis ch. 6: unposed, deshaped), shaped by
  the diffused body's offsets and skinned with its weights, both read at X (eq. 6.7-6.8,
  ``inference.canonical``); with dynamics 'none' X is the static template, with 'learned'
  X_t = D(R(beta, gamma_1..t)) (ch. 6.4: the regressor into the canonical VAE's latent, and its
  decoder; as a default only on bodies within the learned model's body range of its training
  bodies, ``CanonicalModels.covers``, else the default's ``beyond_range`` method, or the static X;
  near the range's edge the two are blended, ``CanonicalModels.beyond_weight``). Then the strain limit
  (``inference.strain``: no edge much below 0.8 of its rest length, where eq. 6.7 squeezes the
  cloth under the arms; a dress's or bottom's none much above 2.0 / 1.9 of it). Collisions: the
  final exact stage alone (the guard's pushes are for garments in the posed space; a layered
  outfit keeps its push out of the body)
- fit 'learned'   : retarget_fit(beta) + R_G(beta) (R_G is a residual on the .mhclo retarget)
- fit 'learned-canonical' : fit 'learned''s garment on the shaped body in its rest pose, posed as
  fit 'canonical' is: skinned with W~ read at the static canonical X, the strain limit, the final
  exact stage alone. R_G, trained on sampled bodies, keeps the one-size garment's length where
  B~s stretches it with a tall or heavy body (edge p99 1.9-2.7 against newton's 1.2-1.5 on such
  bodies, docs/benchmarks.md); a default beyond a learned canonical model's body range
- fit 'retarget'  : retarget_fit(beta) (the .mhclo binding on the body + template correction)
- fit 'none'      : the neutral template, plain LBS
- dynamics 'learned': + R_L(beta, gamma_1..t) per frame, gamma = motion_descriptor (one ORT call)
- dynamics 'none'   : no per-frame displacement
- layers (outfits of more than one garment, with the guard on): the guard pushes each layer out
  of the body only (layer i with margin + i * layer_gap; in an outfit of canonical garments
  without the closest-triangle check), then ``inference.layers`` pulls each
  inner layer back under the layers outside it along its body-anchor segments; the exact repair
  runs last, on every layer
- arms (``lift_arms``): the upper arms are abducted out of the torso where the body shape sinks
  them in (``inference.motion.self_contact``); the body and the garments follow that pose

Units: metres, seconds, radians; Z-up world axes (the glb writer converts to Y-up).
"""
from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np

from inference.body import NEUTRAL_PHENOTYPES, BodyModel, BodyShape, linear_blend_skinning
from inference.canonical import CanonicalModels, default_canonical, margin, push_fields
from inference.defaults import DefaultMethods, DynamicsMode, FitMode, Method, resolve_methods
from inference.errors import InputShapeError, InputValueError
from inference.garment import GarmentAsset
from inference.guard import LayerPlans, guard_layers
from inference.layers import CONTACT_M, STAND_IN_SLACK_M, LayerContacts, body_anchors, body_tree, kept_anchors, untangle_layers
from inference.learned import LearnedGarment, LearnedModels, MissingModelError, default_models
from inference.motion.descriptor import motion_descriptor
from inference.motion.self_contact import arm_lifter, lift_arms
from inference.options import DrapeOptions
from inference.repair import LayerOrder, repair_layers


@dataclass(frozen=True)
class PoseSequence:
    """A motion in the body model's pose contract (inference/body.py).

    rotations   : (T, J, 3) float32 axis-angle, radians
    translation : (T, 3) float32 metres
    fps         : frames per second
    """

    rotations: np.ndarray
    translation: np.ndarray
    fps: float

    def __post_init__(self):
        if self.rotations.ndim != 3 or self.rotations.shape[-1] != 3:
            raise InputShapeError("motion.rotations", "(T, J, 3)", self.rotations.shape)
        if self.translation.shape != (self.rotations.shape[0], 3):
            raise InputShapeError("motion.translation", f"({self.rotations.shape[0]}, 3)", self.translation.shape)
        if not (np.isfinite(self.rotations).all() and np.isfinite(self.translation).all()):
            raise InputValueError("motion", "rotations and translation must be finite")
        if not (np.isfinite(self.fps) and self.fps > 0):
            raise InputValueError("motion.fps", f"must be a positive number, got {self.fps}")

    @property
    def num_frames(self) -> int:
        return int(self.rotations.shape[0])


@dataclass
class DrapedGarment:
    """One garment's result: posed vertices (T, V, 3) float32, Z-up metres, its asset, and the
    method it ran (the request's options resolved against the garment's default)."""

    asset: GarmentAsset
    vertices: np.ndarray
    method: Method


@dataclass
class DrapeResult:
    garments: list[DrapedGarment]
    shape: BodyShape
    bone_poses: np.ndarray  # (T, J, 4, 4)
    body_vertices: np.ndarray | None  # (T, Vb, 3) posed body when computed
    fps: float
    timings_ms: dict[str, float] = field(default_factory=dict)
    wrinkle_state: list[np.ndarray | None] = field(default_factory=list)  # per garment: the GRU state after the last frame (learned dynamics)
    anchors: list[np.ndarray] | None = None  # per garment: its vertices' body anchors (layered outfits; inference.layers)
    # per garment: each vertex's move in the final stage in the last frame (N, 3), for the next chunk of the motion
    repair_state: list[np.ndarray] | None = None


class _Timer:
    def __init__(self):
        self.ms: dict[str, float] = {}

    def __call__(self, name: str):
        timer = self

        class _Span:
            def __enter__(self):
                self.t0 = time.perf_counter()

            def __exit__(self, *exc):
                timer.ms[name] = timer.ms.get(name, 0.0) + (time.perf_counter() - self.t0) * 1e3

        return _Span()


# ---------------------------------------------------------------------- stages
# The fits that run the ch. 4 fit regressor R_G.
LEARNED_FITS = ("learned", "learned-canonical")


def fit_garment(garment: GarmentAsset, hm08_vertices: np.ndarray, mode: FitMode, phenotypes: np.ndarray | None = None, learned: LearnedGarment | None = None) -> np.ndarray:
    """Unposed garment on the body shape, T_bar_c + R_G(beta) (eq. 4.2 without R_L).

    hm08_vertices : (B, 19158, 3) shaped rest body in hm08 order
    phenotypes    : (B, 6) the bodies' phenotypes ('learned' only)
    learned       : the garment's LearnedGarment ('learned' only)
    returns       : (B, V, 3) float32 metres, in the shaped body's rest pose
                    ('none': the neutral template, unchanged)
    """
    if mode == "learned":
        if learned is None or phenotypes is None:
            raise ValueError("fit 'learned' needs the garment's LearnedGarment and the phenotypes")
        # eq. 4.2 with R_G a residual on the .mhclo retarget (inference.learned)
        return (garment.retarget_fit(hm08_vertices) + learned.fit(phenotypes)).astype(np.float32)
    if mode == "retarget":
        return garment.retarget_fit(hm08_vertices).astype(np.float32)
    return np.broadcast_to(garment.template, (len(hm08_vertices),) + garment.template.shape).astype(np.float32)


def garment_dynamics(unposed: np.ndarray, num_frames: int, mode: DynamicsMode = "none", phenotypes: np.ndarray | None = None,
                     gamma: np.ndarray | None = None, learned: LearnedGarment | None = None,
                     segments: Sequence[int] | None = None, h0: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """Per-frame unposed garment T_c(beta, gamma_1..t) = fit + R_L(beta, gamma_1..t) (eq. 4.2).

    unposed    : (B, V, 3) the fitted garment
    phenotypes : (B, 6) ; gamma : (B, T, F) motion descriptor ; learned : the garment's models
                 ('learned' only: each segment in one ORT call)
    segments   : frame counts of independent motions concatenated along T (cross-request
                 batching): the GRU restarts from h0 = 0 at each one's first frame
    h0         : (L, B, H) the GRU state at the first frame, carried from the previous chunk of
                 the same motion (one segment only); None: zeros, the start of a motion
    returns    : (B, T, V, 3) float32 metres ('none': the fit repeated, a broadcast view), and
                 the GRU state after the last frame ('learned'; None otherwise)
    """
    if mode == "learned":
        if learned is None or phenotypes is None or gamma is None:
            raise ValueError("dynamics 'learned' needs the garment's LearnedGarment, the phenotypes and gamma")
        if gamma.shape[:2] != (unposed.shape[0], num_frames):
            raise InputShapeError("gamma", f"({unposed.shape[0]}, {num_frames}, F)", gamma.shape)
        segments = list(segments or [num_frames])
        if h0 is not None and len(segments) != 1:
            raise InputShapeError("segments", "one segment when a GRU state is carried in", tuple(segments))
        bounds = np.cumsum([0, *segments])
        parts, h_t = [], None
        for a, b in zip(bounds[:-1], bounds[1:]):
            delta, h_t = learned.wrinkles(phenotypes, gamma[:, a:b], h0)
            parts.append(delta)
        return unposed[:, None] + np.concatenate(parts, axis=1), h_t
    return np.broadcast_to(unposed[:, None], (unposed.shape[0], num_frames) + unposed.shape[1:]), None


def neutral_relative_transforms(transforms: np.ndarray, shape: BodyShape, neutral: BodyShape) -> np.ndarray:
    """Skinning transforms from the *neutral* rest pose to the posed shaped body: T P_s P_n^-1.

    Used by fit='none', where the garment stays the neutral template (plain LBS baseline).
    transforms : (B, T, J, 4, 4); returns the same shape
    """
    rel = shape.rest_bone_poses.astype(np.float64) @ np.linalg.inv(neutral.rest_bone_poses.astype(np.float64))
    return (transforms.astype(np.float64) @ rel[:, None]).astype(np.float32)


def drape(
    body: BodyModel,
    shape: BodyShape,
    motion: PoseSequence,
    garments: list[GarmentAsset],
    options: DrapeOptions = DrapeOptions(),
    neutral: BodyShape | None = None,
    models: LearnedModels | None = None,
    segments: Sequence[int] | None = None,
    defaults: DefaultMethods | None = None,
    gamma: np.ndarray | None = None,
    wrinkle_state: Sequence[np.ndarray | None] | None = None,
    canonical: CanonicalModels | None = None,
    repair_state: Sequence[np.ndarray] | None = None,
) -> DrapeResult:
    """Dress one shaped body (``body.shape`` of one phenotype vector) in ``garments``
    (innermost first) following ``motion``; ``neutral`` is the neutral body's shape (fit 'none');
    ``models`` the learned-model registry (default: ``inference.learned.default_models()``);
    ``segments``: frame counts of independent motions concatenated in ``motion`` (cross-request
    batching; default one motion): the motion descriptor and the wrinkle GRU restart at each;
    ``defaults``: each garment's default method, used where ``options.fit`` / ``options.dynamics``
    is None (default: ``inference.defaults.default_methods()``, the shipped table);
    ``gamma`` (1, T, F): the motion descriptor of these frames when they are a chunk of a longer
    motion (computed over the whole motion: its finite differences reach across the chunk's
    ends), and ``wrinkle_state`` each garment's GRU state after the previous chunk
    (``DrapeResult.wrinkle_state``; see ``drape_chunks``); ``canonical`` the diffused body and
    canonical garments (fit 'canonical'; default ``inference.canonical.default_canonical()``);
    ``repair_state`` each garment's moves in the final stage in the previous chunk's last frame
    (``DrapeResult.repair_state``: the stage keeps a point on its side of a limb across frames)."""
    timer = _Timer()
    if shape.rest_vertices.shape[0] != 1:
        raise InputShapeError("shape", "one body (B = 1)", shape.rest_vertices.shape)
    if motion.rotations.shape[1] != body.num_bones:
        raise InputShapeError("motion.rotations", f"(T, {body.num_bones}, 3)", motion.rotations.shape)
    segments = [motion.num_frames] if segments is None else [int(n) for n in segments]
    if min(segments) < 1 or sum(segments) != motion.num_frames:
        raise InputShapeError("segments", f"positive frame counts summing to {motion.num_frames}", tuple(segments))

    # per garment: the request's fit / dynamics, else the garment's default (never fit 'none',
    # which stays a uniform option: it changes the skinning transforms and the guard's rest body)
    canonical = canonical or default_canonical()  # (loads nothing until a garment runs fit 'canonical')
    methods = resolve_methods([g.id for g in garments], options.fit, options.dynamics, defaults,
                              beyond=lambda i: canonical.beyond_weight(next(g for g in garments if g.id == i), shape.phenotypes),
                              outfit=len(garments) > 1)
    hm08 = None
    if any(f != "canonical" for m in methods for f in m.fits):  # the MakeHuman bindings of the other fits (~0.7 ms)
        with timer("shape"):
            hm08 = body.hm08_vertices(shape)
    posed = None
    if options.lift_arms:
        with timer("arms"):  # and the lifted motion's poses, which the lift has computed (BodyModel.pose's)
            lifted, _, *posed = arm_lifter(body, shape).lift(motion.rotations, motion.translation, segments, poses=True)
            motion = PoseSequence(lifted, motion.translation, motion.fps)
    with timer("pose"):
        bone_poses, transforms = posed or body.pose(shape.rest_bone_poses, motion.rotations[None], motion.translation[None])
    anchors = None
    repaired = None  # each garment's last frame's moves in the final stage
    body_vertices = None  # the posed body, needed by the guard (exporters pose it themselves)
    if options.guard:
        with timer("body_skin"):
            body_vertices = body.skin(shape.rest_vertices, transforms)  # (1, T, Vb, 3)

    garment_transforms = transforms
    if options.fit == "none":
        if neutral is None:
            neutral = body.shape(NEUTRAL_PHENOTYPES[None])
        garment_transforms = neutral_relative_transforms(transforms, shape, neutral)

    # the ch. 4 models (fit 'learned', or its wrinkle GRU) and the ch. 6 ones (fit 'canonical')
    ch4 = [any(f in LEARNED_FITS for f in m.fits) or (m.dynamics == "learned" and m.fit != "canonical") for m in methods]
    learned: list[LearnedGarment | None] = [None] * len(garments)
    if any(ch4):
        models = models or default_models()
        with timer("models"):  # loaded once per garment by the registry; raises MissingModelError
            learned = [models.get(g.id, "/options/fit" if any(f in LEARNED_FITS for f in m.fits) else "/options/dynamics") if c else None
                       for g, m, c in zip(garments, methods, ch4)]
            for g, m, lg in zip(garments, methods, learned):
                if lg is not None and m.dynamics == "learned" and m.fit != "canonical" and not lg.has_wrinkles:
                    raise MissingModelError("/options/dynamics", f"garment {g.id!r} ships a fit regressor but no wrinkle model; "
                                                                 "use dynamics='none', or fit='canonical'")
    if any(m.fit == "canonical" for m in methods):
        with timer("models"):  # raises MissingModelError for dynamics 'learned' where a garment ships none
            for g, m in zip(garments, methods):
                if m.fit == "canonical" and m.dynamics == "learned":
                    canonical.learned(g.id)
    if gamma is not None:
        if gamma.shape[:2] != (1, motion.num_frames):
            raise InputShapeError("gamma", f"(1, {motion.num_frames}, F)", gamma.shape)
    elif any(m.dynamics == "learned" for m in methods):
        with timer("descriptor"):  # per segment: finite differences never straddle two motions
            bounds = np.cumsum([0, *segments])
            gamma = np.concatenate([motion_descriptor(motion.rotations[None, a:b], motion.translation[None, a:b], motion.fps)
                                    for a, b in zip(bounds[:-1], bounds[1:])], axis=1)

    def run(g: GarmentAsset, m: Method, lg: LearnedGarment | None, h0: np.ndarray | None):
        """One garment's posed frames (1, T, V, 3) by one method, its rest fit (1, V, 3) and
        skinning weights (V, J) for the guard and the layer stage (None where unused; a learned
        canonical model's rest fit is its frames' mean form, for the layer stage's anchors, with no
        weights: the guard plans on its static form), and the GRU state after the last frame."""
        if m.fit == "canonical" and m.dynamics == "learned":
            d = canonical.diffused
            with timer("dynamics"):  # X_t = D(R(beta, gamma_1..t))
                X, h_t = canonical.frames(g, shape.phenotypes, gamma, segments, h0, push=False)
            with timer("skin"):  # pushed out of the canonical body, then eq. 6.7 with W~ and B~s at every frame's own points
                offsets = d.offsets(shape.rest_vertices[0])
                X, fields, shape_offsets = push_fields(d, X, margin(g), offsets)
                frames = d.pose(X, offsets, transforms[0], fields, shape_offsets)
            with timer("strain"):  # the decoded garment's edges back within its category's strain limit (inference.strain)
                out = canonical.strain_limit(g)(frames)[None]
            if len(garments) == 1:
                return out, None, None, h_t
            with timer("fit"):  # the layer stage's anchors on the sequence's mean canonical form (the guard's
                # plan and the layers' contacts on the static form, once per body: below)
                return out, d.deshaped_to_shaped(X.mean(0), offsets)[None], None, h_t
        with timer("fit"):
            if m.fit == "canonical":
                unposed, w = canonical.rest_fit(g, shape.rest_vertices[0])
                unposed = unposed[None]
            elif m.fit == "learned-canonical":  # the fit regressor's garment, W~ read at the static canonical X
                unposed, w = fit_garment(g, hm08, "learned", shape.phenotypes, lg), canonical.weights(g)
            else:
                unposed, w = fit_garment(g, hm08, m.fit, shape.phenotypes, lg), g.skin_weights
        with timer("dynamics"):
            unposed_t, h_t = garment_dynamics(unposed, motion.num_frames, m.dynamics, shape.phenotypes, gamma, lg, segments, h0)
        with timer("skin"):
            skinned = linear_blend_skinning(unposed_t, w, garment_transforms)
        if m.canonical:
            with timer("strain"):  # eq. 6.7's squeeze under the arms (and a stretched dress or bottom): the strain limit
                skinned = canonical.strain_limit(g)(skinned[0])[None]
        return skinned, unposed, w, h_t

    unposed_fits, posed, states, weights = [], [], [], []
    for i, (g, m, lg) in enumerate(zip(garments, methods, learned)):
        h0 = wrinkle_state[i] if wrinkle_state is not None else None
        out, unposed, w, h_t = run(g, m.own, lg, h0)
        if m.beyond is not None:  # near the edge of the learned model's body range: blended into the beyond-range method
            other = run(g, m.beyond, lg, None)[0]
            with timer("blend"):
                out = (1.0 - m.beyond_weight) * out + m.beyond_weight * other
        posed.append(out)
        states.append(h_t)
        if unposed is not None:
            unposed_fits.append(unposed)
            weights.append(w)

    if options.guard:
        margins = [options.margin_m + i * options.layer_gap_m for i in range(len(garments))]  # each layer's body margin
        # the guard's push out of the body: every posed-space garment, and every outfit (it sets the layers' heights,
        # and holds the innermost off the skin: unpushed, the T-shirt under the jacket crossed the skin 3-6x more on 02_02).
        # Its closest-triangle check only where a posed-space garment is in the request: an outfit of canonical
        # garments has the final exact stage after the layers at every level, and the same layer order and skin
        # crossings without the check (docs/benchmarks.md, "Outfits: the guard's cost")
        if len(garments) > 1 or not all(m.canonical for m in methods):
            check = options.guard_check and not all(m.canonical for m in methods)
            # a learned canonical model's rest form follows the motion (its frames' mean form); what
            # is planned once per body stands in its static canonical form shaped to the body
            moving = [m.fit == "canonical" and m.dynamics == "learned" for m in methods]
            with timer("fit"):
                stand_ins = [canonical.rest_fit(g, shape.rest_vertices[0]) if mv else (u[0], w)
                             for g, mv, u, w in zip(garments, moving, unposed_fits, weights)]
            with timer("guard"):
                # Candidates from the rest pose of the shaped body (fit 'none': the neutral template
                # against the neutral body, the pose its skinning transforms start from), kept for
                # the body's next request: a moving garment's plan on its stand-in (its per-frame
                # candidates, ``GuardPlan.dynamic_points``, carry the motion; the layers' numbers
                # are those of a plan on the mean form: docs/benchmarks.md, session 46).
                rest_body = shape.rest_vertices if options.fit != "none" else neutral.rest_vertices
                plans = LayerPlans.build([u[None] for u, _ in stand_ins], [g.faces for g in garments], rest_body, body.faces,
                                         layer_weights=[w for _, w in stand_ins], body_weights=body.dense_weights, rings=check,
                                         between_layers=False, reuse=[True] * len(garments))
                posed = guard_layers(posed, body_vertices, plans, options.margin_m, options.layer_gap_m, check=check)
            skin = plans.skin
            if len(garments) > 1:
                with timer("layers"):  # each inner layer under the ones outside it (inference.layers)
                    # the anchors on a moving garment's mean form (on its stand-in, the intersecting
                    # pairs grow by up to 3.4x on 02_02); the rest kept for the body's next request,
                    # the contacts on the stand-ins within a radius wider by their distance to the mean forms
                    anchors = [body_anchors(u[0], rest_body[0], body_tree(rest_body[0])) if mv else kept_anchors(u[0], rest_body[0])
                               for u, mv in zip(unposed_fits, moving)]
                    contacts = LayerContacts.kept([u for u, _ in stand_ins], [g.faces for g in garments],
                                                  CONTACT_M + (STAND_IN_SLACK_M if any(moving) else 0.0))
                    untangled, _ = untangle_layers([p[0] for p in posed], [g.faces for g in garments], anchors, body_vertices[0], body.faces,
                                                   options.layer_gap_m, margins, contacts)
                    posed = [u[None] for u in untangled]
        else:
            skin = None
        # last: no garment vertex inside the body (exact winding number); a lone canonical
        # garment has this stage alone at every level but 'off'
        if options.guard_exact or all(m.canonical for m in methods):
            with timer("repair"):
                # an outfit's inner points moved out of the body stay under the outer layers where they can
                order = LayerOrder(anchors, [g.faces for g in garments], options.layer_gap_m) if len(garments) > 1 and anchors is not None else None
                came = [p[0, -1] for p in posed]
                posed = repair_layers(posed, body_vertices, body.faces, margins, skin=skin, order=order, faces=[g.faces for g in garments],
                                      segments=segments, moves_before=repair_state)[0]
                repaired = [p[0, -1] - c for p, c in zip(posed, came)]

    return DrapeResult(
        garments=[DrapedGarment(asset=g, vertices=p[0], method=m) for g, p, m in zip(garments, posed, methods)],
        shape=shape,
        bone_poses=bone_poses[0],
        body_vertices=None if body_vertices is None else body_vertices[0],
        fps=motion.fps,
        timings_ms=timer.ms,
        wrinkle_state=states,
        anchors=anchors,
        repair_state=repaired,
    )


def without_root_travel(result: DrapeResult) -> DrapeResult:
    """The result with the root's horizontal travel removed (an "in place" motion): every
    frame's garments, body and bones shifted by -(r_t - r_0) in x and y (Z-up), r_t the root
    bone's position; the vertical and all the motion's dynamics (computed on the travelling
    motion) are kept."""
    root = result.bone_poses[:, 0, :3, 3]
    shift = np.zeros((len(root), 3), np.float32)
    shift[:, :2] = root[:, :2] - root[:1, :2]
    bones = result.bone_poses.copy()
    bones[:, :, :3, 3] -= shift[:, None]
    return DrapeResult(
        garments=[DrapedGarment(asset=g.asset, vertices=g.vertices - shift[:, None], method=g.method) for g in result.garments],
        shape=result.shape, bone_poses=bones,
        body_vertices=None if result.body_vertices is None else result.body_vertices - shift[:, None],
        fps=result.fps, timings_ms=result.timings_ms, wrinkle_state=result.wrinkle_state, anchors=result.anchors,
        repair_state=result.repair_state,
    )


def drape_chunks(
    body: BodyModel,
    shape: BodyShape,
    motion: PoseSequence,
    garments: list[GarmentAsset],
    options: DrapeOptions = DrapeOptions(),
    chunk_frames: int = 120,
    neutral: BodyShape | None = None,
    models: LearnedModels | None = None,
    defaults: DefaultMethods | None = None,
    canonical: CanonicalModels | None = None,
) -> Iterator[tuple[int, DrapeResult]]:
    """``drape`` of one motion in chunks of ``chunk_frames`` frames, each yielded when done as
    (frames done so far, the chunk's result); concatenated, the chunks equal the drape of the
    whole motion (to float rounding). What reaches across frames is computed once over the whole
    motion: the arm lift (it smooths over neighbouring frames) and the motion descriptor (finite
    differences); each garment's wrinkle GRU carries its state from one chunk to the next, and
    the final stage its last frame's moves (it keeps a point on its side of a limb from one frame
    to the next). Every other stage is per frame."""
    if chunk_frames < 1:
        raise InputShapeError("chunk_frames", ">= 1", (chunk_frames,))
    canonical = canonical or default_canonical()
    methods = resolve_methods([g.id for g in garments], options.fit, options.dynamics, defaults,
                              beyond=lambda i: canonical.beyond_weight(next(g for g in garments if g.id == i), shape.phenotypes),
                              outfit=len(garments) > 1)
    if options.lift_arms:
        lifted, _ = lift_arms(body, shape, motion.rotations, motion.translation)
        motion, options = PoseSequence(lifted, motion.translation, motion.fps), options.replace(lift_arms=False)
    gamma = None
    if any(m.dynamics == "learned" for m in methods):
        gamma = motion_descriptor(motion.rotations[None], motion.translation[None], motion.fps)
    state: list[np.ndarray | None] | None = None
    moves: list[np.ndarray] | None = None
    for a in range(0, motion.num_frames, chunk_frames):
        b = min(a + chunk_frames, motion.num_frames)
        part = PoseSequence(motion.rotations[a:b], motion.translation[a:b], motion.fps)
        result = drape(body, shape, part, garments, options, neutral=neutral, models=models, defaults=defaults, canonical=canonical,
                       gamma=None if gamma is None else gamma[:, a:b], wrinkle_state=state, repair_state=moves)
        state, moves = result.wrinkle_state, result.repair_state
        yield b, result
