"""Whether points lie inside the volume a tool sweeps along a straight move.

The swept volume of a convex tool along a segment is convex; the tool here is the cutter of
:class:`stages.geometry.cutter.Cutter` with its shank (the cylinder of radius R above the corner's
centre, up to the stick-out). A ball's sweep is a capsule of centres plus the swept shank: both
tests are closed forms. A bull-nose corner is the horizontal disk of corner centres (radius R − rc)
swept along the move and grown by rc: its distance is a one-dimensional convex minimisation.
"""
from __future__ import annotations

import math

import numpy as np

from stages.geometry.cutter import Cutter

GOLDEN_ITERS = 40
_INV_PHI = (math.sqrt(5.0) - 1.0) / 2.0


def _segment_distance(p, a, b):
    """Distance from points p to segments a→b (all (K, 3))."""
    d = b - a
    dd = np.einsum("ij,ij->i", d, d)
    t = np.clip(np.einsum("ij,ij->i", p - a, d) / np.where(dd > 0, dd, 1.0), 0.0, 1.0)
    return np.linalg.norm(p - a - t[:, None] * d, axis=1)


def _in_swept_cylinder(p, c0, c1, radius, height, eps):
    """Points inside the vertical cylinder (radius, from the centre's z up ``height``) swept c0→c1.

    There is a position t on the move where the point lies within ``radius − eps`` of the axis
    horizontally and between ``c_z(t) + eps`` and ``c_z(t) + height`` vertically: the first is a
    quadratic in t (an interval), the second linear, so the test is exact in closed form.
    """
    r = radius - eps
    d = c1[:, :2] - c0[:, :2]
    w = p[:, :2] - c0[:, :2]
    A = np.einsum("ij,ij->i", d, d)
    B = -2.0 * np.einsum("ij,ij->i", w, d)
    C = np.einsum("ij,ij->i", w, w) - r * r
    with np.errstate(invalid="ignore", divide="ignore"):
        disc = B * B - 4 * A * C
        sq = np.sqrt(np.maximum(disc, 0.0))
        moving = A > 1e-18
        ta = np.where(moving, (-B - sq) / (2 * A), 0.0)
        tb = np.where(moving, (-B + sq) / (2 * A), 1.0)
    reach = np.where(moving, disc >= 0, C <= 0)
    lo, hi = np.maximum(ta, 0.0), np.minimum(tb, 1.0)
    reach &= lo <= hi
    dz = c1[:, 2] - c0[:, 2]
    z_lo, z_hi = c0[:, 2] + lo * dz, c0[:, 2] + hi * dz
    zmin, zmax = np.minimum(z_lo, z_hi), np.maximum(z_lo, z_hi)
    return reach & (p[:, 2] >= zmin + eps) & (p[:, 2] <= zmax + height)


def convex_argmin(f, n: int, iters: int = GOLDEN_ITERS) -> np.ndarray:
    """The t in [0, 1] that minimises each of ``n`` convex functions ``f(t)`` (vectorised over the
    n: ``f`` maps (n,) to (n,)), by golden section, the ends included."""
    lo, hi = np.zeros(n), np.ones(n)
    m1, m2 = hi - _INV_PHI, lo + _INV_PHI
    f1, f2 = f(m1), f(m2)
    for _ in range(iters):
        left = f1 <= f2                                  # the minimum lies in [lo, m2]
        hi = np.where(left, m2, hi)
        lo = np.where(left, lo, m1)
        n1 = np.where(left, hi - _INV_PHI * (hi - lo), m2)
        n2 = np.where(left, m1, lo + _INV_PHI * (hi - lo))
        fn = f(np.where(left, n1, n2))
        f1, f2 = np.where(left, fn, f2), np.where(left, f1, fn)
        m1, m2 = n1, n2
    cand = np.stack([0.5 * (lo + hi), np.zeros(n), np.ones(n)], 1)
    values = np.stack([f(cand[:, k]) for k in range(3)], 1)
    return cand[np.arange(n), np.argmin(values, axis=1)]


def _disk_sweep_distance(p, c0, c1, a):
    """Distance from points to the horizontal disk of radius ``a`` swept c0→c1."""
    seg = c1 - c0

    def f(t):
        c = c0 + t[:, None] * seg
        rho = np.hypot(p[:, 0] - c[:, 0], p[:, 1] - c[:, 1])
        return np.hypot(np.maximum(rho - a, 0.0), p[:, 2] - c[:, 2])

    return f(convex_argmin(f, len(p)))


def inside_sweep(points, tip0, tip1, cutter: Cutter, eps: float = 1e-4) -> np.ndarray:
    """Whether each point lies more than ``eps`` inside the tool swept from ``tip0`` to ``tip1``.

    Parameters
    ----------
    points, tip0, tip1 : (K, 3) mm, one move per point (pairs, vectorised)
    cutter : the tool (its shank counts up to the stick-out)
    eps : mm; a point on the sweep's boundary (a neighbouring pass finishing the same surface)
        is not inside

    Returns
    -------
    (K,) bool
    """
    p = np.asarray(points, float).reshape(-1, 3)
    t0 = np.asarray(tip0, float).reshape(-1, 3)
    t1 = np.asarray(tip1, float).reshape(-1, 3)
    rc, R = cutter.corner_mm, cutter.radius_mm
    up = np.array([0.0, 0.0, rc])
    c0, c1 = t0 + up, t1 + up
    shank = _in_swept_cylinder(p, c0, c1, R, max(cutter.stickout_mm - rc, 0.0), eps)
    if rc <= 0:                                          # flat end: the shank reaches the tip
        return shank
    if cutter.kind == "ball":
        corner = _segment_distance(p, c0, c1) < R - eps
    else:
        corner = _disk_sweep_distance(p, c0, c1, R - rc) < rc - eps
    return shank | corner
