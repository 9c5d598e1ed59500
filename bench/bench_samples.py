"""Render stages on the sample mould, gl vs cpu back end on the same inputs, in one run.

Issue 3's sample check and speed figures: ``cut_filter`` (one ordered scan per tile) over the whole
finishing program, then ``generating`` for the predicted passes of a window of the program, with
both back ends; prints passes/s, the cpu/gl ratio, whether both find the same cutting passes, and
the contact-angle (q) and rotation-angle differences of the generating points.

    python bench/bench_samples.py [--first 1400] [--last 1700] [--px-per-mm 20]

Needs the passes of the sample job: ``pipeline run workflows/mould.yaml`` (stops after split).
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
import pyarrow.parquet as pq

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from stages import cut_filter as cf_stage  # noqa: E402
from stages import generating as gen  # noqa: E402
from stages.geometry.cutter import Cutter  # noqa: E402
from stages.geometry.passes import pass_geometry  # noqa: E402
from stages.geometry.workpiece import load_workpiece  # noqa: E402
from stages.render import make_renderer  # noqa: E402

TOOL = dict(type="ball", diameter_mm=10, flutes=2, helix_deg=30, stickout_mm=40)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--passes", default=os.path.join(ROOT, "runs/mould/tables/passes/mould_finish_t1.parquet"))
    ap.add_argument("--stock", default=os.path.join(ROOT, "data_samples/models/semi.stl"))
    ap.add_argument("--first", type=int, default=1400)
    ap.add_argument("--last", type=int, default=1700)
    ap.add_argument("--px-per-mm", type=float, default=20.0)
    a = ap.parse_args()
    passes = pq.read_table(a.passes)
    shape = Cutter.from_params(TOOL)
    wp = load_workpiece(a.stock)
    ppm = a.px_per_mm
    # 1. cut filter over the whole program
    pg = pass_geometry(passes, TOOL)
    cf, t_cf = {}, {}
    for name in ("gl", "cpu"):
        r = make_renderer(name)
        t = time.perf_counter()
        cf[name] = cf_stage.cut_filter(pg, shape, wp, r, ppm)
        t_cf[name] = time.perf_counter() - t
        print(f"{name:4s} cut_filter: {len(pg.pass_id)} passes in {t_cf[name]:6.1f} s = "
              f"{len(pg.pass_id) / t_cf[name]:7.0f} passes/s, cutting {cf[name]['is_cutting'].sum()}")
    same = np.mean(cf["gl"]["is_cutting"] == cf["cpu"]["is_cutting"])
    print(f"RATIO cut_filter cpu/gl = {t_cf['cpu'] / t_cf['gl']:.1f}x; same cutting flag on {100 * same:.2f} % of passes")
    # 2. generating on a window of the program (the window's own cut filter: earlier passes omitted)
    win = passes.slice(a.first, a.last - a.first)
    pgw = pass_geometry(win, TOOL)
    out = {}
    for name in ("gl", "cpu"):
        r = make_renderer(name)
        c = cf_stage.cut_filter(pgw, shape, wp, r, ppm)
        q = np.where(c["surface_px"] > 0, c["surface_max_contact_deg"], c["cut_max_contact_deg"])
        pred = c["is_cutting"] & (np.nan_to_num(q, nan=-1.0) >= 45.0)
        idx = np.nonzero(pred)[0]
        tips = np.stack([c["pred_x_mm"], c["pred_y_mm"], c["pred_z_mm"]], 1)[idx]
        t = time.perf_counter()
        g, _ = gen.generating(pgw, shape, wp, r, ppm, idx, tips, TOOL["flutes"])
        dt = time.perf_counter() - t
        out[name] = (idx, g)
        views = dict(zip(*np.unique(g["view"], return_counts=True)))
        print(f"{name:4s} generating: {len(idx)} predicted passes of {len(pgw.pass_id)} in {dt:6.1f} s "
              f"= {len(idx) / dt:5.1f} predicted passes/s; views {views}")
    (ig, gg), (ic, gc) = out["gl"], out["cpu"]
    if np.array_equal(ig, ic):
        both = (gg["view"] != "none") & (gc["view"] != "none")
        dq = np.abs(gg["contact_deg"] - gc["contact_deg"])[both]
        dphi = np.abs((gg["rotation_deg"] - gc["rotation_deg"] + 180) % 360 - 180)[both]
        print(f"gl vs cpu on the same {len(ig)} predicted passes: same view on "
              f"{np.mean(gg['view'] == gc['view']) * 100:.1f} %, found by both {both.sum()}; "
              f"|dq| max {dq.max() if both.any() else np.nan:.3f} deg, "
              f"|dq| > 0.2 deg on {int((dq > 0.2).sum())}, |dphi| median {np.median(dphi) if both.any() else np.nan:.2f} deg")
    else:
        print(f"predicted passes differ: gl {len(ig)}, cpu {len(ic)}, common {len(np.intersect1d(ig, ic))}")


if __name__ == "__main__":
    main()
