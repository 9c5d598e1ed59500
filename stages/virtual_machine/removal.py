"""What the earlier passes removed: exact tests of points against the tools swept along them.

The virtual machine's tool is a ball of radius R on a cylinder of radius R reaching the stick-out.
A point is removed before a pass when it lies inside the tool swept along any earlier pass, of
this program or of the programs machined before it on the same stock. The passes are held as
sub-segments of at most :data:`SUB_MM`; a point is tested against the nearest ones in space first
(most points under the stock were cut a row before), then against every earlier one that can
reach it: by 3-D distance where no earlier sub-segment over its plan cell passes at or below it
(then only balls can hold it: a finishing row's neighbours pass above its contact points), else
by plan-view distance with the cylindrical side.
"""
from __future__ import annotations

import numpy as np

SUB_MM = 2.0          # longest sub-segment
CELL_MM = 1.0         # plan cells of the side index


def inside_tool(x, a, ab, R, side):
    """Is point x inside the tool swept along the ball-centre segment a → a + ab (per row)?

    The tool is a ball of radius R on a cylinder of radius R reaching ``side`` above the centre.
    Ball: distance to the segment < R. Side: for the part of the segment whose centre height lies
    in [x_z − side, x_z], the plan-view distance to it < R.

    Parameters
    ----------
    x, a, ab : (n, 3) float
    R, side : float or (n,) float

    Returns
    -------
    (n,) bool
    """
    n = len(x)
    R = np.broadcast_to(np.asarray(R, float), (n,))
    side = np.broadcast_to(np.asarray(side, float), (n,))
    out = _inside_ball(x, a, ab, R)
    # the side only where a centre of the segment lies at or below the point
    k = np.flatnonzero(~out & (np.minimum(a[:, 2], a[:, 2] + ab[:, 2]) <= x[:, 2]))
    if len(k):
        out[k] = _inside_side(x[k], a[k], ab[k], R[k], side[k])
    return out


def _inside_ball(x, a, ab, R):
    xa = x - a
    u = np.clip(np.einsum("ij,ij->i", xa, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-30), 0, 1)
    r = xa - u[:, None] * ab
    return np.einsum("ij,ij->i", r, r) < (R - 1e-6) ** 2


def _inside_side(x, a, ab, R, side):
    """The cylindrical side of :func:`inside_tool`."""
    dz = ab[:, 2]
    flat = np.abs(dz) < 1e-12
    with np.errstate(divide="ignore", invalid="ignore"):
        s_a = np.where(flat, 0.0, (x[:, 2] - side - a[:, 2]) / dz)
        s_b = np.where(flat, 1.0, (x[:, 2] - a[:, 2]) / dz)
    lo = np.clip(np.minimum(s_a, s_b), 0, 1)
    hi = np.clip(np.maximum(s_a, s_b), 0, 1)
    level_ok = np.where(flat, (x[:, 2] >= a[:, 2]) & (x[:, 2] <= a[:, 2] + side),
                        np.maximum(s_a, s_b) >= 0) & (np.minimum(s_a, s_b) <= 1)
    abxy2 = np.maximum(np.einsum("ij,ij->i", ab[:, :2], ab[:, :2]), 1e-30)
    w = np.clip(np.einsum("ij,ij->i", (x - a)[:, :2], ab[:, :2]) / abxy2, lo, hi)
    return level_ok & (np.linalg.norm(a[:, :2] + w[:, None] * ab[:, :2] - x[:, :2], axis=1) < R - 1e-6)


class SweptPasses:
    """The passes of a job up to one program as sub-segments, for :meth:`removed`.

    Parameters
    ----------
    paths : sequence of (Path3, radius_mm, stickout_mm)
        The earlier programs' ball-centre paths and tools, in machining order, then the program's
        own: the earlier programs' sub-segments are owned by pass −1 (before every pass of the
        program), the program's by their pass row.
    """

    def __init__(self, paths):
        owner, a, ab, r, side = [], [], [], [], []
        for k, (path, radius, stickout) in enumerate(paths):
            d = path.c1 - path.c0
            nsub = np.maximum(1, np.ceil(path.length / SUB_MM).astype(np.int64))
            o = np.repeat(np.arange(len(d)), nsub)
            j = np.arange(nsub.sum()) - np.repeat(np.cumsum(nsub) - nsub, nsub)
            step = d[o] / nsub[o, None]
            owner.append(o if k == len(paths) - 1 else np.full(len(o), -1))
            a.append(path.c0[o] + j[:, None] * step)
            ab.append(step)
            r.append(np.full(len(o), float(radius)))
            side.append(np.full(len(o), float(stickout - radius)))        # cylinder above the centre
        self.owner, self.a, self.ab, self.r, self.side = map(np.concatenate, (owner, a, ab, r, side))
        order = np.argsort(self.owner, kind="stable")       # sub-segments by owner: a prefix is "earlier"
        self.owner, self.a, self.ab, self.r, self.side = (v[order] for v in (self.owner, self.a, self.ab, self.r,
                                                                              self.side))
        self.mid = self.a + 0.5 * self.ab
        half = 0.5 * float(np.linalg.norm(self.ab, axis=1).max(initial=0.0))
        self.reach = float(self.r.max(initial=0.0)) + half + 1e-6
        self._trees = (0, None, None)
        if len(self.owner):
            self._side_index()

    def _side_index(self):
        """Per plan cell, the sub-segments whose side can reach into it, sorted by owner, with the
        running lowest centre height: the lowest any earlier sub-segment passes over the cell."""
        lo = np.minimum(self.a, self.a + self.ab)
        hi = np.maximum(self.a, self.a + self.ab)
        self.lo = (lo[:, :2] - self.r[:, None]).min(0) if len(lo) else np.zeros(2)
        c0 = np.floor((lo[:, :2] - self.r[:, None] - self.lo) / CELL_MM).astype(np.int64)
        c1 = np.floor((hi[:, :2] + self.r[:, None] - self.lo) / CELL_MM).astype(np.int64)
        self.shape = (int(c1[:, 0].max(initial=0)) + 1, int(c1[:, 1].max(initial=0)) + 1)
        nx, ny = c1[:, 0] - c0[:, 0] + 1, c1[:, 1] - c0[:, 1] + 1
        k = np.repeat(np.arange(len(c0)), nx * ny)
        off = np.arange(k.size) - np.repeat(np.cumsum(nx * ny) - nx * ny, nx * ny)
        cell = (c0[k, 0] + off % nx[k]) * self.shape[1] + c0[k, 1] + off // nx[k]
        n_own = int(self.owner.max(initial=-1)) + 2
        key = cell * n_own + (self.owner[k] + 1)
        o = np.argsort(key, kind="stable")
        self.key, zmin = key[o], lo[k[o], 2]
        first = np.r_[True, np.diff(self.key // n_own) != 0]
        seg = np.cumsum(first) - 1
        # running minimum within each cell's run: each run offset below the last by more than the
        # heights' span (exact to ~1e-8 mm for a million cells)
        span = float(np.ptp(zmin)) + 1.0 if len(zmin) else 1.0
        shift = seg * 2.0 * span
        self.run_min = np.minimum.accumulate(zmin - shift) + shift
        self.n_own = n_own

    def _lowest_before(self, pts, before):
        """Lowest centre height of the sub-segments owned before ``before`` whose side reaches
        each point's cell (+inf where none)."""
        c = np.floor((pts[:, :2] - self.lo) / CELL_MM).astype(np.int64)
        ok = (c >= 0).all(1) & (c[:, 0] < self.shape[0]) & (c[:, 1] < self.shape[1])
        cell = c[:, 0] * self.shape[1] + c[:, 1]
        at = np.searchsorted(self.key, cell * self.n_own + (before + 1), side="left") - 1
        hit = ok & (at >= 0)
        at = np.where(hit, at, 0)
        hit &= self.key[at] // self.n_own == cell
        return np.where(hit, self.run_min[at], np.inf)

    def _test(self, pts, idx, before, pairs, out, side=True):
        """Mark ``out[idx[i]]`` where the pair (i, sub-segment j) removes it and j is earlier."""
        i, j = pairs
        ok = self.owner[j] < before[i]
        i, j = i[ok], j[ok]
        test = inside_tool if side else (lambda x, a, ab, r, s: _inside_ball(x, a, ab, r))
        out[idx[i[test(pts[i], self.a[j], self.ab[j], self.r[j], self.side[j])]]] = True

    def _trees_before(self, before_max: int):
        """KD-trees (3-D and plan) of the sub-segments owned before ``before_max`` (the candidates
        of a chunk of stations; later passes are never candidates), and their count."""
        from scipy.spatial import cKDTree
        n = int(np.searchsorted(self.owner, before_max, side="left"))
        if self._trees[0] != n or self._trees[1] is None:
            self._trees = (n, cKDTree(self.mid[:n]), cKDTree(self.mid[:n, :2])) if n else (0, None, None)
        return self._trees

    def removed(self, pts: np.ndarray, before: np.ndarray, k_near: int = 8) -> np.ndarray:
        """Whether each point (n, 3) lies inside the tool swept along a sub-segment owned before
        ``before`` (n,) (the pass row of the station it belongs to)."""
        from scipy.spatial import cKDTree
        out = np.zeros(len(pts), bool)
        if not len(pts):
            return out
        n, tree3, tree2 = self._trees_before(int(before.max()))
        if not n:
            return out
        idx = np.arange(len(pts))
        if k_near:
            kn = min(k_near, n)
            _, near = tree3.query(pts, k=kn)
            self._test(pts, idx, before, (np.repeat(idx, kn), near.reshape(-1)), out)
        rest = np.flatnonzero(~out)
        low = self._lowest_before(pts[rest], before[rest]) <= pts[rest, 2]
        for sel, side in ((rest[~low], False), (rest[low], True)):
            if not len(sel):
                continue
            q, tree = (pts[sel, :2], tree2) if side else (pts[sel], tree3)
            sdm = tree.sparse_distance_matrix(cKDTree(q), self.reach, output_type="ndarray")
            j, i = sdm["i"].astype(np.int64), sdm["j"].astype(np.int64)
            self._test(pts[sel], sel, before[sel], (i, j), out, side)
        return out
