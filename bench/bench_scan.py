"""The scan stage (claims 1 and 4–8 as global ordered scans) on the samples, gl vs cpu, in one run.

For the sample job's finishing program and the seed's cylinder (Fig. 16): passes/s of the scan
with each back end, whether both find the same cutting and predicted passes and how far their
generating points' contact angle q and rotation angle φ differ, and where the time goes (share
of each part of the scan: tiles, the ordered scans, surface statistics, strips, engagement).

    python bench/bench_scan.py [--program mould_finish_t1] [--backends gl,cpu] [--px-per-mm 20]
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from collections import defaultdict

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from pipeline.config import load_workflow  # noqa: E402
from stages import parse, scan, split  # noqa: E402
from stages.geometry.cutter import Cutter  # noqa: E402
from stages.geometry.passes import pass_geometry  # noqa: E402
from stages.geometry.workpiece import load_design_surface, load_workpiece  # noqa: E402
from stages.render import make_renderer  # noqa: E402
from stages.surface import program  # noqa: E402
from tests.cylinder_case import TOOL as CYL_TOOL, cylinder_case  # noqa: E402

PARTS = ("tiles", "scan_tile", "surface_stats", "cut_columns", "generating_points", "snapshot_from", "engagement")


def timed(seconds: dict):
    """Wrap the parts of :func:`stages.surface.program.scan_program` to add up their seconds."""
    for name in PARTS:
        fn = getattr(program, name)

        def wrap(*a, _fn=fn, _name=name, **k):
            t = time.perf_counter()
            out = _fn(*a, **k)
            seconds[_name] += time.perf_counter() - t
            return out
        setattr(program, name, wrap)


def sample_case(name: str):
    # the raster along X over everything on the heavy-rest stock (data_samples/rest_overload/)
    wf, base = load_workflow(os.path.join(ROOT, "workflows", "rest_overload.yaml"))
    path = os.path.join(ROOT, "data_samples", "rest_overload", "nc", f"{name}.nc")
    p = parse.run({"program_file": {"path": path, "sha256": "", "program_id": name}}, wf.params(parse.PARAMS, None, base))
    tool = p["programs"].to_pylist()[0]["tool"]
    passes = split.run({"programs": p["programs"], "blocks": p["blocks"]}, wf.params(split.PARAMS, tool, base))["passes"]
    params = wf.params(scan.PARAMS, tool, base)
    return passes, params, str(base / wf.stock), str(base / wf.nominal)


def cylinder():
    import tempfile
    passes, stock, _, _, _ = cylinder_case()
    path = os.path.join(tempfile.mkdtemp(), "stock.stl")
    stock.export(path)
    return passes, {"tool": CYL_TOOL, "prune": {"min_contact_deg": 0.0}}, path, None


def run(passes, params, stock, nominal, backend, ppm):
    pg = pass_geometry(passes, params["tool"])
    wp, design = load_workpiece(stock), load_design_surface(nominal)
    res = program.scan_program(pg, Cutter.from_params(params["tool"]), wp, make_renderer(backend), ppm,
                               float((params.get("prune") or {}).get("min_contact_deg", 45.0)), design=design)
    return scan.tables(pg, res)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--program", default="mould_finish_t1")
    ap.add_argument("--backends", default="gl,cpu")
    ap.add_argument("--px-per-mm", type=float, default=20.0)
    a = ap.parse_args()
    seconds = defaultdict(float)
    timed(seconds)
    for label, case in (("cylinder Fig. 16", cylinder()), (f"sample {a.program}", sample_case(a.program))):
        out = {}
        for b in a.backends.split(","):
            seconds.clear()
            t = time.perf_counter()
            tables = run(*case, b, a.px_per_mm)
            wall = time.perf_counter() - t
            out[b] = tables
            n = tables["cut_filter"].num_rows
            share = ", ".join(f"{k} {100 * v / wall:.0f} %" for k, v in sorted(seconds.items(), key=lambda kv: -kv[1]))
            g = tables["generating"].to_pandas()
            print(f"{label}, {b}: {n} passes in {wall:.1f} s = {n / wall:.0f} passes/s; "
                  f"{int(tables['cut_filter'].column('is_cutting').to_numpy().sum())} cutting, {len(g)} predicted, "
                  f"{int((g.view == 'strip').sum())} with a generating point, {int((g.n2_px > 0).sum())} with a second")
            print(f"  time: {share}")
        if len(out) == 2:
            (b1, t1), (b2, t2) = out.items()
            c1, c2 = (t["cut_filter"].column("is_cutting").to_numpy() for t in (t1, t2))
            px1, px2 = (t["cut_filter"].column("cut_px").to_numpy() for t in (t1, t2))
            g1, g2 = (t["generating"].to_pandas().set_index("pass_id") for t in (t1, t2))
            odd = np.flatnonzero(c1 != c2)
            common = g1.index.intersection(g2.index)
            both = ((g1.loc[common].view == "strip") & (g2.loc[common].view == "strip")).to_numpy()
            h1, h2 = g1.loc[common][both], g2.loc[common][both]
            dq = np.abs(h1.contact_deg - h2.contact_deg).to_numpy()
            dphi = np.abs((h1.rotation_deg - h2.rotation_deg + 180) % 360 - 180).to_numpy()
            print(f"  {b1} vs {b2}: cutting differs on {len(odd)} passes (their cut pixels, largest: "
                  f"{int(np.maximum(px1[odd], px2[odd]).max(initial=0))}); predicted by one only: "
                  f"{len(g1.index.symmetric_difference(g2.index))}; on the {len(dq)} passes both predict with a "
                  f"generating point |dq| max {np.max(dq, initial=0):.3f}°, |dφ| max {np.max(dphi, initial=0):.3f}°")


if __name__ == "__main__":
    main()
