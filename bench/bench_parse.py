"""Benchmark: parse + split of a 300,000-block finishing program on one core.

Goal (issue 2): ≥ 500,000 blocks/s. Run: ``python bench/bench_parse.py [--blocks N]``.
The program is a synthetic raster over a wavy surface written like CAM output (N numbers, modal
coordinates omitted, arcs between rows), so it exercises the same paths as real programs.
"""
from __future__ import annotations

import os
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from raster_job import options_and_program  # noqa: E402
from stages.nc.moves import split_blocks  # noqa: E402
from stages.nc.reader import parse_program  # noqa: E402


def main():
    a, data, params = options_and_program(__doc__.splitlines()[0])
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
