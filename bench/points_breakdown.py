"""Where the error of a closed-loop samples run lies: a breakdown of its probe points.

Reads ``points.parquet`` of a ``bench/closed_loop_pipeline_samples.py`` run (one row per probe
point, ``err_original_um`` and one ``err_<k>_round(s)_um`` column per corrected program machined)
and prints, per program: the RMS and its share of before, what the top 1 % of the points hold and
what the rest would be without them, the RMS on floors / slopes / walls (contact angle < 30°,
30–60°, ≥ 60°, as the bench reports); then the 4 mm cells and the passes holding most of the mean
square of the last program. ``--box X0 X1 Y0 Y1 [Z0 Z1]`` adds the same figures for the points in
that box (``--normal NX NY NZ`` keeps those whose normal lies within 10° of it).

    python3 bench/points_breakdown.py /tmp/cl16/whole/points.parquet
    python3 bench/points_breakdown.py RUN/whole/points.parquet --box 29 72 52.9 53.1 -16.3 -16.2 --normal 0 -1 0
"""
from __future__ import annotations

import argparse

import numpy as np
import pandas as pd


def summary(err: np.ndarray, before_ms: float, q: np.ndarray) -> str:
    """RMS, % of before, top-1 % share and the rest without it, RMS by contact-angle band."""
    sq = err ** 2
    n = sq.size
    order = np.sort(sq)[::-1]
    top = max(n // 100, 1)
    bands = ((q < 30), (q >= 30) & (q < 60), (q >= 60))
    by_q = " ".join(f"{name} {np.sqrt(sq[b].mean()):.2f}" if b.any() else f"{name} -"
                    for name, b in zip(("floors", "slopes", "walls"), bands))
    return (f"RMS {np.sqrt(sq.mean()):8.3f} µm {100 * np.sqrt(sq.mean() / before_ms):6.1f} % of before; "
            f"top 1 % holds {100 * order[:top].sum() / max(order.sum(), 1e-30):5.1f} %, the rest alone "
            f"{100 * np.sqrt(order[top:].sum() / n / before_ms):5.1f} %; {by_q} µm")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("points", help="points.parquet of a closed_loop_pipeline_samples.py run")
    ap.add_argument("--top", type=int, default=15, help="cells and passes listed")
    ap.add_argument("--cell", type=float, default=4.0, help="cell size, mm")
    ap.add_argument("--box", type=float, nargs="+", metavar="C", help="X0 X1 Y0 Y1 [Z0 Z1], mm")
    ap.add_argument("--normal", type=float, nargs=3, metavar=("NX", "NY", "NZ"),
                    help="with --box: only points whose normal is within 10° of this")
    a = ap.parse_args(argv)
    p = pd.read_parquet(a.points)
    cols = ["err_original_um"] + [c for c in p.columns if c.startswith("err_") and c != "err_original_um"]
    if len(cols) < 2:
        raise SystemExit(f"{a.points}: no corrected program's errors (err_<k>_round(s)_um columns)")
    n = len(p)
    before_ms = float((p.err_original_um ** 2).mean())
    q = p.contact_deg.to_numpy()
    print(f"{a.points}: {n:,} probe points, {np.sqrt(before_ms):.3f} µm RMS before")
    for c in cols:
        print(f"  {c:18s} {summary(p[c].to_numpy(), before_ms, q)}")
    share = pd.DataFrame({c: p[c] ** 2 / n for c in cols})   # each point's part of the mean square
    last = cols[-1]
    cells = share.groupby([(p.x_mm // a.cell) * a.cell, (p.y_mm // a.cell) * a.cell]).sum()
    cells.index.names = ["x0_mm", "y0_mm"]
    print(f"\nmean square (µm²) by {a.cell:g} mm cell, the {a.top} holding most after the last program:")
    print(cells.sort_values(last, ascending=False).head(a.top).round(2).to_string())
    passes = share.groupby(p.pass_id).sum()
    print(f"\nmean square (µm²) by the pass the plan probes, the {a.top} holding most after the last program:")
    print(passes.sort_values(last, ascending=False).head(a.top).round(2).to_string())
    if a.box:
        if len(a.box) not in (4, 6):
            raise SystemExit("--box takes X0 X1 Y0 Y1 or X0 X1 Y0 Y1 Z0 Z1")
        sel = p.x_mm.between(a.box[0], a.box[1]) & p.y_mm.between(a.box[2], a.box[3])
        if len(a.box) == 6:
            sel &= p.z_mm.between(a.box[4], a.box[5])
        if a.normal is not None:
            nv = np.asarray(a.normal, float) / np.linalg.norm(a.normal)
            sel &= (p[["nx", "ny", "nz"]].to_numpy() @ nv) >= np.cos(np.radians(10.0))
        b = p[sel]
        print(f"\nbox {a.box}{' normal ' + str(a.normal) if a.normal is not None else ''}: {len(b):,} points")
        for c in cols:
            e = b[c].to_numpy()
            print(f"  {c:18s} RMS {np.sqrt((e ** 2).mean()) if e.size else float('nan'):8.2f} µm, "
                  f"{(e ** 2).sum() / n:7.2f} µm² of the whole mean square")


if __name__ == "__main__":
    main()
