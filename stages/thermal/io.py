"""Drift measurement files: CSV with a header, one on-machine reference measurement per line.

Columns: ``time_s, dx_um, dy_um, dz_um`` (required), ``spindle_rpm`` (the heat input, optional),
``x_mm, y_mm, z_mm`` (axis positions of the measurement, optional: cross terms), ``temp_*`` (°C,
optional). Every error names the file, the line and the column.
"""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from stages import InputError
from stages.thermal.model import POSITION_COLUMNS

REQUIRED = ("time_s", "dx_um", "dy_um", "dz_um")
HEAT_COLUMN = "spindle_rpm"


def read_table(path, required=REQUIRED) -> dict:
    """Columns of a drift CSV as float arrays, times strictly increasing.

    Raises
    ------
    InputError
        Missing file or columns, a value that is not a number, times not increasing, no rows.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file")
    with path.open(newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        raise InputError(f"{path}: empty file (expected a header line with {', '.join(required)})")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in required if c not in header]
    if missing:
        raise InputError(f"{path}:1: missing column(s) {', '.join(missing)}; the header has {', '.join(header)}")
    cols = {h: [] for h in header}
    for line, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != len(header):
            raise InputError(f"{path}:{line}: {len(row)} values for the header's {len(header)} columns")
        for h, v in zip(header, row):
            try:
                x = float(v)
            except ValueError:
                raise InputError(f"{path}:{line}: column {h!r}: {v.strip()!r} is not a number") from None
            if not np.isfinite(x):
                raise InputError(f"{path}:{line}: column {h!r}: {v.strip()!r} is not a finite number")
            cols[h].append((x, line))
    if not cols[required[0]]:
        raise InputError(f"{path}: no data lines under the header")
    t = np.array([x for x, _ in cols["time_s"]])
    lines = [ln for _, ln in cols["time_s"]]
    bad = np.flatnonzero(np.diff(t) <= 0)
    if len(bad):
        i = int(bad[0])
        raise InputError(f"{path}:{lines[i + 1]}: time_s {t[i + 1]:g} is not after the previous line's {t[i]:g} "
                         f"(line {lines[i]}): times must increase")
    if t[0] < 0:
        raise InputError(f"{path}:{lines[0]}: time_s {t[0]:g} is negative (time 0 is the machine's cold start)")
    out = {h: np.array([x for x, _ in v]) for h, v in cols.items()}
    out["_lines"] = np.array(lines)
    return out


def model_columns(data: dict) -> dict:
    """Which optional columns a fit on ``data`` uses: heat input, positions, temperatures."""
    positions = tuple(c for c in POSITION_COLUMNS if c in data and np.ptp(data[c]) > 0)
    return {"heat_column": HEAT_COLUMN if HEAT_COLUMN in data else None, "positions": positions,
            "temperatures": tuple(sorted(c for c in data if c.startswith("temp_")))}
