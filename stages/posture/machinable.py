"""Micro-regions the tool reaches at an orientation, from its z-map (seed eqs. 1–2).

A micro-region i is machinable (δ_i = 1) when it faces the tool (ψ_i < 90°: the contact is on the
ball, not the shank) and the ball centre that touches its centroid lies on the z-map's upper
envelope: its depth along the view is not behind the cell's by more than the region's own offset
plane can change within half a cell's diagonal (regions smaller than a cell are found too); a
micro-region that is its whole face is machinable as well when its face generated a visible cell
(it "owns" one), as the seed marks regions by the z-map's correspondence.
"""
from __future__ import annotations

import numpy as np

from stages.posture.offset import OffsetMesh
from stages.posture.part import Part

TAN_CAP = np.tan(np.radians(85.0))   # steeper offset planes: the tolerance of an 85° one
EPS_CELL = 0.05                      # depth slack for float round-off, in cells


def tile_flags(P, tol, view, depth, ids, n_faces: int):
    """The point test and the owned faces of one tile.

    Parameters
    ----------
    P : (n, 3) the regions' ball centres in the tile's frame (right, up, view) relative to the
        origin; tol : (n,) depth tolerance, mm; view, depth, ids : the tile and its z-map.

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
    dz = depth[row[k], col[k]]
    on[k] = z[k] <= dz + tol[k]
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
            on = np.zeros(part.n, bool)
            owned = np.zeros(offset.n_faces, bool)
        t_on, t_owned = tile_flags(P, tol, views[i], depth, ids, offset.n_faces)
        on |= t_on
        owned |= t_owned
    if cur >= 0:
        yield finish(cur)
