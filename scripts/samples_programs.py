"""The sample process's passes (scripts/make_samples.py): the semi-finishing sweeps that make the stock,
and the three finishing programs as NC text, in machining order.
"""
from __future__ import annotations

import numpy as np

from samples_envelope import Sweeps
from samples_geom import Grid
from samples_nc import NCWriter, footer, header
from samples_process import (ALLOWANCE_MM, BOX, CAM_TOL, OVERLAP_MM, REST_MM, SEMI_T1, SEMI_T2, STEEP_DEG, T1,
                             T2, Tool, cusp_um, stretches, sweeps_of, toolpath)
from samples_strategies import write_levels, write_raster

PROGRAMS = ("10_steep_t1.nc", "20_shallow_t1.nc", "30_pencil_t2.nc")


def semi_finishing(surf, tris: np.ndarray, grid: Grid, log=print) -> tuple[Sweeps, dict]:
    """The semi-finishing passes (never written as NC): the Ø10 contours and raster, then the Ø4 rest
    passes where a Ø10 leaves more than the allowance + ``REST_MM``.

    Returns
    -------
    sweeps : the capsules of both tools' feed moves (the stock is what lies under all of them).
    info : counts per tool.
    """
    info = {}
    steep, shallow, reach, info["t1"] = stretches(surf, tris, grid, SEMI_T1, ALLOWANCE_MM, cover=True)
    tp1 = toolpath(grid, SEMI_T1, ALLOWANCE_MM)
    info["t1"] |= {"contours": write_levels(tp1, steep, SEMI_T1.level_step),
                   "raster": write_raster(tp1, shallow, SEMI_T1.raster_step)}
    s1 = sweeps_of(SEMI_T1, tp1)
    log(f"semi T1: {info['t1']}, {len(s1.a)} moves")
    steep, shallow, _, info["t2"] = stretches(surf, tris, grid, SEMI_T2, ALLOWANCE_MM, rest_of=reach)
    tp2 = toolpath(grid, SEMI_T2, ALLOWANCE_MM)
    info["t2"] |= {"contours": write_levels(tp2, steep, SEMI_T2.level_step, zigzag=True),
                   "rings": write_levels(tp2, shallow, SEMI_T2.raster_step, zigzag=True)}
    s2 = sweeps_of(SEMI_T2, tp2)
    log(f"semi T2: {info['t2']}, {len(s2.a)} moves")
    return s1 + s2, info


def _program(number: int, title: str, tool: Tool, lines: list[str]) -> NCWriter:
    w = NCWriter(n_step=2)
    header(w, number, title, lines + [
        "MODEL MOULD.STL MM - WORK ZERO X0 Y0 PART MIN CORNER - Z0 PARTING FACE",
        f"T{tool.t} BALL D{tool.diameter:.3f} R{tool.radius:.3f} - COORDINATES = TOOL TIP",
        f"STOCK TO LEAVE 0.000 - TOLERANCE {CAM_TOL:.3f} - SEMI-FINISHED ALLOWANCE {ALLOWANCE_MM:.3f}",
    ], tool=tool.t, spindle_rpm=tool.rpm)
    w.block("M8")
    return w


def finishing(surf, tris: np.ndarray, grid: Grid, log=print) -> tuple[dict, dict, dict]:
    """The finishing programs, in machining order.

    Returns
    -------
    texts : file name → NC text.
    info : per program, what it holds (for the console and the README).
    paths : file name → its :class:`samples_moves.Toolpath` (the centre segments, the links).
    """
    steep, shallow, reach, base = stretches(surf, tris, grid, T1, 0.0)
    w10 = _program(1010, "MOULD STEEP T1", T1, [
        f"Z-LEVEL CONTOURS ON WALLS STEEPER THAN {STEEP_DEG:.0f} DEG - CLIMB - STEP DOWN {T1.level_step:.3f}",
        "CAM OPENCAMLIB ADAPTIVEWATERLINE - LEAD IN AND OUT ON QUARTER ARCS"])
    tp10 = toolpath(grid, T1, 0.0, w10)
    i10 = write_levels(tp10, steep, T1.level_step)
    w20 = _program(1020, "MOULD SHALLOW T1", T1, [
        f"PARALLEL ZIGZAG ALONG X ON SLOPES UP TO {STEEP_DEG:.0f} DEG + {OVERLAP_MM:.1f} MM OVERLAP - "
        f"STEPOVER {T1.raster_step:.3f}",
        "CAM OPENCAMLIB BATCHDROPCUTTER - SAMPLING 0.05"])
    tp20 = toolpath(grid, T1, 0.0, w20)
    i20 = write_raster(tp20, shallow, T1.raster_step)
    log(f"finishing T1: contours {i10}, raster {i20}")
    steep2, shallow2, _, base2 = stretches(surf, tris, grid, T2, 0.0, rest_of=reach)
    w30 = _program(1030, "MOULD PENCIL T2", T2, [
        f"REST FINISHING WHERE T1 LEAVES MORE THAN {REST_MM:.3f} - CONTOURS STEP DOWN {T2.level_step:.3f} "
        f"THEN FLOOR RINGS STEPOVER {T2.raster_step:.3f}",
        "CAM OPENCAMLIB ADAPTIVEWATERLINE AND BATCHDROPCUTTER"])
    tp30 = toolpath(grid, T2, 0.0, w30)
    i30 = {"contours": write_levels(tp30, steep2, T2.level_step, zigzag=True),
           "rings": write_levels(tp30, shallow2, T2.raster_step, zigzag=True)}
    log(f"finishing T2: {i30}")
    texts, info, paths = {}, {}, {}
    for name, w, tp, i, tool in zip(PROGRAMS, (w10, w20, w30), (tp10, tp20, tp30), (i10, i20, i30), (T1, T1, T2)):
        footer(w)
        texts[name], paths[name] = w.text(), tp
        info[name] = {**i, "moves": dict(w.moves), "blocks": w.n // w.n_step, "links": dict(tp.links),
                      "tool": tool.t, "diameter": tool.diameter}
    info["steps"] = {"t1_cusp_um": cusp_um(T1.radius, T1.raster_step), "t1_wall_cusp_um": cusp_um(T1.radius, T1.level_step),
                     "t2_cusp_um": cusp_um(T2.radius, T2.raster_step), "box": BOX, **base, "t2": base2}
    return texts, info, paths
