"""The strain limit's ratios against the judge's realism rule, on the validation walk.

    python tools/strain_sweep.py --garment trousers --garment suittrousers --ratio 0.8 0.85 0.9
    python tools/strain_sweep.py --garment dress --max-ratio inf 2.1 2.0 1.9

For each pair of ratios (every --ratio with every --max-ratio; by default the garment's own),
every method of the judge that runs the limit (``inference.strain``) is judged
against the newton reference of each validation case (``training.judge.judge_case``; the
references must be simulated: ``python -m training.reference --garment G --split validation``):
error from newton (cm), edge p1 / p99, folded faces (%), roughness (deg) and the realism failures
that count for a default (worse than newton by its margin and than the retarget by its
tolerance). Validation only: the ratios are choices (``MIN_RATIO_BY_CATEGORY``, ``MAX_RATIO_BY_CATEGORY``).
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import inference.strain as strain  # noqa: E402
from training import judge  # noqa: E402
from training.protocol import SPLITS  # noqa: E402

METHODS = ("retarget", "canonical", "canonical-learned")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--garment", action="append", required=True)
    ap.add_argument("--ratio", type=float, nargs="+", default=[None], help="shortest edge / rest length (compression)")
    ap.add_argument("--max-ratio", type=float, nargs="+", default=[None], help="longest edge / rest length (stretch; inf: none)")
    args = ap.parse_args(argv)
    inputs = judge.Inputs.load()
    methods = {k: v for k, v in judge.METHODS.items() if k in METHODS}
    call = strain.StrainLimit.__call__
    print("| ratio | max ratio | garment | case | method | error cm | edge p1 | edge p99 | folded % | rough deg | fails |\n|---|---|---|---|---|---|---|---|---|---|---|")
    try:
        for ratio, max_ratio in [(a, b) for a in args.ratio for b in args.max_ratio]:
            # every limit built by the pipeline runs at these ratios (None: its own)
            strain.StrainLimit.__call__ = (lambda self, vertices, min_ratio=None, iterations=strain.ITERATIONS, max_ratio=None, _q=ratio, _m=max_ratio:
                                           call(self, vertices, _q, iterations, _m))
            for g in args.garment:
                for case in SPLITS["validation"]:
                    row = judge.judge_case(inputs, case, g, judge.REFERENCE_DIR, methods)
                    if row is None:
                        continue
                    base = row["methods"]["retarget"]["realism"]
                    for m, v in row["methods"].items():
                        r = v["realism"]
                        fails = judge.worse_on_realism(r, row["reference"]["realism"], base)
                        print(f"| {ratio} | {max_ratio} | {g} | {case.name} | {m} | {v['error_cm']:.2f} | {r['edge_p1']:.3f} | {r['edge_p99']:.3f} | "
                              f"{r['folded_pct']:.2f} | {r['roughness_deg']:.1f} | {', '.join(fails)} |", flush=True)
    finally:
        strain.StrainLimit.__call__ = call


if __name__ == "__main__":
    main()
