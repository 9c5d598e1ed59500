"""Drift compensation of a program's vertices (stage ``correct``, workflow section ``drift``).

The programs of a job run in order on one machine. A program's own clock is its ``passes`` table's
``t_start_s``/``t_end_s``, which start at 0 for every program and count cutting moves at their F,
rapids at ``machine.rapid_mm_min`` and dwells (:mod:`stages.nc.moves`). On the model's clock a
program starts at ``drift.start_s`` plus the machining times of the programs before it, each the
``t_end_s`` of its last pass: rapids and dwells between its moves are counted, a dwell after its
last move and any time between programs (tool changes, loading) are not.

A vertex (the end point of a motion block) is reached at the ``t_end_s`` of the pass ending there;
a vertex inside a merged pass (short moves joined into one pass) at the pass's start time plus
its fraction of the pass chord; a block without a pass of its own (a move of no length) when
the pass before it ends. The compensation is the negative of the drift predicted there, at the
vertex's position as programmed. A model with a heat input (``spindle_rpm``) gets the speed of
every pass of the job from its start on; before the job's first pass the model's own convention
holds (its first sample's level from t = 0: the machine ran at that speed since its cold start).
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from stages import InputError
from stages.tables import col, xyz
from stages.thermal.model import AXES, POSITION_COLUMNS, DriftModel

DRIFT_COLUMNS = ("drift_x_um", "drift_y_um", "drift_z_um")


def program_start_s(earlier, start_s: float = 0.0) -> float:
    """When the program starts on the model's clock: ``start_s`` plus the earlier programs'
    machining times (the last ``t_end_s`` of each of their ``passes`` tables), s.

    Parameters
    ----------
    earlier : ``passes@earlier``: [(passes table, params), ...] in machining order, or None
    start_s : when the job's first program starts, s since the machine's cold start
    """
    total = float(start_s)
    for passes, _ in earlier or ():
        if passes.num_rows:
            total += float(np.max(col(passes, "t_end_s")))
    return total


def vertex_times(block_no: np.ndarray, end: np.ndarray, passes: pa.Table) -> np.ndarray:
    """Time (s, the program's clock) at which the tool reaches each vertex.

    Parameters
    ----------
    block_no : (n,) block numbers of the vertices (motion blocks, increasing)
    end : (n, 3) their end points, mm (places a vertex inside a merged pass)
    passes : the program's ``passes`` table (any order)
    """
    n = len(block_no)
    if passes.num_rows == 0:
        return np.zeros(n)
    passes = passes.sort_by("pass_id")
    pb0, pb1 = col(passes, "block_no", np.int64), col(passes, "block_end", np.int64)
    t0, t1 = col(passes, "t_start_s"), col(passes, "t_end_s")
    q = np.searchsorted(pb0, np.asarray(block_no, np.int64), side="right") - 1
    qc = np.maximum(q, 0)
    t = np.where(q < 0, t0[0], t1[qc])
    inside = (q >= 0) & (pb1[qc] > block_no)
    if inside.any():
        a, b = xyz(passes, ("x0_mm", "y0_mm", "z0_mm"))[qc[inside]], xyz(passes, ("x1_mm", "y1_mm", "z1_mm"))[qc[inside]]
        ab = b - a
        f = np.einsum("ij,ij->i", end[inside] - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-24)
        k = qc[inside]
        t[inside] = t0[k] + np.clip(f, 0.0, 1.0) * (t1[k] - t0[k])
    return t


def _heat_history(model: DriftModel, passes: pa.Table, earlier, start_s: float, where: str):
    """Times and heat input of the job's passes up to this program (each pass's speed from its
    start on), for a model with a heat-input column; None for a model without one."""
    if model.heat_column is None:
        return None
    if model.heat_column != "spindle_rpm":
        raise InputError(f"{where}: heat input column {model.heat_column!r}: a program gives only spindle_rpm")
    t, u, offset = [], [], float(start_s)
    for p in [e[0] for e in earlier or ()] + [passes]:
        if p.num_rows and "spindle_rpm" not in p.column_names:
            raise InputError(f"{where}: the model's heat input is spindle_rpm and the passes table has no spindle speed")
        if p.num_rows:
            t.append(offset + col(p, "t_start_s"))
            u.append(col(p, "spindle_rpm"))
            offset += float(np.max(col(p, "t_end_s")))
    return (np.concatenate(t), np.concatenate(u)) if t else None


def drift_compensation(model: DriftModel, block_no, end, passes: pa.Table, earlier=None, start_s: float = 0.0,
                       where: str = "drift.model") -> np.ndarray:
    """The compensation (µm, (n, 3)) of the vertices: minus the drift ``model`` predicts at the time
    the tool reaches each one and at its position.

    Parameters
    ----------
    model : the fitted drift model
    block_no, end : the vertices' block numbers and end points as programmed (mm)
    passes : the program's ``passes`` table (as written: its times)
    earlier : ``passes@earlier`` (the job's programs before this one), or None
    start_s : ``drift.start_s``
    where : names the model file in errors

    Raises
    ------
    InputError
        The model needs temperatures, or a heat input the program does not give.
    """
    end = np.asarray(end, float).reshape(-1, 3)
    n = len(end)
    if n == 0:
        return np.zeros((0, 3))
    if model.temperatures:
        raise InputError(f"{where}: the model needs temperature readings ({', '.join(model.temperatures)}); "
                         "an NC program gives none")
    t = program_start_s(earlier, start_s) + vertex_times(block_no, end, passes)
    data = {"time_s": t}
    for j, c in enumerate(POSITION_COLUMNS):
        data[c] = end[:, j]
    hist = _heat_history(model, passes, earlier, start_s, where)
    if hist is not None:
        # the heat input is piecewise constant from sample to sample: merge the vertices into the
        # pass starts, a vertex before a pass starting at the same time (it ends the pass before)
        ht, hu = hist
        tt = np.concatenate([t, ht])
        order = np.lexsort((np.r_[np.zeros(n), np.ones(ht.size)], tt))
        level = np.concatenate([np.full(n, np.nan), hu])[order]
        # a vertex carries the level of the latest pass start at or before it
        idx = np.where(np.isnan(level), -1, np.arange(level.size))
        idx = np.maximum.accumulate(idx)
        level = np.where(idx >= 0, level[np.maximum(idx, 0)], hu[0])
        full = {"time_s": tt[order], model.heat_column: level}
        for c in POSITION_COLUMNS:
            full[c] = np.concatenate([data[c], np.zeros(ht.size)])[order]
        pred = model.predict(full)
        back = np.empty(order.size, np.int64)
        back[order] = np.arange(order.size)
        rows = back[:n]
        return -np.stack([pred[f"d{a}_um"][rows] for a in AXES], 1)
    pred = model.predict(data)
    return -np.stack([pred[f"d{a}_um"] for a in AXES], 1)


def with_drift(corrected: pa.Table) -> pa.Table:
    """``corrected`` with the drift compensation added to the new coordinates: the path the
    writers write. Arc centres move by their end point's compensation (the drift changes by far
    less than a µm over one arc, so the arc keeps its radius to well within the writing grid).
    A table without drift columns, or with zero compensation, comes back unchanged."""
    if corrected.num_rows == 0 or not set(DRIFT_COLUMNS) <= set(corrected.column_names):
        return corrected
    d = np.stack([col(corrected, c) for c in DRIFT_COLUMNS], 1) / 1000.0
    if not np.any(d):
        return corrected
    out = corrected
    for j, a in enumerate(AXES):
        for name in (f"{a}_new_mm", f"c{a}_new_mm"):
            i = out.schema.get_field_index(name)
            v = out.column(name)
            shifted = pc.add(v, pa.array(d[:, j]))
            out = out.set_column(i, out.schema.field(i), shifted)
    return out


def drift_only(first: pa.Table | None, blocks: pa.Table) -> pa.Table | None:
    """A ``corrected`` table that moves the vertices by the drift compensation alone, from the first
    round's table ``first``: for a program whose error correction is not kept (no round predicted
    better than the program as written) the drift is still there to compensate. None when
    ``first`` carries no compensation."""
    if first is None or first.num_rows == 0 or not set(DRIFT_COLUMNS) <= set(first.column_names):
        return None
    if not any(np.any(col(first, c)) for c in DRIFT_COLUMNS):
        return None
    out = first
    arc = np.isin(col(first, "motion", np.int64), (2, 3))
    rows = np.searchsorted(col(blocks, "block_no", np.int64), col(first, "block_no", np.int64))
    n = first.num_rows
    values = {"move_um": np.zeros(n), "change_um": np.zeros(n), "clipped": np.zeros(n, bool),
              "gouge_limit_um": np.zeros(n)}
    for a in AXES:
        values[f"{a}_new_mm"] = col(first, f"{a}_mm")
        values[f"c{a}_new_mm"] = pa.array(col(blocks, f"c{a}_mm")[rows], mask=~arc)
    for name, v in values.items():
        i = out.schema.get_field_index(name)
        out = out.set_column(i, out.schema.field(i), pa.array(v, out.schema.field(i).type))
    return out


def max_drift_um(corrected: pa.Table) -> float:
    """The largest drift compensation of ``corrected`` (µm), 0 without one."""
    if corrected.num_rows == 0 or not set(DRIFT_COLUMNS) <= set(corrected.column_names):
        return 0.0
    return float(np.linalg.norm(np.stack([col(corrected, c) for c in DRIFT_COLUMNS], 1), axis=1).max())
