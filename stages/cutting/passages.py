"""The tooth passages that finish a surface point: which pass leaves it (kernel of stage ``errors``).

A flute passes a surface point C once per spindle revolution while the tool goes by: the surface
there is cut by discrete tooth passages, within a revolution or so of the moment the tool is
nearest C. Each passage carries the deflection of the pass the tool is on at that moment. On a
pass shorter than the feed per revolution (CAM's 0.05 mm steps over a pocket corner or a boss
foot) those passages belong to its neighbours along the path, and the deepest of them leaves the
surface: a 25 µm pass after a 140 µm rest-material cut is finished with the heavy pass's
deflection, and the heavy pass's own deflected surface is re-cut by the light passes around it.
The seed's render picks one pass per generating point C from the nominal sweeps; this module
completes it: the material left at C is the minimum, over the passes of the path within
``PASSAGE_REVS`` revolutions of feed of C, of

    s_j + e_j(C)          (µm, along the surface normal at C)

with s_j the nominal stand-off of pass j's sweep (the part within the window) from C and e_j(C)
its error at C (``errors.machining_error``: deflection at the spindle angle its flutes pass C,
projected on C's normal, plus shape error at its contact angle to C and runout).

Geometry: the tool is convex and axisymmetric (ball, bull-nose, flat end mill with its cylindrical
side up to the stick-out), so the signed distance from a point to the tool moved along a straight
segment is a convex function of the position along it; it is minimised by golden-section search
(to 1e-10 of the segment), vectorised over (point, segment) pairs.
"""
from __future__ import annotations


import numpy as np

from stages.geometry.clearance import convex_argmin
from stages.geometry.cutter import Cutter

GOLDEN_ITERS = 48          # (√5 − 1)/2 ^ 48 ≈ 1e-10 of the move length


def sweep_distance(points: np.ndarray, tip0: np.ndarray, tip1: np.ndarray, cutter: Cutter):
    """Distance from each point to the tool swept from ``tip0`` to ``tip1`` (pairs, vectorised).

    Parameters
    ----------
    points, tip0, tip1 : ndarray (K, 3)

    Returns
    -------
    dist : ndarray (K,) mm (negative inside)
    t : ndarray (K,) position along the move of the nearest tool position, in [0, 1]
    contact_deg, height_mm : ndarray (K,)
    normal : ndarray (K, 3) outward tool normal at the nearest point
    """
    seg = tip1 - tip0

    def f(t):
        return cutter.distance(points - tip0 - t[:, None] * seg)[0]

    t = convex_argmin(f, len(points), GOLDEN_ITERS)
    dist, q, height, normal = cutter.distance(points - tip0 - t[:, None] * seg)
    return dist, t, q, height, normal


# a flute passes C within half a revolution of the nominal passage; the passages one revolution
# before and after it also sweep C (they sit one feed per revolution away along the path)
PASSAGE_REVS = 1.5


def path_chains(tip0: np.ndarray, tip1: np.ndarray, usable: np.ndarray):
    """Path length at the start of each move and its chain (moves joined end to start).

    Parameters
    ----------
    tip0, tip1 : ndarray (P, 3), moves in execution order
    usable : ndarray (P,) bool, moves that cut (feed moves); the others break the chain

    Returns
    -------
    s0 : ndarray (P,) path length at each move's start (mm, cumulative over usable moves)
    chain : ndarray (P,) int, chain id (-1 for moves that are not usable)
    """
    length = np.linalg.norm(tip1 - tip0, axis=1) * usable
    s0 = np.concatenate([[0.0], np.cumsum(length)[:-1]])
    joined = np.zeros(len(tip0), bool)
    joined[1:] = usable[1:] & usable[:-1] & (np.linalg.norm(tip0[1:] - tip1[:-1], axis=1) < 1e-6)
    chain = np.cumsum(~joined) - 1
    return s0, np.where(usable, chain, -1)


def reaches_inside(t: np.ndarray, ta: np.ndarray, tb: np.ndarray) -> np.ndarray:
    """Whether a neighbouring move reaches the point from inside its extent (bool per pair).

    A move whose tool is nearest the point at one of its own ends (``t`` clamped at 0 with the
    window starting at the move's start ``ta`` = 0, or at 1 with ``tb`` = 1: the point lies beyond
    the move) reaches it only from the vertex it shares with the adjacent move of the chain. There
    the tool's deflection cannot change (the modes take 1/(ζ·ωn), ≈ 6 ms or 1.5 tooth passages on
    the sample, to follow a change of force), so that move's own deflection does not act on the
    point: the adjacent move's passages, which do reach it, carry it.
    """
    return ~(((t <= 0.0) & (ta <= 1e-12)) | ((t >= 1.0) & (tb >= 1.0 - 1e-12)))


def passage_pairs(owner: np.ndarray, s_c: np.ndarray, reach: np.ndarray, s0: np.ndarray,
                  length: np.ndarray, chain: np.ndarray, known: np.ndarray):
    """Moves of the owner's chain (other than the owner) within ``reach`` of path position ``s_c``
    whose error is ``known`` (a move without it still joins the chain).

    Returns
    -------
    row, move : ndarray (K,) int, the point's row and the move
    ta, tb : ndarray (K,) the part of the move inside [s_c − reach, s_c + reach] (fractions)
    """
    from stages.geometry.sweeps import ragged_ranges
    lo, hi = s_c - reach, s_c + reach
    # moves are in execution order, so s0 is non-decreasing: the moves overlapping [lo, hi]
    first = np.searchsorted(s0 + length, lo, side="left")
    last = np.searchsorted(s0, hi, side="right")
    count = np.maximum(last - first, 0)
    move = ragged_ranges(first, count)
    row = np.repeat(np.arange(len(owner)), count)
    keep = (move != owner[row]) & (chain[move] == chain[owner[row]]) & (length[move] > 0) & known[move]
    row, move = row[keep], move[keep]
    ta = np.clip((lo[row] - s0[move]) / length[move], 0.0, 1.0)
    tb = np.clip((hi[row] - s0[move]) / length[move], 0.0, 1.0)
    keep = tb > ta
    return row[keep], move[keep], ta[keep], tb[keep]
