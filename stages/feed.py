"""Stage ``feed``: a scheduled feed per pass (only with a workflow ``feed:`` section).

Where a path offset cannot cancel a deflection (one that changes with the offset: heavy rest
material), the feed is lowered instead. For every predicted pass the force is evaluated at the
programmed feed and at twice it (the model is affine in the feed per tooth, see
:mod:`stages.cutting.feeds`), the deflection follows through the machine's compliance, and the
largest feed per tooth keeping the peak deflection within ``feed.max_deflection_um`` and the chip
within ``feed.max_chip_mm`` is taken. Passes that cut nothing get ``feed.max_mm_min``; cutting
passes without a prediction keep their feed; all within ``feed.min_mm_min`` … ``feed.max_mm_min``,
then lowered so neighbours differ by at most ``feed.max_change``. Rapids keep the rapid rate.
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from stages import forces as forces_stage
from stages.cutting.feeds import affine_deflection, largest_feed_per_tooth, peak_deflection, smooth_down
from stages.cutting.forces import feed_per_tooth_mm
from stages.cutting.frf import deflection_xy
from stages.geometry.cutter import Cutter
from stages.tables import col, list_values, match_passes, pick_entry, program_tool_number

NAME = "feed"
VERSION = "1"
INPUTS = ("passes", "cut_filter", "engagement", "forces")
OUTPUTS = ("feeds",)
PARAMS = ("feed", "tool", "material", "machine.frf")


def used_params(params: dict) -> dict:
    """Without a ``feed:`` section the stage writes an empty table and uses no workflow value."""
    return params if params.get("feed") else {}


def run(inputs: dict, params: dict) -> dict:
    from schemas.feeds import SCHEMA
    opts = params.get("feed")
    passes = inputs["passes"].sort_by("pass_id") if inputs["passes"].num_rows else inputs["passes"]
    if not opts or passes.num_rows == 0:
        return {"feeds": SCHEMA.empty_table()}
    lim_um, chip_max = float(opts["max_deflection_um"]), float(opts["max_chip_mm"])
    f_min, f_max = float(opts["min_mm_min"]), float(opts["max_mm_min"])
    cutter = Cutter.from_params(pick_entry(params["tool"], program_tool_number(passes), "tool"))

    n = passes.num_rows
    motion = col(passes, "motion", np.int64)
    feed = col(passes, "feed_mm_min")
    rpm = col(passes, "spindle_rpm")
    moving = (motion >= 1) & (motion <= 3)
    cut = np.zeros(n, bool)
    cf = inputs["cut_filter"]
    if cf.num_rows:
        cut[match_passes(passes, col(cf, "pass_id", np.int64), "cut_filter")] = col(cf, "is_cutting", bool)

    new = np.where(moving & ~cut, f_max, feed)
    limited = np.where(moving, np.where(cut, "as_programmed", "air"), "rapid").astype(object)
    peak0 = np.full(n, np.nan)
    peak1 = np.full(n, np.nan)
    over = np.zeros(n, bool)
    fr = inputs["forces"]
    rows = np.zeros(0, np.int64)
    if fr.num_rows:
        rows = match_passes(passes, col(fr, "pass_id", np.int64), "forces")
        fz0 = col(fr, "feed_per_tooth_mm")
        dc, de = _affine(inputs, params, passes, fr, fz0)
        per_rev = rpm[rows] * cutter.flutes
        cap = np.minimum(chip_max, f_max / per_rev)
        fz = largest_feed_per_tooth(dc, de, lim_um, cap)
        over[rows] = ~np.isfinite(fz)
        new[rows] = np.where(np.isfinite(fz), fz, 0.0) * per_rev
        limited[rows] = np.where(~np.isfinite(fz) | (fz < cap * (1 - 1e-9)), "deflection",
                                 np.where(chip_max * per_rev <= f_max, "chip", "max_feed"))
        peak0[rows] = peak_deflection(dc, de, fz0)
    raised = moving & (new < f_min)
    lowered = moving & (new > f_max)
    new = np.where(moving, np.clip(new, f_min, f_max), new)
    limited[raised & ~over] = "min_feed"
    limited[lowered] = "max_feed"
    if moving.any():
        k = np.flatnonzero(moving)
        smooth = smooth_down(new[k], float(opts.get("max_change", 0.3)))
        limited[k[smooth < new[k] * (1 - 1e-9)]] = "smoothing"
        new[k] = smooth
    if len(rows):
        peak1[rows] = peak_deflection(dc, de, feed_per_tooth_mm(new[rows], rpm[rows], cutter.flutes))
    dur = col(passes, "t_end_s") - col(passes, "t_start_s")
    dur_new = np.where(moving, dur * feed / new, dur)
    turning = moving & (rpm > 0)
    fz_old = np.where(turning, feed_per_tooth_mm(feed, np.where(turning, rpm, 1.0), cutter.flutes), np.nan)
    fz_new = np.where(turning, feed_per_tooth_mm(new, np.where(turning, rpm, 1.0), cutter.flutes), np.nan)
    table = pa.table({
        "program_id": passes.column("program_id"), "pass_id": passes.column("pass_id"),
        "line_no": passes.column("line_no"), "feed_mm_min": feed, "feed_new_mm_min": new,
        "peak_deflection_um": pa.array(peak0, mask=np.isnan(peak0)),
        "peak_deflection_new_um": pa.array(peak1, mask=np.isnan(peak1)),
        "chip_mm": pa.array(fz_old, mask=np.isnan(fz_old)), "chip_new_mm": pa.array(fz_new, mask=np.isnan(fz_new)),
        "limited_by": pa.array(limited.astype(str)), "overloaded": over,
        "duration_s": dur, "duration_new_s": dur_new,
    }, schema=SCHEMA)
    return {"feeds": table}


def _affine(inputs: dict, params: dict, passes: pa.Table, fr: pa.Table, fz1: np.ndarray):
    """(Dc, De) of every ``forces`` row (feed per tooth ``fz1``): the forces as predicted and again
    at twice the feed."""
    frf = (params.get("machine") or {}).get("frf")
    rpm = col(fr, "spindle_rpm")

    def deflection(forces: pa.Table):
        return deflection_xy(list_values(forces.column("fx_n"), "forces.fx_n"),
                             list_values(forces.column("fy_n"), "forces.fy_n"), rpm, frf)
    doubled = passes.set_column(passes.schema.get_field_index("feed_mm_min"), "feed_mm_min",
                                pc.multiply(passes.column("feed_mm_min"), 2.0))
    f2 = forces_stage.run({"passes": doubled, "engagement": inputs["engagement"]}, params)["forces"]
    if f2.num_rows != fr.num_rows or not np.array_equal(col(f2, "pass_id", np.int64), col(fr, "pass_id", np.int64)):
        raise ValueError("feed: the forces at twice the feed do not line up with the forces table")
    return affine_deflection(deflection(fr), deflection(f2), fz1, 2.0 * fz1)
