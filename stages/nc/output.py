"""The corrected NC programs of one program, as files: the source with moved coordinates and the
scheduled feeds (with a ``feed:`` section), reverse-checked by parsing it back, and on request
Heidenhain LN blocks and a compensation table. The written coordinates are the error correction
plus the thermal drift compensation (``drift_*_um`` of ``corrected``, with a ``drift:`` section)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from stages.nc.feed_words import block_feeds, write_feeds
from stages.nc.heidenhain import write_comp_table, write_ln_program
from stages.nc.reader import parse_program
from stages.nc.words import with_header
from stages.nc.writer import reverse_check, write_program
from stages.tables import col
from stages.thermal.compensate import drift_only, max_drift_um, with_drift


def corrected_programs(inputs: dict, params: dict) -> dict[str, bytes]:
    """{file name: bytes} for the ``<out>/nc/`` directory.

    Parameters
    ----------
    inputs : {"program_file": {path, sha256, program_id}, "blocks", "corrected" (None: no correction
        kept; a file only with scheduled feeds or a drift compensation), "corrected@first" (the
        first round's: its drift compensation), "errors", "passes", "feeds"}
    params : {"correct": {max_move_um, ln_normals, comp_table, ...}}
    """
    f = inputs["program_file"]
    src = Path(f["path"])
    blocks, corrected = inputs["blocks"], inputs["corrected"]
    opts = params.get("correct") or {}
    feeds = inputs.get("feeds")
    if corrected is None:
        corrected = drift_only(inputs.get("corrected@first"), blocks)
    if corrected is None:
        if feeds is None or feeds.num_rows == 0:
            return {}
        from schemas.corrected import SCHEMA
        corrected = SCHEMA.empty_table()
    # the written path: the error correction plus the drift compensation (arc centres with their
    # end points); the reverse check and the LN blocks see the same
    drift_um = max_drift_um(corrected)
    corrected = with_drift(corrected)
    data = src.read_bytes()
    scheduled, n_feed = None, 0
    if feeds is not None and feeds.num_rows:
        scheduled = block_feeds(blocks, inputs["passes"], feeds)
        data, n_feed = write_feeds(data, blocks, scheduled)
    if corrected.num_rows:
        text = write_program(data, blocks, corrected, source_sha256=f["sha256"],
                             max_move_um=opts.get("max_move_um"), feeds_changed=n_feed, drift_um=drift_um)
    else:
        text = with_header(data, f"(FEEDS SCHEDULED - {n_feed} F WORDS - COORDINATES AS PROGRAMMED - "
                                 f"SOURCE SHA256 {f['sha256'].upper()})") if n_feed else data
    check = reverse_check(text, blocks, corrected, path=str(src), program_id=f["program_id"])
    if not check.get("ok", False):
        raise RuntimeError(f"{src}: corrected program failed its reverse check: {check}")
    if scheduled is not None:
        _check_feeds(text, blocks, scheduled, str(src), f["program_id"])
    out = {src.name: text}
    if corrected.num_rows == 0:
        return out
    if opts.get("ln_normals"):
        out[f"{src.stem}_ln.h"] = write_ln_program(blocks, corrected, name=src.stem).encode()
    if opts.get("comp_table"):
        out[f"{src.stem}.3dtc.csv"] = write_comp_table(inputs["errors"]).encode()
    return out


def _check_feeds(text: bytes, blocks, scheduled: np.ndarray, path: str, program_id: str) -> None:
    """The written program's feed on every scheduled cutting block is the scheduled one, to half
    the last digit of a whole-number F word."""
    new, _ = parse_program(text, path, program_id)
    m = col(blocks, "motion", np.int64)
    rows = np.flatnonzero((m >= 1) & (m <= 3) & np.isfinite(scheduled))
    got = col(new, "feed_mm_min")[rows]
    tol = 0.5 * np.where(col(blocks, "inch", bool)[rows], 25.4, 1.0) + 1e-9     # an F word's last digit
    if new.num_rows != blocks.num_rows or np.any(np.abs(got - scheduled[rows]) > tol):
        worst = int(np.argmax(np.abs(got - scheduled[rows]))) if rows.size else 0
        raise RuntimeError(f"{path}: written feeds differ from the schedule (line "
                           f"{int(col(blocks, 'line_no', np.int64)[rows[worst]])}: {got[worst]:g} "
                           f"against {scheduled[rows[worst]]:g} mm/min)")
