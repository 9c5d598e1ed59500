"""Benchmark: corrected vertices per second (stage ``correct``) on a 300,000-vertex program.

Goal (issue 5): ≥ 100,000 corrected vertices/s (seed 003 needed ~3.5 s for 30,000 tool points on a
GPU). Run: ``python bench/bench_correct.py [--blocks N]``. The program is the synthetic raster of
tests/ncprograms.py (rows of short G1 moves joined by arcs); every cutting pass gets an error and a
normal (the raster surface's, with noise), so every vertex and every arc is corrected, and a
generating point (the ball's contact with that normal at the pass's middle) for the gouge limit,
timed with and without it. Also times writing
the corrected program text and its reverse check (parse again), which are not part of the figure.
"""
from __future__ import annotations

import os
import sys
import time

import numpy as np
import pyarrow as pa

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from raster_job import options_and_program  # noqa: E402
from stages.correction.rounds import correct_once  # noqa: E402
from stages.geometry.cutter import Cutter  # noqa: E402
from stages.nc.moves import split_blocks  # noqa: E402
from stages.nc.reader import parse_program  # noqa: E402
from stages.nc.writer import reverse_check  # noqa: E402
from stages.nc.writer import write_program  # noqa: E402


def main():
    a, data, params = options_and_program(__doc__.splitlines()[0])
    blocks, _ = parse_program(data, "bench.nc", "bench")
    passes = split_blocks(blocks, params)
    rng = np.random.default_rng(0)
    n = passes.num_rows
    mid = np.stack([(passes.column(f"{c}0_mm").to_numpy() + passes.column(f"{c}1_mm").to_numpy()) / 2
                    for c in "xyz"], 1)
    # the raster's surface z = 0.5 sin(x/7) cos(y/5) (tests/ncprograms.py): its normals, a few
    # degrees of prediction noise
    gx = 0.5 / 7.0 * np.cos(mid[:, 0] / 7.0) * np.cos(mid[:, 1] / 5.0)
    gy = -0.5 / 5.0 * np.sin(mid[:, 0] / 7.0) * np.sin(mid[:, 1] / 5.0)
    nrm = np.stack([-gx, -gy, np.ones(n)], 1) + rng.normal(0.0, 0.03, (n, 3))
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    cut = passes.column("motion").to_numpy() != 0
    errors = pa.table({"program_id": ["bench"] * n, "pass_id": passes.column("pass_id"),
                       "err_um": rng.normal(5.0, 3.0, n), "nx": nrm[:, 0], "ny": nrm[:, 1], "nz": nrm[:, 2]})
    errors = errors.filter(pa.array(cut))
    shape = Cutter.from_params(params["tool"])
    contact = mid + [0.0, 0.0, shape.corner_mm] - shape.corner_mm * nrm
    generating = pa.table({"pass_id": passes.column("pass_id"), "gen_x_mm": contact[:, 0],
                           "gen_y_mm": contact[:, 1], "gen_z_mm": contact[:, 2],
                           "nx": nrm[:, 0], "ny": nrm[:, 1], "nz": nrm[:, 2]}).filter(pa.array(cut))
    p = {"correct": {"max_move_um": 50.0}}
    best = {}
    for gouge in (False, True):
        best[gouge] = np.inf
        for _ in range(a.repeat):
            t = time.perf_counter()
            corrected = correct_once(blocks, passes, errors, p, generating=generating if gouge else None,
                                     tool_shape=shape if gouge else None)
            best[gouge] = min(best[gouge], time.perf_counter() - t)
    nv = corrected.num_rows
    limited = int((corrected.column("gouge_limit_um").to_numpy() > 0.1).sum())
    n_arc = int(np.isin(corrected.column("motion").to_numpy(), (2, 3)).sum())
    t = time.perf_counter()
    text = write_program(data, blocks, corrected)
    t_write = time.perf_counter() - t
    t = time.perf_counter()
    rep = reverse_check(text, blocks, corrected)
    t_check = time.perf_counter() - t
    print(f"program: {blocks.num_rows} motion blocks, {n} passes ({errors.num_rows} with errors), {n_arc} arcs")
    print(f"correct_once: {nv} vertices in {best[True]:.3f} s = {nv / best[True]:,.0f} corrected vertices/s "
          f"(goal >= 100,000) with the gouge limit ({limited} vertices limited); without it {best[False]:.3f} s = "
          f"{nv / best[False]:,.0f} vertices/s")
    print(f"write_program: {t_write:.3f} s ({nv / t_write:,.0f} blocks/s); reverse check {t_check:.3f} s: "
          f"ok={rep['ok']} max deviation {rep['max_dev_um']:.3f} um")


if __name__ == "__main__":
    main()
