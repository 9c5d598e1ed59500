"""Exact mesh queries of scripts/make_samples.py: the closest point of a triangle mesh to given points
(the contact point of a ball whose centre is known) and the first crossing of rays with a mesh (the
stock's thickness along a surface normal). Brute force over the triangles a coarse grid keeps.
"""
from __future__ import annotations

import numpy as np
import trimesh

PAIRS_PER_CHUNK = 2_000_000      # point-triangle pairs evaluated at once (bounds memory)


class Grid:
    """Triangles binned by their axis-aligned bounds into cubic (or, ``dims=2``, square) cells.

    Parameters
    ----------
    tris : (n, 3, 3) triangles, mm.
    cell : cell edge, mm.
    dims : 3 for a 3-D grid, 2 for columns over xy.
    """

    def __init__(self, tris: np.ndarray, cell: float, dims: int = 3):
        self.tris = np.asarray(tris, float)
        self.dims, self.cell = dims, float(cell)
        lo, hi = self.tris.min(1)[:, :dims], self.tris.max(1)[:, :dims]
        self.lo = lo.min(0) - cell
        c0, c1 = self._cell(lo), self._cell(hi)
        self.shape = c1.max(0) + 2
        span = c1 - c0 + 1
        count = span.prod(1)
        tri = np.repeat(np.arange(len(count)), count)
        off = np.arange(tri.size) - np.repeat(np.cumsum(count) - count, count)
        idx = np.empty((tri.size, dims), np.int64)
        for d in range(dims):                       # row-major offsets inside each triangle's box
            stride = np.prod(span[:, d + 1:], axis=1) if d + 1 < dims else np.ones(len(span), np.int64)
            idx[:, d] = c0[tri, d] + (off // stride[tri]) % span[tri, d]
        key = self._key(idx)
        order = np.argsort(key, kind="stable")
        self.keys, self.tri = key[order], tri[order]

    def _cell(self, p: np.ndarray) -> np.ndarray:
        return np.floor((p - self.lo) / self.cell).astype(np.int64)

    def _key(self, idx: np.ndarray) -> np.ndarray:
        k = idx[:, 0]
        for d in range(1, self.dims):
            k = k * self.shape[d] + idx[:, d]
        return k

    def candidates(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(query index, triangle) pairs of the triangles in the cells the boxes [lo, hi] meet, without
        repeats."""
        c0 = np.clip(self._cell(lo[:, :self.dims]), 0, self.shape - 1)
        c1 = np.clip(self._cell(hi[:, :self.dims]), 0, self.shape - 1)
        span = c1 - c0 + 1
        count = span.prod(1)
        q = np.repeat(np.arange(len(lo)), count)
        off = np.arange(q.size) - np.repeat(np.cumsum(count) - count, count)
        idx = np.empty((q.size, self.dims), np.int64)
        for d in range(self.dims):
            stride = np.prod(span[:, d + 1:], axis=1) if d + 1 < self.dims else np.ones(len(span), np.int64)
            idx[:, d] = c0[q, d] + (off // stride[q]) % span[q, d]
        key = self._key(idx)
        a, b = np.searchsorted(self.keys, key, "left"), np.searchsorted(self.keys, key, "right")
        n = b - a
        qq = np.repeat(q, n)
        tt = self.tri[np.repeat(a - np.cumsum(n) + n, n) + np.arange(n.sum())]
        pair = np.unique(qq * len(self.tris) + tt)
        return pair // len(self.tris), pair % len(self.tris)


def closest_points(grid: Grid, points: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """Closest point of the mesh to each point, searched within ``reach`` (exact inside it).

    Only the triangles whose bounding box lies within ``reach`` of a point are measured.

    Returns
    -------
    cp : (n, 3) closest points (NaN where no triangle lies within ``reach``).
    dist : (n,) distances (inf there).
    """
    points = np.asarray(points, float).reshape(-1, 3)
    cp = np.full(points.shape, np.nan)
    dist = np.full(len(points), np.inf)
    step = max(1, PAIRS_PER_CHUNK // 400)
    for s in range(0, len(points), step):
        p = points[s:s + step]
        q, t = grid.candidates(p - reach, p + reach)
        lo, hi = grid.tris[t].min(1), grid.tris[t].max(1)
        gap = np.maximum(np.maximum(lo - p[q], p[q] - hi), 0.0)
        near = np.einsum("ij,ij->i", gap, gap) <= reach * reach
        q, t = q[near], t[near]
        for a in range(0, q.size, PAIRS_PER_CHUNK):
            qa, ta = q[a:a + PAIRS_PER_CHUNK], t[a:a + PAIRS_PER_CHUNK]
            c = trimesh.triangles.closest_point(grid.tris[ta], p[qa])
            d = np.linalg.norm(c - p[qa], axis=1)
            order = np.lexsort((d, qa))              # per point, nearest first
            first = np.ones(order.size, bool)
            first[1:] = qa[order][1:] != qa[order][:-1]
            k, j = qa[order][first], order[first]
            better = d[j] < dist[s + k]
            dist[s + k[better]] = d[j[better]]
            cp[s + k[better]] = c[j[better]]
    return cp, dist


def contact(grid: Grid, centres: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Contact point, outward normal and slope of a ball of ``radius`` at ``centres`` on the mesh.

    Returns
    -------
    points : (n, 3) the closest point of the mesh to each centre.
    normals : (n, 3) unit vectors from it to the centre (out of the material).
    slope_deg : (n,) angle of that normal from +Z, degrees (0 on a floor, 90 on a vertical wall).
    """
    cp, d = closest_points(grid, centres, radius * (1 + 1e-6) + 1e-4)
    n = (np.asarray(centres, float) - cp) / d[:, None]
    return cp, n, np.degrees(np.arccos(np.clip(n[:, 2], -1.0, 1.0)))


def ray_exit(grid: Grid, origins: np.ndarray, dirs: np.ndarray, reach: float) -> np.ndarray:
    """Distance along each unit ray to its first crossing with the mesh within ``reach``; inf where none.

    Möller–Trumbore against the triangles of the cells the ray's segment box meets (``grid`` may be
    a 2-D grid of columns).
    """
    o, d = np.asarray(origins, float), np.asarray(dirs, float)
    end = o + reach * d
    q, t = grid.candidates(np.minimum(o, end), np.maximum(o, end))
    out = np.full(len(o), np.inf)
    for a in range(0, q.size, PAIRS_PER_CHUNK):
        qa, ta = q[a:a + PAIRS_PER_CHUNK], t[a:a + PAIRS_PER_CHUNK]
        v0, v1, v2 = (grid.tris[ta, k] for k in range(3))
        e1, e2 = v1 - v0, v2 - v0
        pv = np.cross(d[qa], e2)
        det = np.einsum("ij,ij->i", e1, pv)
        ok = np.abs(det) > 1e-15
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        tv = o[qa] - v0
        u = np.einsum("ij,ij->i", tv, pv) * inv
        qv = np.cross(tv, e1)
        v = np.einsum("ij,ij->i", d[qa], qv) * inv
        s = np.einsum("ij,ij->i", e2, qv) * inv
        hit = ok & (u >= -1e-12) & (v >= -1e-12) & (u + v <= 1 + 1e-12) & (s > 0) & (s <= reach)
        np.minimum.at(out, qa[hit], s[hit])
    return out
