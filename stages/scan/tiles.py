"""Tiles of the ordered scans and the render settings shared by the render-chain kernels.
"""
from __future__ import annotations

import math

import numpy as np

from stages.geometry.cutter import Cutter
from stages.geometry.passes import PassGeometry
from stages.geometry.workpiece import Workpiece
from stages.render import View, make_renderer

TILE_PX = 2048           # scan tile side (memory is bounded by the tile, not by the part)


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
