"""Benchmark: diagnosing 100,000 measured points (issue 7 Must show: ≤ 2 min on this machine).

The gap sample job (``workflows/gap.yaml``; its prediction comes from the engine's cache, run it
once first) is probed by the virtual machine at ~100,000 plan points (contact points at 300
fractions of every cutting chord, from ``scripts/make_gap_samples.py``) with thermal drift and
0.5 µm noise; the timed part is what ``pipeline diagnose`` does after reading the file:
association + features, the prediction re-run for the runout signature (forces → deflection →
errors at 7 runout values), the held-out effect ranking with the greedy/swap selection, the final
joint fit with every parameter's standard error (``param_uncertainty``), "how far"
(each fold re-fitted; model effects re-predicted through the stages), the where-map.

    python bench/bench_gap.py [--points 100000]
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=100_000)
    args = ap.parse_args()
    from pipeline.config import load_workflow
    from pipeline.gap_jobs import make_predictor, run_tables, workflow_stock
    from stages.gap.associate import associate
    from stages.gap.measurements import measurement_table
    from stages.gap.predictor import diagnose_points
    from stages.virtual_machine import VirtualMachine
    spec = importlib.util.spec_from_file_location("mk", ROOT / "scripts" / "make_gap_samples.py")
    mk = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mk)
    wf_path = str(ROOT / "workflows" / "gap.yaml")
    wf, base = load_workflow(wf_path)
    tabs, _ = run_tables(wf_path, "errors")
    tool = wf.tool.model_dump()
    n_chords = sum(len(r) for r in mk.contact_points()) - 1
    k = int(np.ceil(args.points / (0.6 * n_chords)))        # ~68 % survive the envelope filter
    plan = mk.plan_rows(mk.contact_points(), fractions=tuple(np.linspace(0.02, 0.98, k)))[: args.points]
    pts, nrm = plan[:, :3], plan[:, 3:]
    vm = VirtualMachine(tabs["passes"], tool, wf.material.model_dump(), wf.machine.model_dump(), workflow_stock(wf, base))
    effect = {"thermal_drift": {"ax_um": 3.0, "ay_um": -4.0, "az_um": -12.0, "tau_s": 5.0}}
    err = vm.probe(pts, nrm, effect, 0.5, np.random.default_rng(1))
    meas = measurement_table(np.arange(len(pts)), pts, nrm, err)
    t0 = time.perf_counter()
    F, rej = associate(meas, tabs["passes"], tabs.get("errors"), tool, 0.05, tabs.get("deflection"))
    t1 = time.perf_counter()
    res = diagnose_points(F, None, predictor=make_predictor(tabs, wf, tool))
    t2 = time.perf_counter()
    out = {"points": int(len(pts)), "passes": int(tabs["passes"].num_rows), "rejected": len(rej),
           "associate_s": round(t1 - t0, 2), "diagnose_s": round(t2 - t1, 2), "total_s": round(t2 - t0, 2),
           "effect": res["effect"], "effects": res["effects"], "params": res["params"],
           "params_se": res["params_se"], "params_se_sigma_um": res["params_se_info"]["sigma_um"], "shrink": round(res["shrink"], 3),
           "how_added": res.get("how_added")}
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
