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

With ``--fit-points DAMP`` step 2 takes its pass-end moves from :func:`node_moves_from_points`
instead: the piecewise-linear path move that best cancels every probe point's error along the
point's own normal (global least squares), not one error per pass. It shows whether the per-pass
representation is what holds the loop.

With ``--secant`` step 2 is the pipeline's rounds (``stages.correct.run`` with ``correct.accelerate``)
fed the machine's error instead of the prediction: each pass's residual becomes the error of the
path it was machined on (:func:`errors_of_path`), and the fixed point moves the original program
with the secant step. It shows what the pipeline's rounds reach when the prediction is exact, pass
by pass. ``--vm-step-mm`` machines at the pipeline bench's finer resolution (its run directory's
original program must have been machined at the same, or it is machined again).

    python3 bench/closed_loop_vm_samples.py RUN_DIR [--rounds 3] [--max-move 300] [--fit-points 0.3 | --secant]
                                            [--vm-step-mm 0.5]
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


def errors_of_path(errors, passes, corrected):
    """The measured residuals of ``errors`` (against the original surface) as errors of the path
    they were machined on, the form the pipeline's rounds predict: e(P) = r − m·n.

    The path P of a round is the original moved by m (µm); its rigid cut lies m·n off the original
    surface (n the outward normal: a move into the material is negative), so the machined surface
    r = m·n + e(P). m is the mean of the moves of the pass's two end vertices (the blocks are cut at
    the pass ends with ``correct.via_points``: each pass starts at the end of block ``block_no`` − 1
    and ends at the end of ``block_end``); ``corrected`` None (the original program): m = 0.
    """
    import pyarrow as pa
    if corrected is None:
        return errors
    bn = corrected.column("block_no").to_numpy()
    col = lambda n: corrected.column(n).to_numpy()  # noqa: E731
    move = 1000.0 * np.stack([col(f"{a}_new_mm") - col(f"{a}_mm") for a in "xyz"], 1)
    def at(b):                  # the move of the end of block b (before the first block: none)
        i = np.clip(np.searchsorted(bn, b), 0, bn.size - 1)
        if np.any((b >= bn[0]) & (bn[i] != b)):
            raise SystemExit("errors_of_path: a pass end is not a block end of the corrected table "
                             "(the run's blocks must be cut at the pass ends: correct.via_points)")
        return np.where((b >= bn[0])[:, None], move[i], 0.0)
    pid = passes.column("pass_id").to_numpy()
    k = np.searchsorted(pid, errors.column("pass_id").to_numpy())
    m = 0.5 * (at(passes.column("block_no").to_numpy()[k] - 1) + at(passes.column("block_end").to_numpy()[k]))
    n = np.stack([errors.column(c).to_numpy() for c in ("nx", "ny", "nz")], 1)
    e = errors.column("err_um").to_numpy() - np.einsum("ij,ij->i", m, n)
    return errors.set_column(errors.schema.get_field_index("err_um"), "err_um", pa.array(e))


def measured_round(blocks, passes, errors, corrected, params: dict, secant: bool, generating=None,
                   tool_shape=None, node_moves=None):
    """One round of the measured loop: the ``corrected`` table after ``errors`` (residuals measured
    on the program of the last round, ``corrected``; None in round 1).

    ``secant`` False: the residuals' moves are added to the last round's (``relax=None``).
    ``secant`` True: the pipeline's rounds (``stages.correct.run``): the fixed point P = P0 − e(P)·n
    on the errors of the machined path (:func:`errors_of_path`), moved from the original program,
    with the halving rule (``correct.relax``) and the secant step (``correct.accelerate``).
    """
    from stages.correct import apply_corrected, correct_once
    if secant:
        return correct_once(blocks, passes, errors_of_path(errors, passes, corrected), params,
                            previous=corrected, relax=float(params["correct"].get("relax", 1.0)),
                            accelerate=True, generating=generating, tool_shape=tool_shape)
    current = blocks if corrected is None else apply_corrected(blocks, corrected)
    return correct_once(current, passes, errors, params, previous=corrected, relax=None,
                        generating=generating, tool_shape=tool_shape, node_moves=node_moves)


def node_moves_from_points(passes, pass_id, points, normals, err_um, radius_mm: float, damp: float):
    """Moves (µm) of the pass-end nodes that best cancel the points' errors along their normals.

    Node k is the start of pass k (``passes`` in pass_id order; the last node the end of the last
    pass), as in :func:`stages.correct.correct_once`. A point of pass k lies where the ball's centre
    (the point + R·n) is nearest the pass's centre line, at fraction t; the tool there moves by
    (1 − t)·M_k + t·M_{k+1}, and the point's error changes by that move along its normal n.
    Solved for all nodes at once by damped least squares (``damp`` µm of move per µm of residual,
    ``scipy.sparse.linalg.lsqr``): min Σ (e_i + ((1 − t_i)·M_k + t_i·M_{k+1})·n_i)² + damp²·Σ |M|².

    Returns
    -------
    moves : (P + 1, 3) array, µm
    residual : (points,) the fit's residual error, µm
    """
    import scipy.sparse as sp
    from scipy.sparse.linalg import lsqr
    pid = passes.column("pass_id").to_numpy()
    k = np.searchsorted(pid, np.asarray(pass_id, np.int64))
    if np.any(k >= pid.size) or np.any(pid[np.minimum(k, pid.size - 1)] != pass_id):
        raise SystemExit("fit-points: a probe point's pass is not in the run's passes table")
    xyz = lambda *c: np.stack([passes.column(n).to_numpy() for n in c], 1)[k]  # noqa: E731
    p0, p1 = xyz("x0_mm", "y0_mm", "z0_mm"), xyz("x1_mm", "y1_mm", "z1_mm")
    n = np.asarray(normals, float)
    centre = np.asarray(points, float) + radius_mm * n - np.array([0.0, 0.0, radius_mm])   # as a tip
    d = p1 - p0
    t = np.clip(np.einsum("ij,ij->i", centre - p0, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-12), 0, 1)
    m = len(k)
    cols = (3 * k[:, None] + np.arange(6)[None, :]).ravel()
    vals = np.concatenate([(1 - t)[:, None] * n, t[:, None] * n], 1).ravel()
    a = sp.csr_matrix((vals, (np.repeat(np.arange(m), 6), cols)), shape=(m, 3 * (pid.size + 1)))
    e = np.asarray(err_um, float)
    sol = lsqr(a, -e, damp=damp, atol=1e-10, btol=1e-10, iter_lim=20000)[0]
    return sol.reshape(-1, 3), e + a @ sol


def main():
    import pandas as pd
    import pyarrow.parquet as pq
    import yaml

    import closed_loop_pipeline_samples as bench
    from stages.geometry import tool_from_params
    from stages.nc_writer import reverse_check, write_program

    ap = argparse.ArgumentParser()
    ap.add_argument("run", type=Path, help="a run directory of bench/closed_loop_pipeline_samples.py")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--max-move", type=float, default=None,
                    help="clip of the total vertex move, µm; default: the run's workflow")
    ap.add_argument("--fit-points", type=float, default=None, metavar="DAMP",
                    help="pass-end moves fitted to every probe point (node_moves_from_points) with this "
                         "damping, instead of para 0084's from one error per pass")
    ap.add_argument("--secant", action="store_true",
                    help="the pipeline's rounds instead of accumulated residuals: the fixed point on the "
                         "measured error of each round's path (errors_of_path) with the secant step "
                         "(correct.accelerate) and the halving rule")
    ap.add_argument("--vm-step-mm", type=float, default=None,
                    help="the machine's deflection resolution along the path (the pipeline bench's option; "
                         "its run directory's original program must be machined at the same)")
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
    if args.secant and args.fit_points is not None:
        raise SystemExit("--secant and --fit-points are two different rounds; give one")
    tag = ("" if args.fit_points is None else f"fit{args.fit_points:g}_") + ("secant_" if args.secant else "")
    tag += "" if args.vm_step_mm is None else f"vm{args.vm_step_mm:g}_"     # the files of this mode
    corrected, report = None, {"run": str(run), "before_rms_um": base, "rounds": []}
    for k in range(1, args.rounds + 1):
        errors = errors_from_points(pts.pass_id.to_numpy(), err, normals)
        fit = None
        if args.fit_points is not None:
            fit, residual = node_moves_from_points(passes, pts.pass_id.to_numpy(), pts[["x_mm", "y_mm", "z_mm"]].to_numpy(),
                                                   normals, err, wf["tool"]["diameter_mm"] / 2.0, args.fit_points)
            print(f"  round {k}: the fit leaves {np.sqrt(np.mean(residual ** 2)):.2f} um RMS at the points", flush=True)
        corrected = measured_round(blocks, passes, errors, corrected, params, args.secant,
                                   generating=generating, tool_shape=shape, node_moves=fit)
        text = write_program(src, blocks, corrected)
        if not reverse_check(text, blocks, corrected)["ok"]:
            raise SystemExit(f"round {k}: the written program does not parse back to the corrected table")
        name = f"{k} {tag.replace('_', ' ')}measured round{'s' if k > 1 else ''}"
        (run / f"{tag}measured_{k}.nc").write_bytes(text)
        res = bench.vm_errors(window, {"original": src, name: text}, wf, cache=run.parent / "vm_cache",
                              dump=run / f"points_{tag}measured_{k}.parquet", vm_step_mm=args.vm_step_mm)
        err = pq.read_table(run / f"points_{tag}measured_{k}.parquet").column(f"err_{name.replace(' ', '_')}_um").to_numpy()
        v = res[name]
        move = corrected.column("move_um").to_numpy()
        print(f"  round {k}: {errors.num_rows} passes with a measured error, max move {move.max():.1f} um "
              f"({int(corrected.column('clipped').to_numpy().sum())} clipped); machined: error RMS "
              f"{v['rms_um']:.3f} um ({100 * v['rms_um'] / base:.1f} % of before), P95 {v['p95_abs_um']:.2f} um, "
              f"max {v['max_abs_um']:.1f} um; by q: "
              + ", ".join(f"{b} {v[b]['rms_um']:.2f} um" for _, _, b in bench.Q_BANDS if v[b]["rms_um"] is not None),
              flush=True)
        report["rounds"].append({"round": k, **v})
    (run / f"summary_{tag}measured.json").write_text(json.dumps(report, indent=1, default=str))


if __name__ == "__main__":
    os.chdir(ROOT)
    main()
