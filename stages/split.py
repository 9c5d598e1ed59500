"""Stage ``split``: motion blocks → passes (linear moves), timed from the feed (seed para 0051).

Arcs become chords within ``split.chord_tol_mm``, long cutting moves equal pieces of at most
``split.max_pass_mm``, runs of short moves are merged where that keeps the path within the chord
tolerance (:func:`stages.nc.moves.split_blocks`). Also completes the ``programs`` row (pass count,
cut length, duration) that ``parse`` started.
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa

from stages.nc.moves import empty_passes, split_blocks
from stages.nc.reader import RAPID
from stages.tables import xyz

NAME = "split"
VERSION = "5"
INPUTS = ("programs", "blocks")
OUTPUTS = ("passes", "programs")
PARAMS = ("split", "machine.rapid_mm_min", "tool")


def run(inputs: dict, params: dict) -> dict[str, pa.Table]:
    status = inputs["programs"].to_pylist()[0]
    passes = split_blocks(inputs["blocks"], params) if status["status"] == "ok" else empty_passes()
    cut = passes.column("motion").to_numpy() != RAPID if passes.num_rows else np.zeros(0, bool)
    length = np.linalg.norm(xyz(passes, ("x1_mm", "y1_mm", "z1_mm")) - xyz(passes, ("x0_mm", "y0_mm", "z0_mm")),
                            axis=1)
    row = dict(status, n_passes=passes.num_rows, cut_length_mm=float(length[cut].sum()),
               duration_s=float(passes.column("t_end_s")[-1].as_py()) if passes.num_rows else 0.0)
    if status["status"] == "ok" and not cut.any():
        row.update(status="failed", message=f"{status['path']}: no cutting move in the program")
    return {"passes": passes, "programs": pa.Table.from_pylist([row])}
