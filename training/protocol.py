"""The evaluation protocol (DESIGN.md §7): which clips train, validate and test, on which bodies.

- training clips  : ``training.datasets.TRAIN_CLIPS`` (the models are trained on these only)
- validation      : CMU 02_02 (walk, subject 2) on the neutral and the heavy body: the per-garment
                    default is chosen here, and so is every constant the judge tunes
- test            : CMU 01_01 (playground, subject 1; the spec's test sequence) and CMU 02_07
                    (subject 2, a trial no model has seen): reported only, never used to choose

Each case simulates a window of ``frames`` frames from ``start`` (30 fps frames of the clip
retargeted to the body, arms lifted as the service does), on a body of ``BODIES``: the neutral
adult and two extreme adults (the heaviest corner, and a light, tall, long-limbed one); the test
split adds a short, heavy, older man on 01_01 (``test-short``, beyond every learned model's body
range, added in session 34 after the beyond-range defaults were chosen on ``bodies``).
Windows are fixed in advance (start past each clip's first second, no other reason).

Units: frames at 30 fps; phenotypes in [0, 1] (anny order: gender, age, muscle, weight, height,
proportions).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from inference.body import NEUTRAL_PHENOTYPES, BodyModel, BodyShape
from inference.motion.asfamc import load_asf_amc
from inference.motion.clips import Clip, ClipLibrary
from inference.motion.importer import ClipSpec, MotionImporter, MotionLimits
from inference.motion.retarget import target_leg_length
from inference.motion.self_contact import lift_arms
from inference.pipeline import PoseSequence
from training.datasets import FPS, MOCAP_DIR, TRAIN_CLIPS, clip_paths, on_neutral_body

BODIES: dict[str, np.ndarray] = {
    "neutral": np.asarray(NEUTRAL_PHENOTYPES, np.float32),
    "heavy": np.array([1.0, 1.0, 1.0, 1.0, 1.0, 1.0], np.float32),
    "light-tall": np.array([0.0, 0.77, 0.0, 1.0, 1.0, 0.0], np.float32),
    # training-only bodies (``training.train_canonical``), away from the test bodies: a short slim
    # woman and a tall muscular man
    "train-slim": np.array([0.0, 0.9, 0.3, 0.2, 0.2, 0.7], np.float32),
    "train-tall": np.array([1.0, 0.8, 0.7, 0.6, 0.8, 0.4], np.float32),
    # validation-only bodies for the learned models' body range (``SPLITS["bodies"]``), 0.22, 0.48
    # and 0.93 from the nearest training body: the neutral adult a little changed, a slim muscular
    # man, and an old, tall, thin woman
    "val-close": np.array([0.6, 0.85, 0.4, 0.6, 0.6, 0.4], np.float32),
    "val-near": np.array([1.0, 0.85, 1.0, 0.3, 0.6, 0.3], np.float32),
    "val-far": np.array([0.0, 1.0, 0.0, 0.0, 1.0, 1.0], np.float32),
    # a test-only body beyond every learned model's range (0.80 from the nearest training body,
    # the neutral one): a short, heavy, older man, where a one-size garment hangs long
    "test-short": np.array([1.0, 0.95, 0.3, 0.9, 0.1, 0.6], np.float32),
}


@dataclass(frozen=True)
class Case:
    """One (clip window, body) the judge simulates and compares on."""

    clip: str
    body: str
    start: int
    frames: int

    @property
    def name(self) -> str:
        return f"{self.clip}[{self.start}:{self.start + self.frames}] {self.body}"

    @property
    def key(self) -> str:
        return f"{self.clip}_{self.start}_{self.frames}_{self.body}"


SPLITS: dict[str, tuple[Case, ...]] = {
    "validation": (Case("02_02", "neutral", 30, 20), Case("02_02", "heavy", 30, 20)),
    "test": (Case("01_01", "neutral", 120, 20), Case("01_01", "heavy", 120, 20), Case("02_07", "light-tall", 60, 20),
             Case("01_01", "test-short", 120, 20)),
    # the validation clip on bodies no model trains on: how far from its training bodies a learned
    # model holds (``inference.defaults``' body range is chosen here, never on the test split)
    "bodies": (Case("02_02", "val-close", 30, 20), Case("02_02", "val-near", 30, 20), Case("02_02", "val-far", 30, 20)),
}
SMOKE = Case("02_02", "neutral", 30, 3)  # CI: three frames of the validation walk

for _cases in SPLITS.values():
    for _c in _cases:
        if _c.clip in TRAIN_CLIPS:
            raise AssertionError(f"{_c.clip} is a training clip")


def load_clip(clip_id: str, body: BodyModel, library: ClipLibrary | None = None) -> Clip:
    """A bundled clip, or a CMU AMC clip of ``training/sources`` retargeted onto the neutral
    body at 30 fps with its feet on z = 0 (as ``training.assets.build_motions`` builds them)."""
    library = library or ClipLibrary()
    if clip_id in library.ids():
        return library.load(clip_id)
    neutral = body.shape(NEUTRAL_PHENOTYPES[None])
    rotations, translation = on_neutral_body(load_asf_amc(*clip_paths(clip_id, MOCAP_DIR)), body, neutral)
    return Clip(id=clip_id, rotations=rotations.astype(np.float32), translation=translation.astype(np.float32), fps=FPS,
                leg_length_m=target_leg_length(neutral), phenotypes=np.asarray(NEUTRAL_PHENOTYPES, np.float32), ground_window_s=0.5)


class SourceClips(ClipLibrary):
    """The clip library of training and evaluation: the bundled clips, the given ``extra`` clips,
    and every CMU AMC clip of ``training/sources`` (``load_clip``: retargeted onto the neutral
    body, as the bundle's clips are built), so that ``MotionImporter`` reads them all."""

    def __init__(self, body: BodyModel, extra: tuple[Clip, ...] = (), assets_dir=None):
        super().__init__(assets_dir)
        self.body = body
        self._extra = {c.id: c for c in extra}

    def ids(self, include_test_only: bool = True) -> list[str]:
        sources = sorted(p.stem for p in MOCAP_DIR.glob("*/*.amc"))
        return list(dict.fromkeys([*self._extra, *super().ids(include_test_only), *sources]))

    def load(self, clip_id: str) -> Clip:
        if clip_id in self._extra:
            return self._extra[clip_id]
        if clip_id not in self._cache:
            self._cache[clip_id] = load_clip(clip_id, self.body, ClipLibrary(self.assets_dir))
        return self._cache[clip_id]


def clip_motion(body: BodyModel, shape: BodyShape, clip: Clip | str, frames: int | None = None, lift: bool = True) -> PoseSequence:
    """A clip on a shaped body as the service imports it: ``MotionImporter`` (the clip adapted to
    the body's leg length, at the clip's frame rate), its first ``frames`` frames (None: all),
    with the arms lifted out of the torso over those frames (``lift_arms``, the pipeline's
    default) unless ``lift`` is False; drape it with ``lift_arms=False`` then."""
    library = SourceClips(body, extra=(clip,) if isinstance(clip, Clip) else ())
    source = library.load(clip.id if isinstance(clip, Clip) else clip)
    n = source.num_frames if frames is None else frames
    if not 1 <= n <= source.num_frames:
        raise ValueError(f"{source.id}: {n} frames asked, the clip has {source.num_frames}")
    spec = ClipSpec(source.id, 0.0, (n - 1) / source.fps)
    motion = MotionImporter(body, library).import_motion(spec, shape, source.fps, MotionLimits(n, n, 0))
    if not lift:
        return motion
    return PoseSequence(lift_arms(body, shape, motion.rotations, motion.translation)[0], motion.translation, motion.fps)


def validation_motions(body: BodyModel, bodies: tuple[str, ...] = ("neutral", "heavy"), lift: bool = True):
    """The validation clip (CMU 02_02, ``SPLITS["validation"]``) on each of ``bodies`` (keys of
    ``BODIES``) as the service imports it (``clip_motion``): yields (body name, shape, motion).
    What the tools that choose a constant measure on."""
    clip = load_clip(SPLITS["validation"][0].clip, body)
    for name in bodies:
        shape = body.shape(np.asarray(BODIES[name], np.float32)[None])
        yield name, shape, clip_motion(body, shape, clip, lift=lift)


def case_motion(body: BodyModel, case: Case, clip: Clip | None = None) -> tuple[BodyShape, PoseSequence, int]:
    """The case's body shape and motion (``clip_motion``: the service's import, arms lifted),
    frames [0, start + frames).

    returns shape, motion (start + frames frames; the learned dynamics run from frame 0), start
    """
    clip = clip or load_clip(case.clip, body)
    if case.start + case.frames > clip.num_frames:
        raise ValueError(f"{case.name}: the clip has {clip.num_frames} frames")
    shape = body.shape(BODIES[case.body][None])
    return shape, clip_motion(body, shape, clip, case.start + case.frames), case.start


def lead_in_motion(rotations: np.ndarray, translation: np.ndarray, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """Poses from the rest pose to a clip's first pose, for a simulation to start from the rest
    drape: rotations s * r_0 (each joint's geodesic from identity), s = smoothstep(k / frames),
    k = 0..frames-1; translation held at t_0 (moving the rest drape up to the clip's height is a
    rigid shift, not dynamics).

    rotations : (T, J, 3) axis-angle radians ; translation : (T, 3) metres
    returns   : (frames, J, 3), (frames, 3) float32 (frame 0 is the rest pose, shifted)
    """
    u = np.arange(frames) / max(frames, 1)
    s = u * u * (3.0 - 2.0 * u)
    return (s[:, None, None] * rotations[0][None]).astype(np.float32), np.repeat(translation[:1], frames, 0).astype(np.float32)
