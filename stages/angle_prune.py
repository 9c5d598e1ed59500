"""Stage ``angle_prune`` (seed 000 claim 8, paras 0102-0106): skip passes that cannot matter.

Tool deflection moves the surface little where the contact angle is small (the surface normal
is close to the tool axis). One global render answers which pass leaves which part of the final
surface: all cutting sweeps, each carrying its pass id and the contact angle (angle of the
envelope normal from the downward tool axis) per pixel, plus the stock, from below with the
depth test. The final-surface image is tiled (tiles of at most ``TILE_PX`` pixels a side, several
tiles per atlas draw), so memory is bounded by the tile size, not by the part or the program.

Per pass: ``max_contact_deg`` = the largest contact angle among the pixels it wins; ``predict`` =
cutting and ``max_contact_deg >= prune.min_contact_deg``. A cutting pass whose surface is not
visible from below (steep walls shrink below a pixel, seed para 0075) falls back to the largest
contact angle over the pixels it cuts (``cut_filter.cut_max_contact_deg``), an upper bound of its
surface's contact angle, so no steep-wall pass is pruned for being invisible (``source = cut``).
"""
from __future__ import annotations

import math

import numpy as np
import pyarrow as pa

import schemas
from stages import InputError
from stages import geometry as geo
from stages.cut_filter import coarse_tolerance, render_settings, z_range
from stages.render import Scene, View

NAME = "angle_prune"
VERSION = "1"
INPUTS = ("passes", "stock", "cut_filter")
OUTPUTS = ("angle_prune",)
PARAMS = ("tool", "render", "prune")

TILE_PX = 1024
TILES_PER_BATCH = 4


def final_surface(pg, shape, wp, renderer, px_per_mm, cutting, tol_mm=None):
    """Per pass: pixels of the final surface it leaves and their largest contact angle."""
    n = len(pg.pass_id)
    tol = coarse_tolerance(px_per_mm) if tol_mm is None else tol_mm
    mesh = geo.envelope_mesh(shape, tol)
    zlo, zhi = z_range(pg, wp, shape)
    bounds = pg.sweep_bounds(shape)
    surface_px = np.zeros(n, np.int64)
    max_q = np.full(n, -np.inf)
    idx = np.nonzero(cutting)[0]
    if not len(idx):
        return surface_px, np.full(n, np.nan)
    lo = np.maximum(bounds[idx, 0, :2].min(0), wp.bounds[0, :2])
    hi = np.minimum(bounds[idx, 1, :2].max(0), wp.bounds[1, :2])
    if np.any(hi <= lo):
        return surface_px, np.full(n, np.nan)
    tile_mm = TILE_PX / px_per_mm
    nx, ny = (max(1, math.ceil((hi[k] - lo[k]) / tile_mm)) for k in (0, 1))
    tiles = []
    for ix in range(nx):
        for iy in range(ny):
            x0, y0 = lo[0] + ix * tile_mm, lo[1] + iy * tile_mm
            w, h = min(tile_mm, hi[0] - x0), min(tile_mm, hi[1] - y0)
            tiles.append(View((x0 + w / 2, y0 + h / 2, 0.0), (0, 0, 1.0), (0, 1.0, 0), w, h,
                              px_per_mm, zlo, zhi))
    for b0 in range(0, len(tiles), TILES_PER_BATCH):
        views = tiles[b0:b0 + TILES_PER_BATCH]
        m = len(views)
        lo_w, hi_w = geo.window_xy_bounds(views)
        win, j = np.nonzero(geo.overlaps(lo_w, hi_w, bounds[idx, 0], bounds[idx, 1]))
        j = idx[j]
        wb = (np.concatenate([lo_w, lo_w]), np.concatenate([hi_w, hi_w]))
        # pass ids are stored as position + 1 so that 0 stays the stock
        scene = Scene.concat([
            geo.workpiece_scene(wp, views, 0),
            geo.segment_scene(mesh, pg.p0[j], pg.p1[j], win + m, j + 1.0, (0, 0, 1.0),
                              window_bounds=wb)])
        images = renderer.render(views + views, scene)
        for imw, imt in zip(images[:m], images[m:]):
            surf = (imt.id >= 1) & (imw.id >= 0) & (imt.depth < imw.depth)
            k = imt.id[surf] - 1
            surface_px += np.bincount(k, minlength=n)
            np.maximum.at(max_q, k, imt.b[surf].astype(float))
    return surface_px, np.where(np.isfinite(max_q), max_q, np.nan)


def run(inputs: dict, params: dict) -> dict:
    passes = inputs["passes"]
    shape = geo.tool_from_params(params["tool"])
    pg = geo.pass_geometry(passes, params["tool"])
    wp = geo.load_workpiece(inputs.get("stock"))
    renderer, ppm = render_settings(params)
    prune = dict(params.get("prune") or {})
    thr = float(prune.get("min_contact_deg", 45.0))
    cf = inputs["cut_filter"]
    miss = [c for c in ("pass_id", "is_cutting", "cut_max_contact_deg") if c not in cf.column_names]
    if miss:
        raise InputError(f"cut_filter: missing columns {miss}")
    n = len(pg.pass_id)
    pos = {int(p): k for k, p in enumerate(pg.pass_id)}
    cutting = np.zeros(n, bool)
    cut_q = np.full(n, np.nan)
    for p, c, q in zip(cf.column("pass_id").to_numpy(),
                       cf.column("is_cutting").to_numpy(zero_copy_only=False),
                       cf.column("cut_max_contact_deg").to_numpy(zero_copy_only=False)):
        if int(p) in pos:
            cutting[pos[int(p)]] = bool(c)
            cut_q[pos[int(p)]] = q
    surface_px, surf_q = final_surface(pg, shape, wp, renderer, ppm, cutting)
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
