"""How well the prediction describes the virtual machine's error of the original program, per pass
and per point (issue 5: what bounds the predicted closed loop; a bench, seconds on a run directory).

It takes a run directory of ``bench/closed_loop_pipeline_samples.py`` (a window or ``--whole``): the
original program's tables (``out/tables``: passes, errors, deflection; the first round's
prediction) and ``points.parquet`` (the probe points, each with the pass the machine associates it
with, that pass's predicted error and the machine's error of the original program). Two
predictions of every probe point against the machine's error:

- **per pass**: the error the errors stage predicts at the pass's generating point (one number per
  pass, along its normal): what the correction stage uses;
- **per point**: the prediction model evaluated at the point itself (``stages.gap.associate.associate``, as
  the gap diagnosis predicts at measured points): the deflection of the point's nearest pass at the
  point's own contact and position angle, projected on the point's own normal, plus the shape error
  at its contact angle, and where the tooth passages of the neighbouring passes along the path sweep
  the point, the deepest of them.

Neither reads the machine (its association of points to passes is the gap stage's own: the pass
whose ball centre passes nearest the point's ideal centre). The deviation is prediction minus
machine, as a share of the machine's error RMS before correction (the closed loop's "% of before"):
a correction fed one of them cannot, to first order, leave less than its deviation.

It also sorts the probe points by their distance from the design model (the workflow's ``nominal``;
``stages.geometry.workpiece.DesignSurface``, never under the true distance, within ~0.1 mm where its surface
samples miss the nearest face): on the design (≤ 5 µm), near it (5–100 µm), off it (> 100 µm: the
probe plan follows the rigid tool's contact lines, so it also probes the tops of the cusps between
wide rows and the fillet the ball leaves in a corner sharper than itself), and gives each class's
part of every program's mean square error in ``points.parquet`` (original, 1 round, 3 rounds …).

With ``--program NAME PASSES DEFLECTION ERRORS`` (repeatable; the parquet files of a corrected
program's prediction, e.g. from the run's pipeline cache, ``out/cache/{split,deflection,errors}``,
one entry per round) it also compares that prediction with the machine's error of the same
program (``points.parquet`` column ``err_<NAME>_um``, spaces as underscores): per point, as an error
against the ORIGINAL surface the probes measure, i.e. the point's stand-off from the corrected
program's nominal tool envelope minus its stand-off from the original's, plus the error predicted
at the point. The closed loop drives the predicted error of its programs to zero, so what the
machine leaves is about this deviation.

    python3 bench/prediction_at_points.py RUN_DIR [--top 20] [--program "1 round" P.parquet D.parquet E.parquet]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


# every probe point is associated (the plan puts some on the tops of cusps and in fillets the
# tool leaves, well off the design and so off the gap stage's measured-part tolerance)
OFF_PART_MM = 10.0


def share_report(dev: np.ndarray, base_rms: float) -> dict:
    """RMS of a deviation as % of ``base_rms``, the share of its mean square held by the top 1 % of
    the points, and the RMS of the rest (over all points) as % of ``base_rms``."""
    dev = np.asarray(dev, float)
    sq = np.sort(dev ** 2)[::-1]
    k = max(len(sq) // 100, 1)
    return {"rms_um": float(np.sqrt(sq.mean())), "pct": float(100 * np.sqrt(sq.mean()) / base_rms),
            "top1_share": float(sq[:k].sum() / max(sq.sum(), 1e-30)),
            "rest_pct": float(100 * np.sqrt(sq[k:].sum() / len(sq)) / base_rms)}


def main():
    import pandas as pd
    import pyarrow as pa
    import pyarrow.parquet as pq
    import yaml

    from stages.gap.associate import associate

    ap = argparse.ArgumentParser()
    ap.add_argument("run", type=Path, help="a run directory of bench/closed_loop_pipeline_samples.py")
    ap.add_argument("--top", type=int, default=12, help="the 4 mm cells with the largest per-point deviation to list")
    ap.add_argument("--program", nargs=4, action="append", default=[], metavar=("NAME", "PASSES", "DEFLECTION", "ERRORS"),
                    help="a corrected program's prediction tables, compared with the machine's err_<NAME>_um")
    args = ap.parse_args()
    run = args.run.resolve()
    wf = yaml.safe_load((run / "wf1.yaml").read_text())
    pts = pd.read_parquet(run / "points.parquet")
    tables = {t: pq.read_table(run / "out" / "tables" / t) for t in ("passes", "errors", "deflection")}
    meas = pa.table({"point_id": np.arange(len(pts), dtype=np.int64),
                     **{c: pts[c].to_numpy(float) for c in ("x_mm", "y_mm", "z_mm", "nx", "ny", "nz")},
                     "err_um": pts.err_original_um.to_numpy(float)})
    F, rejected = associate(meas, tables["passes"], tables["errors"], wf["tool"],
                                deflection=tables["deflection"], off_part_mm=OFF_PART_MM)
    if rejected:
        print(f"{len(rejected)} probe points not associated (left out): e.g. {rejected[:3]}")
    rows = np.asarray(F["point_id"], np.int64)
    sub = pts.iloc[rows].reset_index(drop=True)
    machine = sub.err_original_um.to_numpy(float)
    base = float(np.sqrt(np.mean(pts.err_original_um.to_numpy(float) ** 2)))
    per_pass = sub.predicted_um.fillna(0.0).to_numpy(float)       # not predicted: no correction, 0
    per_point = np.asarray(F["predicted_um"], float)
    same_pass = np.asarray(F["pass_id"], np.int64) == sub.pass_id.to_numpy(np.int64)
    print(f"{run}: {len(sub)} probe points, the machine's error {base:.2f} um RMS before correction; "
          f"the gap stage associates {100 * same_pass.mean():.1f} % of them with the machine's own pass")
    print(f"{'':>10} {'deviation':>12} {'% of before':>12} {'top 1 % holds':>14} {'rest, % of before':>18}")
    report = {}
    for name, pred in (("per pass", per_pass), ("per point", per_point)):
        r = share_report(pred - machine, base)
        report[name] = r
        print(f"{name:>10} {r['rms_um']:>9.2f} um {r['pct']:>11.1f} % {100 * r['top1_share']:>13.0f} % "
              f"{r['rest_pct']:>17.1f} %")
    q = sub.contact_deg.to_numpy(float)
    print("by the probe point's contact angle (RMS of the deviation, um):")
    for lo, hi, label in ((0, 30, "floors q < 30"), (30, 60, "slopes 30-60"), (60, 91, "walls >= 60")):
        m = (q >= lo) & (q < hi)
        if m.any():
            print(f"  {label:>14}: {m.sum():>6} points, per pass {np.sqrt(np.mean((per_pass - machine)[m] ** 2)):6.2f}, "
                  f"per point {np.sqrt(np.mean((per_point - machine)[m] ** 2)):6.2f}")
    cells = pd.DataFrame({"x": sub.x_mm // 4 * 4, "y": sub.y_mm // 4 * 4,
                          "pass_ms": (per_pass - machine) ** 2 / len(sub),
                          "point_ms": (per_point - machine) ** 2 / len(sub), "n": 1})
    g = cells.groupby(["x", "y"]).sum().sort_values("point_ms", ascending=False)
    print(f"the {args.top} 4 mm cells with the most per-point deviation (their part of the mean square, um^2):")
    print(g.head(args.top).round(2).to_string())
    design = design_classes(pts, wf["nominal"])
    standoff0 = np.asarray(F["dist_mm"], float) * 1e3
    for name, *files in args.program:
        col = "err_" + name.replace(" ", "_") + "_um"
        if col not in pts.columns:
            raise SystemExit(f"--program {name!r}: points.parquet has no column {col}")
        t = {k: pq.read_table(f) for k, f in zip(("passes", "deflection", "errors"), files)}
        Fk, rej_k = associate(meas, t["passes"], t["errors"], wf["tool"], deflection=t["deflection"],
                                  off_part_mm=OFF_PART_MM)
        if len(rej_k) or not np.array_equal(np.sort(np.asarray(Fk["point_id"])), np.sort(rows)):
            raise SystemExit(f"--program {name!r}: {len(rej_k)} probe points not associated with its passes")
        at = np.argsort(np.asarray(Fk["point_id"]))[np.argsort(np.argsort(rows))]    # Fk's rows in F's order
        against_original = (np.asarray(Fk["dist_mm"], float)[at] * 1e3 - standoff0
                            + np.asarray(Fk["predicted_um"], float)[at])
        machined = sub[col].to_numpy(float)
        r = share_report(against_original - machined, base)
        print(f"{name}: predicted {100 * np.sqrt(np.mean(against_original ** 2)) / base:.1f} % of before, machined "
              f"{100 * np.sqrt(np.mean(machined ** 2)) / base:.1f} %; per-point deviation {r['rms_um']:.2f} um "
              f"({r['pct']:.1f} % of before), top 1 % holds {100 * r['top1_share']:.0f} %, rest {r['rest_pct']:.1f} %")
    out = sub.assign(predicted_at_point_um=per_point, gap_pass_id=np.asarray(F["pass_id"], np.int64),
                     design_distance_um=design[rows])
    out.to_parquet(run / "points_predicted.parquet")
    return report


DESIGN_CLASSES = ((0.0, 5.0, "on the design (<= 5 um)"), (5.0, 100.0, "near it (5-100 um)"),
                  (100.0, np.inf, "off it (> 100 um)"))


def design_classes(pts, nominal) -> np.ndarray:
    """Print each design-distance class's part of every program's mean square; return the distances (µm)."""
    import trimesh

    from stages.geometry.workpiece import DesignSurface
    mesh = trimesh.load(nominal, force="mesh")
    dist = np.abs(DesignSurface(mesh, spacing_mm=0.1, k=32).signed_distance(
        pts[["x_mm", "y_mm", "z_mm"]].to_numpy(float))) * 1e3
    progs = [c for c in pts.columns if c.startswith("err_") and c.endswith("_um")]
    n = len(pts)
    print("by the probe point's distance from the design model: points; per program, the class's part "
          "of the mean square (um^2) and its RMS as % of its own before")
    for lo, hi, label in DESIGN_CLASSES:
        m = (dist >= lo) & (dist < hi)
        before = np.sum(pts["err_original_um"].to_numpy(float)[m] ** 2)
        parts = []
        for c in progs:
            sq = np.sum(pts[c].to_numpy(float)[m] ** 2)
            parts.append(f"{c[4:-3].replace('_', ' ')} {sq / n:.1f} ({100 * np.sqrt(sq / max(before, 1e-30)):.1f} %)")
        print(f"  {label:>24}: {m.sum():>6} points; " + ", ".join(parts))
    return dist


if __name__ == "__main__":
    main()
