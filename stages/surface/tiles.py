"""Tiles of the ordered scans: windows over the part, the passes each draws and the passes it owns.

A tile owns a set of passes and its window holds all of their sweeps: every pass whose sweep
reaches into the window is drawn, in execution order, so the scan is exact over the whole window
and each owned pass's counts, final-surface pixels and cut log are whole in its own tile. The
passes are split into tiles by their midpoints until a window fits :data:`TILE_PX`; the tiles are
dealt to the shards, so a large program spreads over the workers; memory is bounded by the tile.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.geometry.cutter import Cutter
from stages.geometry.passes import PassGeometry
from stages.geometry.workpiece import Workpiece
from stages.render import View

TILE_PX = 1024           # largest window side, pixels (the cut log grows with the window's area)
PASSES_PER_DRAW = 2000   # sweeps meshed at a time (bounds the triangle arrays)


@dataclass
class Tile:
    view: View               # from below, over the owned passes' sweeps
    lo: np.ndarray           # (2,) xy of the window's corner, mm
    hi: np.ndarray           # (2,)
    drawn: np.ndarray        # pass indices whose sweep reaches into the window, in execution order
    owned: np.ndarray        # pass indices this tile reports


def fine_tolerance(px_per_mm: float) -> float:
    """Mesh tolerance of the scans: a tenth of a pixel (the cut log's depths feed the engagement)."""
    return 0.1 / float(px_per_mm)


def z_range(pg: PassGeometry, wp: Workpiece, cutter: Cutter):
    """Depth range (absolute z) that holds everything a from-below view can see."""
    zs = np.concatenate([pg.p0[:, 2], pg.p1[:, 2], wp.bounds[:, 2]]) if len(pg.p0) else wp.bounds[:, 2]
    return float(zs.min()) - 1.0, float(zs.max()) + cutter.stickout_mm + 1.0


def cutting_candidates(pg: PassGeometry, cutter: Cutter, wp: Workpiece) -> np.ndarray:
    """Passes whose sweep can reach the stock (rapid moves never cut)."""
    b = pg.sweep_bounds(cutter)
    reach = (pg.motion != 0) & (b[:, 0, 2] <= wp.bounds[1, 2])
    reach &= np.all(b[:, 0, :2] <= wp.bounds[1, :2], axis=1) & np.all(b[:, 1, :2] >= wp.bounds[0, :2], axis=1)
    return np.nonzero(reach)[0]


def tiles(pg: PassGeometry, cutter: Cutter, wp: Workpiece, px_per_mm: float, strips: int = 1,
          strip: int | None = None) -> list[Tile]:
    """The tiles over the cutting passes; with ``strip`` of ``strips`` only that shard's share.

    The passes are split in two at the median of their midpoints along the longer side of their
    sweeps' extent until the extent fits :data:`TILE_PX` (a single pass longer than that keeps a
    window of its own size): windows hug the passes they own and overlap only by the sweeps that
    reach across. The leaves go to the shards in turn.
    """
    cand = cutting_candidates(pg, cutter, wp)
    if not len(cand):
        return []
    bounds = pg.sweep_bounds(cutter)[:, :, :2]
    stock_lo = wp.bounds[0, :2] - cutter.radius_mm
    stock_hi = wp.bounds[1, :2] + cutter.radius_mm
    mid = 0.5 * (pg.p0[:, :2] + pg.p1[:, :2])
    pad = 2.0 / px_per_mm
    most = TILE_PX / px_per_mm
    leaves, todo = [], [cand]
    while todo:
        idx = todo.pop()
        lo = np.maximum(bounds[idx, 0].min(0), stock_lo) - pad
        hi = np.minimum(bounds[idx, 1].max(0), stock_hi) + pad
        if len(idx) == 1 or np.all(hi - lo <= most):
            leaves.append((idx, lo, hi))
            continue
        axis = int(np.argmax(hi - lo))
        order = np.argsort(mid[idx, axis], kind="stable")
        half = len(idx) // 2
        todo.extend([np.sort(idx[order[:half]]), np.sort(idx[order[half:]])])
    leaves.sort(key=lambda leaf: (leaf[1][0], leaf[1][1]))
    zlo, zhi = z_range(pg, wp, cutter)
    out = []
    for n, (idx, lo, hi) in enumerate(leaves):
        if strip is not None and n % strips != strip:
            continue
        reach = np.all(bounds[cand, 0] <= hi, axis=1) & np.all(bounds[cand, 1] >= lo, axis=1)
        ctr = 0.5 * (lo + hi)
        view = View((ctr[0], ctr[1], 0.0), (0, 0, 1.0), (0, 1.0, 0), hi[0] - lo[0], hi[1] - lo[1], px_per_mm, zlo, zhi)
        out.append(Tile(view, lo, hi, cand[reach], idx))
    return out
