"""Correction of the sample finishing program from its MEASURED error on the gap issue's virtual
machine: the loop a shop closes with an on-machine probe or a CMM (issue 5; a bench, not a CI test:
one virtual-machine run per round, 13 min for the whole program on this machine).

It takes a run directory of ``bench/closed_loop_pipeline_samples.py`` (a window, or ``--whole``):
its program (``nc/band.nc``), workflow (``wf1.yaml``), the original program's tables
(``out/tables``: blocks, passes, generating; with ``correct.via_points`` the blocks are cut at the
pass ends, so the written programs get via points like the pipeline's) and ``points.parquet`` (the
probe plan, each point's pass by the machine's own association, and the original program's
machined error). Round k:

1. each pass gets the mean machined error of its probe points in the program of round k − 1
   (a residual against the original surface; the normal is their mean normal);
2. ``stages.correct.correct_once`` moves the vertices against it; residuals accumulate on the
   moves so far (``relax=None``), with the workflow's gouge limit and the bench's clip;
3. ``stages.nc_writer.write_program`` writes the program, and the virtual machine machines and probes
   it (cached under ``<run>/../vm_cache`` by program text, like the pipeline bench).

No prediction is involved: the rounds show what the correction itself reaches when its input is the
machine's error per pass, against which the pipeline's predicted rounds can be read.

    python3 bench/closed_loop_vm_samples.py RUN_DIR [--rounds 3] [--max-move 300]
"""
from __future__ import annotations

import argparse
import json
import os
import re
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))


def errors_from_points(pass_id, err_um, normals, min_points: int = 1):
    """``errors`` table (pass_id, err_um, nx, ny, nz) of the per-pass mean of probe-point errors and
    normals; passes with fewer than ``min_points`` points are left out (their vertices follow their
    neighbours)."""
    import pyarrow as pa
    pid = np.asarray(pass_id, np.int64)
    ids, inv, cnt = np.unique(pid, return_inverse=True, return_counts=True)
    mean = lambda v: np.bincount(inv, v, ids.size) / cnt  # noqa: E731
    n = np.stack([mean(normals[:, i]) for i in range(3)], 1)
    n /= np.maximum(np.linalg.norm(n, axis=1), 1e-12)[:, None]
    keep = cnt >= min_points
    return pa.table({"pass_id": ids[keep], "err_um": mean(np.asarray(err_um, float))[keep],
                     "nx": n[keep, 0], "ny": n[keep, 1], "nz": n[keep, 2]})


def main():
    import pandas as pd
    import pyarrow.parquet as pq
    import yaml

    import closed_loop_pipeline_samples as bench
    from stages.correct import apply_corrected, correct_once
    from stages.geometry import tool_from_params
    from stages.nc_writer import reverse_check, write_program

    ap = argparse.ArgumentParser()
    ap.add_argument("run", type=Path, help="a run directory of bench/closed_loop_pipeline_samples.py")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--max-move", type=float, default=None,
                    help="clip of the total vertex move, µm; default: the run's workflow")
    args = ap.parse_args()
    run = args.run.resolve()
    wf = yaml.safe_load((run / "wf1.yaml").read_text())
    table = lambda name: pq.read_table(run / "out" / "tables" / name)  # noqa: E731
    blocks, passes, generating = table("blocks"), table("passes").sort_by("pass_id"), table("generating")
    src = (run / "nc" / "band.nc").read_bytes()
    pts = pd.read_parquet(run / "points.parquet")
    xs, ys = pts.x_mm.to_numpy(), pts.y_mm.to_numpy()
    # the window the pipeline bench probed (its directory name), for the machine's cache key
    m = re.fullmatch(r"x([\d.]+)-([\d.]+)_y([\d.]+)-([\d.]+)", run.name)
    window = tuple(float(v) for v in m.groups()) if m else (-1e9, 1e9, -1e9, 1e9)
    max_move = args.max_move if args.max_move is not None else wf["correct"]["max_move_um"]
    params = {"correct": {**wf["correct"], "max_move_um": float(max_move)}, "tool": wf["tool"]}
    shape = tool_from_params(wf["tool"]) if params["correct"].get("gouge_limit", True) else None
    normals = pts[["nx", "ny", "nz"]].to_numpy()
    err = pts.err_original_um.to_numpy()
    base = float(np.sqrt(np.mean(err ** 2)))
    print(f"{run.name}: {len(pts)} probe points ({xs.min():.0f}–{xs.max():.0f}, {ys.min():.0f}–{ys.max():.0f} mm), "
          f"error RMS {base:.3f} um before")
    corrected, current, report = None, blocks, {"run": str(run), "before_rms_um": base, "rounds": []}
    for k in range(1, args.rounds + 1):
        errors = errors_from_points(pts.pass_id.to_numpy(), err, normals)
        corrected = correct_once(current, passes, errors, params, previous=corrected, relax=None,
                                 generating=generating, tool_shape=shape)
        current = apply_corrected(blocks, corrected)
        text = write_program(src, blocks, corrected)
        if not reverse_check(text, blocks, corrected)["ok"]:
            raise SystemExit(f"round {k}: the written program does not parse back to the corrected table")
        name = f"{k} measured round{'s' if k > 1 else ''}"
        (run / f"measured_{k}.nc").write_bytes(text)
        res = bench.vm_errors(window, {"original": src, name: text}, wf, cache=run.parent / "vm_cache",
                              dump=run / f"points_measured_{k}.parquet")
        err = pq.read_table(run / f"points_measured_{k}.parquet").column(f"err_{name.replace(' ', '_')}_um").to_numpy()
        v = res[name]
        move = corrected.column("move_um").to_numpy()
        print(f"  round {k}: {errors.num_rows} passes with a measured error, max move {move.max():.1f} um "
              f"({int(corrected.column('clipped').to_numpy().sum())} clipped); machined: error RMS "
              f"{v['rms_um']:.3f} um ({100 * v['rms_um'] / base:.1f} % of before), P95 {v['p95_abs_um']:.2f} um, "
              f"max {v['max_abs_um']:.1f} um; by q: "
              + ", ".join(f"{b} {v[b]['rms_um']:.2f} um" for _, _, b in bench.Q_BANDS if v[b]["rms_um"] is not None),
              flush=True)
        report["rounds"].append({"round": k, **v})
    (run / "summary_measured.json").write_text(json.dumps(report, indent=1, default=str))


if __name__ == "__main__":
    os.chdir(ROOT)
    main()
