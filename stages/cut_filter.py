"""Stage ``cut_filter`` (seed 000 claim 7, paras 0052-0054): which passes cut, and where.

One ordered scan per tile (``Renderer.scan``), from below: the stock W first, then the sweep of
every pass in execution order with the depth test and depth writes, as the machine removes the
material. A fragment of pass k passes the depth test where its sweep is in front of W and of the
sweeps of all earlier passes T1 drawn before it: exactly claim 7's cutting region, for every pass
in one render instead of one window per pass. Per pass the scan counts those pixels by position
along the pass (``cut_px``), keeps their largest contact angle, and its final image is the
claim-8 render (which pass leaves which pixel of the final surface), used by ``angle_prune``.
A pass without a cut pixel is not cutting (air moves, passes inside already removed material);
rapid moves (motion 0) never cut.

The prediction point is the tool tip on the pass at the median position (along the pass, from
the pixels' own positions projected on the line of corner centres) of the cut pixels, preferring
the pass interior: it lies inside the cutting part even when the pass cuts only part of its
length. A pass inside a cutting run of one line (its neighbours cut and carry its line on) is
predicted at its middle (:func:`line_interior`).

Sweeps are drawn with a depth bias of ``tol`` (the polygonisation tolerance): a pass must cut
deeper than the meshes' own error into the stock to count, and a pass that repeats an earlier
one ties with it and does not count. Memory is bounded by the tile and the sweeps meshed per
draw, never by the program.
"""
from __future__ import annotations

import math

import numpy as np
import pyarrow as pa

import schemas
from stages.geometry.cutter import Cutter
from stages.geometry.envelope import envelope_mesh
from stages.geometry.passes import (
    CONTINUE_DEG,
    PassGeometry,
    overlaps,
    pass_geometry,
    window_xy_bounds,
)
from stages.geometry.sweeps import ordered_sweep_scene
from stages.geometry.workpiece import Workpiece, load_workpiece, workpiece_scene
from stages.render import View, make_renderer

NAME = "cut_filter"
VERSION = "6"
INPUTS = ("passes", "stock")
OUTPUTS = ("cut_filter",)
PARAMS = ("tool", "render")

TILE_PX = 2048           # scan tile side (memory is bounded by the tile, not by the part)
N_BINS = 20              # bins of the position along a pass for the prediction point
PASSES_PER_DRAW = 2000   # sweeps meshed at a time (bounds the triangle arrays)


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


def z_range(pg: PassGeometry, wp: Workpiece, shape: Cutter):
    """Depth range (absolute z) that holds everything a from-below view can see."""
    zs = np.concatenate([pg.p0[:, 2], pg.p1[:, 2], wp.bounds[:, 2]]) if len(pg.p0) else wp.bounds[:, 2]
    return float(zs.min()) - 1.0, float(zs.max()) + shape.stickout_mm + 1.0


def scan_tiles(pg, shape, wp, px_per_mm, which, zlo, zhi, halo_mm=0.0):
    """From-below tiles (at most TILE_PX a side) over the sweeps of ``which`` within the stock.

    Returns (views, cores): each view covers its core rectangle (lo_xy, hi_xy) plus ``halo_mm``
    on every side, so any window of half-size ``halo_mm`` centred in a core lies in its tile.
    """
    bounds = pg.sweep_bounds(shape)
    if not len(which):
        return [], []
    lo = np.maximum(bounds[which, 0, :2].min(0), wp.bounds[0, :2])
    hi = np.minimum(bounds[which, 1, :2].max(0), wp.bounds[1, :2])
    if np.any(hi <= lo):
        return [], []
    core_mm = TILE_PX / px_per_mm - 2.0 * halo_mm
    if core_mm <= 0:
        raise ValueError(f"tile of {TILE_PX} px too small for a halo of {halo_mm} mm")
    nx, ny = (max(1, math.ceil((hi[k] - lo[k]) / core_mm)) for k in (0, 1))
    views, cores = [], []
    for ix in range(nx):
        for iy in range(ny):
            x0, y0 = lo[0] + ix * core_mm, lo[1] + iy * core_mm
            w, h = min(core_mm, hi[0] - x0), min(core_mm, hi[1] - y0)
            views.append(View((x0 + w / 2, y0 + h / 2, 0.0), (0, 0, 1.0), (0, 1.0, 0),
                              w + 2 * halo_mm, h + 2 * halo_mm, px_per_mm, zlo, zhi))
            cores.append((np.array([x0, y0]), np.array([x0 + w, y0 + h])))
    return views, cores


def cut_filter(pg: PassGeometry, shape: Cutter, wp: Workpiece, renderer,
               px_per_mm: float, tol_mm: float | None = None):
    """Claim-7 and claim-8 renders for every pass, as one ordered scan per tile.

    Returns a dict of numpy columns: is_cutting, cut_px, pred_x/y/z_mm, pred_t,
    cut_max_contact_deg (largest contact angle over the pixels the pass cuts), surface_px and
    surface_max_contact_deg (pixels of the final surface the pass leaves, their largest q).
    """
    n = len(pg.pass_id)
    tol = coarse_tolerance(px_per_mm) if tol_mm is None else tol_mm
    mesh = envelope_mesh(shape, tol)
    zlo, zhi = z_range(pg, wp, shape)
    bounds = pg.sweep_bounds(shape)
    # only passes whose sweep reaches the stock can cut; rapid moves (motion 0) never cut
    reach = pg.motion != 0
    reach &= overlaps(bounds[:, 0], bounds[:, 1], wp.bounds[:1], wp.bounds[1:])[:, 0]
    reach &= bounds[:, 0, 2] <= wp.bounds[1, 2]
    cand = np.nonzero(reach)[0]
    counts = np.zeros((n, N_BINS), np.int64)
    b_max = np.full(n, -np.inf)
    surface_px = np.zeros(n, np.int64)
    surface_q = np.full(n, -np.inf)
    for view in scan_tiles(pg, shape, wp, px_per_mm, cand, zlo, zhi)[0]:
        lo_w, hi_w = window_xy_bounds([view])
        inside = cand[overlaps(lo_w, hi_w, bounds[cand, 0], bounds[cand, 1])[0]]

        def batches(inside=inside):
            for a in range(0, len(inside), PASSES_PER_DRAW):
                k = inside[a:a + PASSES_PER_DRAW]
                # sweeps are pushed back by the mesh tolerance: a pass must cut deeper than
                # the polygonisation error into the stock to count (a repeat never counts)
                yield ordered_sweep_scene(mesh, pg.p0[k], pg.p1[k], k, bias=tol)

        res = renderer.scan(view, workpiece_scene(wp, [view], -2.0), batches(), n, N_BINS)
        counts += res.counts
        b_max = np.maximum(b_max, res.b_max)
        fin = res.final
        won = fin.id >= 0
        surface_px += np.bincount(fin.id[won], minlength=n)
        np.maximum.at(surface_q, fin.id[won], fin.b[won].astype(float))
    cut_px = counts.sum(1)
    out = dict(is_cutting=cut_px > 0, cut_px=cut_px, pred_x_mm=np.full(n, np.nan),
               pred_y_mm=np.full(n, np.nan), pred_z_mm=np.full(n, np.nan), pred_t=np.full(n, np.nan),
               cut_max_contact_deg=np.where(cut_px > 0, b_max, np.nan),
               surface_px=surface_px,
               surface_max_contact_deg=np.where(surface_px > 0, surface_q, np.nan))
    cutting = np.nonzero(cut_px > 0)[0]
    t = prediction_position(counts[cutting])
    t[line_interior(pg, cut_px > 0)[cutting]] = 0.5
    p = pg.p0[cutting] + t[:, None] * (pg.p1[cutting] - pg.p0[cutting])
    out["pred_t"][cutting] = t
    out["pred_x_mm"][cutting], out["pred_y_mm"][cutting], out["pred_z_mm"][cutting] = p.T
    return out


def line_interior(pg: PassGeometry, cuts: np.ndarray) -> np.ndarray:
    """Passes inside a cutting run of one line, predicted at their middle (bool per pass).

    A pass counts when the moves before and after it both cut, are joined to it end to start and
    carry its direction on within :data:`CONTINUE_DEG` (pieces of a line split for
    length or at via points, a curve's CAM chords). Why: the ball at the end of the move before
    has already cut the material over most of such a pass's length, down to a sliver of
    d²/2R (12 µm at 0.5 mm past the joint with a Ø20 ball) that the coarse mesh tolerance (half a
    pixel) hides, so the pass's own cut pixels lie ahead of it, under the ball at its end, and
    their median put the prediction point at the end of the pass (the seed's cylinder cut into
    0.5 mm pieces: t = 0.97 on half of a level's pieces). The surface such a pass leaves is its
    whole length, each point where the tool's centre passes it; at its end the force is that of
    the next move's start, which at a stock edge (the cylinder's exit end, where the force falls
    by 20 % a piece) is another force than the pass's own.
    """
    n = len(pg.pass_id)
    inner = np.zeros(n, bool)
    if n < 3:
        return inner
    d = pg.p1 - pg.p0
    ln = np.linalg.norm(d, axis=1)
    u = d / np.where(ln > 0, ln, 1.0)[:, None]
    cos_on = np.cos(np.radians(CONTINUE_DEG))
    # joint i: move i ends where move i + 1 starts, both cut, and the direction runs on
    joint = (np.linalg.norm(pg.p0[1:] - pg.p1[:-1], axis=1) < 1e-6) & cuts[1:] & cuts[:-1] \
        & (ln[1:] > 0) & (ln[:-1] > 0) & (pg.motion[1:] != 0) & (pg.motion[:-1] != 0) \
        & (np.einsum("ij,ij->i", u[1:], u[:-1]) > cos_on)
    inner[1:-1] = joint[:-1] & joint[1:]
    return inner


def prediction_position(hist):
    """Median position along each pass of its cut pixels, preferring the pass interior.

    ``hist`` (k, N_BINS): cut pixels per bin of the position along the pass (pixels of the end
    copies count at 0 and 1). A point at a vertex lies where the path turns; the surface there
    is a fan that the neighbouring passes share, so the median over the bins within the middle
    60 % of the pass is used where they hold cut pixels (still a position where the pass cuts).
    """
    hist = np.asarray(hist, float).reshape(-1, N_BINS)
    centre = (np.arange(N_BINS) + 0.5) / N_BINS
    inner = (centre >= 0.2) & (centre <= 0.8)
    has_inner = hist[:, inner].sum(1, keepdims=True) > 0
    h = np.where(has_inner & inner[None], hist, np.where(has_inner, 0.0, hist))
    c = np.cumsum(h, 1)
    half = 0.5 * c[:, -1]
    k = np.argmax(c >= half[:, None], axis=1)
    rows = np.arange(len(h))
    before = c[rows, k] - h[rows, k]
    frac = (half - before) / np.maximum(h[rows, k], 1e-12)     # linear within the bin
    return (k + np.clip(frac, 0.0, 1.0)) / N_BINS


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
