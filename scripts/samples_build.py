"""The sample process's files (scripts/make_samples.py): ``models/semi.stl`` from the semi-finishing
sweeps, the finishing programs ``nc/*.nc``, and what the finishing tools meet, measured on them.
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

import samples_stock as stock_mesh
from samples_cam import roundtrip_stl
from samples_geom import Grid
from samples_measure import allowance_met, exact_thickness, program_points, summary
from samples_process import ALLOWANCE_MM, BOX, SEMI_T1, T1, T2, rows_of
from samples_programs import PROGRAMS, finishing, semi_finishing

BASE_CELL = (SEMI_T1.raster_step, SEMI_T1.raster_step / 2)   # stock cells: the raster's rows and ridges on their edges


def make_process(out: Path, surf, tris: np.ndarray, grid: Grid, z_bottom: float, log=print) -> dict:
    """Write ``models/semi.stl`` and ``nc/*.nc`` under ``out``; return what the README reports."""
    t0 = time.time()
    sweeps, semi = semi_finishing(surf, tris, grid, log=log)
    log(f"semi-finishing sweeps: {len(sweeps.a)} moves ({time.time() - t0:.0f} s)")
    hx, hy = BASE_CELL
    row0 = rows_of(SEMI_T1, offset=SEMI_T1.raster_step / 2, margin=SEMI_T1.radius + ALLOWANCE_MM)[0]
    y0 = row0 + np.ceil((BOX[1] - row0) / hy - 1e-9) * hy               # the first lattice row in BOX
    heights = stock_mesh.Heights(sweeps.lower, (BOX[0], y0),
                                 (hx / 2 ** (stock_mesh.LEVELS + 1), hy / 2 ** (stock_mesh.LEVELS + 1)))
    nx, ny = int(np.ceil((BOX[2] - BOX[0]) / hx - 1e-9)), int(np.ceil((BOX[3] - y0) / hy - 1e-9))
    leaves = stock_mesh.adaptive_top(heights, nx, ny, log=log)
    semi_stl = roundtrip_stl(stock_mesh.solid(leaves, heights, z_bottom), out / "models" / "semi.stl")
    log(f"semi.stl: {len(semi_stl.faces)} faces, bounds {np.round(semi_stl.bounds, 3).tolist()} ({time.time() - t0:.0f} s)")

    texts, info, paths = finishing(surf, tris, grid, log=log)
    (out / "nc").mkdir(parents=True, exist_ok=True)
    for old in (out / "nc").glob("*.nc"):
        if old.name not in texts:
            old.unlink()
    for name, text in texts.items():
        (out / "nc" / name).write_text(text)
    stock = Grid(np.asarray(semi_stl.triangles, float), 0.1, dims=2)
    met, exact = {}, {}
    all_t = []
    for name, tool in zip(PROGRAMS, (T1, T1, T2)):
        tips, _ = program_points(texts[name])
        m = allowance_met(grid, stock, tips, tool.radius)
        ok = np.isfinite(m["thickness"])
        e = exact_thickness(sweeps.lower, m["contact"][ok], m["normal"][ok])
        met[name] = summary(m["thickness"]) | {"contacts": int(len(tips))}
        exact[name] = {"max_diff_um": round(1000 * float(np.abs(e - m["thickness"][ok]).max()), 1),
                       "p99_diff_um": round(1000 * float(np.percentile(np.abs(e - m["thickness"][ok]), 99)), 1)}
        all_t.append(m["thickness"])
        log(f"{name}: stock met along the normal {met[name]}, mesh vs exact envelope {exact[name]}")
    met["all"] = summary(np.concatenate(all_t))
    return {"semi": semi, "finishing": info, "allowance": met, "mesh_vs_exact": exact,
            "semi_faces": len(semi_stl.faces), "semi_bounds": semi_stl.bounds, "semi_moves": len(sweeps.a),
            "base_cell": BASE_CELL, "seconds": round(time.time() - t0)}
