"""Scheduled feeds written into a program as F words, every other byte left alone.

F is modal: a cutting block (G1 G2 G3) gets an F word only where its scheduled feed differs from
the feed the control holds when it reaches the block; an F word already on a cutting block carries
that block's feed (so it never brings back the old one). F words on other lines (a G0 line, an F
alone) keep their value: the next cutting block restates the feed if it must. Values keep the
program's F formatting (its most common number of decimals) and are in the block's units
(inch/min under G20).
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa

from stages.geometry.sweeps import ragged_ranges
from stages.nc.lexer import INCH_MM
from stages.nc.words import format_values, scan_words, splice
from stages.tables import col


def _integers(values: np.ndarray, plus: np.ndarray) -> np.ndarray:
    """Whole numbers as right-aligned text rows (uint8, 0 = padding), like ``words.format_values``."""
    texts = [(b"+" if p else b"") + str(int(v)).encode() for v, p in zip(values, plus)]
    width = max(len(t) for t in texts)
    return np.array([[0] * (width - len(t)) + list(t) for t in texts], np.uint8)


def block_feeds(blocks: pa.Table, passes: pa.Table, feeds: pa.Table) -> np.ndarray:
    """Scheduled feed (mm/min) per row of ``blocks``: the lowest of the passes over the block (a
    block split into several passes takes the slowest); NaN for blocks no pass schedules."""
    out = np.full(blocks.num_rows, np.inf)
    if feeds.num_rows == 0 or passes.num_rows == 0:
        return np.full(blocks.num_rows, np.nan)
    pid = col(passes, "pass_id", np.int64)
    order = np.argsort(pid)
    k = order[np.searchsorted(pid[order], col(feeds, "pass_id", np.int64))]
    b0, b1 = col(passes, "block_no", np.int64)[k], col(passes, "block_end", np.int64)[k]
    f = col(feeds, "feed_new_mm_min")
    n = b1 - b0 + 1
    blk = ragged_ranges(b0, n)
    bno = col(blocks, "block_no", np.int64)
    rows = np.searchsorted(bno, blk)
    ok = (rows < bno.size) & (bno[np.minimum(rows, bno.size - 1)] == blk)
    np.minimum.at(out, rows[ok], np.repeat(f, n)[ok])
    return np.where(np.isfinite(out), out, np.nan)


def write_feeds(data: bytes, blocks: pa.Table, feed_mm_min: np.ndarray) -> tuple[bytes, int]:
    """The program with F words for the scheduled feeds.

    Parameters
    ----------
    data : the program text whose ``blocks`` table is given (same lines)
    feed_mm_min : per row of ``blocks``, the scheduled feed (NaN: as programmed)

    Returns
    -------
    (text, number of F words written or changed); ``data`` itself when nothing changes.
    """
    motion = col(blocks, "motion", np.int64)
    line = col(blocks, "line_no", np.int64) - 1
    scale = np.where(col(blocks, "inch", bool), INCH_MM, 1.0)
    sc = scan_words(data)
    fi = np.flatnonzero(sc["letter"] == ord("F"))
    f_val = sc["value"]
    dec = int(np.bincount(sc["decimals"][fi]).argmax()) if fi.size else 0
    unit = 10.0 ** -dec
    cutting = (motion >= 1) & (motion <= 3) & np.isfinite(feed_mm_min)
    want = np.where(cutting, np.rint(feed_mm_min / scale / unit) * unit, np.nan)
    # the F word on each block's line (the last one: it is the one the control keeps)
    f_of_line = np.full(int(sc["line_start"].size) + 1, -1, np.int64)
    f_of_line[sc["line"][fi]] = fi
    f_here = f_of_line[line]
    # events in line order: a cutting block sets the feed it wants, another line's F word its own
    ev_line = np.concatenate([line[cutting], sc["line"][fi]])
    ev_val = np.concatenate([want[cutting], f_val[fi]])
    ev_cut = np.concatenate([np.ones(int(cutting.sum()), bool), np.zeros(fi.size, bool)])
    keep = ev_cut | ~np.isin(ev_line, line[cutting])      # a cutting line's own F word is the block's
    ev_line, ev_val = ev_line[keep], ev_val[keep]
    order = np.argsort(ev_line, kind="stable")
    ev_line, ev_val = ev_line[order], ev_val[order]
    cut_rows = np.flatnonzero(cutting)
    prev = np.searchsorted(ev_line, line[cut_rows], side="left") - 1
    held = np.where(prev >= 0, ev_val[np.maximum(prev, 0)], np.nan)
    tol = 0.5 * unit
    has_f = f_here[cut_rows] >= 0
    replace = has_f & ~(np.abs(f_val[np.maximum(f_here[cut_rows], 0)] - want[cut_rows]) <= tol)
    insert = ~has_f & ~(np.abs(held - want[cut_rows]) <= tol)
    rr, ir = cut_rows[replace], cut_rows[insert]
    if rr.size + ir.size == 0:
        return data, 0
    # replacements: the value span of the F word; insertions: after the line's last word
    wi = f_here[rr]
    last_end = np.full(int(sc["line_start"].size) + 1, -1, np.int64)
    np.maximum.at(last_end, sc["line"], sc["vend"])
    spaced = np.zeros(int(sc["line_start"].size) + 1, bool)
    np.logical_or.at(spaced, sc["line"], sc["blank_before"] & ~sc["first"])
    start = np.concatenate([sc["vstart"][wi], last_end[line[ir]]])
    end = np.concatenate([sc["vend"][wi], last_end[line[ir]]])
    vals = np.concatenate([want[rr], want[ir]])
    decs = np.full(vals.size, dec)
    plus = np.concatenate([sc["plus"][wi], np.zeros(ir.size, bool)])
    lead0 = np.concatenate([sc["lead0"][wi], np.ones(ir.size, bool)])
    body = format_values(vals, decs, plus, lead0) if dec else _integers(vals, plus)
    pre = np.zeros((vals.size, 2), np.uint8)
    pre[rr.size:, 0] = np.where(spaced[line[ir]], 32, 0)
    pre[rr.size:, 1] = ord("F")
    body = np.hstack([pre, body])
    o = np.argsort(start, kind="stable")
    return splice(data, start[o], end[o], body[o]), int(vals.size)
