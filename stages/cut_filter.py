"""Stage ``cut_filter`` (seed 000 claim 7, paras 0052-0054): which passes cut, and where.

One ordered scan per tile from below: the stock, then every pass's sweep in execution order with the
depth test, as the machine removes material; a pass cuts where its sweep passes the test
(:func:`stages.scan.cut_passes.cut_filter`). The prediction point lies inside the part it cuts; the
scan's final image is the claim-8 render that ``angle_prune`` reads.
"""
from __future__ import annotations

import pyarrow as pa

import schemas
from stages.geometry.cutter import Cutter
from stages.geometry.passes import pass_geometry
from stages.geometry.workpiece import load_workpiece
from stages.scan.cut_passes import cut_filter
from stages.scan.tiles import render_settings

NAME = "cut_filter"
VERSION = "6"
INPUTS = ("passes", "stock")
OUTPUTS = ("cut_filter",)
PARAMS = ("tool", "render")


def run(inputs: dict, params: dict) -> dict:
    passes = inputs["passes"]
    shape = Cutter.from_params(params["tool"])
    pg = pass_geometry(passes, params["tool"])
    wp = load_workpiece(inputs.get("stock"))
    renderer, ppm = render_settings(params)
    res = cut_filter(pg, shape, wp, renderer, ppm)
    n = len(pg.pass_id)
    table = pa.table({
        "program_id": pa.array([pg.program_id] * n, pa.string()),
        "pass_id": pa.array(pg.pass_id, pa.int32()),
        "is_cutting": pa.array(res["is_cutting"]),
        "cut_px": pa.array(res["cut_px"], pa.int32()),
        "pred_x_mm": pa.array(res["pred_x_mm"]),
        "pred_y_mm": pa.array(res["pred_y_mm"]),
        "pred_z_mm": pa.array(res["pred_z_mm"]),
        "pred_t": pa.array(res["pred_t"]),
        "cut_max_contact_deg": pa.array(res["cut_max_contact_deg"]),
        "surface_px": pa.array(res["surface_px"], pa.int32()),
        "surface_max_contact_deg": pa.array(res["surface_max_contact_deg"]),
    })
    return {"cut_filter": schemas.check("cut_filter", table)}
