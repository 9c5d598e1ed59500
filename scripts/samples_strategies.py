"""The two machining strategies of the sample process (scripts/make_samples.py), written through a
:class:`samples_moves.Toolpath`: a zig-zag raster along X over the stretches a mask keeps, and Z-level
contours (waterline stretches, top level first, climb).
"""
from __future__ import annotations

import itertools

import numpy as np

from samples_moves import LEAD_MM, Toolpath


# ------------------------------------------------------------------------------------- raster
def zigzag_chains(rows: list[list[np.ndarray]]) -> list[list[np.ndarray]]:
    """The stretches of consecutive rows that overlap in X, as zig-zag chains (each stretch in the
    direction it is cut: the first of a chain towards +X, then alternately).

    Parameters
    ----------
    rows : per row, in increasing Y, its stretches (each (n, 3), X increasing).
    """
    left = [list(r) for r in rows]
    chains = []
    for k in range(len(left)):
        while left[k]:
            s = left[k].pop(0)
            chain, fwd, j = [s], True, k
            while j + 1 < len(left):
                lo, hi = s[:, 0].min(), s[:, 0].max()
                cand = [c for c in left[j + 1] if c[:, 0].max() >= lo and c[:, 0].min() <= hi]
                if not cand:
                    break
                end_x = s[-1, 0] if fwd else s[0, 0]
                nxt = min(cand, key=lambda c: abs((c[-1, 0] if fwd else c[0, 0]) - end_x))
                left[j + 1] = [c for c in left[j + 1] if c is not nxt]
                s, fwd, j = nxt, not fwd, j + 1
                chain.append(s)
            chains.append([c if i % 2 == 0 else c[::-1] for i, c in enumerate(chain)])
    return chains


def nearest_first(items: list, start_of, end_of, pos) -> list:
    """``items`` reordered greedily: each next one starts nearest to where the previous ended."""
    todo, out = list(items), []
    while todo:
        p = np.zeros(3) if pos is None else pos
        i = int(np.argmin([np.linalg.norm(start_of(c)[:2] - p[:2]) for c in todo]))
        out.append(todo.pop(i))
        pos = end_of(out[-1])
    return out


def write_raster(tp: Toolpath, rows: list[list[np.ndarray]], step: float) -> dict:
    """Zig-zag raster over the stretches of each row, consecutive rows joined by a straight feed move
    where it is short and free, else by a retract. Returns counts for the console."""
    chains = nearest_first(zigzag_chains(rows), lambda c: c[0][0], lambda c: c[-1][-1], tp.pos)
    for chain in chains:
        tp.retract_to(chain[0][0])
        for i, s in enumerate(chain):
            if i:
                tp.link(s[0], max_feed_link=3.0 * step)
            for p in s[1:]:
                tp.cut(p)
    return {"chains": len(chains), "stretches": sum(len(c) for c in chains)}


# ------------------------------------------------------------------------------------- levels
def _tangent(s: np.ndarray, at_end: bool) -> np.ndarray:
    p = s[::-1] if at_end else s
    for q in p[1:]:
        d = (q - p[0])[:2]
        if np.linalg.norm(d) > 0.02:
            t = d / np.linalg.norm(d)
            return -t if at_end else t
    return np.array([1.0, 0.0])


def _lead(tp: Toolpath, b: np.ndarray, t: np.ndarray):
    """The free end of a straight lead move onto (or off) the stretch at ``b``, square to it on its
    air side (left of the cutting direction ``t`` for climb, else right); None where no length of
    ``LEAD_MM`` is free."""
    left = np.array([-t[1], t[0], 0.0])
    for length in LEAD_MM:
        for air in (left, -left):          # the right: a stretch cut backwards (zig-zag)
            p = b + length * air
            if tp.free_line(p, b):
                return p
    return None


def _closed(s: np.ndarray) -> bool:
    return len(s) > 3 and bool(np.allclose(s[0], s[-1]))


def _start_near(s: np.ndarray, p: np.ndarray, zigzag: bool):
    """``s`` begun as near ``p`` as it may be: a closed loop at its nearest vertex, an open stretch
    reversed if ``zigzag`` and its end is nearer. Returns the stretch and the distance to ``p``."""
    if _closed(s):
        ring = s[:-1]
        k = int(np.argmin(np.linalg.norm(ring - p, axis=1)))
        ring = np.roll(ring, -k, axis=0)
        return np.vstack([ring, ring[:1]]), float(np.linalg.norm(ring[0] - p))
    if zigzag and np.linalg.norm(s[-1] - p) < np.linalg.norm(s[0] - p):
        s = s[::-1]
    return s, float(np.linalg.norm(s[0] - p))


def level_chains(levels: list[list[np.ndarray]], join_mm: float, zigzag: bool) -> list[tuple[int, list[np.ndarray]]]:
    """Stretches of consecutive levels that start within ``join_mm`` of where the one above ended,
    as chains (down a wall, round a corner); ``zigzag`` lets an open stretch run backwards to do so.
    Returns the chains with the level each begins on."""
    left = [list(lv) for lv in levels]
    chains = []
    for k in range(len(left)):
        while left[k]:
            chain = [left[k].pop(0)]
            for j in range(k + 1, len(left)):
                best = None
                for i, c in enumerate(left[j]):
                    c2, d = _start_near(c, chain[-1][-1], zigzag)
                    if d <= join_mm and (best is None or d < best[0]):
                        best = (d, i, c2)
                if best is None:
                    break
                left[j].pop(best[1])
                chain.append(best[2])
            chains.append((k, chain))
    return chains


def write_levels(tp: Toolpath, levels: list[list[np.ndarray]], step_down: float, zigzag: bool = False) -> dict:
    """Z-level contours (or offset rings): level by level (top first) its stretches, chained level to level
    where the next starts within 2 mm of the last end (a closed loop at its nearest vertex; with
    ``zigzag`` an open stretch may run backwards) and joined there by a straight feed move where
    free; chains begin and end on straight lead moves (at the plunge feed) square to the stretch in
    the air and are reached by a retract. Returns counts for the console."""
    # level by level, nearest first within a level: a chain never runs under stock a higher level
    # still has to remove (a wall's whole height on the flutes)
    chains = []
    for k, group in itertools.groupby(level_chains([lv for lv in levels if lv], 2.0 + step_down, zigzag),
                                      key=lambda kc: kc[0]):
        chains += nearest_first([c for _, c in group], lambda c: c[0][0], lambda c: c[-1][-1],
                                chains[-1][-1][-1] if chains else tp.pos)
    n_closed = n_open = 0
    for chain in chains:
        for i, s in enumerate(chain):
            if _closed(s):
                n_closed += 1
            else:
                n_open += 1
            if i and np.linalg.norm(tp.pos - s[0]) <= 2.0 + step_down and tp.free_line(tp.pos, s[0]):
                tp.cut(s[0])
                tp.links["feed"] += 1
            else:
                if i and not _closed(chain[i - 1]):
                    _lead_out(tp, chain[i - 1])
                if _closed(s) and tp.pos is not None:
                    s = _start_near(s, tp.pos, False)[0]
                lead = _lead(tp, s[0], _tangent(s, False))
                tp.retract_to(s[0] if lead is None else lead)
                tp.cut(s[0], feed=tp.plunge)
            for p in s[1:]:
                tp.cut(p)
        if not _closed(chain[-1]):
            _lead_out(tp, chain[-1])
    return {"chains": len(chains), "closed": n_closed, "open": n_open}


def _lead_out(tp: Toolpath, s: np.ndarray) -> None:
    lead = _lead(tp, s[-1], _tangent(s, True))
    if lead is not None:
        tp.cut(lead, feed=tp.plunge)
