"""Benchmark of the posture job's evaluation (issue 61): the 37 × 37 orientations of the seed's
Fig. 3 grid (rx, ry from −90° to 90° by 5°) on the sample fan made with 100,000 triangles, z-map
cells of 0.2 mm, a Ø6 ball; prints the seconds of each part and the orientations per second.

    python bench/posture_bench.py [--backend gl] [--cell-mm 0.2] [--steps 37] [--triangles 100000]
"""
from __future__ import annotations

import argparse
import os
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
sys.path.insert(0, os.path.join(ROOT, "scripts"))

from make_posture_sample import fan  # noqa: E402
from stages.posture.cover import greedy_cover  # noqa: E402
from stages.posture.efficiency import sin2psi  # noqa: E402
from stages.posture.evaluate import evaluate  # noqa: E402
from stages.posture.offset import inverse_offset  # noqa: E402
from stages.posture.orientations import grid  # noqa: E402
from stages.posture.part import micro_regions  # noqa: E402
from stages.posture.zmap import backend_name  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backend", default="gl")
    ap.add_argument("--cell-mm", type=float, default=0.2)
    ap.add_argument("--steps", type=int, default=37)
    ap.add_argument("--triangles", type=int, default=100_000)
    args = ap.parse_args()
    sectors = int(round((args.triangles / 2 / 0.155) ** 0.5 / 1.0))     # rings ≈ 0.155 · sectors
    rings = max(4, round(args.triangles / 2 / sectors))
    V, F = fan(rings, sectors)
    t0 = time.perf_counter()
    part = micro_regions(V, F, 2.0)
    off = inverse_offset(part, 3.0, args.cell_mm)
    step = 180.0 / (args.steps - 1)
    g = grid("rxry", (-90, 90, step), (-90, 90, step))
    t1 = time.perf_counter()
    res = evaluate(part, off, g, sin2psi, 0.5, args.cell_mm, backend=args.backend)
    t2 = time.perf_counter()
    cov = greedy_cover(res["delta"], part.areas, res["e"], 20, 0.0)
    t3 = time.perf_counter()
    n = len(g["axis"])
    print(f"{len(F)} triangles, {part.n} micro-regions, {len(off.faces)} offset triangles; {n} orientations, "
          f"{args.cell_mm} mm cells, {backend_name(args.backend)}")
    print(f"prepare {t1 - t0:.1f} s, evaluate {t2 - t1:.1f} s ({n / (t2 - t1):.1f} orientations/s), "
          f"cover {t3 - t2:.1f} s; total {t3 - t0:.1f} s")
    print(f"best E {res['e'].max():.3f}; first posture {100 * cov['covered_mm2'][0] / cov['upper_mm2']:.1f} % of the "
          f"upper bound")


if __name__ == "__main__":
    main()
