"""Bytes of an NC program → words: the vectorised tokenizer and the problem list of the reader.
"""
from __future__ import annotations

import numpy as np

from stages import InputError

INCH_MM = 25.4

_UNSUPPORTED_LETTER = {
    "A": "rotary axis words (A/B/C, 4/5-axis) are not supported: 3-axis programs only",
    "B": "rotary axis words (A/B/C, 4/5-axis) are not supported: 3-axis programs only",
    "C": "rotary axis words (A/B/C, 4/5-axis) are not supported: 3-axis programs only",
    "U": "secondary axes (U/V/W) are not supported",
    "V": "secondary axes (U/V/W) are not supported",
    "W": "secondary axes (U/V/W) are not supported",
    "E": "E words (thread lead / extruder) are not supported",
    "L": "repeat counts (L) are not supported",
}


_UNSUPPORTED_CHAR = {
    "#": "macro variables (#) are not supported",
    "[": "macro expressions ([ ]) are not supported",
    "]": "macro expressions ([ ]) are not supported",
    "=": "macro assignments (=) are not supported",
    "/": "block delete (/) is not supported: post the program without optional blocks",
    "*": "arithmetic in blocks is not supported",
}


class Problems:
    """Collects (line index, message) and raises the earliest as ``file:line: message``."""

    def __init__(self, path: str):
        self.path, self.items = path, []

    def add_first(self, mask_or_idx, line_of, msg):
        """Record the first line where ``mask`` holds; ``msg`` may be a callable(index) → str."""
        idx = np.flatnonzero(mask_or_idx) if getattr(mask_or_idx, "dtype", None) == bool else np.asarray(mask_or_idx)
        if idx.size:
            i = int(idx[0])
            self.items.append((int(line_of[i]), msg(i) if callable(msg) else msg))

    def raise_if_any(self):
        if self.items:
            line, msg = min(self.items, key=lambda t: t[0])
            more = len(self.items) - 1
            raise InputError(f"{self.path}:{line + 1}: {msg}" + (f" (and {more} more problem{'s' * (more > 1)})" if more else ""))


def ffill(values: np.ndarray, initial=np.nan) -> np.ndarray:
    """Forward-fill NaNs (modal state): each entry takes the last non-NaN value before it."""
    ok = ~np.isnan(values)
    idx = np.where(ok, np.arange(values.size), -1)
    np.maximum.accumulate(idx, out=idx)
    out = values[np.maximum(idx, 0)]
    out[idx < 0] = initial
    return out


# byte classes for the tokenizer (one table lookup per byte instead of many comparisons)
OTHER, LETTER, NUM, BLANK, NL, OPEN, CLOSE, SEMI, PCT, CTRL = range(10)


CLASS = np.full(256, OTHER, np.uint8)


CLASS[:32] = CTRL


CLASS[[9, 13, 32]] = BLANK


CLASS[10] = NL


CLASS[26] = BLANK  # DOS end-of-file marker


CLASS[ord("A"):ord("Z") + 1] = LETTER


CLASS[ord("a"):ord("z") + 1] = LETTER


CLASS[[ord(c) for c in "0123456789.+-"]] = NUM


CLASS[[ord("("), ord(")"), ord(";"), ord("%")]] = [OPEN, CLOSE, SEMI, PCT]


UPPER = np.arange(256, dtype=np.uint8)


UPPER[ord("a"):ord("z") + 1] -= 32


_POW10 = 10.0 ** np.arange(20)


def tokenize(data: bytes, path: str):
    """Split a program into words.

    Returns
    -------
    letters : (w,) uint8 address letters (upper case)
    values : (w,) float64 values
    w_line : (w,) int line index (0-based) of each word
    n_lines : int
    """
    err = Problems(path)
    raw = np.frombuffer(data, dtype=np.uint8)
    if raw.size == 0:
        raise InputError(f"{path}:1: empty file")
    cls = CLASS[raw]
    is_nl = cls == NL
    # 0-based line of every byte that is not itself a newline (errors and code never are)
    line_of = np.cumsum(is_nl, dtype=np.int32)
    n_lines = int(line_of[-1]) + (0 if is_nl[-1] else 1)

    ctrl = cls == CTRL
    if ctrl.any():
        def _col(i):
            return i - (np.flatnonzero(is_nl[:i])[-1] + 1 if is_nl[:i].any() else 0)
        err.add_first(ctrl, line_of, lambda i: f"binary data (byte 0x{raw[i]:02x} at column {_col(i) + 1}): not a text NC program")
        err.raise_if_any()

    # comments: ( ... ) closed on the same line, and ; to the end of the line outside parentheses
    opens, closes = cls == OPEN, cls == CLOSE
    comment = None
    if opens.any() or closes.any():
        depth = np.cumsum(opens, dtype=np.int32) - np.cumsum(closes, dtype=np.int32)
        err.add_first(depth < 0, line_of, "')' without '('")
        at_eol = np.concatenate((depth[is_nl], depth[-1:]))
        err.add_first(at_eol != 0, np.arange(at_eol.size), "unbalanced parentheses: comment not closed on its line")
        err.raise_if_any()
        comment = (depth > 0) | closes
    semi = cls == SEMI
    if comment is not None:
        semi &= ~comment
    if semi.any():
        cs = np.cumsum(semi, dtype=np.int32)
        start_cs = np.concatenate(([0], cs[is_nl]))
        after_semi = (cs - start_cs[line_of]) > 0
        comment = after_semi if comment is None else comment | after_semi
    code = (cls != BLANK) & ~is_nl
    if comment is not None:
        code &= ~comment
    pos = np.flatnonzero(code)
    ln = line_of[pos]
    first_in_line = np.ones(pos.size, bool)
    first_in_line[1:] = ln[1:] != ln[:-1]
    # '%' lines (tape start/end) carry no code
    pct = raw[pos] == 37
    if pct.any():
        keep = ~np.isin(ln, ln[first_in_line & pct])
        pos, ln, first_in_line = pos[keep], ln[keep], first_in_line[keep]
        err.add_first(raw[pos] == 37, ln, "'%' inside a block")
    ch, kind = UPPER[raw[pos]], cls[pos]
    is_letter = kind == LETTER
    bad = (kind != LETTER) & (kind != NUM)
    if bad.any():
        def _bad_char_msg(i):
            c = chr(ch[i]) if ch[i] < 128 else f"byte 0x{ch[i]:02x}"
            return _UNSUPPORTED_CHAR.get(c, f"unexpected character {c!r} outside a comment")
        err.add_first(bad, ln, _bad_char_msg)
    for letter, why in _UNSUPPORTED_LETTER.items():
        err.add_first(ch == ord(letter), ln, why)
    # every block starts with an address letter
    err.add_first(first_in_line & ~is_letter, ln, "number without an address letter")
    err.raise_if_any()

    starts = np.flatnonzero(is_letter)
    ends = np.empty_like(starts)
    ends[:-1] = starts[1:]
    ends[-1:] = ch.size
    # a word also ends at the end of its line
    vlen = ends - starts - 1
    letters = ch[starts]
    w_line = ln[starts]
    err.add_first(vlen == 0, w_line, lambda i: f"address {chr(letters[i])} without a value")
    err.add_first(vlen > 15, w_line, lambda i: f"value of {chr(letters[i])} is too long")
    err.raise_if_any()
    values = numbers(ch, starts + 1, vlen, letters, w_line, err)
    return letters, values, w_line, n_lines


def numbers(ch, start, length, letters, w_line, err):
    """Convert the value characters of every word to float, vectorised and exactly.

    Horner's rule over the character columns builds an integer mantissa (≤ 15 digits, exact in
    float64) that is divided by 10**decimals: correctly rounded, i.e. equal to Python's float().
    """
    width = int(length.max()) if length.size else 1
    n = start.size
    mant = np.zeros(n)
    decimals = np.zeros(n, np.int64)
    n_dig = np.zeros(n, np.int64)
    n_dot = np.zeros(n, np.int64)
    late_sign = np.zeros(n, bool)
    for j in range(width):
        inside = j < length
        c = np.where(inside, ch[np.minimum(start + j, ch.size - 1)], 0)
        d = c.astype(np.int64) - 48
        is_d = (d >= 0) & (d <= 9)
        mant = np.where(is_d, mant * 10 + d, mant)
        decimals += is_d & (n_dot > 0)
        n_dig += is_d
        n_dot += c == 46
        if j:
            late_sign |= (c == 45) | (c == 43)
    badnum = (n_dig == 0) | (n_dot > 1) | late_sign

    def _msg(i):
        text = bytes(ch[start[i]:start[i] + length[i]]).decode()
        return f"malformed number {text!r} for address {chr(letters[i])}"
    err.add_first(badnum, w_line, _msg)
    err.raise_if_any()
    neg = ch[start] == 45
    return np.where(neg, -mant, mant) / _POW10[decimals]
