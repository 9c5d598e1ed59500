"""ISO/Fanuc-style NC program → motion blocks with resolved modal state.

The parser is vectorised over the whole file (numpy over bytes), because mould programs run to
hundreds of thousands of blocks and the nightly run parses every new one: tokenising, number
conversion and modal-state propagation (forward fill) are array operations, and Python only runs
per *error*, to phrase it. Anything it does not support is rejected with ``file:line: what and why``
and never guessed.

Supported: N, G0/G1/G2/G3 (I J K incremental centre, or R; helical), G4 dwell (P ms / X s), G17/G18/
G19, G90/G91, G20/G21, G94, F, S, T, M3/M4/M5/M6/M0/M1/M8/M9/M30/M2; no-op words that do not change
the path (G40, G43 H, G49, G54–G59, G61, G64, G80, G5.1 Q, O program number, D, H); comments in
``( )`` and after ``;``; ``%`` lines; several words per block, spaces between address and value.
Not supported (rejected): macros (# [ ] =), subprograms (M98/M99), canned cycles (G73–G89), cutter
radius compensation (G41/G42), reference returns and coordinate systems set in the program (G28,
G53, G92, G68), rotary/secondary axes (A B C U V W), feed per revolution (G95), block delete ``/``.
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa

from stages import InputError
from stages.nc.lexer import INCH_MM, Problems, ffill, tokenize

RAPID, LINEAR, ARC_CW, ARC_CCW, DWELL = 0, 1, 2, 3, 4


ARC_RADIUS_TOL_MM = 0.01  # |r_start − r_end| beyond this (plus 1e-4·r) is a programming error


_ADDR = "XYZIJKRFSTNPHDOQ"  # addresses that carry one value per block


# G codes (×10 so G5.1 → 51) by modal group; None = accepted no-op
_G_GROUP = {0: "motion", 10: "motion", 20: "motion", 30: "motion",
            170: "plane", 180: "plane", 190: "plane",
            900: "dist", 910: "dist", 200: "units", 210: "units", 40: "dwell"}


_G_NOOP = {400, 430, 490, 540, 550, 560, 570, 580, 590, 610, 640, 800, 940, 51, 611}


_G_REJECT = {
    **{g * 10: f"canned cycle G{g} is not supported: post the program with cycles expanded" for g in (73, 74, 76, 81, 82, 83, 84, 85, 86, 87, 88, 89)},
    410: "cutter radius compensation (G41) is not supported: post the tool-tip path with compensation off",
    420: "cutter radius compensation (G42) is not supported: post the tool-tip path with compensation off",
    280: "reference return (G28) is not supported: the position after it is machine-dependent",
    530: "machine coordinates (G53) are not supported",
    920: "setting the coordinate system in the program (G92) is not supported",
    680: "coordinate rotation (G68) is not supported",
    950: "feed per revolution (G95) is not supported",
}


_M_OK = {0, 1, 2, 3, 4, 5, 6, 8, 9, 30}


_M_REJECT = {98: "subprogram calls (M98) are not supported", 99: "subprogram return (M99) is not supported"}


def parse_program(data: bytes, path: str, program_id: str) -> tuple[pa.Table, dict]:
    """Parse one program. Returns the ``blocks`` table and a summary dict.

    Raises InputError(``path:line: ...``) for anything unsupported or inconsistent.
    """
    err = Problems(path)
    letters, values, w_line, n_lines, w_col = tokenize(data, path, err)
    if letters.size == 0:
        err.raise_if_any()
        raise InputError(f"{path}:1: no NC blocks in the file (only comments or blank lines)")
    code_lines = w_line[np.concatenate(([True], w_line[1:] != w_line[:-1]))]  # w_line is sorted
    n_blocks = int(code_lines.size)

    # --- G words -> modal groups ----------------------------------------------------------------
    is_g = letters == ord("G")
    g10 = np.round(values[is_g] * 10).astype(np.int64)
    g_line, g_col = w_line[is_g], w_col[is_g]
    known = np.isin(g10, list(_G_GROUP) + list(_G_NOOP))
    rej = np.isin(g10, list(_G_REJECT))
    err.add(rej, g_line, lambda i: _G_REJECT[int(g10[i])], g_col)
    err.add(~known & ~rej, g_line, lambda i: f"unknown or unsupported G code G{_fmt_code(g10[i])}", g_col)
    is_m = letters == ord("M")
    m = values[is_m]
    m_int = m.astype(np.int64)
    m_line, m_col = w_line[is_m], w_col[is_m]
    err.add(np.isin(m_int, list(_M_REJECT)), m_line, lambda i: _M_REJECT[int(m_int[i])], m_col)
    err.add(~np.isin(m_int, list(_M_OK) + list(_M_REJECT)) | (m != m_int), m_line,
            lambda i: f"unknown or unsupported M code M{m[i]:g} (supported: M0 M1 M2 M3 M4 M5 M6 M8 M9 M30)", m_col)
    err.raise_if_any()

    def group_col(name):
        sel = np.isin(g10, [g for g, grp in _G_GROUP.items() if grp == name])
        col = np.full(n_lines, np.nan)
        ln, gv = g_line[sel], g10[sel]
        dup = np.flatnonzero(np.diff(ln) == 0) + 1
        err.add(dup, ln, f"two {name} G codes in one block", g_col[sel])
        col[ln] = gv / 10.0
        return col

    motion_g, plane_g, dist_g, unit_g, dwell_g = (group_col(n) for n in ("motion", "plane", "dist", "units", "dwell"))

    # --- single-valued addresses -> per-line columns ------------------------------------------------
    cols = {}
    for a in _ADDR:
        sel = letters == ord(a)
        ln = w_line[sel]
        dup = np.flatnonzero(np.diff(ln) == 0) + 1
        err.add(dup, ln, f"address {a} appears twice in one block", w_col[sel])
        col = np.full(n_lines, np.nan)
        col[ln] = values[sel]
        cols[a] = col
    err.raise_if_any()
    has = {a: ~np.isnan(c) for a, c in cols.items()}
    for a in "NTOHD":
        v = cols[a]
        err.add(has[a] & ((v != np.round(v)) | (v < 0) | (v > 2**31 - 1)), np.arange(n_lines),
                      f"{a} must be a whole number between 0 and 2147483647")
    err.add(has["F"] & (cols["F"] < 0), np.arange(n_lines), "negative feed")
    err.add(has["S"] & (cols["S"] < 0), np.arange(n_lines), "negative spindle speed")
    err.add(has["Q"] & ~np.isin(np.arange(n_lines), g_line[g10 == 51]), np.arange(n_lines),
                  "Q words are only accepted with G5.1 (canned-cycle Q is not supported)")
    err.add(has["P"] & np.isnan(dwell_g), np.arange(n_lines), "P words are only accepted with G4 (dwell)")

    # M codes per line
    def m_flag(codes):
        f = np.zeros(n_lines, bool)
        f[m_line[np.isin(m_int, codes)]] = True
        return f
    spindle_on, spindle_off, tool_change, prog_end = m_flag([3, 4]), m_flag([5]), m_flag([6]), m_flag([2, 30])

    # lines after the end of program (M2/M30) are not executed
    end_idx = np.flatnonzero(prog_end)
    live = np.ones(n_lines, bool)
    if end_idx.size:
        live[end_idx[0] + 1:] = False

    # --- modal state -------------------------------------------------------------------------------
    inch = ffill(unit_g, 21.0) == 20.0
    incremental = ffill(dist_g, 90.0) == 91.0
    plane = ffill(plane_g, 17.0).astype(np.int16)
    motion = ffill(motion_g)
    scale = np.where(inch, INCH_MM, 1.0)
    feed = ffill(np.where(has["F"], cols["F"] * scale, np.nan))
    sp_state = ffill(np.where(spindle_on, 1.0, np.where(spindle_off, 0.0, np.nan)), 0.0)
    speed = ffill(cols["S"], 0.0)
    # T word selects, M6 loads; a T on the M6 line or before it is the tool in the spindle
    t_sel = ffill(cols["T"])
    tool_in = ffill(np.where(tool_change, t_sel, np.nan))
    is_dwell = ~np.isnan(dwell_g)

    moves = (has["X"] | has["Y"] | has["Z"]) & ~is_dwell
    arc_words = has["I"] | has["J"] | has["K"] | has["R"]
    full_circle = arc_words & ~moves & np.isin(motion, (2.0, 3.0)) & ~is_dwell
    moves |= full_circle
    moves &= live
    err.add(moves & np.isnan(motion), np.arange(n_lines), "coordinates without a motion mode (no G0/G1/G2/G3 before)")
    err.add(arc_words & ~np.isin(motion, (2.0, 3.0)) & ~is_dwell & live, np.arange(n_lines),
                  "I/J/K/R words outside an arc block (G2/G3)")
    cutting = moves & (motion >= 1)
    err.add(cutting & np.isnan(feed), np.arange(n_lines), "cutting move without a feed: no F word before the first G1/G2/G3")
    err.add(cutting & (feed <= 0), np.arange(n_lines), "cutting move with feed F0")
    err.add(cutting & ((sp_state == 0) | (speed <= 0)), np.arange(n_lines),
                  "cutting move with the spindle stopped (no S and M3/M4 before it)")
    # one tool per program (DESIGN §4): the tool that cuts
    tools_cutting = np.unique(tool_in[cutting & ~np.isnan(tool_in)])
    if tools_cutting.size > 1:
        first_second = np.flatnonzero(cutting & (tool_in == tools_cutting[1]))
        err.add(first_second, np.arange(n_lines),
                      f"program cuts with several tools (T{int(tools_cutting[0])}, T{int(tools_cutting[1])}): one tool per program")
    err.raise_if_any()

    # --- positions: absolute anchors + incremental sums, per axis --------------------------------------
    line_idx = np.flatnonzero(moves | is_dwell)
    mv = moves[line_idx]
    pos_end = {}
    known_from = {}
    for a in "XYZ":
        v = cols[a] * scale
        present = has[a] & moves
        absolute = present & ~incremental
        inc = np.where(present & incremental, v, 0.0)
        c = np.cumsum(inc)
        anchor = np.where(absolute, np.arange(n_lines), -1)
        np.maximum.accumulate(anchor, out=anchor)
        base = np.where(anchor >= 0, v[np.maximum(anchor, 0)] - c[np.maximum(anchor, 0)], 0.0)
        p = base + c
        defined = (anchor >= 0) | (np.cumsum(present & incremental) > 0)
        first_def = np.flatnonzero(defined)
        # before an axis is first set the tool is where it was; treat it as already at the first value
        p = np.where(defined, p, p[first_def[0]] if first_def.size else np.nan)
        pos_end[a] = p
        known_from[a] = first_def[0] if first_def.size else n_lines
    # start of each block = end of the previous motion block
    ends = np.stack([pos_end[a][line_idx] for a in "XYZ"], 1)
    starts = np.vstack([ends[:1], ends[:-1]]) if ends.size else ends
    # a move's start is the previous *move's* end (dwells do not move)
    mv_rows = np.flatnonzero(mv)
    if mv_rows.size:
        prev_move = np.maximum.accumulate(np.where(mv, np.arange(mv.size), -1))
        prev_before = np.concatenate(([-1], prev_move[:-1]))
        starts = np.where(prev_before[:, None] >= 0, ends[np.maximum(prev_before, 0)], ends)
    for a in "XYZ":
        # a move starts where the previous one ended: if the axis was first set on this very block
        # or later, the cutting move starts from an unknown position
        bad_cut = cutting[line_idx] & (line_idx <= known_from[a])
        err.add(bad_cut, line_idx, f"cutting move from an unknown position: {a} was never set before it")
    err.raise_if_any()
    if np.isnan(ends).any():
        rows = np.flatnonzero(np.isnan(ends).any(1))
        err.add(rows, line_idx, "move on an axis that is never set")
        err.raise_if_any()

    mot = np.where(is_dwell[line_idx], DWELL, motion[line_idx]).astype(np.int8)
    pl = plane[line_idx]
    centre = np.full((line_idx.size, 3), np.nan)
    arc = (mot == ARC_CW) | (mot == ARC_CCW)
    if arc.any():
        ai = np.flatnonzero(arc)
        centre[ai] = _arc_centres(ai, line_idx, starts, ends, pl, mot, cols, has, scale, err)
        err.raise_if_any()

    dwell_s = np.zeros(line_idx.size)
    dl = is_dwell[line_idx]
    if dl.any():
        li = line_idx[dl]
        dwell_s[dl] = np.where(has["P"][li], cols["P"][li] / 1000.0, np.where(has["X"][li], cols["X"][li], np.nan))
        err.add(np.isnan(dwell_s) & dl, line_idx, "G4 dwell without P (ms) or X (s)")
        err.add((dwell_s < 0) & dl, line_idx, "negative dwell time")
        err.raise_if_any()

    block_no = np.searchsorted(code_lines, line_idx) + 1
    t = tool_in[line_idx]
    table = pa.table({
        "program_id": pa.array([program_id] * line_idx.size, pa.string()),
        "block_no": block_no.astype(np.int32),
        "line_no": (line_idx + 1).astype(np.int32),
        "n_number": pa.array(cols["N"][line_idx], pa.float64(), mask=~has["N"][line_idx]).cast(pa.int32()),
        "motion": mot,
        "plane": pl,
        "x0_mm": starts[:, 0], "y0_mm": starts[:, 1], "z0_mm": starts[:, 2],
        "x1_mm": ends[:, 0], "y1_mm": ends[:, 1], "z1_mm": ends[:, 2],
        "cx_mm": pa.array(centre[:, 0], mask=~arc), "cy_mm": pa.array(centre[:, 1], mask=~arc),
        "cz_mm": pa.array(centre[:, 2], mask=~arc),
        "feed_mm_min": pa.array(feed[line_idx], mask=np.isnan(feed[line_idx])),
        "spindle_rpm": np.where(sp_state[line_idx] > 0, speed[line_idx], 0.0),
        "tool": pa.array(t, pa.float64(), mask=np.isnan(t)).cast(pa.int32()),
        "inch": inch[line_idx],
        "incremental": incremental[line_idx],
        "dwell_s": dwell_s,
        "via_only": np.zeros(line_idx.size, bool),
    })
    summary = {"n_lines": n_lines, "n_blocks": n_blocks,
               "tool": int(tools_cutting[0]) if tools_cutting.size else None}
    return table, summary


def _fmt_code(g10) -> str:
    g10 = int(g10)
    return f"{g10 // 10}" if g10 % 10 == 0 else f"{g10 // 10}.{g10 % 10}"


# plane → (first axis, second axis, normal axis) indices into xyz; arcs are CCW (G3) seen from +normal
PLANE_AXES = {17: (0, 1, 2), 18: (2, 0, 1), 19: (1, 2, 0)}


_OFFSET_LETTER = "IJK"


def _arc_centres(ai, line_idx, starts, ends, plane, mot, cols, has, scale, err):
    """Absolute arc centres for arc rows ``ai``; checks radius consistency (IJK) or R feasibility."""
    out = np.full((ai.size, 3), np.nan)
    li = line_idx[ai]
    s, e = starts[ai], ends[ai]
    sc = scale[li]
    for pl, (a0, a1, an) in PLANE_AXES.items():
        sel = plane[ai] == pl
        if not sel.any():
            continue
        rows, lrow = np.flatnonzero(sel), li[sel]
        has_r = has["R"][lrow]
        off_a = cols[_OFFSET_LETTER[a0]][lrow] * sc[sel]
        off_b = cols[_OFFSET_LETTER[a1]][lrow] * sc[sel]
        has_ij = has[_OFFSET_LETTER[a0]][lrow] | has[_OFFSET_LETTER[a1]][lrow]
        wrong_plane = has[_OFFSET_LETTER[an]][lrow] & ~has_ij
        err.add(wrong_plane, lrow, f"arc centre word {_OFFSET_LETTER[an]} does not belong to plane G{pl}")
        err.add(has_r & has_ij, lrow, "arc with both R and I/J/K: ambiguous")
        err.add(~has_r & ~has_ij, lrow, "arc (G2/G3) without a centre (I/J/K) or radius (R)")
        sa, sb = s[sel][:, a0], s[sel][:, a1]
        ea, eb = e[sel][:, a0], e[sel][:, a1]
        ca = sa + np.nan_to_num(off_a)
        cb = sb + np.nan_to_num(off_b)
        # R form: centre on the perpendicular bisector; R<0 means the arc spans more than 180°
        if has_r.any():
            r = cols["R"][lrow] * sc[sel]
            dx, dy = ea - sa, eb - sb
            d = np.hypot(dx, dy)
            rr = np.abs(r)
            err.add(has_r & (d < 1e-9), lrow, "full circle with R is undefined: use I/J/K")
            err.add(has_r & (d > 2 * rr + 1e-3), lrow,
                          lambda i: f"arc radius R{r[i]:g} too small for a chord of {d[i]:.4f} mm")
            h = np.sqrt(np.maximum(rr ** 2 - (d / 2) ** 2, 0.0))
            ccw = mot[ai][sel] == ARC_CCW
            side = np.where(ccw, 1.0, -1.0) * np.where(r < 0, -1.0, 1.0)
            with np.errstate(invalid="ignore", divide="ignore"):
                ux, uy = -dy / d, dx / d  # left normal of the chord
            rca = sa + dx / 2 + side * h * ux
            rcb = sb + dy / 2 + side * h * uy
            ca = np.where(has_r, rca, ca)
            cb = np.where(has_r, rcb, cb)
        else:
            r0 = np.hypot(sa - ca, sb - cb)
            r1 = np.hypot(ea - ca, eb - cb)
            bad = np.abs(r0 - r1) > ARC_RADIUS_TOL_MM + 1e-4 * np.maximum(r0, r1)
            err.add(bad, lrow, lambda i: f"arc radius inconsistent: {r0[i]:.4f} mm at the start, {r1[i]:.4f} mm at the end")
            err.add(r0 < 1e-6, lrow, "arc of zero radius")
        if has_r.any():
            r0 = np.hypot(sa - ca, sb - cb)
            r1 = np.hypot(ea - ca, eb - cb)
            bad = ~has_r & (np.abs(r0 - r1) > ARC_RADIUS_TOL_MM + 1e-4 * np.maximum(r0, r1))
            err.add(bad, lrow, lambda i: f"arc radius inconsistent: {r0[i]:.4f} mm at the start, {r1[i]:.4f} mm at the end")
        c = np.empty((rows.size, 3))
        c[:, a0], c[:, a1] = ca, cb
        c[:, an] = s[sel][:, an]  # centre's normal coordinate: that of the start (helix rises from there)
        out[rows] = c
    return out


def empty_blocks() -> pa.Table:
    import schemas
    return schemas.empty("blocks")
