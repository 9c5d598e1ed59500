"""Stage ``generating`` (seed 000 claims 1, 4, 5, 6): generating point, φ, q, normal and the
cutting region of every predicted pass.

For each predicted pass at its prediction point (``cut_filter``): the tool M there with φ and q in
its pixels, the sweeps before and after it and the stock, with the depth test; the pixels of M that
stay in front are the surface it leaves, their mean the generating point C (:mod:`stages.scan.generating`).
Steep walls are seen along the surface normal (claim 6). The engagement (claim 5) is the envelope
in the material before the pass (:mod:`stages.scan.engagement`); decode a row with
:func:`stages.scan.engagement.unpack_engagement`.
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa

import schemas
from stages import InputError
from stages.geometry.cutter import Cutter
from stages.geometry.passes import pass_geometry
from stages.geometry.workpiece import load_design_surface, load_workpiece
from stages.scan.contacts import SECOND_COLUMNS
from stages.scan.engagement import ramp_deg
from stages.scan.generating import generating
from stages.scan.tiles import render_settings

NAME = "generating"
VERSION = "17"
INPUTS = ("passes", "stock", "cut_filter", "angle_prune", "nominal")
OUTPUTS = ("generating", "engagement")
PARAMS = ("tool", "render")
# The engine runs a program's predictions as this many shards on separate workers (each shard
# every SHARDS-th predicted pass, so pocket walls and floors spread evenly; each shard repeats the
# ordered scan for its own snapshots, a few % of the work) and joins them with combine_shards.
SHARDS = 4


def run(inputs: dict, params: dict, shard: tuple[int, int] | None = None) -> dict:
    """Generating points and engagement of the predicted passes; with ``shard`` = (i, n) only
    every n-th of them from the i-th on (see ``SHARDS``)."""
    passes = inputs["passes"]
    tool = params["tool"]
    shape = Cutter.from_params(tool)
    pg = pass_geometry(passes, tool)
    wp = load_workpiece(inputs.get("stock"))
    renderer, ppm = render_settings(params)
    cf = inputs["cut_filter"]
    ap = inputs["angle_prune"]
    for name, tab, cols in (("cut_filter", cf, ("pass_id", "is_cutting", "pred_x_mm")),
                            ("angle_prune", ap, ("pass_id", "predict"))):
        miss = [c for c in cols if c not in tab.column_names]
        if miss:
            raise InputError(f"{name}: missing columns {miss}")
    pos = {int(p): k for k, p in enumerate(pg.pass_id)}
    cfp = cf.column("pass_id").to_numpy()
    ok = cf.column("is_cutting").to_numpy(zero_copy_only=False).astype(bool)
    pred = {int(p): (x, y, z) for p, c, x, y, z in zip(
        cfp, ok, cf.column("pred_x_mm").to_numpy(zero_copy_only=False),
        cf.column("pred_y_mm").to_numpy(zero_copy_only=False),
        cf.column("pred_z_mm").to_numpy(zero_copy_only=False)) if c}
    app = ap.column("pass_id").to_numpy()
    apf = ap.column("predict").to_numpy(zero_copy_only=False).astype(bool)
    chosen = sorted(int(p) for p, k in zip(app, apf) if k and int(p) in pred and int(p) in pos)
    if shard is not None:
        i, n = shard
        chosen = chosen[i::n]
    idx = np.array([pos[p] for p in chosen], np.int64)
    tips = np.array([pred[p] for p in chosen], float).reshape(-1, 3)
    gen, eng = generating(pg, shape, wp, renderer, ppm, idx, tips, shape.flutes,
                          design=load_design_surface(inputs.get("nominal")))
    m = len(idx)
    pid = pa.array([pg.program_id] * m, pa.string())
    g = pa.table({"program_id": pid, "pass_id": pa.array(chosen, pa.int32()),
                  **{k: pa.array(gen[k]) for k in ("gen_x_mm", "gen_y_mm", "gen_z_mm",
                                                   "rotation_deg", "contact_deg", "nx", "ny", "nz")},
                  "n_px": pa.array(gen["n_px"], pa.int32()),
                  "view": pa.array(list(gen["view"]), pa.string()),
                  **{k: pa.array(gen[k]) for k in SECOND_COLUMNS},
                  "n2_px": pa.array(gen["n2_px"], pa.int32())})
    e = pa.table({"program_id": pid, "pass_id": pa.array(chosen, pa.int32()),
                  "dz_mm": pa.array([x[1] for x in eng], pa.float64()),
                  "n_z": pa.array([x[0].shape[0] for x in eng], pa.int32()),
                  "n_phi": pa.array([x[0].shape[1] for x in eng], pa.int32()),
                  "mask": pa.array([np.packbits(x[0].reshape(-1)).tobytes() for x in eng], pa.binary()),
                  "feed_dir_x": pa.array([x[2][0] for x in eng], pa.float64()),
                  "feed_dir_y": pa.array([x[2][1] for x in eng], pa.float64()),
                  "ramp_deg": pa.array(ramp_deg(pg.p1[idx] - pg.p0[idx]), pa.float64())})
    return {"generating": schemas.check("generating", g), "engagement": schemas.check("engagement", e)}


def combine_shards(parts: list[dict]) -> dict:
    """The tables of one program from its shards' tables, in pass order."""
    out = {}
    for name in OUTPUTS:
        t = pa.concat_tables([p[name] for p in parts])
        out[name] = t.take(pa.array(np.argsort(t.column("pass_id").to_numpy(), kind="stable")))
    return out
