"""What the finishing tools meet (scripts/make_samples.py), measured by brute force and independently of
the pipeline: at every cutting point of a finishing program, the contact point of its ball on the
nominal model, and the stock's thickness from there along the model's normal to the stock mesh.
"""
from __future__ import annotations

import re

import numpy as np

from samples_geom import Grid, contact, ray_exit

REACH_MM = 3.0        # thicker stock than this is reported as this (rest material, not an allowance)
EDGE_MM = 1.0         # contacts this near the stock's cut sides are left out (the ray may leave through one)


def program_points(text: str) -> tuple[np.ndarray, np.ndarray]:
    """End points of the G1 moves of an NC program (absolute, modal, tool tip) and their feed: the
    points the program cuts through. Returns (n, 3) tips and (n,) feeds, mm and mm/min."""
    pos, g, f = np.full(3, np.nan), None, np.nan
    tips, feeds = [], []
    for line in text.splitlines():
        line = re.sub(r"\(.*?\)", "", line).split(";")[0]
        words = re.findall(r"([A-Z])([-+]?\d*\.?\d+)", line)
        for a, v in words:
            if a == "G" and int(float(v)) in (0, 1, 2, 3):
                g = int(float(v))
            elif a == "F":
                f = float(v)
        new = pos.copy()
        for a, v in words:
            if a in "XYZ":
                new["XYZ".index(a)] = float(v)
        if g == 1 and np.isfinite(new).all() and not np.array_equal(new, pos):
            tips.append(new)
            feeds.append(f)
        pos = new
    return np.array(tips), np.array(feeds)


def allowance_met(nominal: Grid, stock: Grid, tips: np.ndarray, radius: float) -> dict:
    """Stock thickness along the model's normal at the contact points of a ball at ``tips``.

    Parameters
    ----------
    nominal : the design model's triangles (a 3-D :class:`Grid`).
    stock : the stock mesh's triangles (a 2-D :class:`Grid` of columns).
    tips : (n, 3) tool tips; radius : the ball's radius, mm.

    Returns
    -------
    dict with ``thickness`` (n,) mm (NaN off the stock or within ``EDGE_MM`` of its sides,
    ``REACH_MM`` where thicker), ``slope_deg``,
    ``contact`` (n, 3) and ``normal`` (n, 3).
    """
    cp, n, slope = contact(nominal, np.asarray(tips, float) + [0, 0, radius], radius)
    ok = np.isfinite(cp).all(1)
    t = np.full(len(cp), np.nan)
    # start a hair inside the model so a stock face touching it still counts as crossed
    t[ok] = ray_exit(stock, cp[ok] - 1e-6 * n[ok], n[ok], REACH_MM) - 1e-6
    lo, hi = stock.tris.min((0, 1)), stock.tris.max((0, 1))
    inside = ok & (cp[:, 0] > lo[0] + EDGE_MM) & (cp[:, 0] < hi[0] - EDGE_MM) \
        & (cp[:, 1] > lo[1] + EDGE_MM) & (cp[:, 1] < hi[1] - EDGE_MM)
    t[~inside] = np.nan
    t[inside & ~np.isfinite(t)] = REACH_MM
    return {"thickness": t, "slope_deg": slope, "contact": cp, "normal": n}


def summary(t: np.ndarray) -> dict:
    """Median, 95th percentile and maximum of the finite thicknesses, mm, and how many points."""
    t = t[np.isfinite(t)]
    if t.size == 0:
        return {"points": 0}
    return {"points": int(t.size), "median_mm": round(float(np.median(t)), 4),
            "p5_mm": round(float(np.percentile(t, 5)), 4), "p95_mm": round(float(np.percentile(t, 95)), 4),
            "max_mm": round(float(t.max()), 4)}


def exact_thickness(height, points: np.ndarray, normals: np.ndarray, reach: float = REACH_MM,
                    step: float = 0.002) -> np.ndarray:
    """The same thickness on the exact surface ``height`` (xy → z, the semi-finishing sweeps' lower
    envelope) instead of the mesh: the first ``step`` along each normal where the point rises above
    it, refined by bisection to 0.1 µm; ``reach`` where none within it."""
    p, n = np.asarray(points, float), np.asarray(normals, float)
    out = np.full(len(p), reach)
    todo = np.arange(len(p))
    for t in np.arange(step, reach + step / 2, step):
        if not todo.size:
            break
        q = p[todo] + t * n[todo]
        above = q[:, 2] > height(q[:, :2])
        out[todo[above]] = t
        todo = todo[~above]
    hit = out < reach
    a, b = out[hit] - step, out[hit]
    for _ in range(14):
        m = 0.5 * (a + b)
        q = p[hit] + m[:, None] * n[hit]
        above = q[:, 2] > height(q[:, :2])
        b = np.where(above, m, b)
        a = np.where(above, a, m)
    out[hit] = 0.5 * (a + b)
    return out
