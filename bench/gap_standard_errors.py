"""Benchmark: the standard errors the gap diagnosis states against the spread of repeated fits.

Monte Carlo on the rigid virtual machine's sample plan (``tests/gap_helpers.py``): one noise-free
signature per case, Gaussian noise draws, each fitted as the diagnosis fits its final model (the
selection's grid fit, then ``stages.gap.uncertainty.final_fit``). Per parameter: the empirical
standard deviation over the draws / the median stated standard error
(``stages.gap.uncertainty.param_uncertainty``), and the mean's offset from the truth in stated
SE. The line the tests held: ratio within 25 % (0.75–1.25), mean within 0.5 SE. The drift's case
with fresh truths is ``tests/test_gap_uncertainty.py``; these are the longer ones (the servo lag's
envelope fits take ~0.27 s each) and the tool contour (its SE ~10 % above the spread).

    python bench/gap_standard_errors.py [--seed N] [--scale 1.0]
"""
from __future__ import annotations

import argparse
import json
import secrets
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# (effect, truth, probe noise σ µm, draws); the drift's τ as a fraction of the run
CASES = [
    ("thermal_drift", {"ax_um": 3.0, "ay_um": -4.0, "az_um": -8.0, "tau_frac": 0.4}, 0.7, 200),
    ("tool_contour", {"a_um": 5.0, "q0_deg": 25.0, "width_deg": 8.0}, 0.5, 200),
    ("servo_corner", {"a_um": 15.0, "lambda_mm": 0.6}, 0.7, 150),
]


def main():
    from tests.gap_helpers import brute_force_features, repeated_fits
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=None, help="noise seed (default: a fresh one, printed)")
    ap.add_argument("--scale", type=float, default=1.0, help="multiply every case's draws")
    args = ap.parse_args()
    seed = secrets.randbits(32) if args.seed is None else args.seed
    rng = np.random.default_rng(seed)
    out = {"seed": seed, "cases": []}
    for kind, truth, noise, draws in CASES:
        truth = dict(truth)
        if "tau_frac" in truth:
            truth["tau_s"] = truth.pop("tau_frac") * brute_force_features()["duration_s"]
        n = max(int(draws * args.scale), 10)
        t0 = time.perf_counter()
        fits, ses = repeated_fits(kind, truth, noise, n, rng)
        rows = {}
        for k, v in fits.items():
            se = float(np.median(ses[k]))
            ratio, offset = float(np.std(v, ddof=1) / se), float((v.mean() - truth[k]) / se)
            rows[k] = {"spread_over_se": round(ratio, 3), "mean_offset_se": round(offset, 3),
                       "within": bool(abs(ratio - 1) <= 0.25 and abs(offset) <= 0.5)}
        out["cases"].append({"effect": kind, "truth": truth, "noise_um": noise, "draws": n,
                             "wall_s": round(time.perf_counter() - t0, 1), "params": rows})
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
