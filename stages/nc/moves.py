"""Motion blocks → passes (linear moves), timed from the feed.

Seed 000 para 0050–0051: arcs are handled as sets of short linear moves, consecutive moves with
little change in direction or short length may be merged into one pass, long moves split further.
Here:

- arcs (G2/G3, helical included) become chords whose sagitta stays within ``split.chord_tol_mm``;
- cutting moves longer than ``split.max_pass_mm`` (by more than :data:`PIECE_SLACK` of it, so that a
  corrected program splits as the original did) are cut into equal pieces;
- blocks whose end is a via point inside a pass (``via_only``: ``correct.corner_via_mm``, a cut
  the parse stage makes beside a path corner) are joined with the next block into one pass, so the
  passes are those of the uncut program, while the via point lies within ``chord_tol_mm`` of the
  joined pass; one the correction has moved off it (a corrected program, the next round) is a
  vertex of the path and a pass boundary;
- runs of short consecutive cutting moves are merged into passes no longer than
  ``split.merge_max_mm``, but only where every merged vertex stays within ``chord_tol_mm`` of the
  merged pass, so merging never moves the path by more than the chord tolerance;
- a pass keeps ``block_no``/``line_no`` of its first block and ``block_end`` of its last;
- ``t_start_s``/``t_end_s`` accumulate from the program start: cutting moves at the modal F, G0
  at ``machine.rapid_mm_min``, G4 dwells add their time (DESIGN §5).
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa

from stages.nc.reader import ARC_CCW, ARC_CW, DWELL, PLANE_AXES, RAPID

# a path turning by more than this between two G1 lines is a corner (``correct.corner_via_mm``)
CORNER_TURN_DEG = 30.0


_XYZ0 = ("x0_mm", "y0_mm", "z0_mm")


_XYZ1 = ("x1_mm", "y1_mm", "z1_mm")


def arc_chords(start, end, centre, plane, ccw, tol):
    """Chord points of arcs, vectorised.

    Parameters
    ----------
    start, end, centre : (n, 3) float arrays, absolute mm
    plane : (n,) int, 17/18/19
    ccw : (n,) bool, True for G3
    tol : float, maximum sagitta (chord deviation) in mm

    Returns
    -------
    owner : (m,) int, index of the arc each chord belongs to (chords in order)
    p0, p1 : (m, 3) float, chord start and end points (p0 of the first chord = start exactly,
        p1 of the last chord = end exactly)
    """
    n = len(start)
    axes = np.array([PLANE_AXES[int(p)] for p in plane]) if n else np.zeros((0, 3), int)
    rows = np.arange(n)
    a0, a1, an = axes[:, 0], axes[:, 1], axes[:, 2]
    sa, sb = start[rows, a0] - centre[rows, a0], start[rows, a1] - centre[rows, a1]
    ea, eb = end[rows, a0] - centre[rows, a0], end[rows, a1] - centre[rows, a1]
    r = np.hypot(sa, sb)
    th0 = np.arctan2(sb, sa)
    sweep = np.arctan2(eb, ea) - th0
    sweep = np.where(ccw, np.mod(sweep, 2 * np.pi), -np.mod(-sweep, 2 * np.pi))
    full = np.abs(sweep) < 1e-12  # same start and end with I/J/K: a full circle
    sweep = np.where(full, np.where(ccw, 2 * np.pi, -2 * np.pi), sweep)
    # sagitta of a chord spanning angle a: r(1 − cos(a/2)) ≤ tol
    max_step = 2 * np.arccos(np.clip(1 - tol / np.maximum(r, 1e-12), -1, 1))
    max_step = np.where(r <= tol, np.pi, np.maximum(max_step, 1e-6))
    k = np.maximum(1, np.ceil(np.abs(sweep) / max_step)).astype(np.int64)
    owner = np.repeat(rows, k)
    first = np.concatenate(([0], np.cumsum(k)[:-1]))
    j = np.arange(owner.size) - first[owner]
    f0, f1 = j / k[owner], (j + 1) / k[owner]

    def point(f):
        o = owner
        ang = th0[o] + sweep[o] * f
        p = np.empty((o.size, 3))
        p[np.arange(o.size), a0[o]] = centre[o, a0[o]] + r[o] * np.cos(ang)
        p[np.arange(o.size), a1[o]] = centre[o, a1[o]] + r[o] * np.sin(ang)
        p[np.arange(o.size), an[o]] = start[o, an[o]] + (end[o, an[o]] - start[o, an[o]]) * f
        return p

    p0, p1 = point(f0), point(f1)
    p0[j == 0] = start[owner[j == 0]]
    last = j == k[owner] - 1
    p1[last] = end[owner[last]]
    return owner, p0, p1


def corner_ends(p0, p1, is_line, turn_deg=None):
    """Which segments start and end at a path corner.

    A corner is the joint of two consecutive G1 lines (the end of one is the start of the next)
    where the direction turns by more than ``turn_deg`` (:data:`CORNER_TURN_DEG`): a row turning
    up a wall, a pocket's corner in plan view. Joints with arcs are not corners (CAM links with
    tangent arcs).

    Parameters
    ----------
    p0, p1 : (n, 3) float, segment start and end points in program order, mm
    is_line : (n,) bool, the segment is a G1 line (not a rapid, not an arc's chord)

    Returns
    -------
    (at_start, at_end) : (n,) bool each
    """
    turn_deg = CORNER_TURN_DEG if turn_deg is None else turn_deg
    n = len(p0)
    at_start, at_end = np.zeros(n, bool), np.zeros(n, bool)
    if n < 2:
        return at_start, at_end
    d = np.asarray(p1, float) - np.asarray(p0, float)
    length = np.linalg.norm(d, axis=1)
    u = d / np.where(length > 0, length, 1.0)[:, None]
    line = np.asarray(is_line, bool) & (length > 1e-9)
    joined = line[:-1] & line[1:] & np.all(np.abs(np.asarray(p1)[:-1] - np.asarray(p0)[1:]) < 1e-9, axis=1)
    corner = joined & (np.einsum("ij,ij->i", u[:-1], u[1:]) < np.cos(np.radians(turn_deg)))
    at_end[:-1], at_start[1:] = corner, corner
    return at_start, at_end


# A move up to this fraction of a piece longer than a whole number of pieces keeps that number.
# Why: a corrected program's moves are a few µm longer than the original's (a via point moved
# 20 µm off a 0.5 mm piece's line lengthens it by 0.4 µm), and with no slack every such piece of a
# line cut into exact pieces became two: the passes (and, through the via points, the blocks) of
# round 2 were no longer those of round 1, and the prediction jumped between the rounds (the
# cylinder's 0.5 mm passes: 727 → 847 → 940 predicted passes over three rounds).
# 0.5 %: a corrected 0.5 mm piece grows by 0.6 µm at most on the cylinder (0.12 %), while the
# sample program's 5.028 mm wall climbs (0.56 % over 5 mm) stay cut in two as they always were
PIECE_SLACK = 0.005


def piece_count(length, max_len):
    """Equal pieces of at most ``max_len`` (within :data:`PIECE_SLACK`) a move of ``length`` is cut into."""
    return np.maximum(1, np.ceil(np.asarray(length, float) / max_len - PIECE_SLACK)).astype(np.int64)


def split_long(owner, p0, p1, is_cut, max_len):
    """Cut cutting segments longer than ``max_len`` into equal pieces.

    "Longer" allows :data:`PIECE_SLACK` of a piece: a 0.502 mm move with ``max_len`` 0.5 mm is one
    piece, a 1.004 mm move two (:func:`piece_count`).

    Returns
    -------
    (owner, q0, q1, piece): the segments' owners and end points, and whether a segment is a piece
    of a cut one.
    """
    length = np.linalg.norm(p1 - p0, axis=1)
    k = np.where(is_cut, piece_count(length, max_len), 1)
    idx = np.repeat(np.arange(owner.size), k)
    first = np.concatenate(([0], np.cumsum(k)[:-1]))
    j = np.arange(idx.size) - first[idx]
    u = (p1 - p0)[idx] / np.where(length > 0, length, 1.0)[idx, None]
    q0 = p0[idx] + u * (length[idx] * j / k[idx])[:, None]
    q1 = np.where((j + 1 == k[idx])[:, None], p1[idx], p0[idx] + u * (length[idx] * (j + 1) / k[idx])[:, None])
    return owner[idx], q0, q1, k[idx] > 1


def _merge_short(owner, p0, p1, mergeable, merge_max, tol):
    """Merge runs of consecutive short mergeable segments into passes ≤ ``merge_max`` long.

    A run is consecutive segments that are each shorter than ``merge_max`` and mergeable with their
    predecessor (same kind of motion and feed). Runs are chunked by cumulative length; a chunk whose
    interior vertices stray more than ``tol`` from its chord is left unmerged.
    Returns the index of the first and last segment of every output pass.
    """
    n = owner.size
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    length = np.linalg.norm(p1 - p0, axis=1)
    short = mergeable & (length < merge_max)
    joins = np.zeros(n, bool)
    joins[1:] = short[1:] & short[:-1] & np.all(np.abs(p0[1:] - p1[:-1]) < 1e-9, axis=1)
    run = np.cumsum(~joins) - 1
    cum = np.cumsum(length)
    run_start = np.flatnonzero(~joins)
    before = np.concatenate(([0.0], cum))[run_start][run]
    # merge_max 0 turns merging off: every short move is its own chunk
    chunk = (np.floor((cum - before - 1e-12) / merge_max).astype(np.int64) if merge_max > 0
             else np.arange(n))
    key_new = np.ones(n, bool)
    key_new[1:] = (run[1:] != run[:-1]) | (chunk[1:] != chunk[:-1])
    group = np.cumsum(key_new) - 1
    g_first = np.flatnonzero(key_new)
    g_last = np.concatenate((g_first[1:] - 1, [n - 1]))
    # deviation of interior vertices (segment ends inside a group) from the group chord
    a, b = p0[g_first][group], p1[g_last][group]
    ab = b - a
    t = np.einsum("ij,ij->i", p1 - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-30)
    dev = np.linalg.norm(a + ab * np.clip(t, 0, 1)[:, None] - p1, axis=1)
    bad_group = np.zeros(g_first.size, bool)
    np.logical_or.at(bad_group, group, dev > tol)
    # unmerge groups that deviate: every segment becomes its own pass
    keep = ~bad_group
    split_first = np.concatenate([g_first[keep], np.flatnonzero(bad_group[group])])
    split_last = np.concatenate([g_last[keep], np.flatnonzero(bad_group[group])])
    order = np.argsort(split_first, kind="stable")
    return split_first[order], split_last[order]


def _off_chord_groups(join: np.ndarray, a: np.ndarray, b: np.ndarray, tol: float) -> np.ndarray:
    """Per pass: whether the group of passes it would be joined into has an inner vertex more than
    ``tol`` off the group's chord.

    ``join[j]``: pass j joins pass j − 1; ``a``, ``b``: each pass's start and end before joining.
    """
    group = np.cumsum(~join) - 1
    starts = np.flatnonzero(~join)
    ends = np.concatenate((starts[1:] - 1, [join.size - 1]))
    c0, c1 = a[starts][group], b[ends][group]
    inner = np.concatenate((join[1:], [False]))           # pass j's end is inside its group
    d = c1 - c0
    t = np.clip(np.einsum("ij,ij->i", b - c0, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-30), 0, 1)
    off = inner & (np.linalg.norm(c0 + t[:, None] * d - b, axis=1) > tol)
    bad = np.zeros(starts.size, bool)
    np.logical_or.at(bad, group, off)
    return bad[group]


def split_blocks(blocks: pa.Table, params: dict) -> pa.Table:
    """Turn a ``blocks`` table into a ``passes`` table (see module docstring)."""
    sp, machine, tool = params["split"], params["machine"], params["tool"]
    b = {c: blocks.column(c).to_numpy(zero_copy_only=False) for c in blocks.column_names}
    motion = b["motion"].astype(np.int64)
    start = np.stack([b[c] for c in _XYZ0], 1).astype(float) if motion.size else np.zeros((0, 3))
    end = np.stack([b[c] for c in _XYZ1], 1).astype(float) if motion.size else np.zeros((0, 3))
    if tool.get("control_point") == "center":
        # programs of the ball/corner centre: the tip is one corner radius below
        corner = tool["diameter_mm"] / 2 if tool["type"] == "ball" else (tool.get("corner_radius_mm") or 0.0)
        start[:, 2] -= corner
        end[:, 2] -= corner
    is_arc = (motion == ARC_CW) | (motion == ARC_CCW)
    centre = np.stack([np.nan_to_num(b[c].astype(float)) for c in ("cx_mm", "cy_mm", "cz_mm")], 1) if motion.size else np.zeros((0, 3))
    if tool.get("control_point") == "center":
        centre[:, 2] -= corner

    # 1. segments: one per line/rapid block, several per arc (dwells carry time only)
    lin = np.flatnonzero((motion == RAPID) | (motion == 1))
    arc = np.flatnonzero(is_arc)
    a_owner, a0, a1 = arc_chords(start[arc], end[arc], centre[arc], b["plane"][arc], motion[arc] == ARC_CCW, sp["chord_tol_mm"])
    owner = np.concatenate([lin, arc[a_owner]])
    p0 = np.concatenate([start[lin], a0])
    p1 = np.concatenate([end[lin], a1])
    order = np.argsort(owner, kind="stable")  # arcs' chords are already in order within an arc
    owner, p0, p1 = owner[order], p0[order], p1[order]
    # zero-length moves (repeated positions) are not passes
    nz = np.linalg.norm(p1 - p0, axis=1) > 1e-9
    owner, p0, p1 = owner[nz], p0[nz], p1[nz]

    # 2. long cutting moves split; 3. short runs merged
    is_cut = motion[owner] != RAPID
    owner, p0, p1, piece = split_long(owner, p0, p1, is_cut, sp["max_pass_mm"])
    feed = np.nan_to_num(b["feed_mm_min"].astype(float))
    seg_feed = np.where(motion[owner] == RAPID, machine["rapid_mm_min"], feed[owner])
    same_kind = np.ones(owner.size, bool)
    same_kind[1:] = (motion[owner][1:] == motion[owner][:-1]) | (
        (motion[owner][1:] != RAPID) & (motion[owner][:-1] != RAPID))
    same_kind[1:] &= seg_feed[1:] == seg_feed[:-1]
    # the pieces of a cut line stay passes of their own (an end piece is short on purpose)
    via_only = (b["via_only"].astype(bool) if "via_only" in b else np.zeros(motion.size, bool)) & (motion == 1)
    via_side = via_only.copy()                   # the blocks on either side of a via-only cut
    via_side[1:] |= via_only[:-1]
    mergeable = (motion[owner] != RAPID) & same_kind & ~piece & ~via_side[owner]
    if owner.size:
        mergeable[0] = (motion[owner[0]] != RAPID) & ~piece[0] & ~via_side[owner[0]]
    first, last = _merge_short(owner, p0, p1, mergeable, sp["merge_max_mm"], sp["chord_tol_mm"])
    if via_only.any():
        # a via-only cut (correct.corner_via_mm) is a vertex inside a pass: the passes it separates
        # are one (the passes stay those of the uncut program)
        join = np.zeros(first.size, bool)
        join[1:] = (via_only[owner[last[:-1]]] & (owner[last[:-1]] != owner[first[1:]])
                    & (motion[owner[first[1:]]] == 1) & same_kind[first[1:]])
        # ... as long as the via point lies on the joined pass. A correction moves it apart from
        # the corner (that is what it is for), and a pass drawn straight past it is not the path
        # the machine cuts: the sample pocket's corner climb ran 0.2 mm off it after one round
        join &= ~_off_chord_groups(join, p0[first], p1[last], sp["chord_tol_mm"])
        keep = ~join
        last = np.concatenate((last[np.flatnonzero(keep)[1:] - 1], last[-1:]))
        first = first[keep]

    q0, q1 = p0[first], p1[last]
    own0, own1 = owner[first], owner[last]
    length = np.linalg.norm(q1 - q0, axis=1)
    pfeed = seg_feed[first]
    # 4. time: each pass at its feed; a dwell adds its time before the next move
    dur = length / pfeed * 60.0
    dwell = b["dwell_s"].astype(float)
    dwell_before = np.zeros(own0.size)
    if (motion == DWELL).any() and own0.size:
        cum_dwell = np.cumsum(np.where(motion == DWELL, dwell, 0.0))
        prev_cum = np.concatenate(([0.0], cum_dwell[own0[:-1]]))
        dwell_before = cum_dwell[own0] - prev_cum
        dwell_before[0] = cum_dwell[own0[0]]
    t_end = np.cumsum(dur + dwell_before)
    t_start = t_end - dur
    pass_motion = motion[own0]
    n = own0.size
    return pa.table({
        "program_id": pa.array(b["program_id"][own0] if n else [], pa.string()),
        "pass_id": np.arange(n, dtype=np.int32),
        "block_no": b["block_no"][own0].astype(np.int32),
        "block_end": b["block_no"][own1].astype(np.int32),
        "line_no": b["line_no"][own0].astype(np.int32),
        "motion": pass_motion.astype(np.int8),
        "x0_mm": q0[:, 0], "y0_mm": q0[:, 1], "z0_mm": q0[:, 2],
        "x1_mm": q1[:, 0], "y1_mm": q1[:, 1], "z1_mm": q1[:, 2],
        "feed_mm_min": pfeed,
        "spindle_rpm": b["spindle_rpm"][own0].astype(float),
        "tool": _nullable_int(b["tool"][own0].astype(float)),
        "t_start_s": t_start, "t_end_s": t_end,
    })


def _nullable_int(x: np.ndarray) -> pa.Array:
    return pa.array(x, pa.float64(), mask=np.isnan(x)).cast(pa.int32())


def empty_passes() -> pa.Table:
    import schemas
    return schemas.empty("passes")
