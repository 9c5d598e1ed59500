"""One ordered scan of a tile from below (seed 000 claims 7 and 8 at once).

The stock first (less what earlier programs of the job cut: :mod:`stages.surface.chain`), then every
sweep that reaches into the window, in execution order, with the depth
test and depth writes, as the machine removes material (``Renderer.scan``). Per pass: the pixels
it cut by position along the pass, the largest contact angle among them, and the pixels of the
final surface it leaves; per pixel the final surface's owner, contact angle and azimuth; and the
cut log, every depth each cut left, from which the material before any pass follows.

Sweeps are drawn with a depth bias of the mesh tolerance: a pass must cut deeper than the meshes'
own error into the stock to count, and a pass that repeats an earlier one ties with it and does
not count. The logged and final depths are given back without the bias.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.geometry.envelope import EnvelopeMesh
from stages.geometry.passes import PassGeometry
from stages.geometry.sweeps import ordered_sweep_scene
from stages.geometry.workpiece import Workpiece, workpiece_scene
from stages.render import CutLog, Image
from stages.surface.chain import Earlier
from stages.surface.tiles import PASSES_PER_DRAW, Tile

N_BINS = 20              # bins of the position along a pass (prediction point, cut_filter)


@dataclass
class TileScan:
    """What one tile's scan found; pass indices are the program's (``PassGeometry`` rows)."""

    tile: Tile
    counts: np.ndarray        # (n_passes, N_BINS) cut pixels by position along the pass
    b_max: np.ndarray         # (n_passes,) largest contact angle among the cut pixels (-inf: none)
    final: Image              # owner pass index (-1: stock or none), b = q, c = azimuth θ (deg), depth = z
    stock_z: np.ndarray       # (h, w) top of the stock (+inf off it)
    log: CutLog | None        # ident = pass index; depth = z the cut left


def scan_tile(tile: Tile, pg: PassGeometry, wp: Workpiece, mesh: EnvelopeMesh, renderer,
              log: bool = True, earlier: Earlier | None = None) -> TileScan:
    """The tile's scan: the stock, the sweeps of the ``earlier`` programs reaching into the window
    (part of the stock the program meets: ``stock_z``), then the program's drawn passes."""
    n = len(pg.pass_id)
    tol = mesh.tol_mm
    drawn = tile.drawn

    def batches():
        for a in range(0, len(drawn), PASSES_PER_DRAW):
            k = drawn[a:a + PASSES_PER_DRAW]
            yield ordered_sweep_scene(mesh, pg.p0[k], pg.p1[k], k, bias=tol)

    before = earlier.scenes(tile.lo, tile.hi) if earlier else ()
    res = renderer.scan(tile.view, workpiece_scene(wp, [tile.view], -2.0), batches(), n, N_BINS, log=log,
                        before=before)
    fin = res.final
    fin.depth = np.where(fin.id >= 0, fin.depth - tol, fin.depth)     # the bias, not the surface
    cut = res.log
    if cut is not None:
        cut.depth = cut.depth - np.float32(tol)
    return TileScan(tile, res.counts, res.b_max, fin, res.stock_depth, cut)


def surface_stats(ts: TileScan, n: int):
    """(surface_px, surface_max_contact_deg) of every pass over this tile's final image."""
    won = ts.final.id >= 0
    ids = ts.final.id[won]
    px = np.bincount(ids, minlength=n)
    q = np.full(n, -np.inf)
    np.maximum.at(q, ids, ts.final.b[won].astype(float))
    return px, q
