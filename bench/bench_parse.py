"""Benchmark: parse + split of a 300,000-block finishing program on one core.

Goal (issue 2): ≥ 500,000 blocks/s. Run: ``python bench/bench_parse.py [--blocks N]``.
The program is a synthetic raster over a wavy surface written like CAM output (N numbers, modal
coordinates omitted, arcs between rows), so it exercises the same paths as real programs.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
from stages.parse import parse_program  # noqa: E402
from stages.split import split_blocks  # noqa: E402
from tests.ncprograms import raster_program  # noqa: E402


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--blocks", type=int, default=300_000)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    data = raster_program(a.blocks)
    params = {"split": {"chord_tol_mm": 0.001, "max_pass_mm": 5.0, "merge_max_mm": 0.5},
              "machine": {"rapid_mm_min": 30000.0}, "tool": {"type": "ball", "diameter_mm": 6.0, "control_point": "tip"}}
    with tempfile.NamedTemporaryFile(suffix=".nc", delete=False) as f:
        f.write(data)
    best = float("inf")
    for _ in range(a.repeat):
        t0 = time.perf_counter()
        blocks, summary = parse_program(open(f.name, "rb").read(), f.name, "bench")
        t1 = time.perf_counter()
        passes = split_blocks(blocks, params)
        t2 = time.perf_counter()
        best = min(best, t2 - t0)
        print(f"parse {t1 - t0:.3f} s, split {t2 - t1:.3f} s, blocks {summary['n_blocks']}, passes {passes.num_rows}")
    os.unlink(f.name)
    rate = summary["n_blocks"] / best
    print(f"parse+split: {summary['n_blocks']} blocks in {best:.3f} s = {rate:,.0f} blocks/s (goal >= 500,000)")


if __name__ == "__main__":
    main()
