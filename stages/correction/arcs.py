"""Arcs of a corrected program: their sweep and the least-squares refit through moved chord points.

The chord points of an arc (G2/G3) are moved like vertices, then the arc is refitted: the centre
lies on the perpendicular bisector of the moved end points (so the program stays consistent) at the
position that best fits the moved chord points (algebraic circle fit, linear in the one unknown).
Full circles keep their end on their start and fit the centre freely; arcs over 180° with a short
chord (whose bisector would swing with every micrometre) fit the centre freely through the start.
"""
from __future__ import annotations

import numpy as np

from stages.tables import col as _col
from stages.tables import xyz as _xyz

PLANE_AXES = {17: (0, 1, 2), 18: (2, 0, 1), 19: (1, 2, 0)}  # G17/G18/G19: (first, second, normal) axis


PLANE_AXES_LUT = np.zeros((20, 3), np.int64)
for _pl, _ax in PLANE_AXES.items():
    PLANE_AXES_LUT[_pl] = _ax


def arc_sweep(start, end, centre, plane, ccw):
    """Signed sweep (rad) of arcs as the splitter reads them: CCW positive, same start/end = full."""
    axes = PLANE_AXES_LUT[np.clip(plane, 0, 19)]
    r = np.arange(start.shape[0])
    a0, a1 = axes[:, 0], axes[:, 1]
    th0 = np.arctan2(start[r, a1] - centre[r, a1], start[r, a0] - centre[r, a0])
    th1 = np.arctan2(end[r, a1] - centre[r, a1], end[r, a0] - centre[r, a0])
    sweep = np.where(ccw, np.mod(th1 - th0, 2 * np.pi), -np.mod(th0 - th1, 2 * np.pi))
    return np.where(np.abs(sweep) < 1e-12, np.where(ccw, 2 * np.pi, -2 * np.pi), sweep)


def refit_arcs(blk, arc, end, new, max_move, passes, node_move, node_xyz, frame):
    """New centres (absolute mm) of the arc rows, fitted through their moved chord points."""
    rows = np.flatnonzero(arc)
    na = rows.size
    # start of an arc = new end of the previous motion block (the first block starts where it ends)
    new_start = np.vstack([new[:1], new[:-1]])[rows]
    old_start = _xyz(blk, ("x0_mm", "y0_mm", "z0_mm"))[rows]
    old_end, new_end = end[rows], new[rows]
    old_centre = _xyz(blk, ("cx_mm", "cy_mm", "cz_mm"))[rows]
    plane = _col(blk, "plane", np.int64)[rows]
    bno = _col(blk, "block_no", np.int64)[rows]
    axes = PLANE_AXES_LUT[np.clip(plane, 0, 19)]
    r = np.arange(na)

    # interior chord points of each arc: nodes between two passes that both belong to the arc block
    owner = np.zeros(0, np.int64)
    pts = np.zeros((0, 3))
    if node_move is not None and passes.num_rows > 1:
        pb0 = _col(passes, "block_no", np.int64)
        pb1 = _col(passes, "block_end", np.int64)
        k = np.arange(1, pb0.size)                       # node k joins pass k−1 and pass k
        inner = (pb1[k - 1] == pb0[k])
        cand = k[inner]
        cand_block = pb0[cand]
        pos = np.searchsorted(bno, cand_block)
        posc = np.minimum(pos, na - 1)
        hit = bno[posc] == cand_block
        cand, owner = cand[hit], posc[hit]
        mv = node_move[cand].copy()
        size = np.linalg.norm(mv, axis=1)
        big = size > max_move
        mv[big] *= (max_move / size[big])[:, None]
        pts = node_xyz[cand] + frame + mv / 1000.0

    a0, a1, an = axes[:, 0], axes[:, 1], axes[:, 2]
    sa, sb = new_start[r, a0], new_start[r, a1]
    ba, bb = new_end[r, a0] - sa, new_end[r, a1] - sb
    chord = np.hypot(ba, bb)
    full = chord < 1e-9
    # arcs of more than 180° whose chord is short against the radius: the bisector of the moved
    # end points turns with every micrometre of move, so the centre is fitted freely (through the
    # start, like a full circle) and the end is put back on the circle afterwards
    r_old = np.hypot(old_start[r, a0] - old_centre[r, a0], old_start[r, a1] - old_centre[r, a1])
    sweep_old = arc_sweep(old_start, old_end, old_centre, plane, _col(blk, "motion", np.int64)[rows] == 3)
    free = full | ((np.abs(sweep_old) > np.pi) & (chord < 0.5 * r_old))
    # fallback centre: the old centre carried by the mean in-plane move of the end points
    shift = (new_start - old_start + new_end - old_end) / 2
    fa = old_centre[r, a0] + shift[r, a0] - sa
    fb = old_centre[r, a1] + shift[r, a1] - sb
    with np.errstate(invalid="ignore", divide="ignore"):
        ua, ub = -bb / chord, ba / chord
    t0 = (fa - ba / 2) * ua + (fb - bb / 2) * ub
    # chord points relative to the new start, in the plane
    pa_ = pts[np.arange(owner.size), a0[owner]] - sa[owner] if owner.size else np.zeros(0)
    pb_ = pts[np.arange(owner.size), a1[owner]] - sb[owner] if owner.size else np.zeros(0)
    sq = pa_ ** 2 + pb_ ** 2
    g = 2 * (ua[owner] * pa_ + ub[owner] * pb_)
    r0 = sq - (ba[owner] * pa_ + bb[owner] * pb_)
    sgg = np.bincount(owner, g * g, na)
    sgr = np.bincount(owner, np.nan_to_num(g * r0), na)
    use_fit = ~free & (sgg > 1e-18 * np.maximum(chord, 1e-9) ** 2)
    t = np.where(use_fit, sgr / np.where(use_fit, sgg, 1.0), t0)
    ca = np.where(free, fa, ba / 2 + t * np.nan_to_num(ua))
    cb = np.where(free, fb, bb / 2 + t * np.nan_to_num(ub))
    if free.any():
        # free centre c through the start: |p|² − 2 c·p = 0 in least squares over the chord points
        # and the end point (2×2 normal equations per arc)
        qa = np.concatenate([pa_, ba[free]])
        qb = np.concatenate([pb_, bb[free]])
        qo = np.concatenate([owner, np.flatnonzero(free)])
        qq = qa ** 2 + qb ** 2
        sxx = np.bincount(qo, qa * qa, na)
        sxy = np.bincount(qo, qa * qb, na)
        syy = np.bincount(qo, qb * qb, na)
        rx = np.bincount(qo, qa * qq, na) / 2
        ry = np.bincount(qo, qb * qq, na) / 2
        det = sxx * syy - sxy ** 2
        ok = free & (det > 1e-12 * np.maximum(sxx + syy, 1e-30) ** 2)
        ca = np.where(ok, (syy * rx - sxy * ry) / np.where(ok, det, 1.0), ca)
        cb = np.where(ok, (sxx * ry - sxy * rx) / np.where(ok, det, 1.0), cb)
    out = np.empty((na, 3))
    out[r, a0] = sa + ca
    out[r, a1] = sb + cb
    out[r, an] = new_start[r, an]          # the parser's convention: centre at the start's height
    return out, free & ~full
