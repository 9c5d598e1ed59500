"""Via points (``correct.via_points``): a straight cut longer than the split stage's
``max_pass_mm`` is split into several passes whose errors differ along it (on the sample mould a
20 mm climb of a pocket wall beside a corner: 193, 111, 72, 62, 26 µm bottom up), but a program
whose coordinates alone change can only move its two ends, so the middle passes are moved by the
straight interpolation of the end moves. :func:`via_blocks` cuts such a block into the split
stage's pieces in the ``blocks`` table (the parse stage does it when the option is on: the passes
stay the same, the correct stage then moves every piece's end); :func:`write_program` writes the
moved piece ends as ``G1 X Y Z`` lines inserted before the block's own line, only where they leave
the straight line between the written ends by more than the output grid, so a program without
error still comes out byte-identical. Only absolute metric G1 lines with no words but N, G1, X, Y,
Z and F are cut (an inserted line must not repeat an M, S, T or G code, and an F word moves onto
the first inserted line). Given the chord tolerance, plain arcs are cut too, at the split stage's
chords: the chords before the last become G1 pieces, the last stays the arc (its centre); they are
written whenever a point of the arc moves, since the correct stage refits only that last chord's arc.
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa

from stages.nc.moves import corner_ends, split_long
from stages.nc.words import scan_words, small_ints
from stages.tables import col

_VIA_LETTERS = frozenset(b"NGXYZF")


def via_blocks(data: bytes, blocks: pa.Table, max_mm: float, chord_tol_mm: float | None = None,
               corner_via_mm: float = 0.0) -> pa.Table:
    """``blocks`` with every long plain G1 line cut into the split stage's equal pieces, and with
    ``chord_tol_mm`` every plain arc into the split stage's chords.

    Parameters
    ----------
    data : the program bytes ``blocks`` was parsed from
    blocks : its ``blocks`` table (one row per block, one block per line)
    max_mm : ``split.max_pass_mm``: a line of length L becomes ceil(L / max_mm) blocks, exactly the
        pieces :func:`stages.nc.moves.split_long` makes, so the passes do not change
    chord_tol_mm : ``split.chord_tol_mm``; None: arcs are not cut. An absolute metric arc (G2/G3
        word on its own line, no words but N, G, X, Y, Z, I, J, K, R, F; G words only 2, 3, 17,
        18, 19) of two or more chords becomes its chords as G1 pieces, the last chord staying the
        arc (same centre): one arc refitted through its moved ends cannot follow an error that
        changes along it (the sample boss's contour: +35 µm on one side, +7 µm a quarter turn on)
    corner_via_mm : ``correct.corner_via_mm``: a line's piece at a path corner (a G1 line meeting
        another, :func:`stages.nc.moves.corner_ends`) at least twice this long is cut this far from
        the corner, and the cut is marked ``via_only``: the split stage keeps the two blocks one
        pass, so the passes do not change, but the corner vertex's move (for both passes) no
        longer drags the piece's body with it (once the moves have taken the via point off the
        line, the split of the corrected program has a pass boundary there)

    Returns
    -------
    ``blocks`` table: the pieces of a cut line or arc share its ``line_no`` (every piece but the
    last is a via point :func:`write_program` may insert); ``block_no`` is renumbered in order.
    """
    n = blocks.num_rows
    if n == 0 or max_mm <= 0:
        return blocks
    motion = col(blocks, "motion", np.int64)
    line = col(blocks, "line_no", np.int64) - 1
    p0 = np.stack([col(blocks, c) for c in ("x0_mm", "y0_mm", "z0_mm")], 1)
    p1 = np.stack([col(blocks, c) for c in ("x1_mm", "y1_mm", "z1_mm")], 1)
    length = np.linalg.norm(p1 - p0, axis=1)
    k = np.ceil(length / max_mm - 1e-9).astype(np.int64)
    pieces = k > 1
    if corner_via_mm > 0:                        # the lines that get a via point at a corner
        cv_start, cv_end = corner_ends(p0, p1, motion == 1)
        pieces |= (cv_start | cv_end) & (length >= 2 * corner_via_mm * (1 - 1e-9))
    plain = ~col(blocks, "incremental", bool) & ~col(blocks, "inch", bool)
    # one block on the line
    plain &= np.bincount(line, minlength=line.max() + 1)[line] == 1
    cut = (motion == 1) & pieces & plain
    is_arc = (motion == 2) | (motion == 3)
    arc_cut = is_arc & plain if chord_tol_mm else np.zeros(n, bool)
    if cut.any() or arc_cut.any():
        sc = scan_words(data)
        letter, w_line = sc["letter"], sc["line"]
        n_lines = int(max(line.max(), w_line.max() if w_line.size else 0)) + 1
        g = letter == ord("G")
        gval = np.where(g, small_ints(data, sc["vstart"], sc["vend"]), -1)
        # lines: only words an inserted line may carry; G words only G1 / G01 (a G90, G41 … on the
        # line would be repeated or lost)
        bad = ~np.isin(letter, np.frombuffer(bytes(_VIA_LETTERS), np.uint8)) | (g & (gval != 1))
        bad_line = np.bincount(w_line[bad], minlength=n_lines) > 0
        cut &= ~bad_line[line]
        if arc_cut.any():
            # arcs: also the arc words, and the line's own G2/G3 (the inserted G1 lines before it
            # would otherwise change the motion it takes from the line before); a plane word
            # applies from the arc line on, after the inserted lines, as in the source
            bad = (~np.isin(letter, np.frombuffer(bytes(_VIA_LETTERS) + b"IJKR", np.uint8))
                   | (g & ~np.isin(gval, (2, 3, 17, 18, 19))))
            own_g = np.bincount(w_line[g & np.isin(gval, (2, 3))], minlength=n_lines) > 0
            arc_cut &= ~(np.bincount(w_line[bad], minlength=n_lines) > 0)[line] & own_g[line]
    if not (cut.any() or arc_cut.any()):
        return blocks
    idx, q0, q1, _ = split_long(np.arange(n), p0, p1, cut, max_mm)
    via_only = np.zeros(idx.size, bool)
    if corner_via_mm > 0 and cut.any():
        idx, q0, q1, via_only = _corner_vias(idx, q0, q1, cut & cv_start, cut & cv_end, corner_via_mm)
    motion_out, plane_out = motion[idx], col(blocks, "plane", np.int64)[idx]
    centre = np.stack([col(blocks, c) for c in ("cx_mm", "cy_mm", "cz_mm")], 1)[idx]
    r = np.flatnonzero(arc_cut[idx])
    if r.size:
        from stages.nc.moves import arc_chords
        a_owner, a0, a1 = arc_chords(q0[r], q1[r], centre[r], plane_out[r], motion_out[r] == 3, chord_tol_mm)
        k = np.bincount(a_owner, minlength=r.size)
        rep = np.ones(idx.size, np.int64)
        rep[r] = k
        slot = np.repeat(np.arange(idx.size), rep)
        first = (np.cumsum(rep) - rep)[r]
        at = first[a_owner] + np.arange(a_owner.size) - np.repeat(np.cumsum(k) - k, k)
        # the chords before the last are G1 pieces, written (if at all) before the arc's line:
        # they take the plane the control holds before that line
        piece = np.zeros(slot.size, bool)
        piece[at] = True
        piece[(first + k - 1)] = False
        prev_plane = np.where(slot > 0, plane_out[np.maximum(slot - 1, 0)], plane_out[slot])
        idx, q0, q1, via_only = idx[slot], q0[slot], q1[slot], via_only[slot]
        q0[at], q1[at] = a0, a1
        motion_out, plane_out, centre = motion_out[slot], plane_out[slot], centre[slot]
        motion_out[piece] = 1
        plane_out[piece] = prev_plane[piece]
        centre[piece] = np.nan
    out = blocks.take(pa.array(idx))
    cols = dict(zip(("x0_mm", "y0_mm", "z0_mm", "x1_mm", "y1_mm", "z1_mm"), (*q0.T, *q1.T)))
    cols["block_no"] = np.arange(1, idx.size + 1, dtype=np.int32)
    cols["motion"], cols["plane"] = motion_out, plane_out
    if "via_only" in out.column_names:
        cols["via_only"] = via_only
    for j, c in enumerate(("cx_mm", "cy_mm", "cz_mm")):
        cols[c] = pa.array(centre[:, j], pa.float64(), mask=np.isnan(centre[:, j]))
    for name, val in cols.items():
        i = out.schema.get_field_index(name)
        f = out.schema.field(name)
        out = out.set_column(i, f, val if isinstance(val, pa.Array) else pa.array(val, f.type))
    return out


def _corner_vias(idx, q0, q1, at_start, at_end, d):
    """Cut the first piece of a line starting at a corner (``at_start`` per line) and the last
    piece of one ending at a corner ``d`` from the corner, where the piece is long enough (2d,
    3d with both). Returns (idx, q0, q1, via_only): ``via_only`` marks the pieces whose end is
    such a cut."""
    new_line = np.concatenate(([True], idx[1:] != idx[:-1]))
    last = np.concatenate((idx[1:] != idx[:-1], [True]))
    seg = q1 - q0
    plen = np.linalg.norm(seg, axis=1)
    cs = new_line & at_start[idx]
    ce = last & at_end[idx]
    fits = plen >= d * (1 + cs + ce) * (1 - 1e-9)
    cs, ce = cs & fits, ce & fits
    rep = 1 + cs.astype(np.int64) + ce
    src = np.repeat(np.arange(idx.size), rep)
    j = np.arange(src.size) - np.repeat(np.cumsum(rep) - rep, rep)
    # distances of the cuts from the piece's start: [0, d (start corner), L − d (end corner), L]
    cuts = np.zeros((idx.size, 4))
    cuts[:, 1] = np.where(cs, d, plen)
    cuts[:, 2] = np.where(ce, plen - d, plen)
    cuts[:, 3] = plen
    # the k-th boundary of a piece: its distinct cut distances in order
    bounds = np.sort(np.where(np.arange(4)[None, :] <= rep[:, None], cuts, np.inf), axis=1)
    u = seg / np.where(plen > 0, plen, 1.0)[:, None]
    a = q0[src] + u[src] * bounds[src, j][:, None]
    b = np.where((j + 1 == rep[src])[:, None], q1[src], q0[src] + u[src] * bounds[src, j + 1][:, None])
    return idx[src], a, b, j + 1 < rep[src]
