"""Where the tool is in the material: the virtual machine's own engagement (no render).

Micro-edges of the ball (:data:`N_Z` levels) and of the cylindrical side up to the stick-out (every
:data:`SHANK_DZ_MM`), × :data:`N_PHI` position angles, at each station (a pass's mid point, or with
a deflection step the mid point of each of its equal pieces of at most that length, so that the
deflection's resolution along the path does not follow the program's blocks) are in the material
when they lie below the stock (a height field, ``stock.py``) and outside the tool (ball and side)
swept along every earlier pass (exact tests, ``removal.py``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from stages import InputError
from stages.geometry.paths import Path3
from stages.virtual_machine.removal import SweptPasses

# Grid fine enough that the simulated error has converged: a finishing crescent is only a few
# tenths of a millimetre wide, and on a coarser grid (30 × 96 × 96) the error jumped by ±5 µm from
# pass to pass on the seed's cylinder; at 120 × 360 × 192 it is within 0.5 µm of 240 × 720 × 192.
N_Z = 120         # micro-edge levels over the ball
N_PHI = 360       # position angles of the engagement grid
SHANK_DZ_MM = 0.25  # micro-edge length on the cylindrical side (walls: mm-long straight contacts)
STEP_SLACK = 0.005  # fraction of a deflection step a pass may exceed a whole number of steps by
K_NEAR = 8        # sub-segments tested first for each micro-edge (a speed-up only; 0: none)


@dataclass
class Stations:
    """The pieces of the passes the machine takes one engagement and one deflection each for.

    Attributes
    ----------
    pass_row : (S,) int, the pass (row of the path) of each station
    first, count : (P,) int, each pass's first station and number of stations
    mid : (S, 3) float, ball centre at each station's mid point (mm)
    s0 : (S,) float, path length where each station begins (mm)
    """

    pass_row: np.ndarray
    first: np.ndarray
    count: np.ndarray
    mid: np.ndarray
    s0: np.ndarray

    def at(self, rows: np.ndarray, s_glob: np.ndarray) -> np.ndarray:
        """Station of pass ``rows`` at path length ``s_glob`` (clamped to the pass's own stations)."""
        i = np.searchsorted(self.s0, s_glob, side="right") - 1
        return np.clip(i, self.first[rows], self.first[rows] + self.count[rows] - 1)


def make_stations(path: Path3, step_mm: Optional[float] = None, slack: float = STEP_SLACK) -> Stations:
    """Cut the passes into stations.

    Parameters
    ----------
    path : Path3
    step_mm : float, optional
        ``None``: one station per pass (its mid point). A step: every pass cut into equal pieces of
        at most ``step_mm``, so that the deflection's resolution along the path no longer follows
        the program's blocks (a line cut in two at a via point, or written as one block, machines
        the same; one deflection for a 4 mm climb whose foot is buried in a corner is not).
    slack : float
        A pass up to this fraction of a piece longer than a whole number of pieces keeps that
        number: the machine's resolution must not jump where a via point moved by a µm lengthens a
        0.5 mm pass by a nanometre (it doubled there, and at the cylinder's stock end, where the
        deflection falls 6 µm a piece, the surface jumped by µm).

    Returns
    -------
    Stations
    """
    ln = path.length
    if step_mm is None:
        n = np.ones(len(ln), np.int64)
    else:
        if not step_mm > 0:
            raise InputError(f"virtual machine: deflection_step_mm must be > 0, got {step_mm!r}")
        n = np.maximum(1, np.ceil(ln / float(step_mm) - slack).astype(np.int64))
    row = np.repeat(np.arange(len(ln)), n)
    k = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
    f0, f1 = k / n[row], (k + 1) / n[row]
    d = path.c1 - path.c0
    return Stations(pass_row=row, first=np.cumsum(n) - n, count=n,
                    mid=path.c0[row] + (0.5 * (f0 + f1))[:, None] * d[row],
                    s0=path.s0[row] + f0 * ln[row])


def edge_grid(radius_mm: float, stickout_mm: float):
    """Micro-edge levels of a ball end mill.

    :data:`N_Z` levels over the ball (uniform in height), then the cylindrical side every
    :data:`SHANK_DZ_MM` up to the stick-out.

    Returns
    -------
    zc, kappa, ds : (levels,) float
        Height above the tip (mm), axial immersion angle (rad; the contact angle on the ball, 90° on
        the side) and edge length (mm) of each level.
    """
    R = radius_mm
    zc = (np.arange(N_Z) + 0.5) * R / N_Z                       # heights above the tip
    kappa = np.arccos(np.clip(1 - zc / R, -1, 1))             # axial immersion = contact angle
    ds = R * (np.arccos(np.clip(1 - (zc + 0.5 * R / N_Z) / R, -1, 1))
              - np.arccos(np.clip(1 - (zc - 0.5 * R / N_Z) / R, -1, 1)))
    n_side = int(np.ceil(max(stickout_mm - R, 0.0) / SHANK_DZ_MM))
    zs = R + (np.arange(n_side) + 0.5) * SHANK_DZ_MM
    return (np.concatenate([zc, zs]), np.concatenate([kappa, np.full(n_side, np.pi / 2)]),
            np.concatenate([ds, np.full(n_side, SHANK_DZ_MM)]))


def engagement(path: Path3, stations: Stations, stock_h, radius_mm: float, stickout_mm: float,
               k_near: int = K_NEAR, max_points: int = 400_000, earlier=()) -> np.ndarray:
    """Engaged micro-edges at each station's mid point.

    A micro-edge is engaged when it lies below the stock's top and outside the tool (ball and
    cylindrical side up to the stick-out) of every earlier pass, of this program and of the
    programs machined before it on the same stock. Only the levels below the stock's top around
    a pass are tested (a finishing pass touches a thin band; a wall pass its height).

    Parameters
    ----------
    path : Path3
    stations : Stations
    stock_h : callable
        z_top(x, y) of the stock (:func:`stock.stock_height_fn`).
    radius_mm, stickout_mm : float
    k_near : int
        Sub-segments tested first for each micro-edge (nearest in space); 0 tests every earlier
        sub-segment in reach at once. The answer is the same: only the time changes.
    max_points : int
        Micro-edges tested at a time (bounds the memory).
    earlier : sequence of (Path3, radius_mm, stickout_mm)
        The ball-centre paths and tools of the programs machined before this one, in order.

    Returns
    -------
    (S, levels, N_PHI // 8) uint8
        Packed bits (``np.unpackbits(..., axis=2, count=N_PHI)``), position angles from the feed
        direction, counter-clockwise, levels of :func:`edge_grid`.
    """
    p = path
    R = radius_mm
    zc, kappa, _ = edge_grid(radius_mm, stickout_mm)
    n_lev = len(zc)
    phi = (np.arange(N_PHI) + 0.5) * 2 * np.pi / N_PHI              # from the feed direction, CCW
    d = p.c1 - p.c0
    st = stations.pass_row
    mid = stations.mid
    S = len(mid)
    ang0 = np.arctan2(d[st, 1], d[st, 0])
    # levels that can touch the stock: below the highest stock top on the tool's outer ring
    ring = np.linspace(0.0, 2 * np.pi, 73)[:-1]
    top = np.max(stock_h(mid[:, None, 0] + R * np.cos(ring), mid[:, None, 1] + R * np.sin(ring)), axis=1)
    top = np.maximum(top, stock_h(mid[:, 0], mid[:, 1]))
    height = top - (mid[:, 2] - R)                                    # above the tip
    n_of = np.where(np.isfinite(height), np.searchsorted(zc, height, side="right"), 0).astype(np.int64)
    swept = SweptPasses([*earlier, (p, R, stickout_mm)])
    eng = np.zeros((S, n_lev, (N_PHI + 7) // 8), np.uint8)
    rad = np.where(kappa < np.pi / 2 - 1e-12, R * np.sin(kappa), R)
    dzc = zc - R                                                      # relative to the centre
    cost = np.cumsum(n_of * N_PHI)
    s0 = 0
    while s0 < S:
        s1 = int(np.searchsorted(cost, (cost[s0 - 1] if s0 else 0) + max_points, side="right"))
        s1 = min(max(s1, s0 + 1), S)
        rows = np.repeat(np.arange(s0, s1), n_of[s0:s1])                 # (pass, level) pairs
        lev = np.arange(len(rows)) - np.repeat(np.cumsum(n_of[s0:s1]) - n_of[s0:s1], n_of[s0:s1])
        if len(rows):
            a_ = ang0[rows][:, None] + phi[None, :]
            pts = np.stack(np.broadcast_arrays(mid[rows, None, 0] + rad[lev, None] * np.cos(a_),
                                               mid[rows, None, 1] + rad[lev, None] * np.sin(a_),
                                               mid[rows, None, 2] + dzc[lev, None]), -1).reshape(-1, 3)
            owner = np.repeat(rows, N_PHI)
            inside = pts[:, 2] < stock_h(pts[:, 0], pts[:, 1]) - 1e-9
            removed = np.zeros(len(pts), bool)
            cand = np.flatnonzero(inside)
            removed[cand] = swept.removed(pts[cand], st[owner[cand]], k_near)
            E = (inside & ~removed).reshape(-1, N_PHI)
            eng[rows, lev] = np.packbits(E, axis=1)
        s0 = s1
    return eng

