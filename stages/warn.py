"""Stage ``warn``: the passes a path correction cannot help, with their NC line and why.

- ``beyond_move_limit``: a predicted error larger than ``correct.max_move_um`` (the correction is
  clipped there);
- ``rest_material``: stock along the normal (:mod:`stages.surface.allowance`, also the table
  ``allowance``) over ``warnings.rest_factor`` times the allowance (``warnings.allowance_mm``, else
  the program's median);
- ``overloaded``: a deflection over ``feed.max_deflection_um`` even at ``feed.min_mm_min``
  (``feeds`` table, with a ``feed:`` section);
- ``overloaded_as_programmed``: over the limit at the programmed feed, within it at the scheduled
  one (the program as written must not run without its scheduled feeds).
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa

from stages.geometry.cutter import Cutter
from stages.surface.allowance import stock_along_normal
from stages.tables import col, match_passes, pick_entry, program_tool_number

NAME = "warn"
VERSION = "4"
INPUTS = ("passes", "cut_filter", "generating", "engagement", "errors", "feeds")
OUTPUTS = ("allowance", "warnings")
PARAMS = ("tool", "correct.max_move_um", "warnings", "feed.max_deflection_um")

DEFAULTS = {"allowance_mm": None, "rest_factor": 3.0}


def run(inputs: dict, params: dict) -> dict:
    from schemas.allowance import SCHEMA as ALLOWANCE
    from schemas.warnings import SCHEMA as WARNINGS
    passes = inputs["passes"]
    opts = dict(DEFAULTS, **(params.get("warnings") or {}))
    pid = passes.column("program_id")[0].as_py() if passes.num_rows else ""
    rows = []

    def warn(pass_ids, reason, value, limit, text):
        if len(pass_ids) == 0:
            return
        line = col(passes, "line_no", np.int64)[match_passes(passes, pass_ids, reason)]
        rows.append({"pass_id": np.asarray(pass_ids, np.int64), "line_no": line, "reason": reason,
                     "value": np.asarray(value, float), "limit": np.full(len(pass_ids), float(limit)),
                     "message": [text(v) for v in value]})

    errors = inputs["errors"]
    max_move = float((params.get("correct") or {}).get("max_move_um", 50.0))
    if errors.num_rows:
        e = col(errors, "err_um")
        big = np.abs(e) > max_move
        warn(col(errors, "pass_id", np.int64)[big], "beyond_move_limit", e[big], max_move,
             lambda v: f"predicted error {v:+.1f} µm is beyond correct.max_move_um {max_move:g} µm")

    ids, stock = np.zeros(0, np.int64), np.zeros(0)
    if inputs["engagement"].num_rows:
        cutter = Cutter.from_params(pick_entry(params["tool"], program_tool_number(passes), "tool"))
        ids, stock = stock_along_normal(inputs["engagement"], inputs["generating"], inputs["cut_filter"], cutter)
        fin = np.isfinite(stock)
        allowance = opts["allowance_mm"] if opts["allowance_mm"] is not None else (
            float(np.median(stock[fin])) if fin.any() else np.nan)
        limit = float(opts["rest_factor"]) * allowance
        if np.isfinite(limit):
            rest = fin & (stock > limit)
            warn(ids[rest], "rest_material", stock[rest], limit,
                 lambda v: f"{v:.2f} mm of stock along the normal, over {opts['rest_factor']:g} × the allowance "
                           f"{allowance:.2f} mm: rest material the finishing tool should not meet")

    feeds = inputs["feeds"]
    if feeds.num_rows:
        over = col(feeds, "overloaded", bool)
        peak = col(feeds, "peak_deflection_new_um")
        lim = float((params.get("feed") or {}).get("max_deflection_um", np.nan))
        fid = col(feeds, "pass_id", np.int64)
        warn(fid[over], "overloaded", peak[over], lim,
             lambda v: f"deflection {v:.1f} µm at the minimum feed: over feed.max_deflection_um")
        # the program as written overloads these; the scheduled feed brings them within the limit
        peak0 = col(feeds, "peak_deflection_um")
        fixed = (np.nan_to_num(peak0, nan=-np.inf) > lim) & ~over
        warn(fid[fixed], "overloaded_as_programmed", peak0[fixed], lim,
             lambda v: f"deflection {v:.1f} µm at the programmed feed: over feed.max_deflection_um "
                       "(the scheduled feed keeps it within)")

    allowance_t = pa.table({"program_id": pa.array([pid] * len(ids), pa.string()),
                            "pass_id": pa.array(ids, pa.int32()),
                            "stock_mm": pa.array(stock, mask=~np.isfinite(stock))}, schema=ALLOWANCE)
    if not rows:
        return {"allowance": allowance_t, "warnings": WARNINGS.empty_table()}
    cat = {k: np.concatenate([r[k] for r in rows]) if k != "message" else sum((r[k] for r in rows), [])
           for k in ("pass_id", "line_no", "value", "limit", "message")}
    reason = sum(([r["reason"]] * len(r["pass_id"]) for r in rows), [])
    order = np.lexsort((np.arange(len(reason)), cat["pass_id"]))
    table = pa.table({"program_id": pa.array([pid] * len(reason), pa.string()),
                      "pass_id": pa.array(cat["pass_id"][order], pa.int32()),
                      "line_no": pa.array(cat["line_no"][order], pa.int32()),
                      "reason": pa.array([reason[i] for i in order], pa.string()),
                      "value": cat["value"][order], "limit": cat["limit"][order],
                      "message": pa.array([cat["message"][i] for i in order], pa.string())}, schema=WARNINGS)
    return {"allowance": allowance_t, "warnings": table}
