"""The surface a ball-end tool leaves: the lower envelope of its swept balls (scripts/make_samples.py).

A linear move of a ball of radius r sweeps a capsule (the segment between the ball's centres at the
move's ends, thickened by r); from above, a 3-axis ball-end tool removes everything over the lower
surface of the capsules it sweeps, so the surface it leaves at (x, y) is the lowest point over
(x, y) of any capsule: exact, with no sampling along the moves.
"""
from __future__ import annotations

import numpy as np

CELL_MM = 1.0                 # grid cell of the capsule index
PAIRS_PER_CHUNK = 4_000_000   # point-capsule pairs evaluated at once


def lowest_on_capsules(p: np.ndarray, a: np.ndarray, b: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Lowest z of each capsule (a, b, r) on the vertical line through each p (pairwise); +inf off it.

    The capsule's boundary is the cylinder of radius r about the segment, between its ends, and
    the two end spheres: the line enters the capsule through one of them, at the lowest of their
    valid crossings.

    Parameters
    ----------
    p : (n, 2) xy of the vertical lines; a, b : (n, 3) centre segment ends; r : (n,) radii, mm.
    """
    best = np.full(len(p), np.inf)
    for c in (a, b):                                           # end spheres
        h2 = r * r - ((p - c[:, :2]) ** 2).sum(1)
        ok = h2 >= 0
        best[ok] = np.minimum(best[ok], c[ok, 2] - np.sqrt(h2[ok]))
    ab = b - a
    L = np.linalg.norm(ab, axis=1)
    ok = L > 1e-12
    u = ab / np.where(ok, L, 1.0)[:, None]
    d = p - a[:, :2]
    k = (d * u[:, :2]).sum(1)                                  # (q − a)·u = k + ζ u_z, ζ = z − a_z
    qa = 1.0 - u[:, 2] ** 2                                    # |w|² − (w·u)² = r² as a quadratic in ζ
    qb = -2.0 * k * u[:, 2]
    qc = (d * d).sum(1) - k * k - r * r
    disc = qb * qb - 4.0 * qa * qc
    ok &= (qa > 1e-12) & (disc >= 0)
    zeta = (-qb - np.sqrt(np.where(ok, disc, 0.0))) / (2.0 * np.where(ok, qa, 1.0))
    t = k + zeta * u[:, 2]
    ok &= (t >= 0) & (t <= L)
    best[ok] = np.minimum(best[ok], a[ok, 2] + zeta[ok])
    return best


class Sweeps:
    """The capsules of a set of ball moves, indexed over xy.

    Parameters
    ----------
    a, b : (n, 3) ball centres at the start and end of each move, mm.
    r : (n,) ball radii, mm.
    """

    def __init__(self, a: np.ndarray, b: np.ndarray, r: np.ndarray):
        self.a, self.b = np.asarray(a, float), np.asarray(b, float)
        self.r = np.broadcast_to(np.asarray(r, float), (len(self.a),)).copy()
        lo = np.minimum(self.a, self.b)[:, :2] - self.r[:, None]
        hi = np.maximum(self.a, self.b)[:, :2] + self.r[:, None]
        self.lo = lo.min(0) - CELL_MM
        c0, c1 = self._cell(lo), self._cell(hi)
        self.ny = int(c1[:, 1].max()) + 2
        span = c1 - c0 + 1
        count = span[:, 0] * span[:, 1]
        cap = np.repeat(np.arange(len(count)), count)
        off = np.arange(cap.size) - np.repeat(np.cumsum(count) - count, count)
        key = (c0[cap, 0] + off // span[cap, 1]) * self.ny + c0[cap, 1] + off % span[cap, 1]
        order = np.argsort(key, kind="stable")
        self.keys, self.cap = key[order], cap[order]

    def _cell(self, xy: np.ndarray) -> np.ndarray:
        return np.floor((xy - self.lo) / CELL_MM).astype(np.int64)

    def __add__(self, other: "Sweeps") -> "Sweeps":
        return Sweeps(np.vstack([self.a, other.a]), np.vstack([self.b, other.b]), np.concatenate([self.r, other.r]))

    def pairs(self, xy: np.ndarray):
        """The (point, capsule) pairs whose cells meet, in chunks of about ``PAIRS_PER_CHUNK``:
        yields (start, stop, pt, cap, first, has) — the chunk's points [start, stop), each pair's
        point and capsule (a point's pairs contiguous, ``first`` the offset of each point's first,
        ``has`` whether it has any)."""
        c = self._cell(xy)
        key = c[:, 0] * self.ny + c[:, 1]
        inside = (c >= 0).all(1) & (c[:, 1] < self.ny)
        lo = np.searchsorted(self.keys, key, "left")
        n = np.where(inside, np.searchsorted(self.keys, key, "right") - lo, 0)
        start = 0
        while start < len(xy):
            csum = np.cumsum(n[start:])
            stop = start + max(1, int(np.searchsorted(csum, PAIRS_PER_CHUNK)))
            nn = n[start:stop]
            pt = np.repeat(np.arange(start, stop), nn)
            if pt.size:
                cap = self.cap[np.repeat(lo[start:stop] - np.cumsum(nn) + nn, nn) + np.arange(pt.size)]
                yield start, stop, pt, cap, np.cumsum(nn) - nn, nn > 0
            start = stop

    def lower(self, xy: np.ndarray) -> np.ndarray:
        """The surface left at each (x, y): the lowest capsule point over it; +inf where none reaches."""
        xy = np.asarray(xy, float).reshape(-1, 2)
        out = np.full(len(xy), np.inf)
        for start, stop, pt, cap, first, has in self.pairs(xy):
            z = lowest_on_capsules(xy[pt], self.a[cap], self.b[cap], self.r[cap])
            out[start:stop][has] = np.minimum.reduceat(z, first[has])
        return out


def gap(sweeps: Sweeps, points: np.ndarray) -> np.ndarray:
    """Distance from each point to the nearest capsule, less its radius: how far the balls stayed
    from the point (0 where one touched it; the thickness of what they left over it); +inf where
    no capsule's box reaches the point's cell."""
    pts = np.asarray(points, float).reshape(-1, 3)
    out = np.full(len(pts), np.inf)
    for start, stop, pt, cap, first, has in sweeps.pairs(pts[:, :2]):
        a, b = sweeps.a[cap], sweeps.b[cap]
        ab = b - a
        L2 = np.einsum("ij,ij->i", ab, ab)
        t = np.clip(np.einsum("ij,ij->i", pts[pt] - a, ab) / np.where(L2 > 0, L2, 1.0), 0.0, 1.0)
        d = np.linalg.norm(pts[pt] - a - t[:, None] * ab, axis=1) - sweeps.r[cap]
        out[start:stop][has] = np.minimum.reduceat(d, first[has])
    return out
