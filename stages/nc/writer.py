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
"""
from __future__ import annotations

import hashlib

import numpy as np
import pyarrow as pa

from stages.nc.lexer import INCH_MM
from stages.nc.reader import parse_program
from stages.nc.words import ORDER, format_values, header_line, insert_positions, scan_words, splice
from stages.tables import col

_AXES = "XYZ"


_ARC = "IJK"




PLANE_AXES = {17: (0, 1), 18: (2, 0), 19: (1, 2)}   # in-plane axes (first, second) as the parser


def _via_rows(corrected: pa.Table):
    """Which ``corrected`` rows are via points (a piece of a cut line before its last) and which of
    them are written: those whose line's pieces leave the straight line between the new ends (on
    the 0.001 mm grid) — all the pieces of such a line, else none. The pieces of an arc are
    written when any of its points (its start included) moves on that grid: the arc's refitted
    centre is that of its last chord, which is the whole arc only when nothing moved."""
    n = corrected.num_rows
    line = col(corrected, "line_no", np.int64)
    via = np.zeros(n, bool)
    via[:-1] = line[:-1] == line[1:]
    if not via.any():
        return via, via
    new = np.stack([col(corrected, c) for c in ("x_new_mm", "y_new_mm", "z_new_mm")], 1)
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
    arc = np.isin(col(corrected, "motion", np.int64)[g_last], (2, 3))
    if arc.any():
        orig = np.stack([col(corrected, c) for c in ("x_mm", "y_mm", "z_mm")], 1)
        moved = np.linalg.norm(new - orig, axis=1) > 0.5e-3
        any_moved = np.zeros(g_first.size, bool)
        np.logical_or.at(any_moved, group, moved)
        off = np.where(arc, any_moved | (moved[np.maximum(g_first - 1, 0)] & (g_first > 0)), off)
    return via, via & off[group]


def write_program(data: bytes, blocks: pa.Table, corrected: pa.Table, *, source_sha256: str | None = None,
                  max_move_um: float | None = None, feeds_changed: int = 0, drift_um: float = 0.0) -> bytes:
    """The corrected program text.

    Parameters
    ----------
    data : the source program, bytes as read from the file
    blocks : its ``blocks`` table (from :func:`stages.parse.parse_program` on ``data``)
    corrected : the ``corrected`` table (new coordinates per motion block)
    source_sha256 : hash of ``data`` for the header (computed when None)
    max_move_um : the clip limit, for the header (optional)
    feeds_changed : F words the feed schedule wrote into ``data`` (said in the header)
    drift_um : the largest thermal drift compensation in the new coordinates (said in the header)

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
    bno = col(blocks, "block_no", np.int64)
    cbn = col(corrected, "block_no", np.int64)
    rows = np.searchsorted(bno, cbn)
    if np.any(rows >= bno.size) or np.any(bno[np.minimum(rows, bno.size - 1)] != cbn):
        raise ValueError("corrected: block numbers not found in blocks (different program?)")
    line_idx = col(corrected, "line_no", np.int64) - 1
    motion = col(corrected, "motion", np.int64)
    inch = col(blocks, "inch", bool)[rows]
    incr = col(blocks, "incremental", bool)[rows]
    plane = col(blocks, "plane", np.int64)[rows]
    scale = np.where(inch, INCH_MM, 1.0)
    target = np.stack([col(corrected, c) for c in ("x_new_mm", "y_new_mm", "z_new_mm")], 1)
    centre = np.stack([col(corrected, c) for c in ("cx_new_mm", "cy_new_mm", "cz_new_mm")], 1)
    n = cbn.size

    sc = scan_words(data)
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
        for pl, ax in PLANE_AXES.items():
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
    if e_row.size == 0 and not via.any() and not feeds_changed:
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
    for i, chr_ in enumerate(ORDER):
        rank_of[ord(chr_)] = i
    rank = np.where(rep, 0, rank_of[e_letter])
    ins = np.flatnonzero(~rep)
    if ins.size:
        pos, ld, sp = insert_positions(wl, w_row, n, e_row[ins], e_letter[ins])
        start[ins] = end[ins] = pos
        lead[ins], sep[ins] = ld, sp
    plus = rep & wl["plus"][wsafe]
    lead0 = ~rep | wl["lead0"][wsafe]
    body = format_values(e_val, e_dec, plus, lead0)
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
    out = splice(data, start[order], end[order], body[order])

    moved = int(np.count_nonzero(np.bincount(e_row, minlength=n)[~via]))
    n_lines = int((~via).sum())
    move_um = col(corrected, "move_um")
    clipped = int(col(corrected, "clipped", bool).sum())
    rounds = int(col(corrected, "iteration", np.int64).max())
    sha = source_sha256 or hashlib.sha256(data).hexdigest()
    text = (f"(CORRECTED PROGRAM - MACHINING ERROR COMPENSATION - {moved} OF {n_lines} MOTION BLOCKS CHANGED"
            + (f" - {vr.size} VIA LINES INSERTED" if vr.size else "")
            + f" - MAX MOVE {float(move_um.max()):.1f} UM - {clipped} CLIPPED"
            + (f" AT {max_move_um:g} UM" if max_move_um is not None else "")
            + f" - {rounds} ROUND{'S' if rounds != 1 else ''}"
            + (f" - FEEDS SCHEDULED: {feeds_changed} F WORDS" if feeds_changed else "")
            + (f" - THERMAL DRIFT COMPENSATED: MAX {drift_um:.1f} UM" if drift_um else "")
            + f" - SOURCE SHA256 {sha.upper()})").encode("ascii")
    at = header_line(lines)
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
        val = format_values(held[:, j], dec[:, j], np.zeros(m, bool), np.ones(m, bool))
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
        drop = col(corrected, "block_no", np.int64)[via & ~via_w]
        blocks = blocks.filter(pa.array(~np.isin(col(blocks, "block_no", np.int64), drop)))
        corrected = corrected.filter(pa.array(~via | via_w))
    rep = {"n_blocks": (blocks.num_rows, new_blocks.num_rows), "max_dev_um": 0.0, "ok": True, "message": ""}
    if new_blocks.num_rows != blocks.num_rows:
        rep.update(ok=False, message=f"{new_blocks.num_rows} blocks, source has {blocks.num_rows}")
        return rep
    for c in ("motion", "plane", "inch", "incremental"):
        if not np.array_equal(col(new_blocks, c, object), col(blocks, c, object)):
            rep.update(ok=False, message=f"column {c} differs from the source")
            return rep
    # blocks in order (via points renumber them): the corrected rows are the motion blocks
    bno = col(new_blocks, "block_no", np.int64)
    rows = np.searchsorted(col(blocks, "block_no", np.int64), col(corrected, "block_no", np.int64))
    got = np.stack([col(new_blocks, c) for c in ("x1_mm", "y1_mm", "z1_mm")], 1)[rows]
    want = np.stack([col(corrected, c) for c in ("x_new_mm", "y_new_mm", "z_new_mm")], 1)
    # axes the program never set before a block are held at their first value by the parser
    dev = np.abs(got - want)
    inch = col(new_blocks, "inch", bool)[rows]
    grid = np.where(inch, 0.5e-4 * INCH_MM, 0.5e-3) + 1e-9
    rep["max_dev_um"] = float(dev.max() * 1000) if dev.size else 0.0
    # arc centres as the parser reconstructs them (from I J K or R) against the refitted centres
    arc = np.isin(col(corrected, "motion", np.int64), (2, 3))
    if arc.any():
        cgot = np.stack([col(new_blocks, c) for c in ("cx_mm", "cy_mm", "cz_mm")], 1)[rows][arc]
        cwant = np.stack([col(corrected, c) for c in ("cx_new_mm", "cy_new_mm", "cz_new_mm")], 1)[arc]
        rep["max_centre_dev_um"] = float(np.nanmax(np.abs(cgot - cwant)) * 1000)
    rep["max_grid_um"] = float(grid.max() * 1000) if grid.size else 0.0
    if np.any(dev > grid[:, None] + 1e-9):
        i = int(np.argmax(dev.max(1)))
        rep.update(ok=False, message=f"block {int(bno[rows[i]])}: parsed {got[i]} != corrected {want[i]}")
    return rep
