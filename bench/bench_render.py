"""gl vs cpu back end on the same windows, measured in one run (seed 000 para 0097: 8.9× on the
cylinder, 110.8× on a real mould for its GPU vs software method).

Builds the generating-point windows (layers W, T1, T2, M, T1 near seen from below) of every contour level
of the cylinder benchmark (Fig. 16) once, then renders exactly the same scene with both back ends,
and also times the whole ``generating`` and ``cut_filter`` stages with each back end.

    python bench/bench_render.py [--px-per-mm 20] [--repeat 3]
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from stages import cut_filter as cf_stage  # noqa: E402
from stages import generating as gen  # noqa: E402
from stages.geometry.cutter import Cutter  # noqa: E402
from stages.geometry.envelope import envelope_mesh  # noqa: E402
from stages.geometry.passes import pass_geometry  # noqa: E402
from stages.geometry.workpiece import load_workpiece  # noqa: E402
from stages.render import View, make_renderer  # noqa: E402
from tests.cylinder_case import TOOL, cylinder_case  # noqa: E402


def build(ppm):
    passes, stock, q_ref, _, _ = cylinder_case()
    shape = Cutter.from_params(TOOL)
    pg = pass_geometry(passes, TOOL)
    wp = load_workpiece(stock)
    levels = np.nonzero(np.isfinite(q_ref))[0]
    tips = 0.5 * (pg.p0[levels] + pg.p1[levels])
    mesh = envelope_mesh(shape, cf_stage.fine_tolerance(ppm))
    coarse = envelope_mesh(shape, cf_stage.coarse_tolerance(ppm))
    zlo, zhi = cf_stage.z_range(pg, wp, shape)
    R = shape.radius_mm
    fd = pg.feed_deg[levels]
    views = [View((t[0], t[1], 0.0), (0, 0, 1.0), (np.cos(np.radians(a)), np.sin(np.radians(a)), 0),
                  2 * R, 2 * R, ppm, zlo, zhi) for t, a in zip(tips, fd)]
    s_p = pg.s0[levels] + np.linalg.norm(tips - pg.p0[levels], axis=1)
    f = gen.feed_per_tooth(pg, TOOL["flutes"], 1 / ppm)[levels]
    gap = gen.own_path_gap(shape, f, cf_stage.fine_tolerance(ppm))
    scene = gen.layer_scene(views, pg, pg.motion != 0, s_p, f, pg.sweep_bounds(shape), wp, mesh,
                             tips, fd, coarse, gap)
    return dict(views=views * gen.N_LAYERS, scene=scene, pg=pg, shape=shape, wp=wp, levels=levels, tips=tips)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--px-per-mm", type=float, default=20.0)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    case = build(a.px_per_mm)
    n_win = len(case["views"])
    print(f"cylinder Fig.16: {len(case['levels'])} prediction points, {n_win} windows "
          f"({case['views'][0].shape[1]}x{case['views'][0].shape[0]} px), "
          f"{len(case['scene'].tris)} triangles, px_per_mm {a.px_per_mm}")
    timing = {}
    images = {}
    for name in ("gl", "cpu"):
        try:
            r = make_renderer(name)
        except Exception as e:
            print(f"{name}: unavailable ({e})")
            continue
        r.render(case["views"][:4], case["scene"].__class__.concat([]))     # warm-up (context)
        best = np.inf
        for _ in range(a.repeat if name == "gl" else max(1, a.repeat - 2)):
            t = time.perf_counter()
            images[name] = r.render(case["views"], case["scene"])
            best = min(best, time.perf_counter() - t)
        timing[name] = best
        print(f"{name:4s} render of the same windows: {best:7.3f} s  "
              f"({best / len(case['levels']) * 1e3:.1f} ms per prediction point)")
    if len(timing) == 2:
        same = np.mean([np.mean(x.id == y.id) for x, y in zip(images["gl"], images["cpu"])])
        print(f"pixel ids identical gl vs cpu: {100 * same:.3f} %")
        print(f"RATIO render cpu/gl = {timing['cpu'] / timing['gl']:.1f}x  (seed: 8.9x cylinder, "
              f"110.8x mould, GPU vs software)")
    # whole stages (scene building included), same inputs
    for name in timing:
        r = make_renderer(name)
        t = time.perf_counter()
        cf_stage.cut_filter(case["pg"], case["shape"], case["wp"], r, a.px_per_mm)
        t_cf = time.perf_counter() - t
        t = time.perf_counter()
        gen.generating(case["pg"], case["shape"], case["wp"], r, a.px_per_mm, case["levels"],
                       case["tips"], TOOL["flutes"])
        t_gen = time.perf_counter() - t
        print(f"{name:4s} stages: cut_filter {t_cf:6.2f} s ({len(case['pg'].pass_id)} passes), "
              f"generating {t_gen:6.2f} s ({t_gen / len(case['levels']):.2f} s per predicted pass)")


if __name__ == "__main__":
    main()
