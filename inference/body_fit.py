"""Phenotypes from tape measurements: the adult anny body whose ISO 8559-1 measurements
(``inference.measurements``) are the shopper's.

Solves, over the phenotypes x in the adult box (``PHENOTYPE_RANGES``; gender fixed when given),

    min_x  sum_k ((m_k(x) - t_k) / 1 cm)^2 + ((M(x) - t_M) / 1 kg)^2 + (lambda (x - x_0))^2,

with m_k the five measurements, M the body mass (only when a weight is given), x_0 the neutral
adult and lambda = ``PRIOR`` a weak pull that picks, among the bodies that fit, the most
ordinary one (a 1-unit phenotype change weighs as much as ``PRIOR`` cm of misfit). Bounded
trust-region least squares (scipy ``least_squares``, 'trf'), its forward-difference Jacobian
computed as one batch of bodies, stopped once every measurement is within ``STOP_FRACTION`` of
its tolerance (the prior only steers, it is not minimised to the end); restarts from a few other bodies when the first solution
misses a measurement by more than ``TOLERANCE_M``. A measurement that still misses is outside
the adult body space for the others: ``BodyFit.misses`` names it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from inference.body import NEUTRAL_PHENOTYPES, PHENOTYPE_LABELS, PHENOTYPE_RANGES, BodyModel
from inference.errors import InputValueError
from inference.measurements import MEASUREMENTS, BodyMeasurer

TOLERANCE_M = 0.01  # default: a measurement the fit misses by more is "not reachable"
TOLERANCE_KG = 1.0
PRIOR = 0.05
STOP_FRACTION = 0.1  # stop once every measurement is within this fraction of its tolerance
_STEP = 2e-3  # forward-difference step in phenotype units
_SCALE_M = 0.01
_SCALE_KG = 1.0
# anny's gender runs from 0 (male) to 1 (female); a stated gender keeps the fit on its half (the
# extremes are caricatures: ordinary women's measurements fit at gender ~0.6-0.8, not 1)
GENDERS = {"male": (0.0, 0.5), "female": (0.5, 1.0)}


@dataclass(frozen=True)
class BodyFit:
    """The fitted body: phenotypes (6,) in ``PHENOTYPE_LABELS`` order, its measurements (metres,
    ``MEASUREMENTS`` order) and mass (kg), the residuals (fitted - asked, metres / kg), and the
    names of the measurements missed by more than the tolerance (worst first)."""

    phenotypes: np.ndarray
    measurements: np.ndarray
    mass_kg: float
    residuals: np.ndarray
    mass_residual_kg: float | None
    misses: tuple[str, ...]
    evaluations: int


class BodyFitter:
    """Fits phenotypes to measurements for one body model."""

    def __init__(self, body: BodyModel, measurer: BodyMeasurer | None = None):
        self.body = body
        self.measurer = measurer or BodyMeasurer(body)
        self.lower = np.array([PHENOTYPE_RANGES[n][0] for n in PHENOTYPE_LABELS])
        self.upper = np.array([PHENOTYPE_RANGES[n][1] for n in PHENOTYPE_LABELS])

    def evaluate(self, phenotypes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(B, 6) phenotypes -> measurements (B, 5) metres, mass (B,) kg."""
        shape = self.body.shape(np.asarray(phenotypes, np.float32))
        m = self.measurer.measure(shape.rest_vertices, shape.bone_heads)
        return m.as_array(), m.mass_kg

    def fit(self, targets_m: np.ndarray, weight_kg: float | None = None, gender: tuple[float, float] | None = None,
            tolerance_m: float = TOLERANCE_M, tolerance_kg: float = TOLERANCE_KG) -> BodyFit:
        """targets_m: (5,) in ``MEASUREMENTS`` order, metres; weight in kg; gender: the (lo, hi)
        range of the gender phenotype (``GENDERS``; lo == hi fixes it), None for the whole range;
        a measurement missed by more than its tolerance is in ``BodyFit.misses``."""
        targets = np.asarray(targets_m, np.float64)
        if targets.shape != (len(MEASUREMENTS),) or not np.all(np.isfinite(targets)):
            raise InputValueError("measurements", f"expected {len(MEASUREMENTS)} finite values")
        free = np.ones(len(PHENOTYPE_LABELS), bool)
        x0 = NEUTRAL_PHENOTYPES.astype(np.float64).copy()
        lower, upper = self.lower.copy(), self.upper.copy()
        if gender is not None:
            g = PHENOTYPE_LABELS.index("gender")
            lower[g], upper[g] = gender
            x0[g] = 0.5 * (lower[g] + upper[g])
            free[g] = upper[g] > lower[g]
        evaluations = 0

        def full(z: np.ndarray) -> np.ndarray:  # (n, free) -> (n, 6)
            x = np.tile(x0, (len(z), 1))
            x[:, free] = z
            return x

        def residuals(x: np.ndarray, m: np.ndarray, mass: np.ndarray) -> np.ndarray:  # (n, R)
            parts = [(m - targets) / _SCALE_M]
            if weight_kg is not None:
                parts.append(((mass - weight_kg) / _SCALE_KG)[:, None])
            parts.append(PRIOR * (x[:, free] - NEUTRAL_PHENOTYPES[free]))
            return np.concatenate(parts, axis=1)

        cache: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

        def batch(z: np.ndarray):
            nonlocal evaluations
            # forward differences step into the box: backwards at an upper bound
            steps = np.where(z + _STEP <= upper[free], _STEP, -_STEP)
            probes = np.vstack([z, z + np.diag(steps)])
            x = full(probes)
            m, mass = self.evaluate(x)
            evaluations += len(probes)
            r = residuals(x, m, mass)
            jac = (r[1:] - r[0]).T / steps
            cache[z.tobytes()] = (r[0], jac)
            return r[0], jac

        def fun(z):
            hit = cache.get(z.tobytes())
            return hit[0] if hit is not None else batch(z)[0]

        def jac(z):
            hit = cache.get(z.tobytes())
            return hit[1] if hit is not None else batch(z)[1]

        def good_enough(intermediate_result):
            if _worst_miss(intermediate_result.fun, weight_kg is not None, tolerance_m, tolerance_kg) <= STOP_FRACTION:
                raise StopIteration  # every measurement within a tenth of the tolerance

        lo, hi = lower[free], upper[free]
        starts = [x0[free]] + [np.clip(x0[free] + d, lo, hi) for d in _restart_offsets(free.sum())]
        best = None
        for start in starts:
            sol = least_squares(fun, start, jac=jac, bounds=(lo, hi), method="trf", x_scale=1.0,
                                xtol=1e-4, ftol=1e-4, max_nfev=30, callback=good_enough)
            if best is None or sol.cost < best.cost:
                best = sol
            if _worst_miss(best.fun, weight_kg is not None, tolerance_m, tolerance_kg) <= 1.0:
                break
        x = full(best.x[None])
        m, mass = self.evaluate(x)
        res = m[0] - targets
        mass_res = float(mass[0] - weight_kg) if weight_kg is not None else None
        over = [(abs(r) / tolerance_m, n) for r, n in zip(res, MEASUREMENTS) if abs(r) > tolerance_m]
        if mass_res is not None and abs(mass_res) > tolerance_kg:
            over.append((abs(mass_res) / tolerance_kg, "weight"))
        misses = tuple(n for _, n in sorted(over, reverse=True))
        return BodyFit(phenotypes=x[0].astype(np.float32), measurements=m[0], mass_kg=float(mass[0]), residuals=res,
                       mass_residual_kg=mass_res, misses=misses, evaluations=evaluations)


def _restart_offsets(n: int) -> list[np.ndarray]:
    """A few deterministic far starting points (the box's corners along the main axes)."""
    return [np.full(n, 0.35), np.full(n, -0.35), np.r_[0.35, -0.35][np.arange(n) % 2]]


def _worst_miss(r: np.ndarray, with_weight: bool, tolerance_m: float, tolerance_kg: float) -> float:
    """Largest measurement residual in tolerance units (residuals are in 1 cm / 1 kg units)."""
    k = len(MEASUREMENTS) + int(with_weight)
    scale = np.r_[np.full(len(MEASUREMENTS), tolerance_m / _SCALE_M), [tolerance_kg / _SCALE_KG] * int(with_weight)]
    return float(np.max(np.abs(r[:k]) / scale))
