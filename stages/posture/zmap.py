"""The z-map along each tool axis with the generating face of every cell (seed §3), and its windows.

For orientation k the part is seen along −θ_k (``orientations.frames``): per cell the depth of the
nearest inverse-offset triangle (the height the tool-tip centre can come down to) and which face of
the part generated it. Ids in a z-map (``offset.decode``): the face (≥ 0), ``EMPTY`` where no offset lies, ``OCCLUDER``
where an arc or a sphere is nearest. Each orientation's window is the offset's outline in that frame,
cut into tiles of at most ``tile_px`` pixels a side so memory stays bounded at any resolution.

Two back ends, chosen as the product's renders are (``backend: auto | gl | cpu``): moderngl on
headless EGL (:mod:`stages.posture.zmap_gl`: the geometry uploaded once, each window one draw of the
same buffers into a viewport of an atlas) and the product's numpy z-buffer
(:class:`stages.render.cpu.CPURenderer`, the reference), to which the windows are ordinary
:class:`stages.render.View` windows.
"""
from __future__ import annotations

import logging
import math

import numpy as np

from stages import InputError
from stages.posture.offset import OffsetMesh, decode
from stages.render.base import View, make_scene

log = logging.getLogger(__name__)

CPU_TRIANGLES = 2_000_000        # triangles per CPU render call (the offset repeated per window)


def hull_points(offset: OffsetMesh) -> np.ndarray:
    """Points whose projections bound the offset's projection in every direction (its convex hull)."""
    from scipy.spatial import ConvexHull
    v = offset.vertices
    try:
        return v[ConvexHull(v).vertices]
    except Exception:            # flat or degenerate point sets: all points
        return v


def windows(offset: OffsetMesh, frames: np.ndarray, cell_mm: float, tile_px: int):
    """The tiles of every orientation's window.

    Parameters
    ----------
    frames : (n, 3, 3) rows right, up, view direction (``orientations.frames``).
    cell_mm : z-map cell; tile_px : largest tile side in pixels.

    Returns
    -------
    views : list of :class:`View`; owner : (len(views),) the orientation of each tile.
    """
    hp = hull_points(offset)
    proj = np.einsum("kij,pj->kpi", frames, hp)                     # (n, p, 3)
    lo, hi = proj.min(1), proj.max(1)
    ppm = 1.0 / cell_mm
    views, owner = [], []
    for k in range(len(frames)):
        right, up, d = frames[k]
        W = int(math.ceil((hi[k, 0] - lo[k, 0]) * ppm)) + 2
        H = int(math.ceil((hi[k, 1] - lo[k, 1]) * ppm)) + 2
        mid = 0.5 * (lo[k] + hi[k])
        c = mid[0] * right + mid[1] * up
        near, far = lo[k, 2] - 1.0, hi[k, 2] + 1.0
        for r0 in range(0, H, tile_px):
            for c0 in range(0, W, tile_px):
                h, w = min(tile_px, H - r0), min(tile_px, W - c0)
                cc = c + ((c0 + w / 2) - W / 2) * cell_mm * right + ((r0 + h / 2) - H / 2) * cell_mm * up
                views.append(View(tuple(cc), tuple(d), tuple(up), w * cell_mm, h * cell_mm, ppm, near, far))
                owner.append(k)
    return views, np.asarray(owner, np.int64)


def cpu_zmaps(offset: OffsetMesh, views):
    """The z-maps by the numpy z-buffer: yields (i, depth (h, w) mm along the view from its centre,
    +inf where empty; ids (h, w)) for each view in order."""
    from stages.render.cpu import CPURenderer
    r = CPURenderer()
    tris = offset.triangles()
    code = np.where(offset.ids >= 0, offset.ids + 1, 0).astype(np.float64)   # 0: occluder, -1: none
    t = len(tris)
    per = max(1, CPU_TRIANGLES // max(t, 1))
    for a in range(0, len(views), per):
        batch = views[a:a + per]
        nb = len(batch)
        sc = make_scene(np.tile(tris, (nb, 1, 1)), np.repeat(np.arange(nb), t), np.tile(code, nb))
        for j, im in enumerate(r.render(batch, sc)):
            yield a + j, im.depth, decode(im.id)


def zmaps(offset: OffsetMesh, views, backend: str = "auto"):
    """The z-maps of ``views`` by the chosen back end (see :func:`cpu_zmaps` for what is yielded).

    ``auto`` uses gl when a headless EGL context opens and falls back to cpu, logging why; ``gl``
    raises when none opens.
    """
    if backend not in ("auto", "gl", "cpu"):
        raise InputError(f"render.backend: {backend!r} is not one of auto, gl, cpu")
    if backend == "cpu":
        return cpu_zmaps(offset, views)
    try:
        from stages.posture.zmap_gl import GLZmap
        gl = GLZmap(offset)
    except Exception as e:
        if backend == "gl":
            raise
        log.warning("render.backend auto: using the cpu back end (%s)", e)
        return cpu_zmaps(offset, views)
    return gl.zmaps(views)


def backend_name(backend: str) -> str:
    """The back end ``auto`` resolves to here."""
    if backend != "auto":
        return backend
    try:
        from stages.render.gl import gl_context
        gl_context()
        return "gl"
    except Exception:
        return "cpu"
