"""Stage ``errors``: the machining error each predicted pass leaves at its generating point.

Deflection at the generating flute's passage along the surface normal, plus the tool's shape error
at the contact angle, plus runout; the deepest tooth passage of the neighbouring passes where one
cuts deeper (:mod:`stages.cutting.surface_error`). ``err_um`` > 0 is material left (DESIGN §5).
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa

from stages.cutting.forces import DEFAULT_N_ROT
from stages.cutting.surface_error import (
    contact_height_mm, deepest_passage, machining_error, read_profile, second_contact_error, tip_z_nearest)
from stages.geometry.cutter import Cutter
from stages.tables import col, list_values, match_passes, pick_entry, program_tool_number, xyz

NAME = "errors"
VERSION = "6"
INPUTS = ("passes", "generating", "deflection")
OUTPUTS = ("errors",)
PARAMS = ("tool",)


def run(inputs: dict, params: dict) -> dict:
    from schemas.errors import SCHEMA
    passes, gen, defl = inputs["passes"], inputs["generating"], inputs["deflection"]
    # a pass whose surface is removed again later has no generating point (view "none"): no error
    gen = gen.filter(pa.array(np.isfinite(col(gen, "contact_deg"))))
    if gen.num_rows == 0:
        return {"errors": SCHEMA.empty_table()}
    cutter = Cutter.from_params(pick_entry(params.get("tool"), program_tool_number(passes), "tool"))
    profile = read_profile(cutter.profile) if cutter.profile else None

    pass_ids = col(gen, "pass_id", np.int64)
    rows = match_passes(passes, pass_ids, "generating")
    # deflection row of each generating row (missing → NaN deflection error)
    d_ids = col(defl, "pass_id", np.int64) if defl.num_rows else np.zeros(0, np.int64)
    if len(d_ids):
        order = np.argsort(d_ids, kind="stable")
        pos = np.minimum(np.searchsorted(d_ids[order], pass_ids), len(d_ids) - 1)
        have = d_ids[order][pos] == pass_ids
        dx = list_values(defl.column("dx_um"), "deflection.dx_um")[order[pos]]
        dy = list_values(defl.column("dy_um"), "deflection.dy_um")[order[pos]]
        dx[~have] = np.nan
        dy[~have] = np.nan
    else:
        dx = dy = np.full((len(pass_ids), DEFAULT_N_ROT), np.nan)

    gen_xyz = xyz(gen, ("gen_x_mm", "gen_y_mm", "gen_z_mm"))
    normal = xyz(gen, ("nx", "ny", "nz"))
    q = col(gen, "contact_deg")
    tip_z = tip_z_nearest(passes, rows, gen_xyz) - cutter.control_offset_mm
    z_c = contact_height_mm(cutter, q, gen_xyz[:, 2], tip_z)
    res = machining_error(dx, dy, col(gen, "rotation_deg"), q, normal, z_c, cutter, profile)
    finished_by = pass_ids.copy()
    res["contact_deg"] = q.copy()
    if len(d_ids):
        deepest_passage(res, finished_by, passes, rows, gen_xyz, normal, defl, cutter, profile)
    second = second_contact_error(gen, passes, rows, dx, dy, cutter, profile)
    table = pa.table({
        "program_id": gen.column("program_id"),
        "pass_id": pa.array(pass_ids.astype(np.int32)),
        "err_deflection_um": res["err_deflection_um"],
        "defl_x_um": res["defl_x_um"], "defl_y_um": res["defl_y_um"],
        "err_shape_um": res["err_shape_um"],
        "err_um": res["err_um"],
        "nx": normal[:, 0], "ny": normal[:, 1], "nz": normal[:, 2],
        "err_runout_um": res["err_runout_um"],
        "contact_deg": res["contact_deg"],
        "spindle_deg": res["spindle_deg"],
        "flute": res["flute"],
        "finished_by": pa.array(finished_by.astype(np.int32)),
        **second,
    })
    return {"errors": table}
