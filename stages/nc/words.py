"""The words of an NC program as arrays, and text edits on them (the writers' byte-level kit).

:func:`scan_words` finds every address word outside comments in one vectorised pass over the bytes;
:func:`format_values` writes numbers in a word's own format (decimals, ``+``, leading zero);
:func:`insert_positions` says where an added word goes; :func:`splice` replaces byte ranges with
one gather; :func:`with_header` adds a comment line after the ``O`` line. Used by the coordinate
writer (:mod:`stages.nc.writer`), the feed words (:mod:`stages.nc.feed_words`) and the via points
(:mod:`stages.nc.via`).
"""
from __future__ import annotations

import numpy as np

from stages.nc.lexer import BLANK, CLASS, CLOSE, LETTER, NL, NUM, OPEN, SEMI, UPPER, Problems, numbers

ORDER = "NGXYZIJKR"          # where an added word goes: after the last word of an earlier letter


def scan_words(data: bytes) -> dict:
    """Every address word of the program outside comments, vectorised over bytes.

    Returns arrays per word: letter (upper-case byte), line (0-based), value, vstart/vend (byte span
    of the value text), decimals, dot, plus, lead0 (a digit before the point), wstart (letter
    position), first (first word of its line), blank_before; and line_start (byte offset of each
    line start).
    """
    raw = np.frombuffer(data, dtype=np.uint8)
    cls = CLASS[raw]
    is_nl = cls == NL
    line_of = np.cumsum(is_nl) - is_nl              # newline byte belongs to its own line
    line_start = np.concatenate(([0], np.flatnonzero(is_nl) + 1))
    opens, closes = cls == OPEN, cls == CLOSE
    comment = np.zeros(raw.size, bool)
    if opens.any() or closes.any():
        depth = np.cumsum(opens) - np.cumsum(closes)
        comment = (depth > 0) | closes
    semi = (cls == SEMI) & ~comment
    if semi.any():
        cs = np.cumsum(semi)
        start_cs = np.concatenate(([0], cs[is_nl]))
        comment |= (cs - start_cs[line_of]) > 0
    pct_line = np.zeros(line_start.size, bool)
    first_code = np.flatnonzero((cls != BLANK) & ~is_nl)
    if first_code.size:
        fl = line_of[first_code]
        firsts = first_code[np.concatenate(([True], fl[1:] != fl[:-1]))]
        pct_line[line_of[firsts[raw[firsts] == 37]]] = True
    letter = (cls == LETTER) & ~comment & ~pct_line[line_of]
    num = (cls == NUM) & ~comment
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
    blank_before = (pos > 0) & (cls[np.maximum(pos - 1, 0)] == BLANK)
    # values: only needed for X Y Z I J K R and F (exactly as the parser reads them)
    value = np.full(pos.size, np.nan)
    want = np.isin(UPPER[raw[pos]], np.frombuffer(b"XYZIJKRF", np.uint8)) & has_v
    idx = np.flatnonzero(want)
    if idx.size:
        value[idx] = numbers(raw, vstart[idx], vend[idx] - vstart[idx], UPPER[raw[pos[idx]]],
                              line_of[pos[idx]], Problems("<program>"))
    return {"letter": UPPER[raw[pos]], "line": wline, "value": value, "vstart": vstart, "vend": vend,
            "decimals": decimals, "dot": dot, "plus": plus, "lead0": lead0, "wstart": pos, "first": first,
            "blank_before": blank_before, "line_start": line_start}


def small_ints(data: bytes, vstart, vend) -> np.ndarray:
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


def format_values(values, decimals, plus, lead0) -> np.ndarray:
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


def insert_positions(wl, w_row, n, rows, letters):
    """Where added words go: after the last word of an earlier letter in ORDER, else before the first."""
    rank_of = np.full(256, -1, np.int64)
    for i, ch in enumerate(ORDER):
        rank_of[ord(ch)] = i
    wr = rank_of[wl["letter"]]
    ends = np.full((n, len(ORDER)), -1, np.int64)
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


def splice(data: bytes, start, end, body) -> bytes:
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


def header_line(lines) -> int:
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


def with_header(data: bytes, comment: str) -> bytes:
    """``data`` with the line ``comment`` after its O line (else its first %, else first)."""
    lines = data.split(b"\n")
    at = header_line(lines)
    eol = b"\r\n" if lines[max(at, 0)].endswith(b"\r") else b"\n"
    text = comment.encode("ascii")
    if at < 0:
        return text + eol + data
    return b"\n".join(lines[:at + 1]) + b"\n" + text + eol + b"\n".join(lines[at + 1:])
