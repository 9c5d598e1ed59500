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


class ProgramError(InputError):
    """A program that cannot be used, with every problem found: ``problems`` is a list of
    (line, column or None, message), 1-based, in file order. ``str()`` is the first problem as
    ``file:line: message at column c`` and how many more there are."""

    def __init__(self, path: str, problems: list):
        self.path, self.problems = path, problems
        line, col, msg = problems[0]
        more = len(problems) - 1
        super().__init__(f"{path}:{line}: {where(msg, col)}"
                         + (f" (and {more} more problem{'s' * (more > 1)})" if more else ""))


def where(msg: str, col) -> str:
    """A problem's message with its column after what was found ("what at column c: why")."""
    if col is None:
        return msg
    what, sep, why = msg.partition(": ")
    return f"{what} at column {col}{sep}{why}"


class Problems:
    """Collects every problem of a program and raises them together as a :class:`ProgramError`.

    The parser checks in phases (a later phase needs what an earlier one established). Problems
    later phases can live with (a comment not closed on its line, a line of prose, an unsupported
    axis word) are kept and checking goes on; the first phase that finds one they cannot live with
    raises everything found so far.
    """

    # a check that holds on many lines (a pasted text) lists this many of them
    MAX_PER_CHECK = 50

    def __init__(self, path: str):
        self.path, self.items = path, []

    def add(self, mask_or_idx, line_of, msg, col_of=None):
        """Record every index where ``mask`` holds (or every index given), with the line
        ``line_of[i]`` (0-based) and column ``col_of[i]`` (1-based; None: the whole block);
        ``msg`` may be a callable(index) → str."""
        idx = np.flatnonzero(mask_or_idx) if getattr(mask_or_idx, "dtype", None) == bool else np.asarray(mask_or_idx)
        for i in idx[:self.MAX_PER_CHECK].tolist():
            self.items.append((int(line_of[i]) + 1, None if col_of is None else int(col_of[i]),
                               msg(i) if callable(msg) else msg))

    def raise_if_any(self, since: int = 0):
        """Raise every problem so far if there are more than ``since`` (problems that later
        checks can live with, counted before them)."""
        if len(self.items) > since:
            items = sorted(set(self.items), key=lambda t: (t[0], t[1] or 0, t[2]))
            raise ProgramError(self.path, items)


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


def tokenize(data: bytes, path: str, err: Problems | None = None):
    """Split a program into words.

    Returns
    -------
    letters : (w,) uint8 address letters (upper case)
    values : (w,) float64 values
    w_line : (w,) int line index (0-based) of each word
    n_lines : int
    w_col : (w,) int column (1-based, in bytes) of each word's address letter

    ``err`` collects the problems (a new one when None): a line of prose is left out of the words
    and recorded there, and the caller goes on checking the other lines before it raises.

    Raises
    ------
    ProgramError
        with every problem of the first checking phase that found any (line and column each).
    """
    err = Problems(path) if err is None else err
    raw = np.frombuffer(data, dtype=np.uint8)
    if raw.size == 0:
        raise InputError(f"{path}:1: empty file")
    cls = CLASS[raw]
    is_nl = cls == NL
    # 0-based line of every byte that is not itself a newline (errors and code never are)
    line_of = np.cumsum(is_nl, dtype=np.int32)
    n_lines = int(line_of[-1]) + (0 if is_nl[-1] else 1)
    line_start = np.concatenate(([0], np.flatnonzero(is_nl) + 1))
    col_of = np.arange(raw.size) - line_start[line_of] + 1

    ctrl = cls == CTRL
    if ctrl.any():
        err.add(ctrl, line_of, lambda i: f"binary data (byte 0x{raw[i]:02x}): not a text NC program", col_of)
        err.raise_if_any()

    # comments: ( ... ) closed on the same line, and ; to the end of the line outside parentheses
    opens, closes = cls == OPEN, cls == CLOSE
    comment = None
    if opens.any() or closes.any():
        # depth within each line: a comment not closed on its line ends there (and is a problem)
        net = np.cumsum(opens.astype(np.int32) - closes)
        depth = net - np.concatenate(([0], net[is_nl]))[line_of]
        err.add(closes & (depth < 0) & (np.concatenate(([0], depth[:-1])) == 0), line_of, "')' without '('", col_of)
        last = np.concatenate((np.flatnonzero(is_nl) - 1, [raw.size - 1]))
        open_at_eol = (depth[np.maximum(last, 0)] > 0) & (last >= np.concatenate(([0], np.flatnonzero(is_nl) + 1)))
        err.add(open_at_eol, np.arange(open_at_eol.size), "unbalanced parentheses: comment not closed on its line")
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
        err.add(raw[pos] == 37, ln, "'%' inside a block", col_of[pos])
    ch, kind = UPPER[raw[pos]], cls[pos]
    bad = (kind != LETTER) & (kind != NUM)

    def _bad_char_msg(i):
        c = chr(ch[i]) if ch[i] < 128 else f"byte 0x{ch[i]:02x}"
        return _UNSUPPORTED_CHAR.get(c, f"unexpected character {c!r} outside a comment")
    # a line of prose (two letters in a row: no address takes a letter for its value) is one
    # problem, the word it starts with (and its odd characters), not one problem per letter
    letters_raw = (cls == LETTER) & code
    run2 = np.flatnonzero(letters_raw[:-1] & letters_raw[1:] & ~np.concatenate(([False], letters_raw[:-2])))
    if run2.size:
        prose_first = run2[np.concatenate(([True], line_of[run2][1:] != line_of[run2][:-1]))]

        def _word(i):
            end = i
            while end < raw.size and letters_raw[end]:
                end += 1
            return f"unrecognised word {bytes(raw[i:end]).decode('ascii')!r}: an address letter takes a number; text belongs in a comment ( )"
        err.add(prose_first, line_of, _word, col_of)
        prose = np.isin(ln, line_of[prose_first])
        err.add(bad & prose, ln, _bad_char_msg, col_of[pos])
        keep = ~prose
        pos, ln, first_in_line, ch, kind, bad = (a[keep] for a in (pos, ln, first_in_line, ch, kind, bad))
    is_letter = kind == LETTER
    col = col_of[pos]
    for letter, why in _UNSUPPORTED_LETTER.items():
        err.add(ch == ord(letter), ln, why, col)
    # comments closed at the end of their line, prose lines left out, unsupported axes read as
    # words the reader ignores: the words can be read and checked on
    settled = len(err.items)
    err.add(bad, ln, _bad_char_msg, col)
    # every block starts with an address letter
    err.add(first_in_line & ~is_letter, ln, "number without an address letter", col)
    err.raise_if_any(settled)

    starts = np.flatnonzero(is_letter)
    ends = np.empty_like(starts)
    ends[:-1] = starts[1:]
    ends[-1:] = ch.size
    # a word also ends at the end of its line
    vlen = ends - starts - 1
    letters = ch[starts]
    w_line = ln[starts]
    w_col = col[starts]
    err.add(vlen == 0, w_line, lambda i: f"address {chr(letters[i])} without a value", w_col)
    err.add(vlen > 15, w_line, lambda i: f"value of {chr(letters[i])} is too long", w_col)
    err.raise_if_any(settled)
    values = numbers(ch, starts + 1, vlen, letters, w_line, err, w_col, settled)
    return letters, values, w_line, n_lines, w_col


def numbers(ch, start, length, letters, w_line, err, w_col=None, settled=0):
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
    err.add(badnum, w_line, _msg, w_col)
    err.raise_if_any(settled)
    neg = ch[start] == 45
    return np.where(neg, -mant, mant) / _POW10[decimals]
