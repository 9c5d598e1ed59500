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
import re

import numpy as np
import pyarrow as pa

from stages.parse import INCH_MM, parse_program

_WORD = re.compile(rb"\([^)]*\)|;[^\r\n]*|([A-Za-z])[ \t]*([+-]?[0-9]*\.?[0-9]*)")
_AXES = "XYZ"
_ARC = "IJK"
_ORDER = "NGXYZIJKR"          # where an added word goes: after the last word of an earlier letter
_PLANE_AXES = {17: (0, 1), 18: (2, 0), 19: (1, 2)}   # in-plane axes (first, second) as the parser
_OFFSET_LETTER = {0: "I", 1: "J", 2: "K"}


class _Word:
    __slots__ = ("letter", "value", "start", "end", "decimals", "dot", "plus", "lead0")

    def __init__(self, letter, text, start, end):
        self.letter = letter
        self.start, self.end = start, end
        t = text.decode("ascii")
        self.plus = t.startswith("+")
        body = t.lstrip("+-")
        self.dot = "." in body
        self.decimals = len(body.split(".", 1)[1]) if self.dot else 0
        self.lead0 = not body.startswith(".")
        self.value = float(t) if body.strip(".") else 0.0


def _words(line: bytes) -> dict:
    """Words of one block outside comments: (letter → _Word, [(letter, word start, word end)])."""
    out = {}
    order = []
    for m in _WORD.finditer(line):
        if m.group(1) is None:
            continue
        letter = m.group(1).decode().upper()
        w = _Word(letter, m.group(2), m.start(2), m.end(2))
        out[letter] = w
        order.append((letter, m.start(1), m.end(2)))
    return out, order


def _fmt(value: float, decimals: int, style: _Word | None) -> str:
    """``value`` with ``decimals`` decimals in the style of the word it replaces."""
    s = f"{value + 0.0:.{decimals}f}" if decimals > 0 else f"{int(round(value))}."
    if s.startswith("-") and float(s) == 0:
        s = s[1:]
    if style is not None:
        if not style.lead0:
            s = s.replace("0.", ".", 1) if s.lstrip("-").startswith("0.") else s
        if style.plus and not s.startswith("-"):
            s = "+" + s
        if not style.dot and decimals == 0:
            s = s.rstrip(".")
    return s


def _table_np(table: pa.Table, name: str, dtype=float):
    return table.column(name).to_numpy(zero_copy_only=False).astype(dtype)


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

    parsed = [_words(lines[i]) for i in line_idx]
    words = [p[0] for p in parsed]
    # default decimals per letter (for added words and integer-style words): the most common
    default = {}
    for letter in _AXES + _ARC + "R":
        decs = [w[letter].decimals for w in words if letter in w and w[letter].dot and w[letter].decimals]
        default[letter] = (max(set(decs), key=decs.count) if decs else 3)
    present = np.array([[a in w for a in _AXES] for w in words], bool).reshape(n, 3)
    dec = np.array([[(w[a].decimals if a in w and w[a].decimals else default[a]) for a in _AXES] for w in words],
                   np.int64).reshape(n, 3)
    dec = np.where(inch[:, None] & ~present, np.maximum(dec, 4), dec)
    unit = 10.0 ** -dec                                      # resolution in the block's units
    # position the control holds after each block, on the written grid (mm)
    k = np.rint(target / scale[:, None] / unit)
    held = k * unit * scale[:, None]
    prev_held = np.vstack([held[:1], held[:-1]])
    defined = np.maximum.accumulate(present, axis=0)         # the program has set this axis
    orig_val = np.array([[(w[a].value if a in w else np.nan) for a in _AXES] for w in words]).reshape(n, 3)
    # value each word should carry
    inc_val = np.rint((held - prev_held) / scale[:, None] / unit) * unit
    want = np.where(incr[:, None], inc_val, k * unit)
    tol = 0.5 * unit
    change = present & (np.abs(want - orig_val) > tol)
    moved_from_held = np.abs(held - prev_held) > 1e-9 * np.maximum(1.0, np.abs(held))
    first = np.arange(n) == 0
    add = ~present & defined & ~first[:, None] & np.where(incr[:, None], np.abs(inc_val) > tol, moved_from_held)
    # an axis the program has not set yet stays unset; the control still holds the old value there
    edits = {}
    for r, a in zip(*np.nonzero(change | add)):
        edits.setdefault(int(r), {})[_AXES[a]] = _fmt(want[r, a], int(dec[r, a]), words[r].get(_AXES[a]))

    # arc words: centre relative to the written start, or R
    arc = (motion == 2) | (motion == 3)
    for r in np.flatnonzero(arc):
        if r == 0:
            continue
        w = words[r]
        s, e, c = prev_held[r], held[r], centre[r]
        if np.isnan(c).any():
            continue
        a0, a1 = _PLANE_AXES.get(int(plane[r]), (0, 1))
        if "R" in w:
            rad = (np.hypot(*(s - c)[[a0, a1]]) + np.hypot(*(e - c)[[a0, a1]])) / 2
            v0, v1 = (s - c)[[a0, a1]], (e - c)[[a0, a1]]
            sweep = np.arctan2(v0[0] * v1[1] - v0[1] * v1[0], v0 @ v1)
            sweep = np.mod(sweep, 2 * np.pi) if motion[r] == 3 else np.mod(-sweep, 2 * np.pi)
            d_r = w["R"].decimals or default["R"]
            u = 10.0 ** -d_r
            rr = np.rint(rad / scale[r] / u) * u
            half = np.hypot(*(e - s)[[a0, a1]]) / 2 / scale[r]
            while rr < half:                                  # rounding must not make R too short
                rr += u
            val = -rr if sweep > np.pi + 1e-12 else rr
            if abs(val - w["R"].value) > 0.5 * u:
                edits.setdefault(int(r), {})["R"] = _fmt(val, d_r, w["R"])
            continue
        for ax in (a0, a1):
            letter = _OFFSET_LETTER[ax]
            d_o = (w[letter].decimals if letter in w and w[letter].decimals else default[letter])
            u = 10.0 ** -d_o
            val = np.rint((c[ax] - s[ax]) / scale[r] / u) * u
            old = w[letter].value if letter in w else 0.0
            if abs(val - old) > 0.5 * u:
                edits.setdefault(int(r), {})[letter] = _fmt(val, d_o, w.get(letter))

    if not edits:
        return data
    out = list(lines)
    for r, ed in edits.items():
        out[line_idx[r]] = _edit_line(lines[line_idx[r]], parsed[r], ed)
    moved = len(edits)
    move_um = _table_np(corrected, "move_um")
    clipped = int(_table_np(corrected, "clipped", bool).sum())
    rounds = int(_table_np(corrected, "iteration", np.int64).max())
    sha = source_sha256 or hashlib.sha256(data).hexdigest()
    text = (f"(CORRECTED PROGRAM - MACHINING ERROR COMPENSATION - {moved} OF {n} MOTION BLOCKS CHANGED"
            f" - MAX MOVE {float(move_um.max()):.1f} UM - {clipped} CLIPPED"
            + (f" AT {max_move_um:g} UM" if max_move_um is not None else "")
            + f" - {rounds} ROUND{'S' if rounds != 1 else ''} - SOURCE SHA256 {sha.upper()})")
    at = _header_line(lines)
    eol = b"\r" if lines[at].endswith(b"\r") else b""
    out.insert(at + 1, text.encode("ascii") + eol)
    return b"\n".join(out)


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


def _edit_line(line: bytes, parsed, edits: dict) -> bytes:
    words, order = parsed
    repl = []                                   # (start, end, bytes)
    for letter, text in edits.items():
        if letter in words:
            w = words[letter]
            repl.append((w.start, w.end, text.encode()))
    added = [(letter, text) for letter, text in edits.items() if letter not in words]
    if added:
        sep = b" " if any(line[e:e + 1] in (b" ", b"\t") for _, _, e in order[:-1]) or b" " in line.split(b"(")[0].strip() else b""
        groups = {}                              # insertion position → words, in _ORDER
        for letter, text in sorted(added, key=lambda t: _ORDER.index(t[0])):
            rank = _ORDER.index(letter)
            after = [e for l, s, e in order if l in _ORDER and _ORDER.index(l) < rank]
            pos, lead = (max(after), True) if after else ((order[0][1] if order else 0), False)
            groups.setdefault((pos, lead), []).append(letter.encode() + text.encode())
        for (pos, lead), ws in groups.items():
            body = sep.join(ws)
            repl.append((pos, pos, sep + body if lead else body + sep))
    out = line
    for s, e, b in sorted(repl, key=lambda t: (t[0], t[1]), reverse=True):
        out = out[:s] + b + out[e:]
    return out


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
    rep = {"n_blocks": (blocks.num_rows, new_blocks.num_rows), "max_dev_um": 0.0, "ok": True, "message": ""}
    if new_blocks.num_rows != blocks.num_rows:
        rep.update(ok=False, message=f"{new_blocks.num_rows} blocks, source has {blocks.num_rows}")
        return rep
    for c in ("block_no", "motion", "plane", "inch", "incremental"):
        if not np.array_equal(_table_np(new_blocks, c, object), _table_np(blocks, c, object)):
            rep.update(ok=False, message=f"column {c} differs from the source")
            return rep
    bno = _table_np(new_blocks, "block_no", np.int64)
    rows = np.searchsorted(bno, _table_np(corrected, "block_no", np.int64))
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


def write_ln_program(corrected: pa.Table, name: str = "CORRECTED", blocks: pa.Table | None = None,
                     use_new: bool = True, decimals: int = 4) -> str:
    """Heidenhain-style program: one ``L``/``LN`` block per NC vertex with the surface normal.

    ``LN X.. Y.. Z.. NX.. NY.. NZ..`` for vertices with a normal (a predicted pass meets them), plain
    ``L`` elsewhere, ``FMAX`` for rapids. Arcs are written as their end points (controls that
    compensate along normals take straight LN blocks; refine arcs before when they matter).
    ``use_new=False`` writes the original path with normals, for controls that apply the
    compensation themselves (3D-ToolComp with :func:`write_comp_table`); do not use the corrected
    path and the table together, that corrects twice. Coordinates are those of the source program
    (tool tip unless ``tool.control_point`` says centre).
    """
    cols = ("x_new_mm", "y_new_mm", "z_new_mm") if use_new else ("x_mm", "y_mm", "z_mm")
    p = np.stack([_table_np(corrected, c) for c in cols], 1)
    nrm = np.stack([_table_np(corrected, c) for c in ("nx", "ny", "nz")], 1)
    motion = _table_np(corrected, "motion", np.int64)
    out = [f"0 BEGIN PGM {name} MM"]
    prev = np.full(3, np.nan)
    k = 1
    fmt = f"{{:+.{decimals}f}}"
    for i in range(p.shape[0]):
        words = []
        for a, letter in enumerate("XYZ"):
            if not np.isclose(p[i, a], prev[a], atol=0.5 * 10.0 ** -decimals, rtol=0):
                words.append(letter + fmt.format(p[i, a]))
        if not words:
            continue
        prev = p[i]
        has_n = motion[i] != 0 and np.all(np.isfinite(nrm[i]))
        line = f"{k} {'LN' if has_n else 'L'} " + " ".join(words)
        if has_n:
            line += " " + " ".join(f"N{letter}{v:+.7f}" for letter, v in zip("XYZ", nrm[i]))
        if motion[i] == 0:
            line += " FMAX"
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
