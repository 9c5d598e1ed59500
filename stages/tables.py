"""Arrow tables ↔ numpy arrays: the column helpers every stage uses at its boundary."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from stages import InputError


def task_count(n_rows: int, rows_per_task: int, most: int) -> int:
    """Tasks a stage splits one program into: about ``rows_per_task`` rows each, 1 … ``most``."""
    return int(min(most, max(1, -(-int(n_rows) // max(1, int(rows_per_task))))))


def col(table: pa.Table, name: str, dtype=float) -> np.ndarray:
    """One column as a numpy array of ``dtype`` (nulls become NaN for floats)."""
    return table.column(name).to_numpy(zero_copy_only=False).astype(dtype)


def xyz(table: pa.Table, names) -> np.ndarray:
    """Three columns as an (n, 3) float array."""
    if table.num_rows == 0:
        return np.zeros((0, 3))
    return np.stack([col(table, c) for c in names], axis=1)


def list_column(values: np.ndarray) -> pa.ListArray:
    """(P, n) float array → Arrow list<double> column with n values per row."""
    values = np.ascontiguousarray(values, dtype=np.float64)
    n_rows, n = values.shape
    offsets = pa.array(np.arange(n_rows + 1, dtype=np.int32) * n)
    return pa.ListArray.from_arrays(offsets, pa.array(values.ravel()))


def list_values(column, what: str) -> np.ndarray:
    """Arrow list<double> column with equally long rows → (P, n) float array."""
    arr = column.combine_chunks() if isinstance(column, pa.ChunkedArray) else column
    n_rows = len(arr)
    if n_rows == 0:
        return np.zeros((0, 0))
    if arr.null_count:
        raise InputError(f"{what}: null list")
    offsets = np.asarray(arr.offsets)
    lengths = np.diff(offsets)
    if np.any(lengths != lengths[0]):
        raise InputError(f"{what}: rows have different lengths {sorted(set(lengths.tolist()))[:5]}")
    flat = np.asarray(arr.values.to_numpy(zero_copy_only=False), dtype=float)
    return flat[offsets[0]:offsets[-1]].reshape(n_rows, int(lengths[0]))


def nullable_list_column(rows: np.ndarray) -> pa.ListArray:
    """(P, n) float array → Arrow list<double> column; a row of NaN becomes null."""
    rows = np.asarray(rows, float)
    null = np.isnan(rows).all(axis=1)
    off = np.r_[0, np.cumsum(np.where(null, 0, rows.shape[1]))].astype(np.int32)
    return pa.ListArray.from_arrays(pa.array(off, mask=np.r_[null, False]), pa.array(rows[~null].ravel(), pa.float64()))


def padded_list_values(column) -> np.ndarray:
    """Arrow list<double> column with rows of any length (nulls too) → (P, longest) float array,
    NaN where a row is shorter or null."""
    arr = column.combine_chunks() if isinstance(column, pa.ChunkedArray) else column
    n = pc.fill_null(pc.list_value_length(arr), 0).to_numpy().astype(np.int64)
    out = np.full((len(n), int(n.max(initial=0))), np.nan)
    row = np.repeat(np.arange(len(n)), n)
    out[row, np.arange(row.size) - np.repeat(np.cumsum(n) - n, n)] = arr.flatten().to_numpy(zero_copy_only=False)
    return out


def binary_rows(column):
    """Binary column → ((P, L) uint8 when all rows are L bytes long, else a list of arrays), lengths."""
    arr = column.combine_chunks() if isinstance(column, pa.ChunkedArray) else column
    if arr.null_count:
        raise InputError(f"{arr.type} column: null value")
    n = len(arr)
    bufs = arr.buffers()
    offsets = np.frombuffer(bufs[1], dtype=np.int32)[arr.offset:arr.offset + n + 1]
    data = np.frombuffer(bufs[2], dtype=np.uint8) if bufs[2] is not None else np.zeros(0, np.uint8)
    lengths = np.diff(offsets)
    if n and np.all(lengths == lengths[0]):
        return data[offsets[0]:offsets[-1]].reshape(n, int(lengths[0])), lengths
    return [data[offsets[i]:offsets[i + 1]] for i in range(n)], lengths


def pick_entry(entry, tool_t, key: str) -> dict:
    """The workflow entry (tool/material) for T number ``tool_t`` when the workflow gives a list."""
    if isinstance(entry, (list, tuple)):
        for e in entry:
            if e.get("t") == tool_t:
                return e
        raise InputError(f"{key}: no entry for T{tool_t}")
    if entry is None:
        raise InputError(f"{key}: missing")
    return entry


def program_tool_number(passes: pa.Table):
    """The T number a program's passes are cut with (None when the program calls none)."""
    if "tool" not in passes.column_names or passes.num_rows == 0:
        return None
    tools = [t for t in passes.column("tool").to_pylist() if t is not None]
    return tools[0] if tools else None


def match_passes(passes: pa.Table, pass_ids: np.ndarray, table_name: str) -> np.ndarray:
    """Row index into ``passes`` of every pass id (InputError naming the first missing one)."""
    ids = passes.column("pass_id").to_numpy()
    order = np.argsort(ids, kind="stable")
    pos = np.searchsorted(ids[order], pass_ids)
    pos = np.minimum(pos, len(ids) - 1) if len(ids) else pos
    ok = (len(ids) > 0) & (ids[order][pos] == pass_ids) if len(ids) else np.zeros(len(pass_ids), bool)
    if not np.all(ok):
        bad = pass_ids[~ok][0]
        raise InputError(f"{table_name}: pass_id {bad} is not in the passes table")
    return order[pos]


def read_numeric_csv(path, columns, what: str):
    """Named numeric columns of a small CSV table (force records, FRF tables, tool profiles...).

    Returns an (n, len(columns)) float array in the order of ``columns``. Blank lines and lines
    starting with ``#`` are skipped; a missing column or a non-number is an ``InputError`` naming
    the file and line, ``what`` saying which input it is.
    """
    try:
        lines = Path(path).read_text().splitlines()
    except OSError as e:
        raise InputError(f"{what}: cannot read {path}: {e.strerror or e}") from None
    header = [h.strip().lower() for h in lines[0].split(",")] if lines else []
    missing = [c for c in columns if c not in header]
    if missing:
        raise InputError(f"{path}:1: {what} header lacks {missing} (expected {','.join(columns)}), "
                         f"got {lines[0] if lines else ''!r}")
    cols = [header.index(c) for c in columns]
    rows = []
    for n, line in enumerate(lines[1:], start=2):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.split(",")
        try:
            rows.append([float(parts[c]) for c in cols])
        except (ValueError, IndexError):
            raise InputError(f"{path}:{n}: expected numbers {','.join(columns)}, got {line!r}") from None
    return np.array(rows, dtype=float).reshape(-1, len(columns))
