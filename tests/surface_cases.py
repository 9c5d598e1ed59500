"""Running the scan stage's kernel on hand-made passes, for the tests of generating points and
engagement against closed forms."""
from __future__ import annotations

import numpy as np
import pyarrow as pa

from stages import scan
from stages.geometry.cutter import Cutter
from stages.geometry.passes import pass_geometry
from stages.geometry.workpiece import load_design_surface, load_workpiece
from stages.render import make_renderer
from stages.surface.program import scan_program


def passes_table(name, p0, p1, feed=1000.0, rpm=1000.0, motion=None):
    """A ``passes`` table of straight moves ``p0[k] → p1[k]`` (tips), one block each."""
    p0, p1 = np.asarray(p0, float).reshape(-1, 3), np.asarray(p1, float).reshape(-1, 3)
    k = len(p0)
    return pa.table({
        "program_id": [name] * k, "pass_id": pa.array(range(k), pa.int32()),
        "block_no": pa.array(range(k), pa.int32()), "line_no": pa.array(range(1, k + 1), pa.int32()),
        "motion": pa.array([1] * k if motion is None else motion, pa.int8()),
        "x0_mm": p0[:, 0], "y0_mm": p0[:, 1], "z0_mm": p0[:, 2], "x1_mm": p1[:, 0], "y1_mm": p1[:, 1],
        "z1_mm": p1[:, 2], "feed_mm_min": np.full(k, float(feed)), "spindle_rpm": np.full(k, float(rpm)),
        "tool": pa.array([1] * k, pa.int32()), "t_start_s": np.arange(k, dtype=float),
        "t_end_s": np.arange(1, k + 1, dtype=float)})


def predict_at(passes, stock, tool, at: dict, nominal=None, backend="auto", px_per_mm=20.0, **kw) -> dict:
    """The scan stage's tables with the passes ``at`` ({pass_id: tip}) predicted at those tips."""
    pg = pass_geometry(passes, tool)
    index = {int(p): i for i, p in enumerate(pg.pass_id)}
    res = scan_program(pg, Cutter.from_params(tool), load_workpiece(stock), make_renderer(backend), px_per_mm,
                       design=load_design_surface(nominal), at={index[p]: np.asarray(t, float) for p, t in at.items()},
                       **kw)
    return scan.tables(pg, res)


def rows(table, key="pass_id") -> dict:
    return {r[key]: r for r in table.to_pylist()}
