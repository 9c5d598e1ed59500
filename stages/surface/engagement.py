"""The cutting region of each predicted pass (seed 000 claim 5) from the ordered scan's cut log.

The engagement is the part of the tool's envelope at the prediction point p that lies in the
material before the pass: a grid of axial levels × rotation angles (``unpack_engagement``). In
3-axis machining the material is a height field, and an envelope point above pixel x is in it
only where the pass cut x (else the material there lies below the pass's own sweep, which is below
every envelope point over x): so the scan's cut log answers it, the depth each cut replaced being
the material's top before the pass. The tool's own trailing passes just behind p are left out of
"before" (:func:`snapshot_from`). Each cut pixel fills the grid cells whose envelope points lie
over it: on the corner one level band per pixel ring, on the side (at the tool's radius) every
level up to the material's top, which is how a steep wall's layer (a few pixels wide from below)
still gives the side its full height.
"""
from __future__ import annotations

import numpy as np

from stages.geometry.cutter import Cutter
from stages.geometry.passes import PassGeometry, path_turning
from stages.geometry.workpiece import StockTop
from stages.surface.chain import ChainedStock
from stages.surface.ordered import TileScan
from stages.surface.steep import CutsByPixel, refine_steep

N_PHI = 360                 # rotation-angle bins
DZ_PER_RADIUS = 1.0 / 180   # level spacing in tool radii
TRAIL_TURN_DEG = 15.0       # the own trailing path within a radius that turns less than this is left out
CHUNK = 64                  # predictions at a time (bounds the gathered cuts and the grids)
DEPTH_QUANTILES = 8         # quantiles of the material over the engaged cells (a descent's chip limit)


def unpack_engagement(row):
    """Decode one ``engagement`` row.

    Parameters
    ----------
    row : mapping with keys dz_mm, n_z, n_phi, mask (e.g. ``table.slice(i, 1).to_pylist()[0]``).

    Returns
    -------
    E : (n_z, n_phi) bool, True where the envelope point is inside the material.
    z_levels_mm : (n_z,) heights above the tool tip, (k + 0.5) * dz_mm.
    phi_deg : (n_phi,) rotation angles, (j + 0.5) * 360 / n_phi, CCW from the feed direction.
    """
    n_z, n_phi = int(row["n_z"]), int(row["n_phi"])
    bits = np.unpackbits(np.frombuffer(row["mask"], np.uint8), count=n_z * n_phi)
    E = bits.astype(bool).reshape(n_z, n_phi)
    z = (np.arange(n_z) + 0.5) * float(row["dz_mm"])
    phi = (np.arange(n_phi) + 0.5) * 360.0 / n_phi
    return E, z, phi


def snapshot_from(pg, predict_idx, s_tip, reach_mm, turn_deg=TRAIL_TURN_DEG):
    """First pass of each prediction point's own trailing path that its material snapshot leaves out.

    The engagement is the envelope in the material before the cut (claim 5): the stock less the
    sweeps of the earlier passes. The tool's own path straight behind it never reaches into its
    front half (a ball δ behind lies √(R² + δ²) or more from every front point), but in the height
    field its end cap lies only about δ·tanθ·cosφ above the front near the tip: a point δ into a
    short chord (CAM's chords at fillets and corners are a few µm to a few tenths of a mm; the
    sample boss foot has 25 µm ones) lost its engagement there within the render tolerance, and a
    pass the virtual machine cuts at 68 N was predicted without force. So the passes of the own path
    that end within ``reach_mm`` behind the point, while the path is contiguous (no rapid, no gap)
    and turns by at most ``turn_deg`` in all from them to the point's pass, are drawn after the
    snapshot: the front half meets the material as the cut does, whatever the chord length. A
    sharper turn keeps them (a corner's sweep does reach into the front half).

    Parameters
    ----------
    pg : PassGeometry
    predict_idx : (m,) int
        Pass index of each prediction point, ascending.
    s_tip : (m,) float
        Path position of each prediction point (mm).
    reach_mm : float
        How far behind the point the own path is left out (a tool radius: a ball that far behind
        lies outside the footprint of the front half).

    Returns
    -------
    (m,) int
        Pass index j ≤ predict_idx: passes j … predict_idx − 1 are not in the snapshot.
        Non-decreasing with ``predict_idx`` (the scan draws passes in order).
    """
    predict_idx = np.asarray(predict_idx, np.int64)
    n = len(pg.pass_id)
    if n == 0 or len(predict_idx) == 0:
        return predict_idx.copy()
    chain_start, _, C = path_turning(pg)
    j_turn = np.searchsorted(C, C[predict_idx] - turn_deg - 1e-9, side="left")
    j_reach = np.searchsorted(pg.s0 + pg.length, np.asarray(s_tip, float) - reach_mm, side="right")
    j = np.maximum(np.maximum(chain_start[predict_idx], j_turn), j_reach)
    return np.minimum(j, predict_idx)


def ramp_deg(d):
    """Angle (deg) of each feed vector d (P, 3) above the horizontal; ±90 for a plunge."""
    d = np.asarray(d, float).reshape(-1, 3)
    return np.degrees(np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1])))


def before_cuts(ts: TileScan):
    """The cut log as (pass, pixel, depth left, depth before) rows, one per pass and pixel, sorted by
    pass then pixel. The depth before is the previous cut's at that pixel, or the stock's top."""
    log = ts.log
    keep = log.ident >= 0
    pix, ident, z = log.pix[keep], log.ident[keep].astype(np.int64), log.depth[keep].astype(np.float64)
    o = np.lexsort((z, ident, pix))
    pix, ident, z = pix[o], ident[o], z[o]
    first = np.r_[True, (pix[1:] != pix[:-1]) | (ident[1:] != ident[:-1])]
    pix, ident, z = pix[first], ident[first], z[first]
    new_pix = np.r_[True, pix[1:] != pix[:-1]]
    before = np.empty_like(z)
    before[1:] = z[:-1]
    before[new_pix] = ts.stock_z.reshape(-1)[pix[new_pix]]
    o = np.lexsort((pix, ident))
    return ident[o], pix[o], z[o], before[o]


def engagement(ts: TileScan, pg: PassGeometry, cutter: Cutter, pred: np.ndarray, tips: np.ndarray,
               snap: np.ndarray, dz: float, n_phi: int = N_PHI, margin: float = 0.0, stock_top: StockTop | ChainedStock | None = None):
    """Engagement grids of passes ``pred`` (ascending indices) at tips ``tips``.

    The material before a pass at a pixel is the depth its first cut by a pass from ``snap`` on
    replaced (the cuts before the snapshot are all in it). The cuts read are those of the passes
    from ``snap`` to the last whose start lies within a tool radius ahead of the tip along the
    path: a chain's joint copies are drawn by the pass after the joint (the lunes aside,
    :func:`stages.geometry.sweeps.chain_joints`), so what the tool's front removes past the end of
    a pass may be logged by the next. For the same reason the copy at the joint just before the
    snapshot is subtracted from the material in closed form: it was cut before the snapshot.

    Parameters
    ----------
    ts : the scan of the tile that owns the passes
    snap : (m,) first pass of each prediction's trailing path left out (:func:`snapshot_from`)
    dz : level spacing, mm
    margin : material thinner than this over the envelope is not engaged (the scan's mesh
        tolerance: the render cannot tell it from a tie)
    stock_top : the stock's top (:class:`stages.geometry.workpiece.StockTop`, or
        :class:`stages.surface.chain.ChainedStock` after earlier programs); with it the tool's steep
        side is decided in closed form (:func:`stages.surface.steep.refine_steep`)

    Returns
    -------
    n_z : (m,) levels of each grid (up to its highest engaged level; at least one)
    masks : list of packed grids (``np.packbits`` of E (n_z, n_phi), C order), one bytes per prediction
    depth : (m, DEPTH_QUANTILES) quantiles over the engaged cells (before the steep side's closed
        form) of the material's thickness over the cell's envelope point, vertically (mm; 0 where
        none): a pass descending at α cuts at most depth / sin|α| per tooth there (:func:`chip_limit`)
    """
    m = len(pred)
    n_z = np.ones(m, np.int64)
    masks = [b""] * m
    depth = np.zeros((m, DEPTH_QUANTILES))
    if m == 0:
        return n_z, masks, depth
    ident, pix, _, before = before_cuts(ts)
    cuts = CutsByPixel(pix, ident, ts.tile.view.shape) if stock_top is not None else None
    view = ts.tile.view
    h, w = view.shape
    ppm = view.px_per_mm
    x0 = view.center[0] - w / (2 * ppm)
    y0 = view.center[1] - h / (2 * ppm)
    R, rc = cutter.radius_mm, cutter.corner_mm
    hp = 0.71 / ppm                                   # half a pixel's diagonal: the rings leave no gap
    reach = R + hp
    chain_start, chain_end, _ = path_turning(pg)
    s_tip = pg.s0[pred] + np.linalg.norm(tips - pg.p0[pred], axis=1)
    ahead = np.searchsorted(pg.s0, s_tip + reach, side="right") - 1
    last = np.maximum(pred, np.minimum(ahead, chain_end[pred]))
    joint = snap > chain_start[pred]                   # pass snap - 1 ends where pass snap starts
    feed = np.radians(pg.feed_deg)
    binw = 360.0 / n_phi
    for a in range(0, m, CHUNK):
        k = pred[a:a + CHUNK]
        lo = np.searchsorted(ident, snap[a:a + CHUNK], side="left")
        hi = np.searchsorted(ident, last[a:a + CHUNK], side="right")
        cnt = hi - lo
        row = np.repeat(np.arange(len(k)), cnt)
        e = np.repeat(lo - np.cumsum(cnt) + cnt, cnt) + np.arange(row.size)
        px = pix[e]
        dx = x0 + (px % w + 0.5) / ppm - tips[a + row, 0]
        dy = y0 + (px // w + 0.5) / ppm - tips[a + row, 1]
        rho = np.hypot(dx, dy)
        near = rho <= reach
        row, e, px, dx, dy, rho = row[near], e[near], px[near], dx[near], dy[near], rho[near]
        # per prediction and pixel the first cut of the range: the material before the trail
        o = np.lexsort((ident[e], px, row))
        row, e, px, dx, dy, rho = row[o], e[o], px[o], dx[o], dy[o], rho[o]
        first = np.r_[True, (row[1:] != row[:-1]) | (px[1:] != px[:-1])]
        row, e, dx, dy, rho = row[first], e[first], dx[first], dy[first], rho[first]
        top = before[e] - tips[a + row, 2]                # the material's top above the tip
        j = joint[a + row]
        if j.any():                                       # less the copy at the joint before the snapshot
            at = pg.p1[snap[a + row[j]] - 1]
            xy = tips[a + row[j], :2] + np.stack([dx[j], dy[j]], 1)
            low = at[:, 2] + cutter.lowest_z(np.hypot(*(xy - at[:, :2]).T)) - tips[a + row[j], 2]
            top[j] = np.minimum(top[j], np.where(np.isnan(low), np.inf, low))
        top_lev = np.ceil((top - margin) / dz - 0.5).astype(np.int64) - 1   # last level centred below the top
        # the levels whose ring (at their centre height) passes through the pixel
        lev_lo = np.ceil(cutter.lowest_z(np.maximum(rho - hp, 0.0)) / dz - 0.5).astype(np.int64)
        rim = rho + hp >= R
        lev_hi = np.where(rim, top_lev, np.floor(np.nan_to_num(cutter.lowest_z(np.minimum(rho + hp, R)),
                                                              nan=rc) / dz - 0.5).astype(np.int64))
        lev_hi = np.minimum(lev_hi, top_lev)
        ok = lev_hi >= lev_lo
        row, dx, dy, rho, lev_lo, lev_hi, top = row[ok], dx[ok], dy[ok], rho[ok], lev_lo[ok], lev_hi[ok], top[ok]
        phi = np.mod(np.degrees(np.arctan2(dy, dx) - feed[k[row]]), 360.0)
        hw = np.degrees(np.minimum(hp / np.maximum(rho, 1e-9), np.pi))
        b_lo = np.floor((phi - hw) / binw).astype(np.int64)
        b_hi = np.floor((phi + hw) / binw).astype(np.int64)
        nb = np.minimum(b_hi - b_lo + 1, n_phi)
        nl = lev_hi - lev_lo + 1
        cells = nb * nl
        r2 = np.repeat(np.arange(len(row)), cells)
        off = np.arange(r2.size) - np.repeat(np.cumsum(cells) - cells, cells)
        lev = lev_lo[r2] + off // nb[r2]
        b = np.mod(b_lo[r2] + off % nb[r2], n_phi)
        who = row[r2]
        if lev.size:                                      # a cell's share of a descent's chip: ds·cos κ
            n_lev = int(lev.max()) + 1
            _, kappa = cutter.immersion((np.arange(n_lev) + 0.5) * dz)
            share = np.diff(cutter.generator_length(np.arange(n_lev + 1) * dz)) * np.cos(kappa)
            depth[a:a + len(k)] = _cell_quantiles(who, lev, b, n_phi, top[r2] - (lev + 0.5) * dz, share[lev], len(k))
        if stock_top is not None:                         # claim 6: the steep side in closed form
            top_lev = int(lev.max(initial=0)) + 1
            u = np.unique((who * top_lev + lev) * n_phi + b)
            who, lev, b = u // n_phi // top_lev, u // n_phi % top_lev, u % n_phi
            who, lev, b = refine_steep(who, lev, b, n_phi, tips[a:a + len(k)], feed[k], snap[a:a + len(k)],
                                       joint[a:a + len(k)], pg, cutter, dz, view, ts.stock_z, stock_top, cuts, margin)
        n_lev = np.ones(len(k), np.int64)
        np.maximum.at(n_lev, who, lev + 1)
        n_z[a:a + len(k)] = n_lev
        masks[a:a + len(k)] = pack_grids(who, lev * n_phi + b, n_lev * n_phi)
    return n_z, masks, depth


def _cell_quantiles(group, lev, b, n_phi: int, value, weight, m: int) -> np.ndarray:
    """(m, DEPTH_QUANTILES): per group, the weighted quantiles at probabilities (i + ½)/DEPTH_QUANTILES
    of the cells' values (a cell several pixels fill counts once, with its largest value; zeros for
    a group without weight)."""
    out = np.zeros((m, DEPTH_QUANTILES))
    if group.size == 0:
        return out
    key = (group * (int(lev.max()) + 1) + lev) * n_phi + b
    o = np.lexsort((-value, key))
    first = np.r_[True, key[o][1:] != key[o][:-1]]
    group, value, weight = group[o][first], np.maximum(value[o][first], 0.0), weight[o][first]
    o = np.lexsort((value, group))
    group, value, weight = group[o], value[o], np.maximum(weight[o], 0.0)
    total = np.bincount(group, weight, minlength=m)
    has = np.flatnonzero(total > 0)
    cum = np.cumsum(weight)
    before = np.r_[0.0, cum][np.searchsorted(group, np.arange(m))]      # weight of the earlier groups
    pos = group + np.where(total[group] > 0, (cum - before[group]) / np.where(total[group] > 0, total[group], 1.0), 0.0)
    q = (np.arange(DEPTH_QUANTILES) + 0.5) / DEPTH_QUANTILES
    idx = np.searchsorted(pos, has[:, None] + q[None, :], side="left")
    out[has] = value[np.minimum(idx, len(value) - 1)]
    return out


def chip_limit(depth_mm, ramp):
    """The largest chip the material allows a descending pass, per quantile of its cells (NaN: none).

    A tooth removes the material between its edge and the surface the tooth before it left, fz
    back along the feed v. Going back along v from an envelope point of a pass that descends at
    α climbs s·sin|α| in s; where the material over the envelope is only ``depth`` thick (a plunge
    into the cusp of the previous row), the chip there ends at s = depth / sin|α| whatever the
    feed. The micro-edge force is a sum over the engaged cells, so with the limits L_i of the
    cells' quantiles it is taken as that of the feed per tooth mean_i min(fz, L_i)
    (:func:`effective_feed_per_tooth`). Level and climbing passes get NaN.
    """
    depth = np.asarray(depth_mm, float)
    s = np.sin(np.radians(-np.asarray(ramp, float)))[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(s > 1e-9, depth / s, np.nan)


def effective_feed_per_tooth(fz, limits) -> np.ndarray:
    """mean_i min(fz, L_i) per pass: the feed per tooth whose chip the material ahead allows
    (``limits`` (P, Q) from :func:`chip_limit`; a row of NaN keeps fz)."""
    fz = np.asarray(fz, float)
    lim = np.asarray(limits, float).reshape(len(fz), -1)
    if lim.shape[1] == 0:
        return fz
    capped = np.minimum(fz[:, None], np.nan_to_num(lim, nan=np.inf)).mean(axis=1)
    return np.where(np.all(np.isnan(lim), axis=1), fz, capped)


def pack_grids(grid: np.ndarray, cell: np.ndarray, size: np.ndarray) -> list[bytes]:
    """Packed bit grids (``np.packbits`` of each, C order) with the cells ``cell`` of grid ``grid``
    set; grid i has ``size[i]`` cells. One array operation for all the grids."""
    nbytes = (size + 7) // 8
    start = np.concatenate([[0], np.cumsum(nbytes)])
    bits = np.zeros(int(start[-1]) * 8, bool)
    bits[start[grid] * 8 + cell] = True
    data = np.packbits(bits).tobytes()
    return [data[start[i]:start[i + 1]] for i in range(len(size))]
