"""Corrected NC programs: the source text with only coordinate values changed (issue 5).

:func:`write_program` rewrites the coordinate words (X Y Z, and the arc words I J K / R) of the
motion blocks of the source program with the coordinates of a ``corrected`` table and leaves every
other byte alone: comments, N/G/M/S/T/F words, spacing, line endings, ``%`` lines. Values keep the
formatting of the word they replace (decimals, leading zero, explicit ``+``); a word is only
rewritten when its value on the written grid changes, so a program without moves comes out
byte-identical. Modal omission is respected: a coordinate word is added to a block only when the
block's new value differs from the position the control already holds and the word was absent
(and never before the program first sets that axis); G91 blocks get incremental values computed on
the written grid (no drift); G20 blocks get inch values. A header comment after the ``O`` line (or
the first ``%``) says what changed; it carries no date so the output is deterministic.

:func:`reverse_check` parses the written program again and checks that it has the same blocks
(count, order, motion kinds, planes) at the new coordinates. :func:`write_ln_program` writes the
corrected path as Heidenhain-style ``LN`` blocks with surface normals, :func:`write_comp_table` a
contact-angle compensation table (radius deviation per angle, like a 3D-ToolComp ``.3DTC`` file).

Via points (``correct.via_points``, off by default): a straight cut longer than the split stage's
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

import hashlib

import numpy as np
import pyarrow as pa

from stages.parse import (_BLANK, _CLASS, _CLOSE, _LETTER, _NL, _NUM, _OPEN, _SEMI, _UPPER, INCH_MM, _Errors,
                          _numbers, parse_program)

_AXES = "XYZ"
_ARC = "IJK"
_ORDER = "NGXYZIJKR"          # where an added word goes: after the last word of an earlier letter
_PLANE_AXES = {17: (0, 1), 18: (2, 0), 19: (1, 2)}   # in-plane axes (first, second) as the parser


def _table_np(table: pa.Table, name: str, dtype=float):
    return table.column(name).to_numpy(zero_copy_only=False).astype(dtype)


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
        pieces :func:`stages.split.split_long` makes, so the passes do not change
    chord_tol_mm : ``split.chord_tol_mm``; None: arcs are not cut. An absolute metric arc (G2/G3
        word on its own line, no words but N, G, X, Y, Z, I, J, K, R, F; G words only 2, 3, 17,
        18, 19) of two or more chords becomes its chords as G1 pieces, the last chord staying the
        arc (same centre): one arc refitted through its moved ends cannot follow an error that
        changes along it (the sample boss's contour: +35 µm on one side, +7 µm a quarter turn on)
    corner_via_mm : ``correct.corner_via_mm``: a line's piece at a path corner (a G1 line meeting
        another, :func:`stages.split.corner_ends`) at least twice this long is cut this far from
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
    motion = _table_np(blocks, "motion", np.int64)
    line = _table_np(blocks, "line_no", np.int64) - 1
    p0 = np.stack([_table_np(blocks, c) for c in ("x0_mm", "y0_mm", "z0_mm")], 1)
    p1 = np.stack([_table_np(blocks, c) for c in ("x1_mm", "y1_mm", "z1_mm")], 1)
    from stages.split import corner_ends, split_long
    length = np.linalg.norm(p1 - p0, axis=1)
    k = np.ceil(length / max_mm - 1e-9).astype(np.int64)
    pieces = k > 1
    if corner_via_mm > 0:                        # the lines that get a via point at a corner
        cv_start, cv_end = corner_ends(p0, p1, motion == 1)
        pieces |= (cv_start | cv_end) & (length >= 2 * corner_via_mm * (1 - 1e-9))
    plain = ~_table_np(blocks, "incremental", bool) & ~_table_np(blocks, "inch", bool)
    # one block on the line
    plain &= np.bincount(line, minlength=line.max() + 1)[line] == 1
    cut = (motion == 1) & pieces & plain
    is_arc = (motion == 2) | (motion == 3)
    arc_cut = is_arc & plain if chord_tol_mm else np.zeros(n, bool)
    if cut.any() or arc_cut.any():
        sc = _scan(data)
        letter, w_line = sc["letter"], sc["line"]
        n_lines = int(max(line.max(), w_line.max() if w_line.size else 0)) + 1
        g = letter == ord("G")
        gval = np.where(g, _small_int(data, sc["vstart"], sc["vend"]), -1)
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
    motion_out, plane_out = motion[idx], _table_np(blocks, "plane", np.int64)[idx]
    centre = np.stack([_table_np(blocks, c) for c in ("cx_mm", "cy_mm", "cz_mm")], 1)[idx]
    r = np.flatnonzero(arc_cut[idx])
    if r.size:
        from stages.split import arc_chords
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


def _small_int(data: bytes, vstart, vend) -> np.ndarray:
    """Value of words written as 1–3 plain digits (G1, G01, G17), −1 for any other text."""
    raw = np.frombuffer(data, np.uint8)
    vlen = vend - vstart
    k = np.arange(3)[None, :]
    ch = raw[np.minimum(vstart[:, None] + k, raw.size - 1)].astype(np.int64) - ord("0")
    inside = k < vlen[:, None]
    ok = (vlen >= 1) & (vlen <= 3) & np.all(~inside | ((ch >= 0) & (ch <= 9)), axis=1)
    val = np.zeros(vstart.size, np.int64)
    for j in range(3):
        val = np.where(inside[:, j], val * 10 + ch[:, j], val)
    return np.where(ok, val, -1)


def _via_rows(corrected: pa.Table):
    """Which ``corrected`` rows are via points (a piece of a cut line before its last) and which of
    them are written: those whose line's pieces leave the straight line between the new ends (on
    the 0.001 mm grid) — all the pieces of such a line, else none. The pieces of an arc are
    written when any of its points (its start included) moves on that grid: the arc's refitted
    centre is that of its last chord, which is the whole arc only when nothing moved."""
    n = corrected.num_rows
    line = _table_np(corrected, "line_no", np.int64)
    via = np.zeros(n, bool)
    via[:-1] = line[:-1] == line[1:]
    if not via.any():
        return via, via
    new = np.stack([_table_np(corrected, c) for c in ("x_new_mm", "y_new_mm", "z_new_mm")], 1)
    # the written ends: the row before the line's first piece and the line's own row
    group = np.cumsum(np.concatenate(([True], line[1:] != line[:-1]))) - 1
    g_first = np.flatnonzero(np.concatenate(([True], group[1:] != group[:-1])))
    g_last = np.concatenate((g_first[1:] - 1, [n - 1]))
    a = new[np.maximum(g_first - 1, 0)][group]
    b = new[g_last][group]
    ab = b - a
    t = np.einsum("ij,ij->i", new - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-30)
    dev = np.linalg.norm(a + ab * np.clip(t, 0, 1)[:, None] - new, axis=1)
    off = np.zeros(g_first.size, bool)
    np.logical_or.at(off, group, via & (dev > 0.5e-3))
    arc = np.isin(_table_np(corrected, "motion", np.int64)[g_last], (2, 3))
    if arc.any():
        orig = np.stack([_table_np(corrected, c) for c in ("x_mm", "y_mm", "z_mm")], 1)
        moved = np.linalg.norm(new - orig, axis=1) > 0.5e-3
        any_moved = np.zeros(g_first.size, bool)
        np.logical_or.at(any_moved, group, moved)
        off = np.where(arc, any_moved | (moved[np.maximum(g_first - 1, 0)] & (g_first > 0)), off)
    return via, via & off[group]


def write_program(data: bytes, blocks: pa.Table, corrected: pa.Table, *, source_sha256: str | None = None,
                  max_move_um: float | None = None) -> bytes:
    """The corrected program text.

    Parameters
    ----------
    data : the source program, bytes as read from the file
    blocks : its ``blocks`` table (from :func:`stages.parse.parse_program` on ``data``)
    corrected : the ``corrected`` table (new coordinates per motion block)
    source_sha256 : hash of ``data`` for the header (computed when None)
    max_move_um : the clip limit, for the header (optional)

    Returns
    -------
    bytes; identical to ``data`` when no written coordinate changes.
    """
    if corrected.num_rows == 0:
        return data
    via, via_w = _via_rows(corrected)
    if via.any():
        corrected = corrected.filter(pa.array(~via | via_w))
        via = via_w[~via | via_w]
    lines = data.split(b"\n")
    bno = _table_np(blocks, "block_no", np.int64)
    cbn = _table_np(corrected, "block_no", np.int64)
    rows = np.searchsorted(bno, cbn)
    if np.any(rows >= bno.size) or np.any(bno[np.minimum(rows, bno.size - 1)] != cbn):
        raise ValueError("corrected: block numbers not found in blocks (different program?)")
    line_idx = _table_np(corrected, "line_no", np.int64) - 1
    motion = _table_np(corrected, "motion", np.int64)
    inch = _table_np(blocks, "inch", bool)[rows]
    incr = _table_np(blocks, "incremental", bool)[rows]
    plane = _table_np(blocks, "plane", np.int64)[rows]
    scale = np.where(inch, INCH_MM, 1.0)
    target = np.stack([_table_np(corrected, c) for c in ("x_new_mm", "y_new_mm", "z_new_mm")], 1)
    centre = np.stack([_table_np(corrected, c) for c in ("cx_new_mm", "cy_new_mm", "cz_new_mm")], 1)
    n = cbn.size

    sc = _scan(data)
    # words of the motion lines: row of each word (−1: not a motion line)
    line_row = np.full(len(lines) + 1, -1, np.int64)
    line_row[line_idx[~via]] = np.flatnonzero(~via)
    w_row = line_row[sc["line"]]
    on_row = w_row >= 0
    wl = {k: v[on_row] for k, v in sc.items() if k != "line_start"}
    w_row = w_row[on_row]
    letter = wl["letter"]
    # default decimals per letter (added words, integer-style words): the most common in the program,
    # but never coarser than 1 µm / 0.0001 in: a correction of a few µm must survive being written
    default = {}
    for ch in _AXES + _ARC + "R":
        d = wl["decimals"][(letter == ord(ch)) & wl["dot"] & (wl["decimals"] > 0)]
        default[ch] = max(int(np.bincount(d).argmax()) if d.size else 3, 3)

    def by_letter(chars):
        """(n, len(chars)) arrays: present, value, decimals, word index."""
        m = len(chars)
        present = np.zeros((n, m), bool)
        value = np.full((n, m), np.nan)
        decs = np.zeros((n, m), np.int64)
        widx = np.full((n, m), -1, np.int64)
        for j, ch in enumerate(chars):
            sel = np.flatnonzero(letter == ord(ch))
            r = w_row[sel]
            present[r, j] = True
            value[r, j] = wl["value"][sel]
            decs[r, j] = np.maximum(wl["decimals"][sel], default[ch])
            widx[r, j] = sel
            decs[~present[:, j], j] = default[ch]
        return present, value, decs, widx

    present, orig_val, dec, widx = by_letter(_AXES)
    dec = np.where(inch[:, None] & ~present, np.maximum(dec, 4), dec)
    # a via point is written with the decimals of its line's own words
    own_row = np.flatnonzero(~via)[np.minimum(np.searchsorted(np.flatnonzero(~via), np.arange(n)), (~via).sum() - 1)]
    dec[via] = dec[own_row[via]]
    unit = 10.0 ** -dec                                      # resolution in the block's units
    # position the control holds after each block, on the written grid (mm)
    k = np.rint(target / scale[:, None] / unit)
    held = k * unit * scale[:, None]
    prev_held = np.vstack([held[:1], held[:-1]])
    defined = np.maximum.accumulate(present, axis=0)         # the program has set this axis
    # value each word should carry
    inc_val = np.rint((held - prev_held) / scale[:, None] / unit) * unit
    want = np.where(incr[:, None], inc_val, k * unit)
    tol = 0.5 * unit
    change = present & (np.abs(want - orig_val) > tol)
    moved_from_held = np.abs(held - prev_held) > 1e-9 * np.maximum(1.0, np.abs(held))
    first = np.arange(n) == 0
    # an axis the program has not set yet stays unset; the first block has nothing to differ from
    add = ~present & defined & ~first[:, None] & np.where(incr[:, None], np.abs(inc_val) > tol, moved_from_held)
    change &= ~via[:, None]              # via points become lines of their own (below)
    add &= ~via[:, None]
    e_row, e_col = np.nonzero(change | add)
    e_val = want[e_row, e_col]
    e_dec = dec[e_row, e_col]
    e_letter = np.array([ord(c) for c in _AXES])[e_col]

    e_word = widx[e_row, e_col]

    # arc words: centre relative to the written start (I J K), or R
    ar = np.flatnonzero(((motion == 2) | (motion == 3)) & (np.arange(n) > 0) & ~np.isnan(centre).any(1))
    a_present, a_val, a_dec, a_widx = by_letter(_ARC + "R")
    if ar.size:
        lut = np.zeros((20, 2), np.int64)
        for pl, ax in _PLANE_AXES.items():
            lut[pl] = ax
        ax2 = lut[np.clip(plane[ar], 0, 19)]
        s, e, c = prev_held[ar], held[ar], centre[ar]
        rr_ = np.arange(ar.size)
        sc_ = scale[ar]
        x_rows, x_cols, x_vals, x_decs = [], [], [], []
        # R form: radius through the written end points, negative beyond 180°
        has_r = a_present[ar, 3]
        v0 = np.stack([s[rr_, ax2[:, 0]] - c[rr_, ax2[:, 0]], s[rr_, ax2[:, 1]] - c[rr_, ax2[:, 1]]], 1)
        v1 = np.stack([e[rr_, ax2[:, 0]] - c[rr_, ax2[:, 0]], e[rr_, ax2[:, 1]] - c[rr_, ax2[:, 1]]], 1)
        rad = (np.linalg.norm(v0, axis=1) + np.linalg.norm(v1, axis=1)) / 2
        sweep = np.arctan2(v0[:, 0] * v1[:, 1] - v0[:, 1] * v1[:, 0], np.einsum("ij,ij->i", v0, v1))
        sweep = np.where(motion[ar] == 3, np.mod(sweep, 2 * np.pi), np.mod(-sweep, 2 * np.pi))
        u = 10.0 ** -a_dec[ar, 3]
        rad_w = np.rint(rad / sc_ / u) * u
        half = np.linalg.norm(v1 - v0, axis=1) / 2 / sc_
        rad_w = np.where(rad_w < half, np.ceil(half / u) * u, rad_w)   # rounding must not make R too short
        val = np.where(sweep > np.pi + 1e-12, -rad_w, rad_w)
        ch = has_r & (np.abs(val - a_val[ar, 3]) > 0.5 * u)
        x_rows.append(ar[ch]), x_cols.append(np.full(ch.sum(), 3)), x_vals.append(val[ch]), x_decs.append(a_dec[ar, 3][ch])
        # I J K: centre − written start on the plane's two axes (absent word = 0)
        for j in (0, 1):
            ax = ax2[:, j]
            d_o = a_dec[ar, ax]
            u = 10.0 ** -d_o
            val = np.rint((c[rr_, ax] - s[rr_, ax]) / sc_ / u) * u
            old = np.where(a_present[ar, ax], a_val[ar, ax], 0.0)
            ch = ~has_r & (np.abs(val - old) > 0.5 * u)
            x_rows.append(ar[ch]), x_cols.append(ax[ch]), x_vals.append(val[ch]), x_decs.append(d_o[ch])
        xr, xc = np.concatenate(x_rows), np.concatenate(x_cols)
        e_row = np.concatenate([e_row, xr])
        e_val = np.concatenate([e_val, np.concatenate(x_vals)])
        e_dec = np.concatenate([e_dec, np.concatenate(x_decs)])
        e_letter = np.concatenate([e_letter, np.frombuffer(b"IJKR", np.uint8)[xc]])
        e_word = np.concatenate([e_word, a_widx[xr, xc]])
    if e_row.size == 0 and not via.any():
        return data

    # replacements of present words (value span), insertions of absent ones (letter + value)
    m = e_row.size
    rep = e_word >= 0
    wsafe = np.maximum(e_word, 0)
    start = np.where(rep, wl["vstart"][wsafe], 0)
    end = np.where(rep, wl["vend"][wsafe], 0)
    lead = np.zeros(m, bool)
    sep = np.zeros(m, bool)
    rank_of = np.full(256, 0, np.int64)
    for i, chr_ in enumerate(_ORDER):
        rank_of[ord(chr_)] = i
    rank = np.where(rep, 0, rank_of[e_letter])
    ins = np.flatnonzero(~rep)
    if ins.size:
        pos, ld, sp = _insert_positions(wl, w_row, n, e_row[ins], e_letter[ins])
        start[ins] = end[ins] = pos
        lead[ins], sep[ins] = ld, sp
    plus = rep & wl["plus"][wsafe]
    lead0 = ~rep | wl["lead0"][wsafe]
    body = _format(e_val, e_dec, plus, lead0)
    # prefix (separator, letter) and suffix (separator) of inserted words
    pre = np.zeros((m, 2), np.uint8)
    pre[:, 0] = np.where(~rep & lead & sep, 32, 0)
    pre[:, 1] = np.where(~rep, e_letter, 0)
    suf = np.where(~rep & ~lead & sep, 32, 0).astype(np.uint8)[:, None]
    body = np.hstack([pre, body, suf])
    seq = np.zeros(m, np.int64)
    vr = np.flatnonzero(via)
    if vr.size:
        v_body = _via_lines(data, sc, wl, w_row, own_row[vr], held[vr], dec[vr], defined[vr], line_idx[vr])
        width = max(body.shape[1], v_body.shape[1])
        body = np.vstack([np.pad(body, ((0, 0), (width - body.shape[1], 0))),
                          np.pad(v_body, ((0, 0), (0, width - v_body.shape[1])))])
        start = np.concatenate([start, sc["line_start"][line_idx[vr]]])
        end = np.concatenate([end, sc["line_start"][line_idx[vr]]])
        rank = np.concatenate([rank, np.full(vr.size, -1)])
        seq = np.concatenate([seq, vr])
    order = np.lexsort((seq, rank, start))
    out = _splice(data, start[order], end[order], body[order])

    moved = int(np.count_nonzero(np.bincount(e_row, minlength=n)[~via]))
    n_lines = int((~via).sum())
    move_um = _table_np(corrected, "move_um")
    clipped = int(_table_np(corrected, "clipped", bool).sum())
    rounds = int(_table_np(corrected, "iteration", np.int64).max())
    sha = source_sha256 or hashlib.sha256(data).hexdigest()
    text = (f"(CORRECTED PROGRAM - MACHINING ERROR COMPENSATION - {moved} OF {n_lines} MOTION BLOCKS CHANGED"
            + (f" - {vr.size} VIA LINES INSERTED" if vr.size else "")
            + f" - MAX MOVE {float(move_um.max()):.1f} UM - {clipped} CLIPPED"
            + (f" AT {max_move_um:g} UM" if max_move_um is not None else "")
            + f" - {rounds} ROUND{'S' if rounds != 1 else ''} - SOURCE SHA256 {sha.upper()})").encode("ascii")
    at = _header_line(lines)
    first_line = lines[max(at, 0)]
    eol = b"\r\n" if first_line.endswith(b"\r") else b"\n"
    if at < 0:
        return text + eol + out
    hpos = int(sc["line_start"][at + 1]) if at + 1 < sc["line_start"].size else len(data)
    # edits before the header position change its offset in the output
    before = start[order] < hpos
    shift = int(((body[order] != 0).sum(1) - (end[order] - start[order]))[before].sum())
    hpos += shift
    if hpos >= len(out) and not out.endswith(b"\n"):
        return out + eol + text
    return out[:hpos] + text + eol + out[hpos:]


def _via_lines(data, sc, wl, w_row, own, held, dec, defined, line) -> np.ndarray:
    """Byte rows (0-padded) of the inserted via lines ``G1 X.. Y.. Z..`` (+ the line's F word on
    its first via line), spaced like the line (0-based ``line``, its row ``own``) they precede,
    with its line ending."""
    m = own.size
    raw = np.frombuffer(data, np.uint8)
    n_rows = int(max(own.max(), w_row.max() if w_row.size else 0)) + 1
    spaced = np.zeros(n_rows, bool)
    np.logical_or.at(spaced, w_row, wl["blank_before"] & ~wl["first"])
    sep = np.where(spaced[own], 32, 0).astype(np.uint8)[:, None]
    parts = [np.tile(np.frombuffer(b"G1", np.uint8), (m, 1))]
    for j, ch in enumerate(_AXES):
        val = _format(held[:, j], dec[:, j], np.zeros(m, bool), np.ones(m, bool))
        val[~defined[:, j]] = 0
        lead = np.where(defined[:, j], ord(ch), 0).astype(np.uint8)[:, None]
        parts += [np.where(defined[:, j, None], sep, 0).astype(np.uint8), lead, val]
    # the line's F word goes onto its first via line (the feed would change a few lines late)
    first_via = np.concatenate(([True], own[1:] != own[:-1]))
    f_sel = np.flatnonzero(wl["letter"] == ord("F"))
    f_of_row = np.full(n_rows, -1, np.int64)
    f_of_row[w_row[f_sel]] = f_sel
    fw = np.where(first_via, f_of_row[own], -1)
    if (fw >= 0).any():
        s0, s1 = wl["wstart"][np.maximum(fw, 0)], wl["vend"][np.maximum(fw, 0)]
        flen = np.where(fw >= 0, s1 - s0, 0)
        k = np.arange(int(flen.max()))[None, :]
        fbytes = np.where(k < flen[:, None], raw[np.minimum(s0[:, None] + k, raw.size - 1)], 0).astype(np.uint8)
        parts += [np.where(fw[:, None] >= 0, sep, 0).astype(np.uint8), fbytes]
    ls = sc["line_start"]
    nl = ls[np.minimum(line + 1, ls.size - 1)] - 1          # the line's newline byte
    crlf = (line + 1 < ls.size) & (raw[np.maximum(nl - 1, 0)] == 13)
    eol = np.zeros((m, 2), np.uint8)
    eol[:, 0] = np.where(crlf, 13, 10)
    eol[:, 1] = np.where(crlf, 10, 0)
    parts.append(eol)
    return np.hstack(parts)


def _splice(data: bytes, start, end, body) -> bytes:
    """``data`` with the byte ranges [start, end) (sorted, disjoint) replaced by the rows of ``body``
    (uint8 matrix, 0 = padding), assembled with one gather instead of a Python loop."""
    raw = np.frombuffer(data, np.uint8)
    mask = body != 0
    blen = mask.sum(1)
    bbytes = body[mask]
    src = np.concatenate([raw, bbytes])
    boff = raw.size + np.concatenate(([0], np.cumsum(blen)[:-1]))
    gap_start = np.concatenate(([0], end))
    gap_len = np.concatenate((start, [raw.size])) - gap_start
    seg_start = np.empty(2 * start.size + 1, np.int64)
    seg_len = np.empty(2 * start.size + 1, np.int64)
    seg_start[0::2], seg_len[0::2] = gap_start, gap_len
    seg_start[1::2], seg_len[1::2] = boff, blen
    total = int(seg_len.sum())
    first = np.concatenate(([0], np.cumsum(seg_len)[:-1]))
    idx = np.repeat(seg_start - first, seg_len) + np.arange(total)
    return src[idx].tobytes()


def _scan(data: bytes) -> dict:
    """Every address word of the program outside comments, vectorised over bytes.

    Returns arrays per word: letter (upper-case byte), line (0-based), value, vstart/vend (byte span
    of the value text), decimals, dot, plus, lead0 (a digit before the point), wstart (letter
    position), first (first word of its line), blank_before; and line_start (byte offset of each
    line start).
    """
    raw = np.frombuffer(data, dtype=np.uint8)
    cls = _CLASS[raw]
    is_nl = cls == _NL
    line_of = np.cumsum(is_nl) - is_nl              # newline byte belongs to its own line
    line_start = np.concatenate(([0], np.flatnonzero(is_nl) + 1))
    opens, closes = cls == _OPEN, cls == _CLOSE
    comment = np.zeros(raw.size, bool)
    if opens.any() or closes.any():
        depth = np.cumsum(opens) - np.cumsum(closes)
        comment = (depth > 0) | closes
    semi = (cls == _SEMI) & ~comment
    if semi.any():
        cs = np.cumsum(semi)
        start_cs = np.concatenate(([0], cs[is_nl]))
        comment |= (cs - start_cs[line_of]) > 0
    pct_line = np.zeros(line_start.size, bool)
    first_code = np.flatnonzero((cls != _BLANK) & ~is_nl)
    if first_code.size:
        fl = line_of[first_code]
        firsts = first_code[np.concatenate(([True], fl[1:] != fl[:-1]))]
        pct_line[line_of[firsts[raw[firsts] == 37]]] = True
    letter = (cls == _LETTER) & ~comment & ~pct_line[line_of]
    num = (cls == _NUM) & ~comment
    pos = np.flatnonzero(letter)
    boundary = letter | comment | is_nl
    big = raw.size
    nxt_b = np.where(boundary, np.arange(raw.size), big)
    nxt_b = np.minimum.accumulate(nxt_b[::-1])[::-1]
    nxt_b = np.append(nxt_b, big)
    w_end = nxt_b[np.minimum(pos + 1, big)]
    nxt_num = np.where(num, np.arange(raw.size), big)
    nxt_num = np.append(np.minimum.accumulate(nxt_num[::-1])[::-1], big)
    prv_num = np.maximum.accumulate(np.where(num, np.arange(raw.size), -1))
    vstart = nxt_num[np.minimum(pos + 1, big)]
    vend = prv_num[np.maximum(w_end - 1, 0)] + 1
    has_v = vstart < w_end
    vstart = np.where(has_v, vstart, pos + 1)
    vend = np.where(has_v, np.maximum(vend, vstart), pos + 1)
    # value text properties
    dotpos = np.where(raw == 46, np.arange(raw.size), big)
    dotpos = np.append(np.minimum.accumulate(dotpos[::-1])[::-1], big)[vstart]
    dot = dotpos < vend
    decimals = np.where(dot, vend - dotpos - 1, 0)
    c0 = raw[np.minimum(vstart, big - 1)]
    sign = has_v & ((c0 == 43) | (c0 == 45))
    body0 = raw[np.minimum(vstart + sign, big - 1)]
    lead0 = ~(has_v & (body0 == 46))
    plus = has_v & (c0 == 43)
    wline = line_of[pos]
    first = np.concatenate(([True], wline[1:] != wline[:-1])) if pos.size else np.zeros(0, bool)
    blank_before = (pos > 0) & (cls[np.maximum(pos - 1, 0)] == _BLANK)
    # values: only needed for X Y Z I J K R (Python float on their text; exact like the parser)
    value = np.full(pos.size, np.nan)
    want = np.isin(_UPPER[raw[pos]], np.frombuffer(b"XYZIJKR", np.uint8)) & has_v
    idx = np.flatnonzero(want)
    if idx.size:
        value[idx] = _numbers(raw, vstart[idx], vend[idx] - vstart[idx], _UPPER[raw[pos[idx]]],
                              line_of[pos[idx]], _Errors("<program>"))
    return {"letter": _UPPER[raw[pos]], "line": wline, "value": value, "vstart": vstart, "vend": vend,
            "decimals": decimals, "dot": dot, "plus": plus, "lead0": lead0, "wstart": pos, "first": first,
            "blank_before": blank_before, "line_start": line_start}


def _format(values, decimals, plus, lead0) -> np.ndarray:
    """Fixed-point text of every value (``decimals`` ≥ 1 each), vectorised.

    Returns a uint8 matrix, one right-aligned row per value, 0 = padding. ``plus``: write ``+`` on
    non-negative values; ``lead0=False``: no ``0`` before the point (``-.5``).
    """
    decimals = np.maximum(decimals.astype(np.int64), 1)
    k = np.rint(values * 10.0 ** decimals)
    neg = k < 0                                  # −0 is written 0
    k = np.abs(k).astype(np.int64)
    p10 = 10 ** np.arange(19, dtype=np.int64)
    n_dig = np.searchsorted(p10, k, side="right")            # digits of k (0 for k = 0)
    n_int = np.maximum(n_dig - decimals, np.where(lead0, 1, 0))
    width = int((decimals + n_int).max()) + 2 if values.size else 2
    r = np.arange(width)[::-1][None, :]                      # position from the right
    d = decimals[:, None]
    digit_idx = np.where(r < d, r, r - 1)
    digits = (k[:, None] // p10[np.clip(digit_idx, 0, 18)]) % 10 + 48
    is_digit = (r < d) | ((r > d) & (r <= d + n_int[:, None]))
    sign_at = d + n_int[:, None] + 1
    out = np.where(is_digit, digits, 0)
    out = np.where(r == d, 46, out)
    out = np.where((r == sign_at) & neg[:, None], 45, out)
    out = np.where((r == sign_at) & ~neg[:, None] & plus[:, None], 43, out)
    return out.astype(np.uint8)


def _insert_positions(wl, w_row, n, rows, letters):
    """Where added words go: after the last word of an earlier letter in _ORDER, else before the first."""
    rank_of = np.full(256, -1, np.int64)
    for i, ch in enumerate(_ORDER):
        rank_of[ord(ch)] = i
    wr = rank_of[wl["letter"]]
    ends = np.full((n, len(_ORDER)), -1, np.int64)
    ok = wr >= 0
    np.maximum.at(ends, (w_row[ok], wr[ok]), wl["vend"][ok])
    cum = np.maximum.accumulate(ends, axis=1)
    first_word = np.full(n, -1, np.int64)
    fw = np.flatnonzero(wl["first"])
    first_word[w_row[fw]] = wl["wstart"][fw]
    spaced = np.zeros(n, bool)
    np.logical_or.at(spaced, w_row, wl["blank_before"] & ~wl["first"])
    rank = rank_of[letters]
    after = np.where(rank > 0, cum[rows, np.maximum(rank - 1, 0)], -1)
    lead = after >= 0
    pos = np.where(lead, after, first_word[rows])
    return pos, lead, spaced[rows]
def _header_line(lines) -> int:
    """Index of the line after which the header goes: the O line, else the first %, else before line 0."""
    first_pct = None
    for i, ln in enumerate(lines):
        s = ln.strip()
        if not s:
            continue
        if s.startswith(b"%"):
            first_pct = i if first_pct is None else first_pct
            continue
        if s[:1] in (b"O", b"o") and s[1:2].isdigit():
            return i
        if s.startswith(b"(") or s.startswith(b";"):
            continue
        break
    return first_pct if first_pct is not None else -1


def reverse_check(text: bytes, blocks: pa.Table, corrected: pa.Table, path: str = "<corrected>",
                  program_id: str | None = None) -> dict:
    """Parse the corrected program and compare it with the source blocks and the new coordinates.

    Returns
    -------
    dict: ok (bool), n_blocks (source, corrected), max_dev_um (largest |parsed − x_new|, µm, over
    the motion blocks), max_grid_um (the writing resolution it is allowed), message.
    """
    pid = program_id or (blocks.column("program_id")[0].as_py() if blocks.num_rows else "p")
    new_blocks, _ = parse_program(text, path, pid)
    # the blocks the program should have: the source's, less the via points not written
    via, via_w = _via_rows(corrected) if corrected.num_rows else (np.zeros(0, bool),) * 2
    if via.any():
        drop = _table_np(corrected, "block_no", np.int64)[via & ~via_w]
        blocks = blocks.filter(pa.array(~np.isin(_table_np(blocks, "block_no", np.int64), drop)))
        corrected = corrected.filter(pa.array(~via | via_w))
    rep = {"n_blocks": (blocks.num_rows, new_blocks.num_rows), "max_dev_um": 0.0, "ok": True, "message": ""}
    if new_blocks.num_rows != blocks.num_rows:
        rep.update(ok=False, message=f"{new_blocks.num_rows} blocks, source has {blocks.num_rows}")
        return rep
    for c in ("motion", "plane", "inch", "incremental"):
        if not np.array_equal(_table_np(new_blocks, c, object), _table_np(blocks, c, object)):
            rep.update(ok=False, message=f"column {c} differs from the source")
            return rep
    # blocks in order (via points renumber them): the corrected rows are the motion blocks
    bno = _table_np(new_blocks, "block_no", np.int64)
    rows = np.searchsorted(_table_np(blocks, "block_no", np.int64), _table_np(corrected, "block_no", np.int64))
    got = np.stack([_table_np(new_blocks, c) for c in ("x1_mm", "y1_mm", "z1_mm")], 1)[rows]
    want = np.stack([_table_np(corrected, c) for c in ("x_new_mm", "y_new_mm", "z_new_mm")], 1)
    # axes the program never set before a block are held at their first value by the parser
    dev = np.abs(got - want)
    inch = _table_np(new_blocks, "inch", bool)[rows]
    grid = np.where(inch, 0.5e-4 * INCH_MM, 0.5e-3) + 1e-9
    rep["max_dev_um"] = float(dev.max() * 1000) if dev.size else 0.0
    # arc centres as the parser reconstructs them (from I J K or R) against the refitted centres
    arc = np.isin(_table_np(corrected, "motion", np.int64), (2, 3))
    if arc.any():
        cgot = np.stack([_table_np(new_blocks, c) for c in ("cx_mm", "cy_mm", "cz_mm")], 1)[rows][arc]
        cwant = np.stack([_table_np(corrected, c) for c in ("cx_new_mm", "cy_new_mm", "cz_new_mm")], 1)[arc]
        rep["max_centre_dev_um"] = float(np.nanmax(np.abs(cgot - cwant)) * 1000)
    rep["max_grid_um"] = float(grid.max() * 1000)
    if np.any(dev > grid[:, None] + 1e-9):
        i = int(np.argmax(dev.max(1)))
        rep.update(ok=False, message=f"block {int(bno[rows[i]])}: parsed {got[i]} != corrected {want[i]}")
    return rep


def write_ln_program(blocks: pa.Table, corrected: pa.Table, name: str = "CORRECTED", use_new: bool = True,
                     chord_tol_mm: float = 0.001, decimals: int = 4) -> str:
    """Heidenhain-style program: ``LN`` blocks with the surface normals of the corrected path.

    One block per NC vertex: ``LN X.. Y.. Z.. NX.. NY.. NZ..`` where a predicted pass meets the
    vertex (its unit normal, out of material), plain ``L`` elsewhere, ``FMAX`` for rapids, ``F`` when
    the feed changes. LN blocks are straight, so arcs are written as chords within
    ``chord_tol_mm`` of the (refitted) arc, each with the arc's end normal turned about the arc axis
    to the chord point. ``use_new=False`` writes the original path with normals, for controls that
    apply the compensation themselves (3D-ToolComp with :func:`write_comp_table`); do not use the
    corrected path and the table together, that corrects twice. Coordinates are in the frame of the
    source program (tool tip unless ``tool.control_point`` says centre).
    """
    from stages.split import arc_chords
    cols = ("x_new_mm", "y_new_mm", "z_new_mm") if use_new else ("x_mm", "y_mm", "z_mm")
    p = np.stack([_table_np(corrected, c) for c in cols], 1)
    nrm = np.stack([_table_np(corrected, c) for c in ("nx", "ny", "nz")], 1)
    motion = _table_np(corrected, "motion", np.int64)
    bno = _table_np(blocks, "block_no", np.int64)
    rows = np.searchsorted(bno, _table_np(corrected, "block_no", np.int64))
    feed = np.nan_to_num(_table_np(blocks, "feed_mm_min")[rows])
    plane = _table_np(blocks, "plane", np.int64)[rows]
    if use_new:
        centre = np.stack([_table_np(corrected, c) for c in ("cx_new_mm", "cy_new_mm", "cz_new_mm")], 1)
    else:
        centre = np.stack([_table_np(blocks, c) for c in ("cx_mm", "cy_mm", "cz_mm")], 1)[rows]
    start = np.vstack([p[:1], p[:-1]])
    # expand arcs into chord end points; lines keep their vertex
    arc = np.flatnonzero(((motion == 2) | (motion == 3)) & ~np.isnan(centre).any(1))
    pts, nn, src = p, nrm, np.arange(p.shape[0])
    if arc.size:
        owner, _, q1 = arc_chords(start[arc], p[arc], centre[arc], plane[arc], motion[arc] == 3, chord_tol_mm)
        axis = np.zeros((arc.size, 3))
        axis[np.arange(arc.size), np.array([{17: 2, 18: 1, 19: 0}[int(v)] for v in plane[arc]])] = 1.0
        # turn the end normal about the arc axis by the angle from the end to the chord point
        c, e = centre[arc][owner], p[arc][owner]
        ax = axis[owner]
        u, v = e - c, q1 - c
        u -= np.einsum("ij,ij->i", u, ax)[:, None] * ax
        v -= np.einsum("ij,ij->i", v, ax)[:, None] * ax
        ang = np.arctan2(np.einsum("ij,ij->i", np.cross(u, v), ax), np.einsum("ij,ij->i", u, v))
        n0 = nrm[arc][owner]
        cos, sin = np.cos(ang)[:, None], np.sin(ang)[:, None]
        n1 = n0 * cos + np.cross(ax, n0) * sin + ax * np.einsum("ij,ij->i", ax, n0)[:, None] * (1 - cos)
        keep = np.ones(p.shape[0], bool)
        keep[arc] = False
        line_rows = np.flatnonzero(keep)
        order_key = np.concatenate([line_rows.astype(float), arc[owner] + (np.arange(owner.size) + 1.0) / (owner.size + 2)])
        o = np.argsort(order_key, kind="stable")
        pts = np.concatenate([p[line_rows], q1])[o]
        nn = np.concatenate([nrm[line_rows], n1])[o]
        src = np.concatenate([line_rows, arc[owner]])[o]
    out = [f"0 BEGIN PGM {name} MM"]
    prev = np.full(3, np.nan)
    prev_f = None
    k = 1
    res = 0.5 * 10.0 ** -decimals
    for i in range(pts.shape[0]):
        words = [f"{letter}{pts[i, a]:+.{decimals}f}" for a, letter in enumerate("XYZ")
                 if not abs(pts[i, a] - prev[a]) <= res]
        if not words:
            continue
        prev = pts[i]
        r = src[i]
        has_n = motion[r] != 0 and np.all(np.isfinite(nn[i]))
        line = f"{k} {'LN' if has_n else 'L'} " + " ".join(words)
        if has_n:
            line += " " + " ".join(f"N{letter}{v:+.7f}" for letter, v in zip("XYZ", nn[i]))
        if motion[r] == 0:
            line += " FMAX"
        elif feed[r] != prev_f:
            line += f" F{feed[r]:g}"
            prev_f = feed[r]
        out.append(line)
        k += 1
    out.append(f"{k} END PGM {name} MM")
    return "\n".join(out) + "\n"


def write_comp_table(errors: pa.Table, step_deg: float = 1.0, max_deg: float = 90.0) -> str:
    """Contact-angle compensation table (like a Heidenhain ``.3DTC`` file) as CSV.

    Radius deviation per contact angle: the predicted error turned into an equivalent tool-contour
    error (seed 002: 2 µm left at a 45° contact → a tool 2 µm smaller there), i.e. ``−err_um`` as mm,
    averaged per angle bin, linearly interpolated over empty bins (held at the ends).
    """
    q = _table_np(errors, "contact_deg") if errors.num_rows else np.zeros(0)
    e = _table_np(errors, "err_um") if errors.num_rows else np.zeros(0)
    ok = np.isfinite(q) & np.isfinite(e)
    q, e = q[ok], e[ok]
    angles = np.arange(0.0, max_deg + step_deg / 2, step_deg)
    b = np.clip(np.rint(q / step_deg).astype(np.int64), 0, angles.size - 1)
    s = np.bincount(b, e, angles.size)
    c = np.bincount(b, None, angles.size)
    have = c > 0
    dev = np.zeros(angles.size)
    if have.any():
        dev = np.interp(angles, angles[have], -(s[have] / c[have]))
    lines = ["# contact-angle compensation table (3DTC-like): radius deviation of the ball per contact angle",
             "# angle 0 = tip, 90 = equator; deviation in mm, negative = the tool cuts as if smaller",
             "angle_deg,radius_deviation_mm,n_passes"]
    lines += [f"{a:.1f},{d / 1000.0:+.5f},{int(cnt)}" for a, d, cnt in zip(angles, dev, c)]
    return "\n".join(lines) + "\n"
