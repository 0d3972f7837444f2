"""Round trip of the body fit (``inference.body_fit``): random adult bodies -> their measurements
-> fitted phenotypes -> the fitted body's measurements, against the asked ones.

    python -m bench.body_fit --bodies 200 [--seed 0] [--with-weight] [--with-gender]

Bodies are drawn uniformly from the adult phenotype box (``PHENOTYPE_RANGES``). Prints per
measurement the mean and max |fitted - asked| (cm), how many bodies miss a measurement by more
than the 1 cm tolerance, and the CPU time per fit.
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from inference.body import PHENOTYPE_LABELS, PHENOTYPE_RANGES, BodyModel
from inference.body_fit import GENDERS, BodyFitter
from inference.measurements import MEASUREMENTS


def random_adults(n: int, seed: int) -> np.ndarray:
    lo = np.array([PHENOTYPE_RANGES[k][0] for k in PHENOTYPE_LABELS])
    hi = np.array([PHENOTYPE_RANGES[k][1] for k in PHENOTYPE_LABELS])
    return np.random.default_rng(seed).uniform(lo, hi, (n, len(PHENOTYPE_LABELS)))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--bodies", type=int, default=200)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--with-weight", action="store_true", help="also give the body mass (kg)")
    ap.add_argument("--with-gender", action="store_true", help="also give the gender (male below 0.5, female above)")
    args = ap.parse_args(argv)
    fitter = BodyFitter(BodyModel.load())
    phenotypes = random_adults(args.bodies, args.seed)
    targets, mass = fitter.evaluate(phenotypes)
    errors, mass_errors, misses, cpu = [], [], 0, 0.0
    for i in range(args.bodies):
        t0 = time.process_time()
        fit = fitter.fit(targets[i], weight_kg=float(mass[i]) if args.with_weight else None,
                         gender=GENDERS["female" if phenotypes[i, 0] >= 0.5 else "male"] if args.with_gender else None)
        cpu += time.process_time() - t0
        errors.append(np.abs(fit.residuals) * 100.0)
        if fit.mass_residual_kg is not None:
            mass_errors.append(abs(fit.mass_residual_kg))
        misses += bool(fit.misses)
    e = np.array(errors)
    print(f"{args.bodies} random adult bodies (seed {args.seed}), weight given: {args.with_weight}, gender given: {args.with_gender}")
    print("| measurement | mean abs error (cm) | max abs error (cm) |\n|---|---|---|")
    for k, name in enumerate(MEASUREMENTS):
        print(f"| {name} | {e[:, k].mean():.3f} | {e[:, k].max():.3f} |")
    if mass_errors:
        print(f"| weight (kg) | {np.mean(mass_errors):.3f} | {np.max(mass_errors):.3f} |")
    print(f"bodies missing a measurement by > 1 cm (or 1 kg): {misses} / {args.bodies}")
    print(f"CPU per fit: {cpu / args.bodies * 1e3:.0f} ms (process time, all threads)")


if __name__ == "__main__":
    main()
