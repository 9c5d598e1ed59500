"""Stage ``cut_filter`` (seed 000 claim 7, paras 0052-0054): which passes cut, and where.

For every non-rapid pass the sweep of the pass T0, the sweeps of all earlier passes T1 that reach
its neighbourhood, and the workpiece W are rendered from below in a window aligned with the pass
(width: tool diameter, length: the pass plus the tool diameter, feed direction up). Pixels where
T0 stays in front of W and T1 are cut by this pass. A pass without such a pixel is not cutting
(air moves, passes inside already removed material); rapid moves (motion 0) never cut.

The prediction point is the tool tip on the pass at the median position (along the pass) of the
cut pixels: it is the position of an actual cut pixel, so it lies inside the cutting part even
when the pass cuts only part of its length or several separate parts.

T0 is drawn with a depth bias of ``tol`` (the polygonisation tolerance): a pass must cut deeper
than the meshes' own error to count, so a pass that repeats an earlier one does not "cut" by
round-off. Windows of many passes are rendered together (one atlas framebuffer per draw).
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa

import schemas
from stages import geometry as geo
from stages.render import View, Scene, make_renderer

NAME = "cut_filter"
VERSION = "1"
INPUTS = ("passes", "stock")
OUTPUTS = ("cut_filter",)
PARAMS = ("tool", "render")

ID_W, ID_T1, ID_T0 = 0, 1, 2
WINDOWS_PER_BATCH = 64


def coarse_tolerance(px_per_mm: float) -> float:
    """Mesh tolerance for the pass-level renders: half a pixel (cut/no-cut, angle prune)."""
    return 0.5 / float(px_per_mm)


def fine_tolerance(px_per_mm: float) -> float:
    """Mesh tolerance for the generating-point renders: a tenth of a pixel."""
    return 0.1 / float(px_per_mm)


def render_settings(params):
    rp = dict(params.get("render") or {})
    ppm = float(rp.get("px_per_mm", 20.0))
    return make_renderer(rp.get("backend", "auto")), ppm


def z_range(pg: geo.PassGeometry, wp: geo.Workpiece, shape: geo.ToolShape):
    """Depth range (absolute z) that holds everything a from-below view can see."""
    zs = np.concatenate([pg.p0[:, 2], pg.p1[:, 2], wp.bounds[:, 2]]) if len(pg.p0) else wp.bounds[:, 2]
    return float(zs.min()) - 1.0, float(zs.max()) + shape.stickout_mm + 1.0


def cut_filter(pg: geo.PassGeometry, shape: geo.ToolShape, wp: geo.Workpiece, renderer,
               px_per_mm: float, tol_mm: float | None = None):
    """Claim-7 sub-render for every pass. Returns a dict of numpy columns."""
    n = len(pg.pass_id)
    tol = coarse_tolerance(px_per_mm) if tol_mm is None else tol_mm
    mesh = geo.envelope_mesh(shape, tol)
    out = dict(is_cutting=np.zeros(n, bool), cut_px=np.zeros(n, np.int64),
               pred_x_mm=np.full(n, np.nan), pred_y_mm=np.full(n, np.nan),
               pred_z_mm=np.full(n, np.nan), pred_t=np.full(n, np.nan),
               cut_max_contact_deg=np.full(n, np.nan))
    zlo, zhi = z_range(pg, wp, shape)
    R = shape.radius_mm
    bounds = pg.sweep_bounds(shape)
    cutting_motion = pg.motion != 0
    # only passes whose sweep reaches the stock can cut
    reach = cutting_motion & geo.overlaps(bounds[:, 0], bounds[:, 1], wp.bounds[:1], wp.bounds[1:])[:, 0]
    reach &= bounds[:, 0, 2] <= wp.bounds[1, 2]
    cand = np.nonzero(reach)[0]
    margin = 2.0 / px_per_mm
    wins = pass_windows(pg, shape, wp, px_per_mm, zlo, zhi, cand)
    cand = np.array([i for i in cand if wins[i] is not None], np.int64)
    for b0 in range(0, len(cand), WINDOWS_PER_BATCH):
        idx = cand[b0:b0 + WINDOWS_PER_BATCH]
        views = [wins[i] for i in idx]
        m = len(views)
        all_views = views + views                 # layer 0: W alone, layer 1: T1 + T0
        lo_w, hi_w = geo.window_xy_bounds(views)
        # earlier passes reaching each window (T1), and the pass itself (T0)
        ov = geo.overlaps(lo_w, hi_w, bounds[:, 0], bounds[:, 1])
        ov &= cutting_motion[None, :]
        ov &= np.arange(n)[None, :] < idx[:, None]
        win, j = np.nonzero(ov)
        k = np.arange(m)
        wb = (np.concatenate([lo_w, lo_w]), np.concatenate([hi_w, hi_w]))
        scene = Scene.concat([
            geo.workpiece_scene(wp, views, ID_W),
            geo.segment_scene(mesh, pg.p0[j], pg.p1[j], win + m, np.full(len(j), ID_T1),
                              (0, 0, 1.0), window_bounds=wb),
            geo.segment_scene(mesh, pg.p0[idx], pg.p1[idx], k + m, np.full(m, ID_T0),
                              (0, 0, 1.0), bias=tol, window_bounds=wb),
        ])
        images = renderer.render(all_views, scene)
        for i, v, imw, imt in zip(idx, views, images[:m], images[m:]):
            # cut: T0 in front of every earlier sweep and of the stock, inside the stock
            cut = (imt.id == ID_T0) & (imw.id >= 0) & (imt.depth < imw.depth)
            npx = int(cut.sum())
            out["cut_px"][i] = npx
            if npx == 0:
                continue
            out["is_cutting"][i] = True
            rows, cols = np.nonzero(cut)
            pts = v.pixel_points(rows, cols, imt.depth[cut] - tol)
            # position along the pass of the tool axis nearest (in xy) to each cut pixel: the
            # tool that cut a pixel stood over it (a 3-D projection would misplace descents)
            d = pg.p1[i] - pg.p0[i]
            dd = float(d[:2] @ d[:2])
            t = (np.clip((pts[:, :2] - pg.p0[i, :2]) @ d[:2] / dd, 0, 1) if dd > 1e-12
                 else np.full(len(pts), 0.5))
            # median of the cut pixels: a position where this pass really cuts
            tm = float(np.sort(t)[(len(t) - 1) // 2])
            p = pg.p0[i] + tm * d
            out["pred_t"][i] = tm
            out["pred_x_mm"][i], out["pred_y_mm"][i], out["pred_z_mm"][i] = p
            out["cut_max_contact_deg"][i] = float(np.max(imt.b[cut]))
    return out


def pass_windows(pg, shape, wp, px_per_mm, zlo, zhi, which):
    """From-below window of each pass: tool diameter wide, along the pass, clipped to the stock.

    Only pixels over the stock can be cut, so the window covers the part of the sweep's footprint
    that lies over the stock's xy bounds. Returns a list (None where the footprint misses it).
    """
    R = shape.radius_mm
    margin = 2.0 / px_per_mm
    out = [None] * len(pg.p0)
    corners = np.array([[x, y] for x in wp.bounds[:, 0] for y in wp.bounds[:, 1]])
    for i in which:
        d = (pg.p1[i] - pg.p0[i])[:2]
        L = float(np.hypot(*d))
        u = d / L if L > 1e-9 else np.array([0.0, 1.0])
        v = np.array([-u[1], u[0]])
        rel = corners - pg.p0[i, :2]
        a0, a1 = max(-R, (rel @ u).min()) - margin, min(L + R, (rel @ u).max()) + margin
        c0, c1 = max(-R, (rel @ v).min()) - margin, min(R, (rel @ v).max()) + margin
        if a1 <= a0 or c1 <= c0:
            continue
        c = pg.p0[i, :2] + 0.5 * (a0 + a1) * u + 0.5 * (c0 + c1) * v
        out[i] = View((c[0], c[1], 0.0), (0, 0, 1.0), (u[0], u[1], 0.0), c1 - c0, a1 - a0,
                      px_per_mm, zlo, zhi)
    return out


def run(inputs: dict, params: dict) -> dict:
    passes = inputs["passes"]
    shape = geo.tool_from_params(params["tool"])
    pg = geo.pass_geometry(passes, params["tool"])
    wp = geo.load_workpiece(inputs.get("stock"))
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
    })
    return {"cut_filter": schemas.check("cut_filter", table)}
