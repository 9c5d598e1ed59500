"""Cross-sections of the machined bar: sides, face orientation and twist, thickness.

A section is one row of the height map, r(θ_j) at equally spaced θ_j over the full circle.
"""
from __future__ import annotations

import numpy as np


def face_minima(r, prominence_mm: float) -> np.ndarray:
    """Column indices of the faces of one section (the lowest point of each), circular.

    Local minima of r(θ) belong to one face unless the ridge between neighbours rises at least
    ``prominence_mm`` above both: a twisted blade's face is many cuts meeting at µm ridges, or an
    arc of constant radius whose equal minima scipy's prominence would count one by one.
    """
    from scipy.signal import find_peaks
    r = np.asarray(r, dtype=float)
    k = int(np.argmax(r))                       # start at the highest point: every minimum is interior
    x = np.roll(r, -k)
    cand = find_peaks(-np.append(x, x[0]))[0]
    if cand.size == 0:
        return cand
    ridge = np.maximum.reduceat(x, cand)        # highest point from each minimum to the next
    ridge[-1] = x[0]                            # the last one wraps over the highest point
    low = np.maximum(x[cand], x[np.roll(cand, -1)])
    sep = ridge - low >= prominence_mm          # a face ends after minimum i
    if not sep.any():
        return np.zeros(0, dtype=int)           # round within the prominence
    group = np.concatenate([[0], np.cumsum(sep[:-1])])
    order = np.lexsort((x[cand], group))
    first = np.unique(group[order], return_index=True)[1]
    return np.sort((cand[order[first]] + k) % r.size)


def count_sides(r, prominence_mm: float) -> np.ndarray:
    """Number of faces of each section (rows of ``r``), see ``face_minima``."""
    r = np.atleast_2d(r)
    return np.array([face_minima(row, prominence_mm).size for row in r], dtype=int)


def harmonics(r, workpiece_radius_mm: float, pmax: int) -> np.ndarray:
    """Fourier coefficients 0…pmax over θ of the depth of cut (R_W - r) of each row, (rows, pmax + 1).

    A p-gon's faces at angles ψ + 2πk/p give coefficient p the phase -pψ.
    """
    depth = workpiece_radius_mm - np.atleast_2d(r)
    return np.fft.rfft(depth, axis=1)[:, :pmax + 1] / depth.shape[1]


def face_orientation(c_p, p: int) -> np.ndarray:
    """The orientation ψ (rad, continuous along the rows) of a p-fold section from its p-th coefficient."""
    return np.unwrap(-np.angle(np.asarray(c_p))) / p


def twist_deg_per_mm(z_mm, c_p, p: int) -> float:
    """Rate at which the faces turn along the axis, degrees per mm (+: counter-clockwise seen from +z
    as z grows): the least-squares slope of the face orientation."""
    psi = face_orientation(c_p, p)
    z = np.asarray(z_mm, dtype=float)
    if p < 1 or z.size < 2:
        return 0.0
    return float(np.degrees(np.polyfit(z, psi, 1)[0]))


def section_xy(r, theta):
    """Section outline points, mm."""
    r = np.asarray(r, dtype=float)
    return r * np.cos(theta), r * np.sin(theta)


def caliper_width(r, theta) -> float:
    """Least width of a section between two parallel lines (its thickness), mm.

    Exact for the polygon of the section's points: the least width of a convex polygon is across
    one of its edges, to the vertex farthest from it, which is found by the edges' normal angles.
    """
    from scipy.spatial import ConvexHull
    pts = np.column_stack(section_xy(r, theta))
    V = pts[ConvexHull(pts).vertices]            # counter-clockwise
    E = np.roll(V, -1, axis=0) - V
    n = np.column_stack([E[:, 1], -E[:, 0]]) / np.hypot(E[:, 0], E[:, 1])[:, None]   # outward
    a = np.unwrap(np.arctan2(n[:, 1], n[:, 0]))  # increasing by 2π over the hull
    H = len(V)
    # vertex i lies between edges i-1 and i: the support vertex in direction γ is where γ falls
    aa = np.concatenate([a - 2 * np.pi, a, a + 2 * np.pi])
    m = np.searchsorted(aa, a + np.pi) % H
    return float(np.min(np.einsum("ij,ij->i", n, V - V[m])))


class SectionStats:
    """Figures of the whole part gathered chunk by chunk: the depth harmonics of every row, the
    least and largest radius, and the full rows of ``keep_rows`` (the analysed sections)."""

    def __init__(self, nz: int, workpiece_radius_mm: float, keep_rows, pmax: int):
        self.rw, self.pmax = workpiece_radius_mm, pmax
        self.c = np.zeros((nz, pmax + 1), dtype=complex)
        self.keep = np.unique(np.asarray(keep_rows, dtype=int))
        self.rows: dict[int, np.ndarray] = {}
        self.r_min, self.r_max = np.inf, -np.inf

    def add(self, i0: int, r: np.ndarray) -> None:
        self.c[i0:i0 + len(r)] = harmonics(r, self.rw, self.pmax)
        self.r_min = min(self.r_min, float(r.min()))
        self.r_max = max(self.r_max, float(r.max()))
        for i in self.keep[(self.keep >= i0) & (self.keep < i0 + len(r))]:
            self.rows[int(i)] = r[i - i0].copy()

    def figures(self, z_mm, theta, prominence_mm: float) -> dict:
        """sides (the most common count over the kept sections, and their range), twist, thickness."""
        keep = sorted(self.rows)
        R = np.array([self.rows[i] for i in keep])
        sides = count_sides(R, prominence_mm)
        vals, counts = np.unique(sides, return_counts=True)
        p = int(vals[np.argmax(counts)])
        twist = twist_deg_per_mm(z_mm, self.c[:, p], p) if 1 <= p <= self.pmax else None
        widths = [caliper_width(row, theta) for row in R]
        return {"sides": p, "sides_range": [int(sides.min()), int(sides.max())],
                "twist_deg_per_mm": twist, "min_thickness_mm": float(min(widths)),
                "max_radius_mm": self.r_max, "min_radius_mm": self.r_min}
