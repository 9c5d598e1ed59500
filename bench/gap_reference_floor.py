"""The gap diagnosis's own prediction error on the effect-free reference part, by distance to a corner.

The blind check (``pipeline blind-check workflows/gap.yaml``) first probes a reference part without
any effect and calibrates the force-model scale s0 on it; what is left is the prediction's own
error against the virtual machine (the "model floor"). This bench builds that reference part the
same way (the workflow's plan, the same virtual machine, s0 fitted the same way) but probes it
without noise, and prints the residual RMS by path distance to the nearest corner, and the servo lag
(smooth form, best λ of the catalogue's grid) that the residual near corners reads as.

    python bench/gap_reference_floor.py [--noise-um 0]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
BANDS_MM = (0.0, 0.25, 0.5, 1.0, 2.0, np.inf)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--noise-um", type=float, default=0.0)
    ap.add_argument("--workflow", default=str(ROOT / "workflows" / "gap.yaml"))
    args = ap.parse_args()
    import pyarrow as pa
    from pipeline.config import load_workflow
    from pipeline.gap_jobs import measurement_spec, program_tool, read_points, run_tables, workflow_stock
    from stages.gap.associate import associate
    from stages.gap.calibration import apply_baseline
    from stages.gap.measurements import measurement_table, points_and_normals
    from stages.gap.servo import servo_smooth
    from stages.virtual_machine import VirtualMachine
    wf, base = load_workflow(args.workflow)
    spec = measurement_spec(wf, base)
    tabs, _ = run_tables(args.workflow, "errors")
    passes = tabs["passes"]
    prog = passes.column("program_id").to_pylist()[0]
    sub = passes.filter(pa.compute.equal(passes.column("program_id"), prog))
    tool = program_tool(wf, sub)
    vm = VirtualMachine(sub, tool, wf.material.model_dump(), wf.machine.model_dump(), workflow_stock(wf, base))
    plan, _, _ = read_points(spec.file, spec, require_deviation=False)
    pts, nrm = points_and_normals(plan)
    err = vm.probe(pts, nrm, {}, args.noise_um, np.random.default_rng(1))
    t0 = time.perf_counter()
    F, rej = associate(measurement_table(np.arange(len(pts)), pts, nrm, err), sub, tabs.get("errors"), tool,
                       spec.off_part_mm, tabs.get("deflection"))
    t_assoc = time.perf_counter() - t0
    d = F["pred_deflection_um"]
    s0 = float(1.0 + np.dot(d, F["residual_um"]) / np.dot(d, d)) if np.dot(d, d) > 0 else 1.0
    F = apply_baseline(F, s0)
    r = F["residual_um"]
    cd = np.where(np.isfinite(F["corner_dist_mm"]), F["corner_dist_mm"], np.inf)
    rms = lambda v: float(np.sqrt(np.mean(v ** 2))) if len(v) else float("nan")  # noqa: E731
    bands = []
    for lo, hi in zip(BANDS_MM[:-1], BANDS_MM[1:]):
        m = (cd >= lo) & (cd < hi)
        bands.append({"corner_dist_mm": [lo, hi if np.isfinite(hi) else None], "n": int(m.sum()),
                      "rms_um": rms(r[m]), "mean_um": float(r[m].mean()) if m.any() else None,
                      "max_abs_um": float(np.abs(r[m]).max()) if m.any() else None})
    near = cd < 1.0
    # the servo lag the residual reads as (smooth form, least squares per λ of the catalogue's grid)
    best = None
    for lam in np.geomspace(0.05, 5.0, 24):
        x = servo_smooth(F, lam)
        if not np.any(x):
            continue
        a = float(x @ r / (x @ x))
        sse = float(np.sum((r - a * x) ** 2))
        if best is None or sse < best[0]:
            best = (sse, a, float(lam))
    out = {"points": int(len(r)), "rejected": len(rej), "force_scale_s0": s0, "noise_um": args.noise_um,
           "rms_um": rms(r), "rms_near_1mm_um": rms(r[near]), "rms_beyond_1mm_um": rms(r[~near]),
           "n_near_1mm": int(near.sum()), "bands": bands,
           "reads_as_servo": {"a_um": best[1], "lambda_mm": best[2]} if best else None,
           "associate_s": round(t_assoc, 2)}
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
