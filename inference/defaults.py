"""Each garment's default method: the fit and dynamics a drape runs when the request names none.

The table is one hand-written file, ``assets/models/defaults.json``, set from the validation
protocol's results (docs/evaluation.md: the learned model ships as a garment's default only
where it beats the baselines, otherwise the baseline does):

    {"format": 1,
     "garments": {"<garment id>": {"fit": "canonical" | "learned-canonical" | "learned" | "retarget",
                                   "dynamics": "learned" | "none",
                                   "reason": "<one sentence>", "evidence": "docs/evaluation.md",
                                   "beyond_range": {"fit": ..., "dynamics": ..., "reason": ...}}}}

``beyond_range`` (optional, only beside fit 'canonical' with dynamics 'learned'): the method a
body beyond the learned canonical model's body range runs instead
(``inference.canonical.CanonicalModels.covers``), chosen on the validation clip on bodies no
model trains on (``training.protocol.SPLITS["bodies"]``); without it, the static canonical form.

It names every catalog garment and nothing else (``DefaultMethods.load`` checks, so a bad file
stops the service at start-up). fit 'none' (plain LBS of the neutral template) is never a
default: it changes the skinning transforms and the guard's rest body of the whole drape, so it
stays an explicit option that applies to every garment. ``resolve_methods`` turns a request's
options (None: each garment's own default) into the method each garment runs.
"""
from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal, NoReturn, get_args

from inference.body import ASSETS_DIR
from inference.errors import InputValueError
from inference.garment import catalog_ids

FitMode = Literal["canonical", "learned-canonical", "learned", "retarget", "none"]
DynamicsMode = Literal["learned", "none"]
FIT_MODES: tuple[str, ...] = get_args(FitMode)
DYNAMICS_MODES: tuple[str, ...] = get_args(DynamicsMode)
DEFAULT_FIT_MODES: tuple[str, ...] = ("canonical", "learned-canonical", "learned", "retarget")  # fit 'none' is explicit only (module docstring)
# The fits posed by the diffused body (thesis eq. 6.7-6.8): no guard push, the final exact stage alone.
CANONICAL_FITS: frozenset[str] = frozenset({"canonical", "learned-canonical"})
DEFAULTS_FILE = "models/defaults.json"  # relative to the assets folder
DEFAULTS_FORMAT = 1
_ENTRY_KEYS = frozenset({"fit", "dynamics", "reason", "evidence"})
_OPTIONAL_KEYS = frozenset({"beyond_range"})
_BEYOND_KEYS = frozenset({"fit", "dynamics", "reason"})


class DefaultMethodsError(ValueError):
    """The defaults file is missing, malformed, or does not name exactly the catalog's garments."""


@dataclass(frozen=True)
class Method:
    """What one garment runs: fit 'canonical' | 'learned-canonical' | 'learned' | 'retarget' |
    'none', dynamics 'learned' | 'none' (``inference.pipeline`` describes each)."""

    fit: FitMode
    dynamics: DynamicsMode
    # Near the edge of a learned canonical model's body range: the beyond-range method blended in,
    # posed = (1 - beyond_weight) * own + beyond_weight * beyond, before the collision stages.
    beyond: Method | None = None
    beyond_weight: float = 0.0

    @property
    def own(self) -> Method:
        """The method without its blend."""
        return Method(self.fit, self.dynamics)

    @property
    def fits(self) -> tuple[str, ...]:
        """The fits this method runs (two when blended)."""
        return (self.fit,) if self.beyond is None else (self.fit, self.beyond.fit)

    @property
    def canonical(self) -> bool:
        """Posed by the diffused body (``CANONICAL_FITS``), blend included."""
        return all(f in CANONICAL_FITS for f in self.fits)


@dataclass(frozen=True)
class BeyondRange:
    """A default's method on bodies beyond its learned canonical model's body range, and why."""

    fit: FitMode
    dynamics: DynamicsMode
    reason: str

    @property
    def method(self) -> Method:
        return Method(self.fit, self.dynamics)

    def __post_init__(self):
        _check_default(self.fit, self.dynamics, self.reason)


@dataclass(frozen=True)
class DefaultMethod:
    """One garment's entry of the defaults file: its default method and why it was chosen."""

    fit: FitMode
    dynamics: DynamicsMode
    reason: str
    evidence: str
    beyond_range: BeyondRange | None = None

    @property
    def method(self) -> Method:
        return Method(self.fit, self.dynamics)

    def __post_init__(self):
        _check_default(self.fit, self.dynamics, self.reason)
        if not isinstance(self.evidence, str) or not self.evidence.strip():
            raise DefaultMethodsError("evidence must be a non-empty string")
        if self.beyond_range is not None and self.method != Method("canonical", "learned"):
            raise DefaultMethodsError("beyond_range goes only with fit 'canonical' and dynamics 'learned' (the default with a body range)")

    def as_dict(self) -> dict:
        d = asdict(self)
        if self.beyond_range is None:
            del d["beyond_range"]
        return d


def _check_default(fit: str, dynamics: str, reason: str) -> None:
    if fit not in DEFAULT_FIT_MODES:
        raise DefaultMethodsError(f"fit {fit!r} is not a default fit; expected one of {list(DEFAULT_FIT_MODES)} "
                                  "(fit 'none' is an explicit option only)")
    if dynamics not in DYNAMICS_MODES:
        raise DefaultMethodsError(f"dynamics {dynamics!r}, expected one of {list(DYNAMICS_MODES)}")
    if not isinstance(reason, str) or not reason.strip():
        raise DefaultMethodsError("reason must be a non-empty string")


class DefaultMethods:
    """The defaults table: garment id -> ``DefaultMethod``."""

    def __init__(self, entries: Mapping[str, DefaultMethod], source: str = "defaults"):
        self._entries = dict(sorted(entries.items()))
        self.source = source

    @classmethod
    def from_json(cls, data: object, garment_ids: Iterable[str], source: str = "defaults") -> "DefaultMethods":
        """Validate the parsed file against the catalog's ``garment_ids`` (``DefaultMethodsError``
        naming the file and the entry otherwise)."""
        def fail(message: str) -> NoReturn:
            raise DefaultMethodsError(f"{source}: {message}")

        if not isinstance(data, dict) or set(data) != {"format", "garments"}:
            fail('expected an object with exactly the keys "format" and "garments"')
        if data["format"] != DEFAULTS_FORMAT:
            fail(f"format {data['format']!r}, expected {DEFAULTS_FORMAT}")
        garments = data["garments"]
        if not isinstance(garments, dict):
            fail('"garments" must be an object: garment id -> {fit, dynamics, reason, evidence}')
        known = set(garment_ids)
        unknown, missing = sorted(set(garments) - known), sorted(known - set(garments))
        if unknown:
            fail(f"unknown garment ids {unknown}; the catalog has {sorted(known)}")
        if missing:
            fail(f"no default method for garments {missing}: every catalog garment needs one")
        entries = {}
        for gid, entry in garments.items():
            if not isinstance(entry, dict) or not _ENTRY_KEYS <= set(entry) <= _ENTRY_KEYS | _OPTIONAL_KEYS:
                fail(f"garments.{gid}: expected the keys {sorted(_ENTRY_KEYS)} (and optionally {sorted(_OPTIONAL_KEYS)})")
            entry = dict(entry)
            if "beyond_range" in entry:
                if not isinstance(entry["beyond_range"], dict) or set(entry["beyond_range"]) != _BEYOND_KEYS:
                    fail(f"garments.{gid}.beyond_range: expected exactly the keys {sorted(_BEYOND_KEYS)}")
                try:
                    entry["beyond_range"] = BeyondRange(**entry["beyond_range"])
                except DefaultMethodsError as exc:
                    fail(f"garments.{gid}.beyond_range: {exc}")
            try:
                entries[gid] = DefaultMethod(**entry)
            except DefaultMethodsError as exc:
                fail(f"garments.{gid}: {exc}")
        return cls(entries, source)

    @classmethod
    def load(cls, path: Path | str, garment_ids: Iterable[str]) -> "DefaultMethods":
        """Read and validate the defaults file at ``path`` against the catalog's ``garment_ids``."""
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except OSError as exc:
            raise DefaultMethodsError(f"{path}: cannot read the garments' default methods ({exc.strerror})") from exc
        except json.JSONDecodeError as exc:
            raise DefaultMethodsError(f"{path}: not valid JSON ({exc})") from exc
        return cls.from_json(data, garment_ids, str(path))

    def get(self, garment_id: str) -> DefaultMethod:
        """The garment's entry; ``DefaultMethodsError`` if the table has none."""
        try:
            return self._entries[garment_id]
        except KeyError:
            raise DefaultMethodsError(f"{self.source}: no default method for garment {garment_id!r}") from None

    def __contains__(self, garment_id: object) -> bool:
        return garment_id in self._entries

    def as_dict(self) -> dict[str, dict]:
        """garment id -> entry, sorted by id (the file's ``garments`` object)."""
        return {gid: e.as_dict() for gid, e in self._entries.items()}


def default_methods(assets_dir: Path | str = ASSETS_DIR) -> DefaultMethods:
    """The shipped table of an assets folder, ``assets_dir/models/defaults.json``, checked against
    its garments (read on each call: a service loads it once, at start-up)."""
    return DefaultMethods.load(Path(assets_dir) / DEFAULTS_FILE, catalog_ids(assets_dir))


# In an outfit, a default's fit 'learned-canonical' runs the static canonical form instead. The fit
# regressor's one-size garment does not share the static form's grading with the other layers and
# leaves 2-11 % of its vertices inside the body before the final stage; layered, on the validation
# walk (neutral, heavy) and the bodies split, the intersecting triangle pairs between layers rose
# 1.1-8.8x against the static form (crop top under shirt, heavy body: 519 -> 1,149 per frame;
# shirt under jacket, val-near: 52 -> 458; T-shirt under jacket, session 34: 37 -> 145), measured
# with ``tools/outfit_layers.py`` (docs/benchmarks.md, "A compact fit regressor").
OUTFIT_FIT = {"learned-canonical": Method("canonical", "none")}


def resolve_methods(garment_ids: Sequence[str], fit: str | None = None, dynamics: str | None = None,
                    defaults: DefaultMethods | None = None, beyond: Callable[[str], float] | None = None,
                    outfit: bool = False) -> list[Method]:
    """The method each garment runs: ``fit`` / ``dynamics`` where given (the same for every
    garment), else the garment's own default from ``defaults`` (default: ``default_methods()``,
    read only when an option is None).

    beyond : garment id -> how far beyond its learned canonical model's body range this body is,
             0 (within) .. 1 (beyond) (``inference.canonical.CanonicalModels.beyond_weight``):
             at 1 a default of fit 'canonical' with dynamics 'learned' runs the entry's
             ``beyond_range`` method (without one, dynamics 'none': the static canonical form),
             between 0 and 1 a blend of the two (``Method.beyond_weight``); never where the request
             names the fit or the dynamics
    outfit  : the request layers several garments: where the fit comes from the defaults, fit
              'learned-canonical' (a garment's default or its beyond-range method) runs the static
              canonical form instead (``OUTFIT_FIT``)
    returns : one ``Method`` per garment id, in order
    """
    if fit is not None and fit not in FIT_MODES:
        raise InputValueError("/options/fit", f"{fit!r}, expected one of {list(FIT_MODES)} or null")
    if dynamics is not None and dynamics not in DYNAMICS_MODES:
        raise InputValueError("/options/dynamics", f"{dynamics!r}, expected one of {list(DYNAMICS_MODES)} or null")
    if (fit is None or dynamics is None) and defaults is None:
        defaults = default_methods()

    def layered(m: Method) -> Method:
        return OUTFIT_FIT.get(m.fit, m) if outfit and fit is None else m

    out = []
    for g in garment_ids:
        m = layered(Method(fit if fit is not None else defaults.get(g).fit, dynamics if dynamics is not None else defaults.get(g).dynamics))
        if dynamics is None and m == Method("canonical", "learned") and beyond is not None:
            w = float(beyond(g))
            entry = defaults.get(g).beyond_range if fit is None else None
            other = layered(entry.method) if entry is not None else Method("canonical", "none")  # beyond the learned model's body range
            if w >= 1.0:
                m = other
            elif w > 0.0:
                m = Method("canonical", "learned", beyond=other, beyond_weight=round(w, 4))
        out.append(m)
    return out
