"""Stage ``angle_prune`` (seed 000 claim 8, paras 0102-0106): skip passes that cannot matter.

Tool deflection moves the surface little where the contact angle is small (the surface normal
is close to the tool axis). The claim-8 render, all cutting sweeps each carrying its pass id and
the contact angle (angle of the envelope normal from the downward tool axis) per pixel, plus the
stock, from below with the depth test, is the final image of the ordered scan that
``cut_filter`` already runs (``surface_px``, ``surface_max_contact_deg``); this stage decides.

Per pass: ``max_contact_deg`` = the largest contact angle among the final-surface pixels it
leaves; ``predict`` = cutting and ``max_contact_deg >= prune.min_contact_deg``. A cutting pass
whose surface is not visible from below (steep walls shrink below a pixel, seed para 0075) falls
back to the largest contact angle over the pixels it cuts (``cut_max_contact_deg``), an upper
bound of its surface's contact angle, so no steep-wall pass is pruned for being invisible
(``source = cut``).
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa

import schemas
from stages import InputError
from stages.geometry.passes import pass_geometry

NAME = "angle_prune"
VERSION = "2"
INPUTS = ("passes", "cut_filter")
OUTPUTS = ("angle_prune",)
PARAMS = ("tool", "prune")


def _rows_of(pass_ids, table_ids):
    """Row of each pass in the cut_filter table (-1 where missing)."""
    table_ids = np.asarray(table_ids)
    if not len(table_ids):
        return np.full(len(pass_ids), -1)
    order = np.argsort(table_ids, kind="stable")
    k = np.clip(np.searchsorted(table_ids[order], pass_ids), 0, len(order) - 1)
    return np.where(table_ids[order][k] == pass_ids, order[k], -1)


def run(inputs: dict, params: dict) -> dict:
    passes = inputs["passes"]
    pg = pass_geometry(passes, params["tool"])
    prune = dict(params.get("prune") or {})
    thr = float(prune.get("min_contact_deg", 45.0))
    cf = inputs["cut_filter"]
    miss = [c for c in ("pass_id", "is_cutting", "cut_max_contact_deg", "surface_px",
                        "surface_max_contact_deg") if c not in cf.column_names]
    if miss:
        raise InputError(f"cut_filter: missing columns {miss}")
    n = len(pg.pass_id)
    row = _rows_of(pg.pass_id, cf.column("pass_id").to_numpy())
    have = row >= 0

    def col(name, fill):
        out = np.full(n, fill, dtype=float)
        out[have] = cf.column(name).to_numpy(zero_copy_only=False).astype(float)[row[have]]
        return out

    cutting = col("is_cutting", 0.0) > 0.5
    cut_q = col("cut_max_contact_deg", np.nan)
    surface_px = col("surface_px", 0.0).astype(np.int64)
    surf_q = col("surface_max_contact_deg", np.nan)
    visible = surface_px > 0
    max_q = np.where(visible, surf_q, np.where(cutting, cut_q, np.nan))
    source = np.where(visible, "surface", np.where(cutting, "cut", "none"))
    predict = cutting & (np.nan_to_num(max_q, nan=-1.0) >= thr)
    table = pa.table({
        "program_id": pa.array([pg.program_id] * n, pa.string()),
        "pass_id": pa.array(pg.pass_id, pa.int32()),
        "max_contact_deg": pa.array(max_q),
        "predict": pa.array(predict),
        "surface_px": pa.array(surface_px, pa.int32()),
        "source": pa.array(list(source), pa.string()),
    })
    return {"angle_prune": schemas.check("angle_prune", table)}
