"""Precomputed numpy banks for the self-supervised garment training, so a training step is cheap.

- ``harmonic_basis``: the low-rank output basis of ``training.models`` (manifold harmonics).
- ``ShapeBank``: bodies of many adult shapes (the corners of the phenotype box + uniform
  samples) with what the SNUG losses need per shape: the shaped rest body around the garment,
  its vertex normals, the ``.mhclo`` retarget fit of the garment, KD-tree collision candidates.
- ``MotionBank``: CMU training clips retargeted onto the neutral body at 30 fps, with the motion
  descriptor gamma (eq. 6.17) of every frame and the 3-frame windows of SNUG §5.2.5.

Units: metres, seconds, radians. Arrays float32 (indices int32/int64).
"""
from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import eigsh

from inference.body import BodyModel
from inference.garment import GarmentAsset
from inference.mesh import vertex_normals
from inference.metrics import inside_mask
from inference.motion.asfamc import load_asf_amc
from inference.motion.bvh import load_bvh
from inference.motion.descriptor import DESCRIPTOR_LAYOUT, motion_descriptor
from inference.motion.retarget import ground, retarget, target_leg_length
from inference.motion.self_contact import ArmLifter
from training.models import phenotype_box
from training.candidates import body_candidates

log = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parents[1]
MOCAP_DIR = REPO_ROOT / "training" / "sources" / "mocap" / "cmu-asfamc"
CACHE_DIR = REPO_ROOT / "build" / "cache"
FPS = 30.0
# SNUG §5.2.5: the GRU is trained on sub-sequences of 3 frames.
WINDOW_FRAMES = 3
# CMU training clips (subject, trial). Never 01_01 (the spec's test sequence); 02_02 is held out
# for validation. AMC files under training/sources/mocap/cmu-asfamc/<subject>/, or a BVH file of
# BVH_CLIPS under training/sources/mocap/. 131_01 (CMU: "start, walk, stop", Michael Jackson
# styled) since session 13: with the two subjects' walks, runs and jumps alone the GRUs did not
# generalise to the dance clip (docs/archive/evaluation-ch4-ch5.md, "An unseen motion").
TRAIN_CLIPS = ("01_14", "02_01", "02_03", "02_04", "02_05", "02_09", "131_01")
VALIDATION_CLIP = "02_02"
TEST_ONLY_CLIPS = ("01_01", "02_07")  # the judge's test clips (training.protocol): reported only
# Clips that are never trained on: 01_01, and 131_03 (the bundled "dance" clip), which is the
# second validation of the wrinkle GRUs (a clip not trained on, ``training.evaluate --clip dance``).
HELD_OUT_CLIPS = TEST_ONLY_CLIPS + ("131_03",)
# CMU clips that come as (cgspeed) BVH conversions, in metres: subject 131, Michael Jackson styled.
BVH_CLIPS = {"131_01": "bvh/scaled_131_01.bvh", "131_03": "bvh/scaled_131_03.bvh"}
# Descriptor entries that scale with the body's size (root linear velocity and acceleration).
_LINEAR_SLICES = (DESCRIPTOR_LAYOUT["root_linear_velocity"], DESCRIPTOR_LAYOUT["root_linear_acceleration"])


# ------------------------------------------------------------------------------ basis
def graph_laplacian(num_vertices: int, edges: np.ndarray) -> sp.csc_matrix:
    """Combinatorial graph Laplacian L = D - A (V, V) of a mesh's edges (E, 2)."""
    e = np.asarray(edges, np.int64)
    A = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(num_vertices, num_vertices))
    A = ((A + A.T) > 0).astype(np.float64).tocsr()
    return (sp.diags(np.asarray(A.sum(1)).ravel()) - A).tocsc()


def harmonic_basis(num_vertices: int, edges: np.ndarray, k: int, cache: Path | None = None) -> np.ndarray:
    """The k smoothest manifold harmonics (eigenvectors of the graph Laplacian), (V, k) float32.

    Columns are scaled to unit RMS over the vertices (|phi|_2 = sqrt(V)), so a coefficient is
    the RMS displacement in metres of its mode. The constant mode of every connected component
    comes first (eigenvalue 0: rigid translation). Cached as ``cache`` (.npy) when given.
    """
    if cache is not None and cache.exists():
        U = np.load(cache)
        if U.shape == (num_vertices, k):
            return U
    k_eff = min(k, num_vertices - 2)
    # shift-invert just below 0: L is positive semi-definite, its null space is the constants
    _, U = eigsh(graph_laplacian(num_vertices, edges), k=k_eff, sigma=-1e-3, which="LM")
    U = (U * np.sqrt(num_vertices)).astype(np.float32)
    if k_eff < k:
        U = np.concatenate([U, np.zeros((num_vertices, k - k_eff), np.float32)], 1)
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        np.save(cache, U)
    return U


# ------------------------------------------------------------------------------ shapes
N_CORNERS = 2**6  # corners of the 6-dimensional phenotype box


def sample_adult_phenotypes(n: int, rng: np.random.Generator, corners: bool = True) -> np.ndarray:
    """n phenotype vectors (n, 6) float32 in the adult box (inference.body.PHENOTYPE_RANGES):
    the ``N_CORNERS`` corners first when ``corners`` (as many as fit in n), then uniform samples."""
    lo, hi = phenotype_box()
    rows = []
    if corners:
        rows = [lo + np.array(c, np.float32) * (hi - lo) for c in itertools.product((0, 1), repeat=6)][:n]
    uniform = lo + rng.random((n - len(rows), 6)).astype(np.float32) * (hi - lo)
    return np.concatenate([np.array(rows, np.float32).reshape(-1, 6), uniform], 0).astype(np.float32)


@dataclass
class ShapeBank:
    """Per-shape data of one garment for the static and dynamic losses (N shapes).

    phenotypes      : (N, 6)
    rest_bone_poses : (N, J, 4, 4), the shaped skeleton (inference.body.BodyShape)
    leg_length_m    : (N,) metres (inference.motion.retarget.target_leg_length)
    retarget        : (N, V, 3) metres, the .mhclo retarget fit (GarmentAsset.retarget_fit)
    body_index      : (M,) int64, the body vertices kept: every vertex that is a collision
                      candidate of some garment vertex for some shape (the body near the garment)
    body_points     : (N, M, 3) metres, shaped rest body at ``body_index``
    body_normals    : (N, M, 3) unit outward vertex normals (of the whole body mesh)
    body_weights    : (M, J) skinning weights of the kept body vertices
    candidates      : (N, V, k) int32, the k kept body vertices nearest to each retarget vertex
    rest_vertices   : (N, Vb, 3) float32 metres, the whole shaped rest body (the closed skin of
                      the exact inside test, ``inside_mask``)
    """

    phenotypes: np.ndarray
    rest_bone_poses: np.ndarray
    leg_length_m: np.ndarray
    retarget: np.ndarray
    body_index: np.ndarray
    body_points: np.ndarray
    body_normals: np.ndarray
    body_weights: np.ndarray
    candidates: np.ndarray
    rest_vertices: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.phenotypes)

    def inside_mask(self, body: BodyModel, shape_idx: np.ndarray, transforms: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Exact inside test of garment points against the posed closed skin (winding number >= 1,
        ``inference.metrics.inside_mask``): shapes ``shape_idx`` (B,) posed by ``transforms``
        (B, T, J, 4, 4), points (B*T, V, 3) metres; returns (B*T, V) bool."""
        B, T = transforms.shape[:2]
        skin = body.skin(self.rest_vertices[shape_idx], transforms).reshape(B * T, -1, 3)
        return inside_mask(points, skin, body.faces)

    @classmethod
    def build(cls, body: BodyModel, asset: GarmentAsset, phenotypes: np.ndarray, k: int = 8, chunk: int = 32) -> "ShapeBank":
        """Shape ``phenotypes`` (N, 6), fit the garment, find its collision candidates."""
        phenotypes = np.asarray(phenotypes, np.float32)
        parts: dict[str, list] = {n: [] for n in ("poses", "legs", "retarget", "points", "normals", "cand")}
        for s in range(0, len(phenotypes), chunk):
            shape = body.shape(phenotypes[s : s + chunk])
            fit = asset.retarget_fit(body.hm08_vertices(shape))
            parts["poses"].append(shape.rest_bone_poses)
            parts["legs"].append([target_leg_length(shape, b) for b in range(len(fit))])
            parts["retarget"].append(fit)
            parts["points"].append(shape.rest_vertices)
            parts["normals"].append(np.stack([vertex_normals(v, body.faces) for v in shape.rest_vertices]))
            parts["cand"].append(body_candidates(fit, shape.rest_vertices, k))
        points = np.concatenate(parts["points"])
        normals = np.concatenate(parts["normals"])
        cand = np.concatenate(parts["cand"])
        keep = np.unique(cand)  # the body near the garment, for every shape
        remap = np.full(points.shape[1], -1, np.int64)
        remap[keep] = np.arange(len(keep))
        return cls(
            phenotypes=phenotypes,
            rest_bone_poses=np.concatenate(parts["poses"]).astype(np.float32),
            leg_length_m=np.concatenate([np.asarray(x, np.float32) for x in parts["legs"]]),
            retarget=np.concatenate(parts["retarget"]).astype(np.float32),
            body_index=keep,
            body_points=np.ascontiguousarray(points[:, keep]),
            body_normals=np.ascontiguousarray(normals[:, keep]),
            body_weights=np.ascontiguousarray(body.dense_weights[keep]),
            candidates=remap[cand].astype(np.int32),
            rest_vertices=points.astype(np.float32),
        )


# ------------------------------------------------------------------------------ motions
def clip_paths(clip_id: str, mocap_dir: Path = MOCAP_DIR) -> tuple[Path, Path]:
    """ASF and AMC paths of a CMU clip id 'SS_TT' (subject, trial) that comes as AMC."""
    subject = clip_id.split("_")[0]
    return mocap_dir / subject / f"{subject}.asf", mocap_dir / subject / f"{clip_id}.amc"


def load_training_clip(clip_id: str, body: BodyModel, neutral, mocap_dir: Path = MOCAP_DIR, max_frames: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A CMU clip retargeted onto the neutral body at 30 fps, feet on z = 0 (as the bundled clips).

    returns rotations (T, 31, 3) float32 radians, translation (T, 3) float32 metres
    """
    if clip_id in HELD_OUT_CLIPS:
        raise ValueError(f"{clip_id} is held out for testing or validation: never train on it")
    if clip_id in BVH_CLIPS:
        source = load_bvh(mocap_dir.parent / BVH_CLIPS[clip_id])
    else:
        source = load_asf_amc(*clip_paths(clip_id, mocap_dir))
    if max_frames is not None:  # source frames at the source rate (CMU: 120 fps)
        source = source.frames(0, int(max_frames * source.fps / FPS) + 1)
    rotations, translation = on_neutral_body(source, body, neutral)
    T = len(rotations) if max_frames is None else min(max_frames, len(rotations))
    return rotations[:T], translation[:T]


def on_neutral_body(source, body: BodyModel, neutral) -> tuple[np.ndarray, np.ndarray]:
    """A parsed mocap clip (BVH or ASF/AMC) retargeted onto the neutral body at 30 fps, feet on
    z = 0 over the first half second: how ``training.assets.build_motions`` builds the bundled
    clips, and how training and evaluation bring in the CMU clips they read from
    ``training/sources``. returns rotations (T, 31, 3) radians, translation (T, 3) metres."""
    result = retarget(source, body, neutral, fps=FPS, grounded=False)
    translation = ground(body, neutral, result.rotations[None], result.translation[None], FPS, 0.5)[0]
    return result.rotations, translation


@dataclass
class MotionBank:
    """Concatenated clips on the neutral body, 30 fps (N frames in all).

    clip_ids     : clip id per clip ; clip_start : (C + 1,) frame offsets of the clips
    rotations    : (N, 31, 3) radians ; translation : (N, 3) metres (neutral body)
    gamma        : (N, F) motion descriptor of each frame within its clip (eq. 6.17)
    leg_length_m : leg length of the neutral body the clips are on
    windows      : (W,) int64, first frame of every 3-frame window inside one clip
    """

    clip_ids: list[str]
    clip_start: np.ndarray
    rotations: np.ndarray
    translation: np.ndarray
    gamma: np.ndarray
    leg_length_m: float
    windows: np.ndarray
    fps: float = FPS

    @classmethod
    def build(cls, clip_ids: tuple[str, ...] | list[str], body: BodyModel, neutral, mocap_dir: Path = MOCAP_DIR, max_frames: int | None = None) -> "MotionBank":
        rots, trans, gam, starts, windows = [], [], [], [0], []
        for cid in clip_ids:
            r, t = load_training_clip(cid, body, neutral, mocap_dir, max_frames)
            gam.append(motion_descriptor(r[None], t[None], FPS)[0])
            windows.append(starts[-1] + np.arange(max(len(r) - WINDOW_FRAMES + 1, 0)))
            rots.append(r)
            trans.append(t)
            starts.append(starts[-1] + len(r))
            log.info("clip %s: %d frames", cid, len(r))
        return cls(
            clip_ids=list(clip_ids),
            clip_start=np.array(starts, np.int64),
            rotations=np.concatenate(rots).astype(np.float32),
            translation=np.concatenate(trans).astype(np.float32),
            gamma=np.concatenate(gam).astype(np.float32),
            leg_length_m=float(target_leg_length(neutral, 0)),
            windows=np.concatenate(windows).astype(np.int64),
        )

    def save(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, clip_ids=np.array(self.clip_ids), clip_start=self.clip_start, rotations=self.rotations,
                 translation=self.translation, gamma=self.gamma, leg_length_m=np.float64(self.leg_length_m), windows=self.windows)

    @classmethod
    def load(cls, path: Path) -> "MotionBank":
        with np.load(path, allow_pickle=False) as f:
            return cls(clip_ids=[str(c) for c in f["clip_ids"]], clip_start=f["clip_start"], rotations=f["rotations"],
                       translation=f["translation"], gamma=f["gamma"], leg_length_m=float(f["leg_length_m"]), windows=f["windows"])

    @classmethod
    def cached(cls, clip_ids, body: BodyModel, neutral, max_frames: int | None = None, cache_dir: Path = CACHE_DIR) -> "MotionBank":
        """``build`` once, then from ``cache_dir`` (keyed by the clip ids and max_frames)."""
        path = cache_dir / f"motions_{'-'.join(clip_ids)}_{max_frames or 'all'}.npz"
        if path.exists():
            return cls.load(path)
        bank = cls.build(clip_ids, body, neutral, max_frames=max_frames)
        bank.save(path)
        return bank

    def gamma_statistics(self, std_floor: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
        """Mean and std (F,) float32 of gamma over all frames (std floored at ``std_floor``)."""
        return self.gamma.mean(0).astype(np.float32), np.maximum(self.gamma.std(0), std_floor).astype(np.float32)

    def windows_of(self, length: int) -> np.ndarray:
        """Start frames of the windows of ``length`` frames that stay within one clip."""
        if length < WINDOW_FRAMES:
            raise ValueError(f"windows need at least {WINDOW_FRAMES} frames (inertia, eq. 5.6), got {length}")
        clip = np.searchsorted(self.clip_start, self.windows, side="right") - 1
        return self.windows[self.windows + length <= self.clip_start[clip + 1]]

    def window_frames(self, starts: np.ndarray, length: int = WINDOW_FRAMES) -> np.ndarray:
        """Frame indices (B, length) of windows starting at ``starts`` (B,)."""
        return np.asarray(starts)[:, None] + np.arange(length)[None]


def scale_motion(translation: np.ndarray, gamma: np.ndarray, ratio: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The neutral body's motion on bodies with leg lengths ``ratio`` (B,) x the neutral one:
    root translation and the root linear velocity / acceleration entries of gamma scaled
    (as ``inference.motion.clips.adapt_clip`` scales translation; the floor correction is a
    vertical offset that changes neither the garment's inertia nor its contacts).

    translation : (B, T, 3) ; gamma : (B, T, F) ; returns both scaled (copies)
    """
    r = np.asarray(ratio, np.float32)[:, None, None]
    g = gamma.copy()
    for s in _LINEAR_SLICES:
        g[..., s] *= r
    return translation * r, g


# Clip frames on each side of a window that its arm correction sees (the correction widens each
# frame's angle over its neighbours, inference.motion.self_contact.SMOOTH_FRAMES).
LIFT_CONTEXT = 2


class WindowLifter:
    """The arm correction of the runtime (``inference.motion.self_contact``) on training windows,
    so that the GRU trains on the poses it will see (the service lifts the arms by default).

    Each window is lifted with up to LIFT_CONTEXT frames of its clip on each side, on its bank
    shape (an ``ArmLifter`` per shape, built on first use). The window's gamma gets the change
    that lifting makes to the descriptor: gamma + (desc(lifted context) - desc(context)), the same
    finite-difference stencil on both, so the clip-level differences of the cached gamma stay.
    The correction is invariant to the root translation: the neutral body's is used.
    """

    def __init__(self, body: BodyModel, bank: ShapeBank, motions: MotionBank):
        self.body, self.bank, self.motions = body, bank, motions
        self._lifters: dict[int, ArmLifter] = {}

    def lifter(self, shape: int) -> ArmLifter:
        if shape not in self._lifters:
            self._lifters[shape] = ArmLifter(self.body, self.body.shape(self.bank.phenotypes[shape][None]))
        return self._lifters[shape]

    def __call__(self, shape_idx: np.ndarray, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Lifted rotations (B, T, J, 3) and gamma (B, T, F) of windows ``frames`` (B, T) (consecutive
        frames of one clip each) on bank shapes ``shape_idx`` (B,)."""
        m = self.motions
        rotations, gamma = m.rotations[frames].copy(), m.gamma[frames].copy()
        clip = np.searchsorted(m.clip_start, frames[:, 0], side="right") - 1
        for b, (s, f) in enumerate(zip(shape_idx, frames)):  # per window: each has its own body
            a = max(int(m.clip_start[clip[b]]), int(f[0]) - LIFT_CONTEXT)
            e = min(int(m.clip_start[clip[b] + 1]), int(f[-1]) + 1 + LIFT_CONTEXT)
            rot, trans = m.rotations[a:e], m.translation[a:e]
            lifted, angles = self.lifter(int(s)).lift(rot, trans)
            if not angles.any():
                continue
            win = f - a
            rotations[b] = lifted[win]
            delta = motion_descriptor(lifted[None], trans[None], m.fps)[0] - motion_descriptor(rot[None], trans[None], m.fps)[0]
            gamma[b] += delta[win]
        return rotations, gamma


def pose_windows(body: BodyModel, bank: ShapeBank, shape_idx: np.ndarray, motions: MotionBank, frames: np.ndarray,
                 lifter: WindowLifter | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Skinning transforms and gamma of windows on bank shapes (numpy, per training step).

    shape_idx : (B,) into ``bank`` ; frames : (B, T) into ``motions`` ; lifter : the arm
    correction of these windows (None: the clips' poses as retargeted)
    returns   : transforms (B, T, J, 4, 4) float32 (rest -> posed, inference.body.BodyModel.pose)
                and gamma (B, T, F) float32
    """
    ratio = bank.leg_length_m[shape_idx] / motions.leg_length_m
    rotations, gamma = lifter(shape_idx, frames) if lifter is not None else (motions.rotations[frames], motions.gamma[frames])
    translation, gamma = scale_motion(motions.translation[frames], gamma, ratio)
    _, transforms = body.pose(bank.rest_bone_poses[shape_idx], rotations, translation)
    return transforms, gamma
