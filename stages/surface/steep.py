"""Claim 6 for the cutting region: the engagement on the tool's steep side, in closed form.

Seen from below a steep wall is edge-on, so where the material's edge crosses a level's ring on
the side of the tool the grid rasterized from the cut log (:func:`stages.surface.engagement.
engagement`) is right to a pixel only; on a wall finished with a radial depth of one pixel that is
the whole engaged arc. There, the cells within a few bins of a change along φ are decided by the
geometry itself: the ring point is in the material before the pass when it lies under the stock's
top (:class:`stages.geometry.workpiece.StockTop`, exact between pixels; with the earlier programs'
cuts, :class:`stages.surface.chain.ChainedStock`) and inside none of the
sweeps that cut around it before the snapshot (:func:`stages.geometry.clearance.inside_sweep`),
nor inside the tool at the chain's joint just before the snapshot.
"""
from __future__ import annotations

import numpy as np

from stages.geometry.clearance import inside_sweep
from stages.geometry.cutter import Cutter
from stages.geometry.passes import PassGeometry
from stages.geometry.workpiece import StockTop
from stages.surface.chain import ChainedStock

STEEP_DEG = 60.0      # levels where the tool's side is steeper than this are refined
WALL_STEP_PX = 2.0    # four pixels of the stock's top that differ by more (in pixels' worth of height) hold a wall
EDGE_PX = 3.0         # cells within this many pixels (along the ring) of a change are decided exactly


class CutsByPixel:
    """The cut log indexed by pixel: which pass last cut each pixel before a given pass (the
    sweeps that leave the material's surface there at that moment)."""

    def __init__(self, pix: np.ndarray, ident: np.ndarray, shape: tuple[int, int]):
        self.shape = shape
        self.n = int(ident.max(initial=-1)) + 2
        self.key = np.sort(pix.astype(np.int64) * self.n + ident.astype(np.int64))

    def pairs(self, px: np.ndarray, before: np.ndarray, half: int = 1):
        """(point, pass) of the last pass before ``before[i]`` to cut each pixel within ``half``
        of each point's pixel ``px[i]`` (flat index), without repeats."""
        h, w = self.shape
        d = np.arange(-half, half + 1)
        col = np.clip(px[:, None, None] % w + d[None, None, :], 0, w - 1)
        row = np.clip(px[:, None, None] // w + d[None, :, None], 0, h - 1)
        pixel = (row * w + col).reshape(len(px), -1)
        pt = np.repeat(np.arange(len(px)), pixel.shape[1])
        pixel = pixel.reshape(-1)
        at = np.searchsorted(self.key, pixel * self.n + before[pt], side="left") - 1
        hit = at >= 0
        at = np.where(hit, at, 0)
        hit &= self.key[at] // self.n == pixel
        pair = np.unique(pt[hit] * self.n + self.key[at[hit]] % self.n)
        return pair // self.n, pair % self.n


def refine_steep(who: np.ndarray, lev: np.ndarray, b: np.ndarray, n_phi: int, tips: np.ndarray, feed_rad: np.ndarray,
                 snap: np.ndarray, joint: np.ndarray, pg: PassGeometry, cutter: Cutter, dz: float, view,
                 stock_z: np.ndarray, top: StockTop | ChainedStock, cuts: CutsByPixel, margin: float):
    """The engaged cells of m predictions' grids with those on the tool's steep side near a change
    along φ decided in closed form.

    Parameters
    ----------
    who, lev, b : the rasterized grids' engaged cells (prediction, level, φ bin), without repeats
    tips (m, 3), feed_rad (m,) : the predictions' tips and feed directions
    snap : (m,) first pass each snapshot leaves out; joint (m,) whether pass snap − 1 ends where
        pass snap starts (its tool copy there is cut before the snapshot)
    view, stock_z : the tile's from-below view and stock top image (absolute z, +inf off it)
    margin : material thinner than this is not engaged (the scan's mesh tolerance)

    Returns
    -------
    who, lev, b of the engaged cells
    """
    if not len(who):
        return who, lev, b
    n_lev = int(lev.max()) + 1
    z = (np.arange(n_lev) + 0.5) * dz
    r = cutter.profile_radius(z)
    steep = (z > cutter.corner_height(STEEP_DEG)) & np.isfinite(r)
    reach = np.where(steep, np.ceil(np.degrees(EDGE_PX / view.px_per_mm / np.where(steep, r, 1.0))
                                    / (360.0 / n_phi)), 0).astype(np.int64)
    key = np.sort((who * n_lev + lev) * n_phi + b)
    ring, cell = key // n_phi, key % n_phi

    def engaged(ring_, cell_):
        k = ring_ * n_phi + cell_ % n_phi
        at = np.minimum(np.searchsorted(key, k), len(key) - 1)
        return key[at] == k

    # changes along φ on steep levels: an engaged cell whose left or right neighbour is not
    on = steep[ring % n_lev]
    left = on & ~engaged(ring, cell - 1)
    right = on & ~engaged(ring, cell + 1)
    ch_ring = np.concatenate([ring[left], ring[right]])
    ch_at = np.concatenate([cell[left], cell[right] + 1])         # the change lies before this bin
    if not len(ch_ring):
        return who, lev, b
    rr = reach[ch_ring % n_lev]
    n = 2 * rr
    idx = np.repeat(np.arange(len(ch_ring)), n)
    off = np.arange(idx.size) - np.repeat(np.cumsum(n) - n, n) - rr[idx]
    cand = np.unique(ch_ring[idx] * n_phi + (ch_at[idx] + off) % n_phi)
    i, li, bi = cand // n_phi // n_lev, cand // n_phi % n_lev, cand % n_phi
    th = feed_rad[i] + np.radians((bi + 0.5) * 360.0 / n_phi)
    P = tips[i] + np.stack([r[li] * np.cos(th), r[li] * np.sin(th), z[li]], 1)
    material = _under_stock(P, view, stock_z, top, margin)
    ppm, (h, w) = view.px_per_mm, view.shape
    x0 = view.center[0] - w / (2 * ppm)
    y0 = view.center[1] - h / (2 * ppm)
    cx = np.clip(np.floor((P[:, 0] - x0) * ppm).astype(np.int64), 0, w - 1)
    cy = np.clip(np.floor((P[:, 1] - y0) * ppm).astype(np.int64), 0, h - 1)
    pi, pj = cuts.pairs(cy * w + cx, snap[i])
    cut = np.zeros(len(P), bool)
    cut[pi[inside_sweep(P[pi], pg.p0[pj], pg.p1[pj], cutter, eps=margin)]] = True
    at_joint = np.nonzero(joint[i])[0]
    if len(at_joint):
        J = pg.p1[snap[i[at_joint]] - 1]
        cut[at_joint] |= inside_sweep(P[at_joint], J, J, cutter, eps=margin)
    keep = np.concatenate([np.setdiff1d(key, cand, assume_unique=True), cand[material & ~cut]])
    return keep // n_phi // n_lev, keep // n_phi % n_lev, keep % n_phi


def _under_stock(P: np.ndarray, view, stock_z: np.ndarray, top: StockTop | ChainedStock, margin: float) -> np.ndarray:
    """Whether points lie more than ``margin`` under the stock's top: between pixels on a smooth
    top, bilinear; where the four pixels around a point hold a wall of the stock and neither all
    lie above nor all below it, the stock's triangles decide."""
    ppm = view.px_per_mm
    h, w = stock_z.shape
    x0 = view.center[0] - w / (2 * ppm)
    y0 = view.center[1] - h / (2 * ppm)
    i0 = np.clip(np.floor((P[:, 0] - x0) * ppm - 0.5).astype(np.int64), 0, w - 2)
    j0 = np.clip(np.floor((P[:, 1] - y0) * ppm - 0.5).astype(np.int64), 0, h - 2)
    four = np.stack([stock_z[j0, i0], stock_z[j0, i0 + 1], stock_z[j0 + 1, i0], stock_z[j0 + 1, i0 + 1]], 1)
    four = np.where(np.isfinite(four), four, -np.inf)     # off the stock: no material
    lim = P[:, 2] + margin
    tx = np.clip((P[:, 0] - x0) * ppm - 0.5 - i0, 0.0, 1.0)
    ty = np.clip((P[:, 1] - y0) * ppm - 0.5 - j0, 0.0, 1.0)
    finite = np.isfinite(four).all(1)
    smooth = finite & (np.ptp(np.where(finite[:, None], four, 0.0), axis=1) <= WALL_STEP_PX / ppm)
    bilinear = ((1 - ty) * ((1 - tx) * four[:, 0] + tx * four[:, 1])
                + ty * ((1 - tx) * four[:, 2] + tx * four[:, 3]))
    out = np.where(smooth, bilinear > lim, (four > lim[:, None]).all(1))
    unsure = ~smooth & ~out & (four > lim[:, None]).any(1)
    if unsure.any():                                   # a wall of the stock between the pixels
        out[unsure] = top.under(P[unsure], margin)
    return out
