"""Micro-regions the tool reaches at an orientation, from its z-map (seed eqs. 1–2).

A micro-region i is machinable (δ_i = 1) when it faces the tool (ψ_i < 90°: the contact is on the
ball, not the shank) and the ball centre that touches its centroid lies on the z-map's upper
envelope: not behind the plane of the offset face that generated its cell by more than a quarter
cell, measured along that plane's normal (exact where that face goes on over the centre; against
arcs and spheres, which have no one plane, the depth may differ by what the region's own offset
plane changes over half a cell's diagonal), so micro-regions smaller than a cell are found as well. A micro-region that is its whole face is machinable also when its face
generated a visible cell (it "owns" one), as the seed reads the z-map's correspondence.
"""
from __future__ import annotations

import numpy as np

from stages.posture.offset import EMPTY, OCCLUDER, OffsetMesh
from stages.posture.part import Part

TAN_CAP = np.tan(np.radians(85.0))   # steeper offset planes: the tolerance of an 85° one
COS_STEEP = np.cos(np.radians(89.5))  # offset faces steeper than this carry no depth
EPS_CELL = 0.25                      # depth slack: a ball centre within a quarter cell of the envelope is on it


def tile_flags(P, tol, grad, eps, view, depth, ids, n_faces: int):
    """The point test and the owned faces of one tile.

    Parameters
    ----------
    P : (n, 3) the regions' ball centres in the tile's frame (right, up, view) relative to the
        origin; tol : (n,) depth tolerance against arcs and spheres, mm; grad : (n_faces, 3) depth
        gradient of each offset face in the view, mm/mm (NaN for faces too steep to carry a depth),
        and the view component of its normal; eps : how far behind the generating face's plane (along
        its normal) a centre may lie, mm; view, depth, ids : the tile and its z-map.

    Returns
    -------
    on : (n,) bool, the centre projects into the tile and lies on the envelope;
    owned : (n_faces,) bool, faces owning a cell of the tile.
    """
    h, w = view.shape
    right, up, d = view.basis()
    c = np.asarray(view.center, float)
    x = (P[:, 0] - c @ right) * view.px_per_mm + w / 2
    y = (P[:, 1] - c @ up) * view.px_per_mm + h / 2
    z = P[:, 2] - c @ d
    col, row = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    inside = (col >= 0) & (col < w) & (row >= 0) & (row < h)
    on = np.zeros(len(P), bool)
    k = np.nonzero(inside)[0]
    win = ids[row[k], col[k]]
    dz = depth[row[k], col[k]]
    ok = win == EMPTY
    occ = win == OCCLUDER
    ok[occ] = z[k[occ]] <= dz[occ] + tol[k[occ]]
    f = np.nonzero(win >= 0)[0]
    g = grad[win[f]]
    steep = np.isnan(g[:, 0])
    carried = dz[f] + (g[:, 0] * (x[k[f]] - col[k[f]] - 0.5) + g[:, 1] * (y[k[f]] - row[k[f]] - 0.5)) / view.px_per_mm
    # how far the centre lies behind the generating face's plane, measured along that plane's normal
    behind = (z[k[f]] - carried) * g[:, 2]
    ok[f] = np.where(steep, z[k[f]] <= dz[f] + tol[k[f]], behind <= eps)
    on[k] = ok
    own = ids[ids >= 0]
    owned = np.bincount(own, minlength=n_faces)[:n_faces] > 0 if len(own) else np.zeros(n_faces, bool)
    return on, owned


def orientation_flags(part: Part, offset: OffsetMesh, axes, frames, views, owner, images, cell_mm: float):
    """δ per orientation: yields (k, (n_regions,) bool) as soon as orientation k's tiles are rendered.

    ``images`` yields (i, depth, ids) for ``views`` in order (``zmap.zmaps``); ``owner[i]`` is the
    orientation of view i; ``frames`` (n, 3, 3) and ``axes`` (n, 3) the orientations' frames and axes.
    """
    nrm = part.normals
    pn = offset.plane_normals[part.parent]
    slack = EPS_CELL * cell_mm
    # a neighbour's plane carried half a cell's diagonal departs from the region's surface by at most
    # that times the angle between smooth neighbours (the offset's crease angle)
    eps = slack + 0.5 * np.sqrt(2.0) * cell_mm * np.sin(np.radians(offset.crease_deg))
    cur, on, owned = -1, None, None

    def finish(k):
        facing = nrm @ axes[k] > 1e-9
        return k, facing & (on | (owned[part.parent] & part.whole))

    for i, depth, ids in images:
        k = int(owner[i])
        if k != cur:
            if cur >= 0:
                yield finish(cur)
            cur = k
            P = offset.centres @ frames[k].T
            cz = np.abs(pn @ axes[k])
            tan = np.sqrt(np.maximum(0.0, 1 - cz * cz)) / np.maximum(cz, 1e-12)
            tol = 0.5 * np.sqrt(2.0) * cell_mm * np.minimum(tan, TAN_CAP) + slack
            pv = offset.plane_normals @ frames[k].T
            steep = np.abs(pv[:, 2]) < COS_STEEP
            grad = np.empty((len(pv), 3))
            grad[:, :2] = -pv[:, :2] / np.where(steep, 1.0, pv[:, 2])[:, None]
            grad[:, 2] = np.abs(pv[:, 2])
            grad[steep, 0] = np.nan
            on = np.zeros(part.n, bool)
            owned = np.zeros(offset.n_faces, bool)
        t_on, t_owned = tile_flags(P, tol, grad, eps, views[i], depth, ids, offset.n_faces)
        on |= t_on
        owned |= t_owned
    if cur >= 0:
        yield finish(cur)
