"""Compare the tables of two runs of the same workflow (e.g. before and after a refactoring).

    python3 scripts/compare_runs.py RUN_A RUN_B [--rtol 1e-9] [--atol 1e-9] [--ignore-columns a,b]

Each run directory holds ``tables/<table>/*.parquet``. Rows are matched on the table's key columns
(program_id plus pass_id / block_no / point_id where present); numbers must agree within
``atol + rtol·|b|``, everything else exactly. Prints one line per table and exits 1 on any
difference. Columns or tables present in only one run are listed (with ``--ignore-columns`` to
allow the ones a change meant to drop).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

KEYS = ("program_id", "pass_id", "block_no", "point_id", "rank", "effect")


def read_table(run: Path, name: str) -> pa.Table:
    files = sorted((run / "tables" / name).glob("*.parquet"))
    return pa.concat_tables([pq.read_table(f) for f in files], promote_options="default")


def _values(col: pa.ChunkedArray):
    if pa.types.is_list(col.type) or pa.types.is_large_list(col.type):
        return [np.asarray(v, float) if v is not None else None for v in col.to_pylist()]
    return col.to_numpy(zero_copy_only=False)


def compare_column(a, b, rtol: float, atol: float) -> tuple[int, float]:
    """(number of differing rows, largest absolute difference of numbers) of two aligned columns."""
    if isinstance(a, list):
        bad, worst = 0, 0.0
        for x, y in zip(a, b):
            if x is None or y is None:
                bad += (x is None) != (y is None)
                continue
            if x.shape != y.shape:
                bad += 1
                continue
            d = np.abs(x - y)
            both_nan = np.isnan(x) & np.isnan(y)
            if np.any(~both_nan & ~(d <= atol + rtol * np.abs(y))):
                bad += 1
            worst = max(worst, float(np.nanmax(np.where(both_nan, 0.0, d), initial=0.0)))
        return bad, worst
    if a.dtype.kind in "fiu" and b.dtype.kind in "fiu":
        x, y = a.astype(float), b.astype(float)
        both_nan = np.isnan(x) & np.isnan(y)
        d = np.abs(x - y)
        ok = both_nan | (d <= atol + rtol * np.abs(y))
        return int((~ok).sum()), float(np.max(np.where(both_nan, 0.0, np.nan_to_num(d, nan=np.inf)), initial=0.0))
    return int(sum(1 for x, y in zip(a, b) if not (x == y or (x is None and y is None)))), 0.0


def compare_tables(ta: pa.Table, tb: pa.Table, rtol: float, atol: float, ignore: set[str]) -> list[str]:
    problems = []
    ca, cb = set(ta.column_names) - ignore, set(tb.column_names) - ignore
    if ca != cb:
        problems.append(f"columns only in A {sorted(ca - cb)}, only in B {sorted(cb - ca)}")
    if ta.num_rows != tb.num_rows:
        return problems + [f"rows {ta.num_rows} against {tb.num_rows}"]
    keys = [k for k in KEYS if k in ca & cb]
    if keys:
        ta, tb = ta.sort_by([(k, "ascending") for k in keys]), tb.sort_by([(k, "ascending") for k in keys])
    for c in sorted(ca & cb):
        bad, worst = compare_column(_values(ta.column(c)), _values(tb.column(c)), rtol, atol)
        if bad:
            problems.append(f"{c}: {bad} rows differ (largest {worst:.3g})")
    return problems


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run_a", type=Path)
    ap.add_argument("run_b", type=Path)
    ap.add_argument("--rtol", type=float, default=1e-9)
    ap.add_argument("--atol", type=float, default=1e-9)
    ap.add_argument("--ignore-columns", default="", help="comma-separated columns to leave out")
    ap.add_argument("--rename", default="", help="comma-separated old=new table names (A's name = B's)")
    args = ap.parse_args(argv)
    ignore = {c for c in args.ignore_columns.split(",") if c}
    rename = dict(r.split("=") for r in args.rename.split(",") if r)
    names_a = {p.name for p in (args.run_a / "tables").iterdir() if p.is_dir()}
    names_b = {p.name for p in (args.run_b / "tables").iterdir() if p.is_dir()}
    failed = False
    for name in sorted(names_a | set(rename)):
        other = rename.get(name, name)
        if name not in names_a or other not in names_b:
            print(f"{name:>14}: only in {'A' if name in names_a else 'B'}")
            failed = True
            continue
        ta, tb = read_table(args.run_a, name), read_table(args.run_b, other)
        problems = compare_tables(ta, tb, args.rtol, args.atol, ignore)
        print(f"{name:>14}: {ta.num_rows} rows, " + ("identical within tolerance" if not problems else "; ".join(problems)))
        failed |= bool(problems)
    for name in sorted(names_b - names_a - set(rename.values())):
        print(f"{name:>14}: only in B")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
