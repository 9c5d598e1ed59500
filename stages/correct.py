"""Stage ``correct``: move NC vertices against the predicted error (seed 000 claim 9, para 0084).

One round of vertex moves (:func:`stages.correction.rounds.correct_once`). Predictions are relative
to the path they were made for, so every round applies its move to the ORIGINAL program (``blocks``,
``passes@first``): the command that leaves the original surface is the fixed point P = P0 − e(P)·n
(seed 003's iterative derivation). A pass this round did not predict keeps its round-1 error
(``errors@first``). ``generating@first`` (the original program's surfaces), the ``nominal`` model
(the surfaces the job's other programs finish) and the tool drive the gouge limit. The stage graph
repeats the chain from ``correct_blocks`` to here until :func:`converged`.

With a ``drift:`` section every vertex also gets the thermal drift compensation
(:mod:`stages.thermal.compensate`: the drift the model predicts when the tool reaches it, the
program starting after the job's earlier programs, ``passes@earlier``) in ``drift_*_um``, apart from
``x_new_mm``…: the next round predicts on the path in the workpiece frame, where the drift and its
compensation cancel; the writers add it.
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa

from stages.correction.rounds import correct_once, errors_on_passes, match_passes, pass_midpoints, with_missing_from
from stages.geometry.cutter import Cutter
from stages.geometry.workpiece import load_design_surface
from stages.tables import col, pick_entry, program_tool_number, xyz

NAME = "correct"
VERSION = "18"
INPUTS = ("blocks@first", "passes@first", "passes", "errors", "errors@first", "generating@first", "corrected@previous",
          "passes@earlier", "nominal")
OUTPUTS = ("corrected",)
# tol_um and max_iter steer the rounds and ln_normals / comp_table the writer: changing them re-uses
# every cached round
# drift.model is a file: its content enters the cache key (pipeline.config.FILE_KEYS)
PARAMS = ("correct.max_move_um", "correct.relax", "correct.gouge_limit", "correct.normal_tol_deg", "tool", "drift")


def run(inputs: dict, params: dict) -> dict[str, pa.Table]:
    passes = inputs["passes@first"]
    errors = errors_on_passes(inputs["errors"], inputs["passes"], passes)
    errors = with_missing_from(errors, inputs.get("errors@first"))
    opts = params.get("correct") or {}
    cutter = None
    if opts.get("gouge_limit", True) and params.get("tool") is not None:
        cutter = Cutter.from_params(pick_entry(params["tool"], program_tool_number(passes), "tool"))
    corrected = correct_once(inputs["blocks@first"], passes, errors, params,
                             previous=inputs.get("corrected@previous"), relax=float(opts.get("relax", 1.0)),
                             generating=inputs.get("generating@first"), tool_shape=cutter,
                             design=load_design_surface(inputs.get("nominal")) if cutter is not None else None)
    if params.get("drift") and corrected.num_rows:
        corrected = _with_drift_columns(corrected, passes, inputs.get("passes@earlier"), params["drift"])
    return {"corrected": corrected}


def _with_drift_columns(corrected: pa.Table, passes: pa.Table, earlier, drift: dict) -> pa.Table:
    """``corrected`` with the drift compensation of its vertices (at their programmed positions)."""
    from stages.thermal import load_model
    from stages.thermal.compensate import DRIFT_COLUMNS, drift_compensation
    path = drift["model"]
    comp = drift_compensation(load_model(path), col(corrected, "block_no", np.int64),
                              xyz(corrected, ("x_mm", "y_mm", "z_mm")), passes, earlier,
                              float(drift.get("start_s") or 0.0), where=str(path))
    for j, name in enumerate(DRIFT_COLUMNS):
        i = corrected.schema.get_field_index(name)
        corrected = corrected.set_column(i, corrected.schema.field(i), pa.array(comp[:, j]))
    return corrected


def converged(corrected: pa.Table, params: dict) -> bool:
    """Whether the round changed no vertex by ``correct.tol_um`` or more (the rounds stop)."""
    change = col(corrected, "change_um") if corrected.num_rows else np.zeros(0)
    return not (change.size and float(change.max()) >= float((params.get("correct") or {}).get("tol_um", 0.1)))


# a round whose prediction lowers the deviation RMS by less than this fraction of the best earlier
# one stops the rounds: another full prediction of the program would not pay for itself
STALL_FRACTION = 0.01


def stalled(records: list[dict]) -> bool:
    """Whether the last round's prediction did not lower the deviation from the original surface
    (``rms_dev_um``) by :data:`STALL_FRACTION` below every earlier round's."""
    devs = [r.get("rms_dev_um") for r in records]
    if len(devs) < 2 or devs[-1] is None or all(d is None for d in devs[:-1]):
        return False
    return devs[-1] > (1.0 - STALL_FRACTION) * min(d for d in devs[:-1] if d is not None)


def kept_round(records: list[dict], stopped: bool) -> int:
    """The round whose ``corrected`` table is the published correction.

    Round k's record is the prediction of the program corrected in round k − 1 (round 1: the program
    as written). Rounds that ran to ``tol_um`` or ``max_iter`` publish the last correction. Rounds that
    stalled publish the correction whose prediction deviated least from the original surface, and
    none (0) when no corrected program was predicted to deviate less than the program as written:
    a path offset does not help there (a deflection that changes with the offset).
    """
    if not stopped:
        return len(records)
    devs = [np.inf if r.get("rms_dev_um") is None else r["rms_dev_um"] for r in records]
    return int(np.argmin(devs))            # index k − 1 of the best round k is the round that corrected it


def round_record(tables: dict) -> dict:
    """What a round predicted and changed, for ``run.json``.

    ``rms_err_um``: predicted error of the path this round predicted on, relative to that path.
    ``rms_dev_um``: the same as deviation from the ORIGINAL program's surface, e + (P − P0)·n with
    the path shift at each pass midpoint: its distance to the chord of the original pass (the one in
    the same block whose midpoint is nearest, where the corrected program split into other passes).
    ``max_change_um``: the largest vertex change this round made.
    """
    errors, cor = tables["errors"], tables["corrected"]
    p, p0 = tables["passes"].sort_by("pass_id"), tables["passes@first"].sort_by("pass_id")
    err = col(errors, "err_um") if errors.num_rows else np.zeros(0)
    fin = np.isfinite(err)
    dev = None
    if errors.num_rows:
        eid = col(errors, "pass_id", np.int64)
        target, ok = match_passes(eid, p, p0)
        ok = np.ones(eid.size, bool) if ok is None else ok
        # the path shift at the pass's midpoint: to the nearest point of the original pass's chord
        mid = pass_midpoints(p)[np.searchsorted(col(p, "pass_id", np.int64), eid)]
        row0 = np.minimum(np.searchsorted(col(p0, "pass_id", np.int64), target), p0.num_rows - 1)
        a, b = xyz(p0, ("x0_mm", "y0_mm", "z0_mm"))[row0], xyz(p0, ("x1_mm", "y1_mm", "z1_mm"))[row0]
        ab = b - a
        t = np.clip(np.einsum("ij,ij->i", mid - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-24), 0, 1)
        shift = mid - (a + t[:, None] * ab)
        dev = np.where(ok, err + 1000.0 * np.einsum("ij,ij->i", shift, xyz(errors, ("nx", "ny", "nz"))), np.nan)
    change = col(cor, "change_um") if cor.num_rows else np.zeros(0)
    move = col(cor, "move_um") if cor.num_rows else np.zeros(0)
    rms = lambda x: float(np.sqrt(np.mean(x ** 2))) if x.size else 0.0  # noqa: E731
    return {"n_errors": int(fin.sum()), "rms_err_um": rms(err[fin]),
            "max_abs_err_um": float(np.abs(err[fin]).max()) if fin.any() else 0.0,
            "rms_dev_um": None if dev is None else rms(dev[fin & np.isfinite(dev)]),
            "max_change_um": float(change.max()) if change.size else 0.0,
            "max_move_um": float(move.max()) if move.size else 0.0,
            "clipped": int(np.count_nonzero(col(cor, "clipped", bool))) if cor.num_rows else 0}
