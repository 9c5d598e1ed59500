"""The greedy union of postures (seed §6, eq. 6): U_A = ∪ U(θ_k) over the chosen postures.

The upper bound is the union of the machinable regions of every orientation of the grid (nothing
more can be reached with these orientations). Postures are added greedily, each time the one that
adds the most area not yet covered (ties: the higher E), until the union reaches the upper bound
(within ``tolerance`` of it) or ``max_postures`` are chosen: a set cover, for which greedy is
within a factor 1 + ln n of the fewest postures, and what a shop does by hand.
"""
from __future__ import annotations

import numpy as np

BLOCK = 64            # orientations unpacked at a time


def _gains(delta_bits, weight, n_regions):
    """Σ weight_i δ_ki for every orientation k, from the packed δ rows."""
    out = np.empty(len(delta_bits))
    for a in range(0, len(delta_bits), BLOCK):
        d = np.unpackbits(delta_bits[a:a + BLOCK], axis=1, count=n_regions)
        out[a:a + BLOCK] = d @ weight
    return out


def greedy_cover(delta_bits, areas, e=None, max_postures: int = 20, tolerance: float = 0.0) -> dict:
    """Greedy cover of the upper bound.

    Parameters
    ----------
    delta_bits : (n, ceil(m / 8)) uint8, packed δ of n orientations over m micro-regions.
    areas : (m,) mm²; e : (n,) E, for ties; tolerance : fraction of the upper bound that may stay
        uncovered when the cover stops.

    Returns
    -------
    dict: ``chosen`` (N,) orientation indices in the order chosen, ``gain_mm2`` (N,) area each adds,
    ``covered_mm2`` (N,) cumulative, ``upper_mm2`` the upper bound, ``reached`` whether the union
    reached it, ``first`` (m,) the step (0-based) whose posture first machines each region (−1:
    none), ``upper`` (m,) bool, the regions of the upper bound.
    """
    areas = np.asarray(areas, float)
    m = len(areas)
    upper = np.unpackbits(np.bitwise_or.reduce(delta_bits, axis=0), count=m).astype(bool)
    upper_area = float(areas[upper].sum())
    e = np.zeros(len(delta_bits)) if e is None else np.asarray(e, float)
    covered = np.zeros(m, bool)
    first = np.full(m, -1, np.int64)
    chosen, gains, cum = [], [], []
    area = 0.0
    g = _gains(delta_bits, areas, m)
    while len(chosen) < max_postures and area < upper_area * (1 - tolerance) - 1e-12:
        best = np.flatnonzero(g >= g.max() - 1e-12 * max(1.0, g.max()))
        k = int(best[np.argmax(e[best])])
        if g[k] <= 0:
            break
        new = np.unpackbits(delta_bits[k], count=m).astype(bool) & ~covered
        gains.append(float(g[k]))
        # only the bytes holding newly covered regions change the other orientations' gains
        idx = np.flatnonzero(new)
        cols, pos = np.unique(idx // 8, return_inverse=True)
        pick, w = 8 * pos + idx % 8, areas[idx]
        for a in range(0, len(delta_bits), BLOCK):              # in blocks: memory stays small
            g[a:a + BLOCK] -= np.unpackbits(delta_bits[a:a + BLOCK, cols], axis=1)[:, pick] @ w
        first[new] = len(chosen)
        covered |= new
        area = float(areas[covered].sum())
        chosen.append(k)
        cum.append(area)
    return dict(chosen=np.asarray(chosen, np.int64), gain_mm2=np.asarray(gains), covered_mm2=np.asarray(cum),
                upper_mm2=upper_area, reached=bool(area >= upper_area * (1 - tolerance) - 1e-9),
                first=first, upper=upper)
