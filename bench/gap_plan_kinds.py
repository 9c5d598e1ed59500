"""Benchmark: the blind check's figures on a plan kind (issue 59), read from its summary.

Runs ``pipeline blind-check`` first unless ``--summary`` names an existing ``blind/summary.json``,
then prints: thermal-drift cases whose z amplitude exceeds 3σ named (first) and with their x/y
parts reported not observable; tool-contour claims with the centre outside the measured contact
angles; claims on no-effect cases; top-1; median held-out shrink.

    python bench/gap_plan_kinds.py workflows/gap_floors.yaml --plan-kind floors --cases 56 --seed N
    python bench/gap_plan_kinds.py --summary runs/gap_floors/blind/summary.json --plan data_samples/gap_floors/plan.csv
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def figures(s: dict, qmin: float, qmax: float) -> dict:
    cases = s["cases_detail"]
    drift = [c for c in cases if list(c["truth"]) == ["thermal_drift"]
             and abs(c["truth"]["thermal_drift"]["az_um"]) > 3 * c["noise_um"]]
    named = [c for c in drift if c["found"][:1] == ["thermal_drift"]]
    no_xy = [c for c in named if {"ax_um", "ay_um"} <= set(c["not_observable"].get("thermal_drift", []))]
    no_y = [c for c in named if "ay_um" in c["not_observable"].get("thermal_drift", [])]
    contour = [c for c in cases if "tool_contour" in c["found"]]
    outside = [c for c in contour if not qmin - 1e-6 <= c["params"]["tool_contour"]["q0_deg"] <= qmax + 1e-6]
    none = [c for c in cases if not c["truth"]]
    cases = [c for c in cases if "outside_ok" not in c]
    singles = [c for c in cases if len(c["truth"]) == 1 and "outside_ok" not in c]
    extra = [c for c in singles if len(c["found"]) > 1]
    return {"plan_kind": s.get("plan_kind"), "cases": len(cases), "q_range_deg": [qmin, qmax],
            "drift_z_over_3sigma": len(drift), "drift_named_first": len(named), "drift_xy_not_observable": len(no_xy),
            "drift_y_not_observable": len(no_y),
            "contour_claims": len(contour), "contour_centre_outside": len(outside),
            "none_cases": len(none), "none_claimed": sum(1 for c in none if c["found"]),
            "single_cases": len(singles), "single_with_extra": len(extra),
            "top1_accuracy": s["top1_accuracy"], "median_shrink": s["median_shrink"],
            "param_error": s["param_error"], "pair_order_ok": s.get("pair_order_ok"),
            "unexplained": s.get("unexplained"), "possible": s.get("possible")}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("workflow", nargs="?")
    ap.add_argument("--plan-kind", default="full")
    ap.add_argument("--cases", type=int, default=56)
    ap.add_argument("--pairs", type=int, default=0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--kinds")
    ap.add_argument("--out")
    ap.add_argument("--summary")
    ap.add_argument("--plan", help="with --summary from before the blind check recorded its plan: the full plan (CSV)")
    a = ap.parse_args()
    if a.summary:
        s = json.loads(Path(a.summary).read_text())
    else:
        from pipeline.gap_jobs import blind_check
        s = blind_check(a.workflow, a.cases, a.seed, a.out, pairs=a.pairs, plan_kind=a.plan_kind,
                        kinds=a.kinds.split(",") if a.kinds else None)
    if "plan" in s:                     # the contact angles of the plan the blind check probed
        qmin, qmax = s["plan"]["contact_deg"]
    else:                               # a summary written before the blind check recorded them
        from pipeline.config import Measurements
        from pipeline.gap_jobs import read_points
        from stages.gap.measurements import points_and_normals
        from stages.gap.plans import contact_deg, plan_mask
        pts, nrm = points_and_normals(read_points(a.plan, Measurements(file=a.plan), require_deviation=False)[0])
        q = contact_deg(nrm[plan_mask(pts, nrm, s.get("plan_kind") or a.plan_kind)])
        qmin, qmax = float(q.min()), float(q.max())
    print(json.dumps(figures(s, qmin, qmax), indent=2))

if __name__ == "__main__":
    main()
