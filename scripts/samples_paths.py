"""Toolpath pieces of scripts/make_samples.py: OpenCAMLib raster rows and Z-level loops of a ball, the
contact of each point on the model, and the stretches a strategy keeps (steep, shallow, rest).

A path point is the tool tip (OpenCAMLib's CL point); the ball's centre is the tip + r·Z. A stretch is
a run of consecutive points a strategy keeps, cut as one polyline.
"""
from __future__ import annotations

import numpy as np

from samples_cam import FLUTE_LEN, SAMPLE, crop_surface, densify_rows, douglas_peucker, drop_tips, quiet_fds
from samples_geom import Grid, contact


def raster_rows(surf, diameter: float, ys: np.ndarray, x0: float, x1: float) -> list[np.ndarray]:
    """Drop-cutter rows along X at each y: tips every ``SAMPLE`` mm, steep stretches refined to 3-D
    steps ≤ ``SAMPLE``; (n, 3) per row, x increasing."""
    xs = np.round(np.arange(x0, x1 + 1e-9, SAMPLE), 6)
    X, Y = np.meshgrid(xs, ys)
    Z = drop_tips(surf, diameter, np.column_stack([X.ravel(), Y.ravel()])).reshape(X.shape)
    rows_x, rows_z = densify_rows(surf, diameter, ys, [xs] * len(ys), list(Z), SAMPLE)
    return [np.column_stack([x, np.full(x.size, y), z]) for y, x, z in zip(ys, rows_x, rows_z)]


def level_loops(tris: np.ndarray, diameter: float, z: float, box, sampling: float = 0.5,
                min_sampling: float = 0.01, flat: bool = False) -> list[np.ndarray]:
    """OpenCAMLib adaptive Waterline loops of a ball (or, ``flat``, a flat end mill) at tip height
    ``z`` over the triangles near ``box`` (x0, y0, x1, y1), as (n, 3) closed polylines (the first
    point not repeated).

    The adaptive fibres are ``sampling`` apart, refined down to ``min_sampling`` where the loop
    bends, so the chords between loop points stay within a micron of the exact loop.
    """
    from opencamlib import ocl

    surf = crop_surface(tris, box)
    kind = ocl.CylCutter if flat else ocl.BallCutter
    cutter = kind(float(diameter), FLUTE_LEN)              # keep a reference: OCL stores a pointer
    wl = ocl.AdaptiveWaterline()
    wl.setSTL(surf)
    wl.setCutter(cutter)
    wl.setZ(float(z))
    wl.setSampling(float(sampling))
    wl.setMinSampling(float(min_sampling))
    with quiet_fds():
        wl.run()
        loops = wl.getLoops()
    # OpenCAMLib's threads may start a loop anywhere and list the loops in any order: each loop
    # counter-clockwise from its lowest-x (then lowest-y) point, the loops in the order of those
    loops = [_canonical(np.array([[p.x, p.y, p.z] for p in L])) for L in loops if len(L) > 2]
    return sorted(loops, key=lambda L: (L[0, 0], L[0, 1]))


def _canonical(loop: np.ndarray) -> np.ndarray:
    x, y = loop[:, 0], loop[:, 1]
    if np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) < 0:
        loop = loop[::-1]
    return np.roll(loop, -int(np.lexsort((loop[:, 1], loop[:, 0]))[0]), axis=0)


def contacts(grid: Grid, tips: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Contact point, outward normal and slope (deg) of the ball of ``radius`` whose tips are ``tips``."""
    return contact(grid, np.asarray(tips, float) + [0.0, 0.0, radius], radius)


def path_length(points: np.ndarray) -> np.ndarray:
    """Cumulative 3-D length of a polyline at each of its points."""
    seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(seg)])


def dilate(mask: np.ndarray, points: np.ndarray, dist: float, closed: bool) -> np.ndarray:
    """``mask`` grown by ``dist`` mm of 3-D path length on both sides of each kept run."""
    if dist <= 0 or not mask.any() or mask.all():
        return mask.copy()
    s = path_length(np.vstack([points, points[:1]]) if closed else points)
    total = s[-1]
    s = s[:len(points)]
    kept = s[mask]
    # distance to the nearest kept point along the path (both ways round a closed loop)
    j = np.clip(np.searchsorted(kept, s), 1, kept.size - 1) if kept.size > 1 else np.zeros(s.size, int)
    d = np.minimum(np.abs(s - kept[j]), np.abs(s - kept[np.maximum(j - 1, 0)]))
    if closed:
        d = np.minimum(d, np.minimum(total - s + kept[0], s + total - kept[-1]))
    return mask | (d <= dist)


def runs(mask: np.ndarray, closed: bool) -> list[np.ndarray]:
    """Index arrays of the maximal runs of True; on a closed loop a run may wrap past the end (and
    a loop kept whole is one run that starts at 0 and is marked by its length = len(mask))."""
    n = mask.size
    if not mask.any():
        return []
    if mask.all():
        return [np.arange(n)]
    edges = np.flatnonzero(np.diff(np.concatenate([[0], mask.astype(np.int8), [0]])))
    out = [np.arange(a, b) for a, b in zip(edges[::2], edges[1::2])]
    if closed and mask[0] and mask[-1] and len(out) > 1:
        out[0] = np.concatenate([out.pop(), out[0]])
    return out


def simplify(points: np.ndarray, tol: float) -> np.ndarray:
    """The points Douglas–Peucker keeps within ``tol`` (the CAM tolerance), ends included."""
    return points[douglas_peucker(points, tol)] if len(points) > 2 else points


def climb(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """The stretch in the direction that keeps the material on the tool's right (climb milling with
    M3: inside a pocket counter-clockwise, round a boss clockwise), judged by the contact normals."""
    t = np.gradient(points[:, :2], axis=0)
    left = np.column_stack([-t[:, 1], t[:, 0]])
    return points if np.sum(left * normals[:, :2]) >= 0 else points[::-1]


def min_length(stretches: list[np.ndarray], length: float) -> list[np.ndarray]:
    """Stretches at least ``length`` mm long (3-D): shorter ones are dropped."""
    return [s for s in stretches if len(s) > 1 and path_length(s)[-1] >= length]


def in_box(points: np.ndarray, box) -> np.ndarray:
    """Whether each point's xy lies in ``box`` (x0, y0, x1, y1)."""
    return (points[:, 0] >= box[0]) & (points[:, 0] <= box[2]) & (points[:, 1] >= box[1]) & (points[:, 1] <= box[3])


def resample(loop: np.ndarray, step: float) -> np.ndarray:
    """A closed loop's xy with points at most ``step`` apart (its own points kept), not closed."""
    ring = np.vstack([loop[:, :2], loop[:1, :2]])
    seg = np.linalg.norm(np.diff(ring, axis=0), axis=1)
    n = np.maximum(1, np.ceil(seg / step).astype(int))
    t = np.concatenate([np.arange(k) / k for k in n])
    i = np.repeat(np.arange(len(seg)), n)
    return ring[i] + t[:, None] * (ring[i + 1] - ring[i])


def floor_levels(tris: np.ndarray, box, min_area: float = 5.0) -> list[float]:
    """Heights of the model's horizontal floors (faces facing +Z) that meet ``box``, highest first."""
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    area = 0.5 * np.linalg.norm(n, axis=1)
    up = n[:, 2] > 0.99999 * 2 * area
    c = tris.mean(1)
    up &= in_box(c, box)
    z = np.round(c[up, 2], 3)
    levels = [float(v) for v in np.unique(z) if area[up][z == v].sum() >= min_area]
    return sorted(levels, reverse=True)
