"""Claim 6 for the cutting region: the engagement on the tool's steep side, in closed form.

Seen from below a steep wall is edge-on, so where the material's edge crosses a level's ring on
the side of the tool the grid rasterized from the cut log (:func:`stages.surface.engagement.
engagement`) is right to a pixel only; on a wall finished with a radial depth of one pixel that is
the whole engaged arc. There, the cells within a few bins of a change along φ are decided by the
geometry itself: the ring point is in the material before the pass when it lies under the stock's
top (:class:`stages.geometry.workpiece.StockTop`, exact between pixels) and inside none of the
sweeps that cut around it before the snapshot (:func:`stages.geometry.clearance.inside_sweep`),
nor inside the tool at the chain's joint just before the snapshot.
"""
from __future__ import annotations

import numpy as np

from stages.geometry.clearance import inside_sweep
from stages.geometry.cutter import Cutter
from stages.geometry.passes import PassGeometry
from stages.geometry.workpiece import StockTop

STEEP_DEG = 60.0      # levels where the tool's side is steeper than this are refined
EDGE_PX = 3.0         # cells within this many pixels (along the ring) of a change are decided exactly


class CutsByPixel:
    """The cut log indexed by pixel: which passes cut each pixel (a tile's candidates for
    having removed material at a point)."""

    def __init__(self, pix: np.ndarray, ident: np.ndarray, shape: tuple[int, int]):
        o = np.lexsort((ident, pix))
        self.pix, self.ident = pix[o], ident[o]
        self.shape = shape

    def pairs(self, px: np.ndarray, before: np.ndarray, half: int = 1):
        """(point, pass) of the passes with an index below ``before[i]`` that cut within ``half``
        pixels of each point's pixel ``px[i]`` (flat index), without repeats."""
        h, w = self.shape
        d = np.arange(-half, half + 1)
        col = np.clip(px[:, None, None] % w + d[None, None, :], 0, w - 1)
        row = np.clip(px[:, None, None] // w + d[None, :, None], 0, h - 1)
        key = (row * w + col).reshape(len(px), -1)
        pt = np.repeat(np.arange(len(px)), key.shape[1])
        key = key.reshape(-1)
        lo = np.searchsorted(self.pix, key, side="left")
        n = np.searchsorted(self.pix, key, side="right") - lo
        i = np.repeat(pt, n)
        j = self.ident[np.repeat(lo - np.cumsum(n) + n, n) + np.arange(int(n.sum()))].astype(np.int64)
        keep = j < before[i]
        pairs = np.unique(np.stack([i[keep], j[keep]], 1), axis=0)
        return pairs[:, 0], pairs[:, 1]


def refine_steep(grid: np.ndarray, rows: np.ndarray, tips: np.ndarray, feed_rad: np.ndarray, snap: np.ndarray,
                 joint: np.ndarray, pg: PassGeometry, cutter: Cutter, dz: float, view, stock_z: np.ndarray,
                 top: StockTop, cuts: CutsByPixel, margin: float) -> None:
    """Decide the uncertain cells of engagement grids on the tool's steep side, in place.

    Parameters
    ----------
    grid : (m, L, n_phi) bool, the rasterized grids of m predictions
    rows : (m,) the predictions' pass indices; tips (m, 3); feed_rad (m,) feed direction
    snap : (m,) first pass each snapshot leaves out; joint (m,) whether pass snap − 1 ends where
        pass snap starts (its tool copy there is cut before the snapshot)
    view, stock_z : the tile's from-below view and stock top image (absolute z, +inf off it)
    margin : material thinner than this is not engaged (the scan's mesh tolerance)
    """
    m, L, n_phi = grid.shape
    if m == 0 or L == 0:
        return
    z = (np.arange(L) + 0.5) * dz
    r = cutter.profile_radius(z)
    steep = (z > cutter.corner_height(STEEP_DEG)) & np.isfinite(r)
    if not steep.any():
        return
    ppm = view.px_per_mm
    reach = np.ceil(np.degrees(EDGE_PX / ppm / np.maximum(r, 1e-9)) / (360.0 / n_phi)).astype(np.int64)
    change = grid != np.roll(grid, 1, axis=2)              # between bins b − 1 and b
    near = np.zeros_like(grid)
    for s in range(-int(reach[steep].max()), int(reach[steep].max()) + 1):
        near |= np.roll(change, s, axis=2) & ((s >= -reach) & (s < reach))[None, :, None]
    i, lev, b = np.nonzero(near & steep[None, :, None])
    if not len(i):
        return
    th = feed_rad[i] + np.radians((b + 0.5) * 360.0 / n_phi)
    P = tips[i] + np.stack([r[lev] * np.cos(th), r[lev] * np.sin(th), z[lev]], 1)
    in_stock = _under_stock(P, view, stock_z, top, margin)
    w = view.shape[1]
    x0 = view.center[0] - view.shape[1] / (2 * ppm)
    y0 = view.center[1] - view.shape[0] / (2 * ppm)
    cx = np.clip(np.floor((P[:, 0] - x0) * ppm).astype(np.int64), 0, view.shape[1] - 1)
    cy = np.clip(np.floor((P[:, 1] - y0) * ppm).astype(np.int64), 0, view.shape[0] - 1)
    pi, pj = cuts.pairs(cy * w + cx, snap[i])
    cut = np.zeros(len(P), bool)
    hit = inside_sweep(P[pi], pg.p0[pj], pg.p1[pj], cutter, eps=margin)
    cut[pi[hit]] = True
    at_joint = np.nonzero(joint[i])[0]
    if len(at_joint):
        J = pg.p1[snap[i[at_joint]] - 1]
        cut[at_joint] |= inside_sweep(P[at_joint], J, J, cutter, eps=margin)
    grid[i, lev, b] = in_stock & ~cut


def _under_stock(P: np.ndarray, view, stock_z: np.ndarray, top: StockTop, margin: float) -> np.ndarray:
    """Whether points lie more than ``margin`` under the stock's top. Between four pixels whose tops
    all lie above (below) the point the answer is theirs; otherwise the stock's triangles decide."""
    ppm = view.px_per_mm
    h, w = stock_z.shape
    x0 = view.center[0] - w / (2 * ppm)
    y0 = view.center[1] - h / (2 * ppm)
    i0 = np.clip(np.floor((P[:, 0] - x0) * ppm - 0.5).astype(np.int64), 0, w - 2)
    j0 = np.clip(np.floor((P[:, 1] - y0) * ppm - 0.5).astype(np.int64), 0, h - 2)
    four = np.stack([stock_z[j0, i0], stock_z[j0, i0 + 1], stock_z[j0 + 1, i0], stock_z[j0 + 1, i0 + 1]], 1)
    four = np.where(np.isfinite(four), four, -np.inf)     # off the stock: no material
    lim = P[:, 2] + margin
    out = (four > lim[:, None]).all(1)
    unsure = ~out & (four > lim[:, None]).any(1)
    if unsure.any():
        out[unsure] = top.z(P[unsure, :2]) > lim[unsure]
    return out
