"""The canonical-space garment model at runtime (thesis ch. 6.3.2), fit 'canonical'.

A garment X in the canonical space (unposed, deshaped: on the neutral body in its rest pose) is
shaped and posed by the diffused body (``inference.diffused``, eq. 6.7-6.8):

    M_G(X, beta, theta) = sum_j W~_j(X) T_j(beta, theta) (X + B~s(X, beta))

with W~ and B~s read at the garment's own canonical points, not fixed per vertex. The canonical
body is constant, so a garment outside it (SDF(X) >= margin, one lookup) stays outside the posed
body wherever the body's own deformation does not fold space onto itself (the armpit and the
crotch when the limbs close, the arms sunk into a heavy torso): there the final exact stage
(``inference.repair``) moves the few vertices it must.

Two forms of X:

- static (dynamics 'none'): the garment's template pushed out of the canonical body to its
  margin (``push_out``: the templates are made collision-free on the neutral body, 4 mm - 13 cm
  from its skin, so this moves nothing on the shipped catalog; it guards a template added later);
  W~ and B~s are read once per request; once posed, the strain limit below (on the
  validation walk it takes the static crew-neck tee's, crop top's and shirt's edge p1 from
  0.62-0.65 to 0.75-0.77, where the skinned baselines have 0.69-0.71);
- learned (dynamics 'learned', thesis ch. 6.4): X_t = D(R(beta, gamma_1..t)), the regressor R
  into the latent of the garment's canonical VAE and its decoder D (``CanonicalGarment``: two
  ONNX models, a whole sequence in one call each, the GRU state in and out), pushed out to the
  margin; W~ and B~s are read at every frame's own points (eq. 6.7); once posed, its shortest
  edges are pushed back to 0.8 of their rest length and, for a dress or a bottom, its longest
  pulled back to 2.0 / 1.9 (``inference.strain``: the decoder's smooth basis compresses the short
  edges under the arms, and overstretches a one-size garment on a heavy body).

Units: metres. Arrays: float32, batch axis first.
"""
from __future__ import annotations

import json
import threading
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort
import scipy.sparse

from inference.diffused import DEFAULT_PATH, BodyOffsets, DiffusedBody
from inference.errors import InputShapeError, InputValueError
from inference.garment import GarmentAsset
from inference.learned import MODELS_DIR, MissingModelError, ort_session
from inference.mesh import content_key
from inference.strain import StrainLimit

MODEL_FILE = "canonical.json"  # in assets/models/<garment>/, next to the ONNX files it names
# ``CanonicalModels.rest_fit`` kept per garment and body (a sparse product, ~0.6 ms for the jacket)
FIT_ENTRIES = 32
# A learned canonical model serves, as a garment's default, the bodies whose phenotypes lie within
# this Euclidean distance of one of its training bodies (canonical.json's ``train_phenotypes``;
# phenotypes in [0, 1], ``inference.body.PHENOTYPE_LABELS``); farther, its regressor (trained on
# four bodies) extrapolates worse than the static canonical form, which the default falls back to
# (``covers``). Chosen on the validation clip on three bodies no model trains on, 0.23, 0.48 and
# 0.93 from the nearest training body (``training.protocol.SPLITS["bodies"]``; docs/benchmarks.md):
# the learned tops are closer to newton than the static form at 0.23 (mean 1.69 against 2.10 cm)
# but not at 0.48 (3.26 against 2.99); the learned bottoms and dress not even at 0.23 (3.15
# against 2.32). Each range is the midpoint between the last distance that holds and the next.
BODY_RANGE = 0.1
BODY_RANGE_BY_CATEGORY = {"top": 0.35}
# Within BLEND_BAND of the range (as a share of it) on either side, the default blends from the
# learned model into the beyond-range method (``beyond_weight``, a smoothstep of the distance), so
# that a body changed a little at the edge does not change its garment at once: on the walk, one
# step of 0.02 across the T-shirt's range moved its vertices by 1.8 cm on average, 10 cm at most.
BLEND_BAND = 0.25

# Central-difference step of the SDF gradient, metres (well inside the fine grid's 15 mm cells).
GRADIENT_STEP_M = 0.002
# Push iterations: the trilinear SDF is not exactly a distance, so a point is pushed again from
# where the last push left it (on points within 4 mm of the neutral skin, 3 passes left 4 %
# of them more than 0.5 mm short of the margin, at the head and toes; 6 passes left 0.25 %).
PUSH_STEPS = 6
# A point within this of the margin counts as there (the trilinear SDF's own error is ~1 mm).
PUSH_TOLERANCE_M = 1e-4


def sdf_gradient(diffused: DiffusedBody, points: np.ndarray) -> np.ndarray:
    """Unit gradient (N, 3) of the canonical SDF at points (N, 3), by central differences."""
    h = np.float32(GRADIENT_STEP_M)
    e = np.eye(3, dtype=np.float32) * h
    probe = np.concatenate([points[:, None] + e[None], points[:, None] - e[None]], 1)  # (N, 6, 3)
    s = diffused.sdf(probe)
    g = (s[:, :3] - s[:, 3:]) / (2 * h)
    return g / np.maximum(np.linalg.norm(g, axis=-1, keepdims=True), 1e-12)


def push_out(diffused: DiffusedBody, X: np.ndarray, margin_m: float, steps: int = PUSH_STEPS) -> tuple[np.ndarray, int]:
    """Points with SDF(X) < margin (less ``PUSH_TOLERANCE_M``) moved along the SDF's gradient to SDF = margin:
    X' = X + (margin - SDF(X)) grad SDF / |grad SDF|, repeated ``steps`` times.

    X : (..., 3) canonical points, metres ; returns (X' float32 (..., 3), number of points moved)
    """
    X = np.array(X, np.float32, copy=True)
    if X.shape[-1] != 3:
        raise InputShapeError("X", "(..., 3)", X.shape)
    flat = X.reshape(-1, 3)
    low = np.flatnonzero(diffused.sdf(flat) < margin_m - PUSH_TOLERANCE_M)  # only these are looked at again
    moved = len(low)
    for _ in range(steps):
        if not len(low):
            break
        s = diffused.sdf(flat[low])
        low = low[s < margin_m - PUSH_TOLERANCE_M]
        s = s[s < margin_m - PUSH_TOLERANCE_M]
        flat[low] += (margin_m - s)[:, None] * sdf_gradient(diffused, flat[low])
    return X, int(moved)


def push_fields(diffused: DiffusedBody, X: np.ndarray, margin_m: float,
                offsets: BodyOffsets | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """``push_out`` and the fields eq. 6.7 reads (``DiffusedBody.fields``) in one gather: the SDF
    is the fields' last channel (the same interpolation, bitwise), so only the points pushed are
    read again; with the body's ``offsets``, B~s(X', beta) comes from the same pass
    (``DiffusedBody.fields_and_offsets``). X (..., 3) metres -> (X' float32 (..., 3), fields
    (..., K + 1), B~s (..., 3) or None)."""
    X = np.array(X, np.float32, copy=True)

    def read(points: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        return (diffused.fields(points), None) if offsets is None else diffused.fields_and_offsets(points, offsets)

    fields, shape_offsets = read(X)
    low = fields[..., -1] < margin_m - PUSH_TOLERANCE_M
    if low.any():
        X[low] = push_out(diffused, X[low], margin_m)[0]
        fields[low], again = read(X[low])
        if shape_offsets is not None:
            shape_offsets[low] = again
    return X, fields, shape_offsets


@dataclass
class CanonicalGarment:
    """One garment's learned canonical model: the regressor R (phenotypes (B, 6), gamma (B, T, F),
    h0 (L, B, H) -> z (B, T, latent), hT) and the VAE decoder D (z (N, latent) -> X (N, V, 3)).

    meta : canonical.json (files, shapes, the training record)
    """

    garment_id: str
    meta: dict
    regressor: ort.InferenceSession
    decoder: ort.InferenceSession

    @classmethod
    def load(cls, directory: Path | str, threads: int = 1) -> "CanonicalGarment":
        directory = Path(directory)
        meta = json.loads((directory / MODEL_FILE).read_text())
        return cls(str(meta["garment"]), meta, ort_session(directory / meta["regressor"]["file"], threads),
                   ort_session(directory / meta["decoder"]["file"], threads))

    @property
    def state_shape(self) -> tuple[int, int]:
        """(L, H): GRU layers and hidden size; the state is (L, B, H)."""
        L, _, H = self.meta["regressor"]["inputs"]["h0"]
        return int(L), int(H)

    def sequence(self, phenotypes: np.ndarray, gamma: np.ndarray, h0: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """X_t = D(R(beta, gamma_1..t)) for one body: phenotypes (1, 6), gamma (1, T, F), h0 (L, 1, H)
        or None (zeros: a motion's first frame) -> canonical frames (T, V, 3) float32 metres, hT."""
        p = np.ascontiguousarray(phenotypes, np.float32)
        g = np.ascontiguousarray(gamma, np.float32)
        F = int(self.meta["regressor"]["inputs"]["gamma"][2])
        if p.shape != (1, 6) or not np.isfinite(p).all():
            raise InputShapeError("phenotypes", "(1, 6), finite", p.shape)
        if g.ndim != 3 or g.shape[0] != 1 or g.shape[2] != F:
            raise InputShapeError("gamma", f"(1, T, {F})", g.shape)
        L, H = self.state_shape
        h0 = np.zeros((L, 1, H), np.float32) if h0 is None else np.ascontiguousarray(h0, np.float32)
        if h0.shape != (L, 1, H):
            raise InputShapeError("h0", f"({L}, 1, {H})", h0.shape)
        z, hT = self.regressor.run(None, {"phenotypes": p, "gamma": g, "h0": h0})
        (X,) = self.decoder.run(None, {"z": z[0]})
        if not np.isfinite(X).all():
            raise InputValueError("motion", "the canonical model gave non-finite vertices for this motion")
        return X, hT


class CanonicalModels:
    """The diffused body and each garment's canonical forms, loaded once, shared by every request:
    the static one (every garment) and the learned one (garments whose ``models_dir/<id>/``
    holds ``canonical.json``)."""

    def __init__(self, diffused_path: Path | str = DEFAULT_PATH, models_dir: Path | str = MODELS_DIR, threads: int = 1):
        self.diffused_path = Path(diffused_path)
        self.models_dir = Path(models_dir)
        self.threads = threads
        self._diffused: DiffusedBody | None = None
        self._templates: dict[str, tuple[np.ndarray, np.ndarray, scipy.sparse.csr_matrix]] = {}
        self._learned: dict[str, CanonicalGarment] = {}
        self._limits: dict[str, StrainLimit] = {}
        self._ranges: dict[str, np.ndarray | None] = {}
        self._fits: OrderedDict = OrderedDict()  # rest_fit per garment and body (LRU)
        self._lock = threading.Lock()

    @property
    def diffused(self) -> DiffusedBody:
        with self._lock:
            if self._diffused is None:
                self._diffused = DiffusedBody.load(self.diffused_path)
            return self._diffused

    def template(self, garment: GarmentAsset) -> np.ndarray:
        """X of the garment (V, 3) float32: its template pushed out of the canonical body to its
        collision margin (``material.collision_margin_m``)."""
        return self._static(garment)[0]

    def _static(self, garment: GarmentAsset) -> tuple[np.ndarray, np.ndarray, scipy.sparse.csr_matrix]:
        """X, W~(X) (V, J) and the shape operator at X (``DiffusedBody.shape_operator``), once per garment."""
        diffused = self.diffused
        with self._lock:
            if garment.id not in self._templates:
                X = push_out(diffused, garment.template, margin(garment))[0]
                self._templates[garment.id] = (X, diffused.weights(X), diffused.shape_operator(X))
            return self._templates[garment.id]

    def weights(self, garment: GarmentAsset) -> np.ndarray:
        """W~(X) (V, J) float32 at the garment's static canonical form X (eq. 6.4), once per garment."""
        return self._static(garment)[1]

    def rest_fit(self, garment: GarmentAsset, rest_vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The garment shaped to a body in its rest pose, T_G(X, beta) = X + B~s(X, beta) (eq. 6.8),
        (V, 3) float32, and its skinning weights W~(X) (V, J) (eq. 6.4), X the static canonical form.

        rest_vertices : (Vb, 3) the body's rest vertices (``BodyShape.rest_vertices[0]``)
        """
        X, W, S = self._static(garment)
        d = self.diffused
        v = np.asarray(rest_vertices, np.float32)
        if v.shape != d.neutral_vertices.shape:
            raise InputShapeError("rest_vertices", str(d.neutral_vertices.shape), v.shape)
        key = (garment.id, content_key(v))  # a shopper's body comes back with every outfit and motion
        with self._lock:
            hit = self._fits.get(key)
            if hit is not None:
                self._fits.move_to_end(key)
                return hit, W
        fit = (X + S @ (v - d.neutral_vertices)).astype(np.float32)
        fit.flags.writeable = False
        with self._lock:
            self._fits[key] = fit
            while len(self._fits) > FIT_ENTRIES:
                self._fits.popitem(last=False)
        return fit, W

    def strain_limit(self, garment: GarmentAsset) -> StrainLimit:
        """The garment's strain limit (``inference.strain``) on its rest lengths, once per garment."""
        with self._lock:
            if garment.id not in self._limits:
                self._limits[garment.id] = StrainLimit.for_garment(garment)
            return self._limits[garment.id]

    def available(self, garment_id: str) -> bool:
        """Whether the garment ships a learned canonical model (without loading it)."""
        return (self.models_dir / garment_id / MODEL_FILE).exists()

    def train_phenotypes(self, garment_id: str) -> np.ndarray | None:
        """The phenotypes (n, 6) of the bodies the garment's learned model was trained on
        (canonical.json's ``train_phenotypes``, read once); None without a learned model or a record."""
        with self._lock:
            if garment_id not in self._ranges:
                path = self.models_dir / garment_id / MODEL_FILE
                bodies = json.loads(path.read_text()).get("train_phenotypes") if path.exists() else None
                self._ranges[garment_id] = None if not bodies else np.asarray(list(bodies.values()), np.float32).reshape(-1, 6)
            return self._ranges[garment_id]

    def covers(self, garment: GarmentAsset, phenotypes: np.ndarray) -> bool:
        """Whether the garment's learned model serves a body by default: its phenotypes (6,) or
        (1, 6) within its category's range (``BODY_RANGE_BY_CATEGORY``, else ``BODY_RANGE``) of a
        training body's (a model with no record covers every body)."""
        train = self.train_phenotypes(garment.id)
        if train is None:
            return True
        p = np.asarray(phenotypes, np.float32).reshape(1, 6)
        return bool(np.linalg.norm(train - p, axis=1).min() <= BODY_RANGE_BY_CATEGORY.get(garment.category, BODY_RANGE))

    def beyond_weight(self, garment: GarmentAsset, phenotypes: np.ndarray) -> float:
        """How far beyond the garment's body range a body is (``covers``): 0 within (1 -
        BLEND_BAND) of the range, 1 beyond (1 + BLEND_BAND) of it, a smoothstep between (0.5 at
        the range); 0 for a model with no record of its bodies."""
        train = self.train_phenotypes(garment.id)
        if train is None:
            return 0.0
        r = BODY_RANGE_BY_CATEGORY.get(garment.category, BODY_RANGE)
        d = float(np.linalg.norm(train - np.asarray(phenotypes, np.float32).reshape(1, 6), axis=1).min())
        t = min(max((d - r * (1.0 - BLEND_BAND)) / (2.0 * r * BLEND_BAND), 0.0), 1.0)
        return t * t * (3.0 - 2.0 * t)

    def learned(self, garment_id: str, field: str = "/options/dynamics") -> CanonicalGarment:
        """The garment's learned canonical model; ``MissingModelError`` (naming ``field``) if none."""
        with self._lock:
            if garment_id not in self._learned:
                if not self.available(garment_id):
                    raise MissingModelError(field, f"garment {garment_id!r} has no learned canonical model "
                                                   f"(assets/models/{garment_id}/{MODEL_FILE}); use dynamics 'none' with fit 'canonical'")
                self._learned[garment_id] = CanonicalGarment.load(self.models_dir / garment_id, self.threads)
            return self._learned[garment_id]

    def load_all(self, garment_ids) -> list[str]:
        """The diffused body, and every listed garment's learned model that ships (a service's
        start-up: no request pays for it, a broken file stops the start); the ids loaded. Reads
        the fields once, so that the compiled interpolation is ready too."""
        self.diffused.sdf(np.zeros((1, 3), np.float32))
        loaded = [g for g in garment_ids if self.available(g)]
        for g in loaded:
            self.learned(g)
        return loaded

    def frames(self, garment: GarmentAsset, phenotypes: np.ndarray, gamma: np.ndarray, segments: list[int],
               h0: np.ndarray | None = None, push: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """The learned canonical frames X_t (T, V, 3) of one body over motions concatenated along
        T (``segments``: their frame counts; the GRU restarts from zeros at each, or from ``h0``
        when there is one segment), pushed out of the canonical body to the garment's margin
        (``push``; else as decoded, for ``push_fields``), and the GRU state after the last frame."""
        model = self.learned(garment.id)
        if int(model.meta["vertices"]) != garment.num_vertices:
            raise InputShapeError("canonical model", f"({garment.num_vertices} vertices)", (int(model.meta["vertices"]),))
        if h0 is not None and len(segments) != 1:
            raise InputShapeError("segments", "one segment when a GRU state is carried in", tuple(segments))
        bounds = np.cumsum([0, *segments])
        parts, hT = [], h0
        for a, b in zip(bounds[:-1], bounds[1:]):
            X, hT = model.sequence(phenotypes, gamma[:, a:b], h0)
            parts.append(X)
        X = np.concatenate(parts)
        return (push_out(self.diffused, X, margin(garment))[0] if push else X), hT


def margin(garment: GarmentAsset) -> float:
    """The garment's clearance from the canonical body, metres (its collision margin)."""
    return float(garment.material.get("collision_margin_m", 0.003))


_DEFAULT: CanonicalModels | None = None


def default_canonical() -> CanonicalModels:
    """The process-wide canonical models over the repository's assets."""
    global _DEFAULT
    if _DEFAULT is None:
        _DEFAULT = CanonicalModels()
    return _DEFAULT
