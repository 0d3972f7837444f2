"""Bodies from tape measurements and measurements of bodies: request models in, response models
out, around ``inference.body_fit`` and ``inference.measurements`` (run on a pool worker)."""
from __future__ import annotations

from inference.body import PHENOTYPE_LABELS, BodyModel
from inference.body_fit import GENDERS, BodyFitter
from inference.measurements import MEASUREMENTS, STANDARD
from service.errors import ProblemDetail, ProblemException, problem_from_exception
from service.schemas import (BodyFitRequest, BodyFitResponse, BodyMeasurementResiduals, BodyMeasurements,
                             BodyMeasurementsResponse, Phenotypes)

_CM = 100.0


def _measurements(values_m, mass_kg: float) -> BodyMeasurements:
    return BodyMeasurements(**{f"{n}_cm": round(float(v) * _CM, 2) for n, v in zip(MEASUREMENTS, values_m)},
                            weight_kg=round(float(mass_kg), 2))


def _phenotypes(values) -> Phenotypes:
    return Phenotypes(**{n: round(float(v), 4) for n, v in zip(PHENOTYPE_LABELS, values)})


class BodyService:
    def __init__(self, body: BodyModel):
        self.fitter = BodyFitter(body)

    def measure(self, phenotypes: Phenotypes) -> BodyMeasurementsResponse:
        values = [[getattr(phenotypes, n) for n in PHENOTYPE_LABELS]]
        m, mass = self.fitter.evaluate(values)
        return BodyMeasurementsResponse(phenotypes=phenotypes, measurements=_measurements(m[0], mass[0]), standard=STANDARD)

    def fit(self, request: BodyFitRequest) -> BodyFitResponse:
        targets = [getattr(request, f"{n}_cm") / _CM for n in MEASUREMENTS]
        gender = GENDERS[request.gender] if request.gender is not None else None
        tol_cm = request.tolerance_cm
        fit = self.fitter.fit(targets, weight_kg=request.weight_kg, gender=gender, tolerance_m=tol_cm / _CM, tolerance_kg=tol_cm)
        if fit.misses:
            errors = []
            for name in fit.misses:
                if name == "weight":
                    asked, got, unit = request.weight_kg, fit.mass_kg, "kg"
                else:
                    k = MEASUREMENTS.index(name)
                    asked, got, unit = targets[k] * _CM, fit.measurements[k] * _CM, "cm"
                field = "weight_kg" if name == "weight" else f"{name}_cm"
                errors.append({"pointer": f"/{field}", "detail": f"no adult body with the other measurements has {name} {asked:g} {unit}: "
                                                                 f"the closest has {got:.1f} {unit} (tolerance {tol_cm:g} {unit})"})
            raise ProblemException(422, "Outside the adult body space",
                                   f"these measurements do not fit together on an adult body; the furthest off: {fit.misses[0]}", errors)
        residuals = {f"{n}_cm": round(float(r) * _CM, 3) for n, r in zip(MEASUREMENTS, fit.residuals)}
        return BodyFitResponse(
            phenotypes=_phenotypes(fit.phenotypes),
            measurements=_measurements(fit.measurements, fit.mass_kg),
            residuals=BodyMeasurementResiduals(**residuals, weight_kg=None if fit.mass_residual_kg is None else round(fit.mass_residual_kg, 3)),
            tolerance_cm=tol_cm, tolerance_kg=tol_cm, standard=STANDARD,
        )

    def run(self, operation: str, request) -> BodyFitResponse | BodyMeasurementsResponse | ProblemDetail:
        """One operation ('fit' | 'measure'), its problem document on failure (picklable)."""
        try:
            return self.fit(request) if operation == "fit" else self.measure(request)
        except Exception as exc:  # noqa: BLE001 - answered as a problem, the worker lives on
            return problem_from_exception(exc)
