"""The semi-finished stock as a watertight mesh (scripts/make_samples.py): the surface the semi-finishing
sweeps leave, a height field sampled where it bends.

The top is a tree of rectangular cells over the stock's box. A cell is split while the surface at its
centre, the middles of its edges and its quarter points departs from the cell's two triangles by more
than ``TOL_MM`` along the surface normal, at most ``LEVELS`` times along each axis, and only across
the axis along which it bends (a wall parallel to X splits cells in Y only); the last split only for
departures over ``TOL_LAST_MM`` (vertical steps), not for the scallops the Z-level passes leave on steep
walls (≤ 7 µm; across a wall of 88° they repeat every 0.01 mm: no cell resolves them, and every cell
lies within them). Base cell rows lie on the semi-finishing raster's rows and on the ridges between
them, so a flat area's scallops need no split. A cell with vertices of smaller neighbours on its edges
is a fan about its centre through all of them (no cracks).
"""
from __future__ import annotations

import numpy as np
import trimesh

TOL_MM = 0.005        # largest departure of the mesh from the surface along the normal before a split
TOL_LAST_MM = 0.015   # the same, for the last split along an axis
LEVELS = 5            # splits of a base cell along each axis at most
KEY = 1 << 24         # vertex key = i·KEY + j on the lattice (half the finest cell: every centre is on it)

# sample points of a cell in its unit square: the centre, edge middles (bottom, right, top, left),
# quarter points
_U = np.array([0.5, 0.5, 1.0, 0.5, 0.0, 0.25, 0.75, 0.75, 0.25])
_V = np.array([0.5, 0.0, 0.5, 1.0, 0.5, 0.25, 0.25, 0.75, 0.75])


class Heights:
    """Heights of the surface at lattice vertices, evaluated once each."""

    def __init__(self, height, origin, unit):
        self.height, self.origin, self.unit = height, np.asarray(origin, float), np.asarray(unit, float)
        self.keys, self.z = np.zeros(0, np.int64), np.zeros(0)

    def get(self, ij: np.ndarray) -> np.ndarray:
        ij = np.asarray(ij, np.int64).reshape(-1, 2)
        k = ij[:, 0] * KEY + ij[:, 1]
        pos = np.searchsorted(self.keys, k)
        have = (self.keys[np.minimum(pos, self.keys.size - 1)] == k) if self.keys.size else np.zeros(k.size, bool)
        if not have.all():
            new = np.unique(k[~have])
            xy = self.origin + np.column_stack([new // KEY, new % KEY]) * self.unit
            keys, z = np.concatenate([self.keys, new]), np.concatenate([self.z, self.height(xy)])
            order = np.argsort(keys)
            self.keys, self.z = keys[order], z[order]
            pos = np.searchsorted(self.keys, k)
        return self.z[pos]

    def xyz(self, ij: np.ndarray) -> np.ndarray:
        ij = np.asarray(ij, np.int64).reshape(-1, 2)
        return np.column_stack([self.origin + ij * self.unit, self.get(ij)])


def _departure(z, zs, hx, hy):
    """Departure along the normal of the heights ``zs`` at the sample points of cells from each of the
    cells' two triangulations (corner heights z (k, 4): (0,0), (1,0), (1,1), (0,1); cell sizes hx, hy
    (k,) mm): the larger over the samples of the better one, and whether that is the diagonal
    (0,0)-(1,1)."""
    z00, z10, z11, z01 = (z[:, i, None] for i in range(4))
    hx, hy = hx[:, None], hy[:, None]
    u, v = _U[None], _V[None]
    lo = u >= v                                            # diagonal 00-11: triangles 00-10-11, 00-11-01
    f1 = np.where(lo, z00 + (z10 - z00) * u + (z11 - z10) * v, z00 + (z11 - z01) * u + (z01 - z00) * v)
    g1 = np.where(lo, ((z10 - z00) / hx) ** 2 + ((z11 - z10) / hy) ** 2, ((z11 - z01) / hx) ** 2 + ((z01 - z00) / hy) ** 2)
    lo = u + v <= 1                                        # diagonal 10-01: triangles 00-10-01, 10-11-01
    f2 = np.where(lo, z00 + (z10 - z00) * u + (z01 - z00) * v, z11 + (z11 - z01) * (u - 1) + (z11 - z10) * (v - 1))
    g2 = np.where(lo, ((z10 - z00) / hx) ** 2 + ((z01 - z00) / hy) ** 2, ((z11 - z01) / hx) ** 2 + ((z11 - z10) / hy) ** 2)
    e1 = (np.abs(f1 - zs) / np.sqrt(1 + g1)).max(1)
    e2 = (np.abs(f2 - zs) / np.sqrt(1 + g2)).max(1)
    return np.minimum(e1, e2), e1 <= e2


def _bends(z, zs, hx, hy):
    """Whether the surface bends along X and along Y in each cell: the middles of the bottom edge, the
    centre and the top edge off the lines between their left and right neighbours (along X), and the
    transposed, by more than half ``TOL_MM`` along the normal."""
    z00, z10, z11, z01 = z.T
    c, b, r, t, lft = zs[:, :5].T
    g2 = ((z10 + z11 - z00 - z01) / (2 * hx)) ** 2 + ((z01 + z11 - z00 - z10) / (2 * hy)) ** 2
    n = np.sqrt(1 + g2)
    along_x = np.maximum.reduce([np.abs(b - (z00 + z10) / 2), np.abs(c - (lft + r) / 2), np.abs(t - (z01 + z11) / 2)]) / n
    along_y = np.maximum.reduce([np.abs(lft - (z00 + z01) / 2), np.abs(c - (b + t) / 2), np.abs(r - (z10 + z11) / 2)]) / n
    return along_x > TOL_MM / 2, along_y > TOL_MM / 2


def adaptive_top(heights: Heights, nx: int, ny: int, log=print) -> np.ndarray:
    """Leaf cells (i, j, size x, size y, main diagonal) over ``nx`` × ``ny`` base cells, in lattice
    units; every corner and every split cell's sample height is in ``heights`` after."""
    size = 2 ** (LEVELS + 1)
    I, J = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    cells = np.column_stack([I.ravel() * size, J.ravel() * size, np.full(I.size, size), np.full(I.size, size)])
    leaves = []
    while len(cells):
        ij, sx, sy = cells[:, :2], cells[:, 2], cells[:, 3]
        corners = np.stack([ij, ij + np.column_stack([sx, 0 * sy]), ij + cells[:, 2:4], ij + np.column_stack([0 * sx, sy])], 1)
        z = heights.get(corners.reshape(-1, 2)).reshape(-1, 4)
        quarter = (sx % 4 == 0) & (sy % 4 == 0)
        u = np.where(quarter[:, None], _U[None], np.where(_U[None] % 0.5 == 0, _U[None], 0.5))
        v = np.where(quarter[:, None], _V[None], np.where(_V[None] % 0.5 == 0, _V[None], 0.5))
        pts = ij[:, None, :] + np.stack([u * sx[:, None], v * sy[:, None]], -1).astype(np.int64)
        zs = heights.get(pts.reshape(-1, 2)).reshape(len(cells), -1)
        hx, hy = sx * heights.unit[0], sy * heights.unit[1]
        err, main = _departure(z, zs, hx, hy)
        bx, by = _bends(z, zs, hx, hy)
        last_x, last_y = sx == 4, sy == 4
        can_x, can_y = sx > 2, sy > 2
        fail = err > TOL_MM
        both = ~bx & ~by                                  # bends diagonally: split both ways
        split_x = fail & can_x & (bx | both) & (~last_x | (err > TOL_LAST_MM))
        split_y = fail & can_y & (by | both) & (~last_y | (err > TOL_LAST_MM))
        keep = ~(split_x | split_y)
        leaves.append(np.column_stack([cells[keep], main[keep]]))
        log(f"  stock cells: {len(cells)}, {int(split_x.sum())} split across X, {int(split_y.sum())} across Y")
        nxt = []
        for sel, kx, ky in ((split_x & split_y, 2, 2), (split_x & ~split_y, 2, 1), (~split_x & split_y, 1, 2)):
            c = cells[sel]
            if len(c):
                w, h = c[:, 2] // kx, c[:, 3] // ky
                for a in range(kx):
                    for b in range(ky):
                        nxt.append(np.column_stack([c[:, 0] + a * w, c[:, 1] + b * h, w, h]))
        cells = np.vstack(nxt) if nxt else np.zeros((0, 4), np.int64)
    return np.vstack(leaves)


def _edge_positions(leaves: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(leaf index, lattice position) of every lattice point on the leaves' edges, counter-clockwise
    from each leaf's corner (0, 0): the candidates of its boundary."""
    i, j, sx, sy = leaves[:, 0], leaves[:, 1], leaves[:, 2], leaves[:, 3]
    n = 2 * (sx + sy)
    leaf = np.repeat(np.arange(len(leaves)), n)
    k = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
    a, b = sx[leaf], sy[leaf]
    li, lj = i[leaf], j[leaf]
    x = np.select([k < a, k < a + b, k < 2 * a + b], [li + k, li + a, li + a - (k - a - b)], li)
    y = np.select([k < a, k < a + b, k < 2 * a + b], [lj, lj + (k - a), lj + b], lj + b - (k - 2 * a - b))
    return leaf, np.column_stack([x, y])


def triangles(leaves: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The top's vertices (lattice ij, (n, 2)) and triangles (indices, counter-clockwise from above)."""
    i, j, sx, sy, main = leaves.T
    corners = np.stack([np.column_stack([i, j]), np.column_stack([i + sx, j]), np.column_stack([i + sx, j + sy]),
                        np.column_stack([i, j + sy])], 1)
    vkeys = np.unique(corners[..., 0] * KEY + corners[..., 1])
    leaf, pos = _edge_positions(leaves)
    on = np.isin(pos[:, 0] * KEY + pos[:, 1], vkeys)
    fan = np.bincount(leaf[on], minlength=len(leaves)) > 4           # more than its corners on its edges
    tris = []
    for m, order in ((True, (0, 1, 2, 0, 2, 3)), (False, (0, 1, 3, 1, 2, 3))):
        sel = ~fan & (main.astype(bool) == m)
        tris.append(corners[sel][:, order].reshape(-1, 3, 2))
    keep = on & fan[leaf]
    leaf, pos = leaf[keep], pos[keep]
    first = np.r_[True, leaf[1:] != leaf[:-1]]
    last = np.r_[leaf[1:] != leaf[:-1], True]
    nxt = np.arange(1, len(leaf) + 1)
    nxt[last] = np.flatnonzero(first)                     # each leaf's ring closes on its first vertex
    centre = np.column_stack([i + sx // 2, j + sy // 2])
    tris.append(np.stack([centre[leaf], pos, pos[nxt]], 1))
    tris = np.vstack(tris)
    keys = tris[..., 0] * KEY + tris[..., 1]
    uk, inv = np.unique(keys, return_inverse=True)
    return np.column_stack([uk // KEY, uk % KEY]), inv.reshape(-1, 3)


def solid(leaves: np.ndarray, heights: Heights, z_bottom: float) -> trimesh.Trimesh:
    """Watertight solid: the adaptive top, vertical sides down to ``z_bottom``, a flat bottom."""
    ij, faces = triangles(leaves)
    top = heights.xyz(ij)
    imax, jmax = ij[:, 0].max(), ij[:, 1].max()
    idx = np.arange(len(ij))
    sides = ((ij[:, 1] == 0, ij[:, 0]), ((ij[:, 0] == imax) & (ij[:, 1] > 0), ij[:, 1]),
             ((ij[:, 1] == jmax) & (ij[:, 0] < imax), -ij[:, 0]),
             ((ij[:, 0] == 0) & (ij[:, 1] > 0) & (ij[:, 1] < jmax), -ij[:, 1]))
    ring = np.concatenate([idx[m][np.argsort(key[m])] for m, key in sides])   # counter-clockwise from above
    nb, base = ring.size, len(top)
    bottom = top[ring].copy()
    bottom[:, 2] = z_bottom
    verts = np.vstack([top, bottom, [[top[:, 0].mean(), top[:, 1].mean(), z_bottom]]])
    k = np.arange(nb)
    k1 = (k + 1) % nb
    faces = np.vstack([faces, np.column_stack([ring[k], base + k, base + k1]),
                       np.column_stack([ring[k], base + k1, ring[k1]]),
                       np.column_stack([np.full(nb, base + nb), base + k1, base + k])])
    mesh = trimesh.Trimesh(verts, faces, process=False)
    if not (mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0):
        raise RuntimeError("stock mesh is not a valid closed solid")
    return mesh
