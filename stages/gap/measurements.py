"""Measured points of a machined part (DESIGN §6 ``measurements``, §8; issue 7).

Reads a CMM-style CSV (x y z, normal i j k, deviation; optional point id and time stamp) or a
Parquet file with the ``measurements`` columns. Column names are matched case-insensitively from a
list of usual CMM spellings; a workflow mapping (``measurements: {file, columns: {x_mm: X, ...}}``)
names other columns. Units: coordinates in mm (``length_unit: inch`` or ``um`` converts), deviation
in µm (``deviation_unit: mm`` converts); a header that states a unit (``dev_mm``, ``Dev [mm]``)
is honoured and must not contradict the declared one.

Never silent: a missing column, a non-number, duplicated point ids, deviations whose size says
they are in the other unit, are errors (``InputError`` naming file and line). Individual bad rows —
a NaN, a normal that is not a unit vector (|n| off by more than ``NORMAL_TOL``) — are rejected and
listed (``Rejected``), never dropped quietly; points off the part are rejected later, by the
diagnosis, which knows the machined surface. If more than half the rows are rejected, that is an
error too.
"""
from __future__ import annotations

import csv
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from stages import InputError

NORMAL_TOL = 0.02          # |n| must be within 2 % of 1 (then it is renormalised)
COLUMNS = ("point_id", "x_mm", "y_mm", "z_mm", "nx", "ny", "nz", "err_um", "t_s")
ALIASES = {
    "point_id": ("point_id", "id", "point", "name", "pt", "no"),
    "x_mm": ("x_mm", "x", "meas_x", "actual_x", "nominal_x", "x_nom"),
    "y_mm": ("y_mm", "y", "meas_y", "actual_y", "nominal_y", "y_nom"),
    "z_mm": ("z_mm", "z", "meas_z", "actual_z", "nominal_z", "z_nom"),
    "nx": ("nx", "i", "ni", "normal_x", "vec_i"),
    "ny": ("ny", "j", "nj", "normal_y", "vec_j"),
    "nz": ("nz", "k", "nk", "normal_z", "vec_k"),
    "err_um": ("err_um", "deviation", "dev", "deviation_um", "dev_um", "error", "err", "deviation_mm", "dev_mm"),
    "t_s": ("t_s", "time", "time_s", "t"),
}
LENGTH = {"mm": 1.0, "um": 1e-3, "inch": 25.4}
DEVIATION = {"um": 1.0, "mm": 1e3, "inch": 25.4e3}


@dataclass
class Rejected:
    """Rows not used, each with the file line and why."""

    rows: list = field(default_factory=list)  # (point_id, line, reason)

    def add(self, ids, lines, reason):
        for i, ln in zip(np.atleast_1d(ids), np.atleast_1d(lines)):
            self.rows.append((int(i), int(ln), reason))

    def __len__(self):
        return len(self.rows)

    def to_csv(self, path) -> None:
        with open(path, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["point_id", "line", "reason"])
            w.writerows(self.rows)


def _unit_in_header(name: str) -> Optional[str]:
    m = re.search(r"(?:[_\s\[(])(mm|um|µm|inch|in)\]?\)?$", name.strip().lower())
    if not m:
        return None
    return {"µm": "um", "in": "inch"}.get(m.group(1), m.group(1))


def _clean(h: str) -> str:
    return re.sub(r"[\s\[\]()]+", "_", h.strip().lower()).strip("_").replace("µm", "um")


def read_measurements(path, columns: Optional[dict] = None, length_unit: str = "mm",
                      deviation_unit: Optional[str] = None, require_deviation: bool = True):
    """Read a measurement file → (``measurements`` table, ``Rejected``, line numbers per row).

    Parameters
    ----------
    path : str or Path
        ``.csv`` (CMM export) or ``.parquet`` (DESIGN §6 columns).
    columns : dict, optional
        Mapping from our column names (``x_mm``, ``nx``, ``err_um``, ``point_id``, ``t_s``...) to the
        file's header names.
    length_unit, deviation_unit : str
        Units of coordinates (mm, um, inch) and of the deviation (um, mm); ``deviation_unit`` None
        means µm unless the header says otherwise.
    require_deviation : bool
        False for a measurement plan (points and normals only); err_um is then NaN.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"measurements: no such file {path}")
    if length_unit not in LENGTH:
        raise InputError(f"measurements.length_unit: {length_unit!r} is not one of {sorted(LENGTH)}")
    if deviation_unit is not None and deviation_unit not in DEVIATION:
        raise InputError(f"measurements.deviation_unit: {deviation_unit!r} is not one of {sorted(DEVIATION)}")
    columns = dict(columns or {})
    unknown = sorted(set(columns) - set(COLUMNS))
    if unknown:
        raise InputError(f"measurements.columns: unknown key(s) {unknown} (keys are {', '.join(COLUMNS)})")
    if path.suffix.lower() == ".parquet":
        try:
            tab = pq.read_table(path)
        except Exception as e:  # pyarrow raises several types for bad files
            raise InputError(f"{path}: cannot read Parquet: {e}") from None
        header = list(tab.column_names)
        data = {h: np.asarray(tab.column(h).to_numpy(zero_copy_only=False)) for h in header}
        lines = np.arange(len(tab)) + 1            # row numbers (1-based) for messages
    else:
        header, data, lines = _read_csv(path)
    cleaned = {_clean(h): h for h in header}
    pick: dict[str, Optional[str]] = {}
    for col in COLUMNS:
        if col in columns:
            if columns[col] not in header:
                raise InputError(f"{path}:1: measurements.columns.{col} names {columns[col]!r}, "
                                 f"not a column of the file ({', '.join(header)})")
            pick[col] = columns[col]
            continue
        pick[col] = next((cleaned[a] for a in ALIASES[col] if a in cleaned), None)
    need = ["x_mm", "y_mm", "z_mm", "nx", "ny", "nz"] + (["err_um"] if require_deviation else [])
    missing = [c for c in need if pick[c] is None]
    if missing:
        raise InputError(f"{path}:1: no column for {missing} (header: {', '.join(header)}); name them in the "
                         f"workflow's measurements.columns mapping")
    n = len(lines)

    def num(col):
        h = pick[col]
        v = data[h]
        try:
            return np.asarray(v, dtype=float)
        except (ValueError, TypeError):
            for i, x in enumerate(v):
                try:
                    float(x)
                except (ValueError, TypeError):
                    raise InputError(f"{path}:{lines[i]}: column {h!r}: {x!r} is not a number") from None
            raise

    xyz = np.stack([num("x_mm"), num("y_mm"), num("z_mm")], 1) * LENGTH[length_unit]
    nrm = np.stack([num("nx"), num("ny"), num("nz")], 1)
    # deviation unit: declared, or stated in the header; they must agree
    dev_unit = deviation_unit
    if pick["err_um"] is not None:
        hu = _unit_in_header(pick["err_um"])
        if hu is not None and dev_unit is not None and hu != dev_unit:
            raise InputError(f"{path}:1: deviation column {pick['err_um']!r} says {hu}, the workflow says "
                             f"deviation_unit: {dev_unit}")
        dev_unit = dev_unit or hu or "um"
        err = num("err_um") * DEVIATION[dev_unit]
    else:
        err = np.full(n, np.nan)
    t = num("t_s") if pick["t_s"] is not None else np.full(n, np.nan)
    if pick["point_id"] is not None:
        try:
            ids = np.asarray(data[pick["point_id"]], dtype=np.int64)
        except (ValueError, TypeError):
            # text ids (CMM point names): keep their order as ids, duplicates still caught below
            names = np.asarray(data[pick["point_id"]], dtype=str)
            _, first, inv = np.unique(names, return_index=True, return_inverse=True)
            if len(first) != n:
                dup = np.flatnonzero(np.bincount(inv) > 1)[0]
                rows = np.flatnonzero(inv == dup)
                raise InputError(f"{path}:{lines[rows[1]]}: point {names[rows[1]]!r} repeats line {lines[rows[0]]}")
            ids = np.arange(n, dtype=np.int64)
    else:
        ids = np.arange(n, dtype=np.int64)
    order = np.argsort(ids, kind="stable")
    same = np.flatnonzero(np.diff(ids[order]) == 0)
    if same.size:
        a, b = order[same[0]], order[same[0] + 1]
        raise InputError(f"{path}:{lines[max(a, b)]}: duplicated point id {ids[a]} (also line {lines[min(a, b)]})")

    rej = Rejected()
    bad_num = ~np.all(np.isfinite(xyz), 1) | ~np.all(np.isfinite(nrm), 1)
    if require_deviation:
        bad_num |= ~np.isfinite(err)
    rej.add(ids[bad_num], lines[bad_num], "NaN or missing value")
    norm = np.linalg.norm(np.nan_to_num(nrm), axis=1)
    bad_n = ~bad_num & (np.abs(norm - 1) > NORMAL_TOL)
    for i in np.flatnonzero(bad_n):
        rej.add(ids[i], lines[i], f"normal length {norm[i]:.4f} is not 1 (tolerance {NORMAL_TOL})")
    keep = ~(bad_num | bad_n)
    if n == 0:
        raise InputError(f"{path}: no measured points")
    if keep.sum() < 0.5 * n:
        raise InputError(f"{path}: {n - keep.sum()} of {n} rows rejected (first: line {rej.rows[0][1]}: "
                         f"{rej.rows[0][2]}); check the columns and units")
    if require_deviation and keep.any():
        e = np.abs(err[keep])
        med = float(np.median(e))
        if dev_unit == "um" and np.all(e < 0.05) and med > 0:
            raise InputError(f"{path}: every deviation is below 0.05 µm (median {med:.2g}): the deviation "
                             f"column looks like mm; say deviation_unit: mm")
        if dev_unit == "mm" and med > 1000:
            raise InputError(f"{path}: median deviation {med / 1e3:.3g} mm: the deviation column looks like "
                             f"µm; say deviation_unit: um")
    nrm = nrm / np.where(norm > 0, norm, 1)[:, None]
    tab = pa.table({
        "point_id": pa.array(ids[keep]), "x_mm": xyz[keep, 0], "y_mm": xyz[keep, 1], "z_mm": xyz[keep, 2],
        "nx": nrm[keep, 0], "ny": nrm[keep, 1], "nz": nrm[keep, 2], "err_um": err[keep], "t_s": t[keep],
    })
    return tab, rej, lines[keep]


def _read_csv(path: Path):
    text = path.read_text(errors="replace").splitlines()
    rows = [(i + 1, ln) for i, ln in enumerate(text) if ln.strip() and not ln.lstrip().startswith("#")]
    if not rows:
        raise InputError(f"{path}: empty measurement file")
    first = rows[0][1]
    delim = max([",", ";", "\t", " "], key=lambda d: len(first.split(d)) if d != " " else len(first.split()))
    split = (lambda s: s.split()) if delim == " " else (lambda s: [c.strip() for c in s.split(delim)])
    header = split(first)
    body = rows[1:]
    vals = [split(ln) for _, ln in body]
    lines = np.array([i for i, _ in body], dtype=np.int64)
    for (i, ln), v in zip(body, vals):
        if len(v) != len(header):
            raise InputError(f"{path}:{i}: {len(v)} fields, the header has {len(header)}")
    cols = list(zip(*vals)) if vals else [()] * len(header)
    data = {}
    for h, c in zip(header, cols):
        arr = np.array(c, dtype=object)
        low = np.char.lower(arr.astype(str)) if len(arr) else arr
        try:
            data[h] = np.where(np.isin(low, ["nan", "", "na", "null"]), np.nan, arr).astype(float)
        except (ValueError, TypeError):
            data[h] = arr
    return header, data, lines


def write_measurements(table: pa.Table, path) -> None:
    """Write a ``measurements`` table: CSV (CMM-like header) or Parquet by the path's suffix.

    Parameters
    ----------
    table : pa.Table
        ``point_id``, ``x_mm, y_mm, z_mm`` (mm, 5 decimals in CSV), ``nx, ny, nz`` (6), ``err_um``
        (µm, 4), ``t_s`` (s, 4).
    path : str or Path
        Written through a temporary file and renamed.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    if path.suffix.lower() == ".parquet":
        pq.write_table(table, tmp)
    else:
        cols = ["point_id", "x_mm", "y_mm", "z_mm", "nx", "ny", "nz", "err_um", "t_s"]
        d = {c: table.column(c).to_numpy() for c in cols}
        with open(tmp, "w") as f:
            f.write(",".join(cols) + "\n")
            for i in range(table.num_rows):
                f.write(f"{d['point_id'][i]},{d['x_mm'][i]:.5f},{d['y_mm'][i]:.5f},{d['z_mm'][i]:.5f},"
                        f"{d['nx'][i]:.6f},{d['ny'][i]:.6f},{d['nz'][i]:.6f},{d['err_um'][i]:.4f},{d['t_s'][i]:.4f}\n")
    tmp.replace(path)


def points_and_normals(table: pa.Table) -> tuple[np.ndarray, np.ndarray]:
    """The points and normals of a ``measurements`` table (or plan).

    Parameters
    ----------
    table : pa.Table
        With ``x_mm, y_mm, z_mm, nx, ny, nz``.

    Returns
    -------
    pts : (n, 3) ndarray
        mm.
    nrm : (n, 3) ndarray
        Unit normals.
    """
    pts = np.stack([table.column(c).to_numpy() for c in ("x_mm", "y_mm", "z_mm")], 1)
    nrm = np.stack([table.column(c).to_numpy() for c in ("nx", "ny", "nz")], 1)
    return pts, nrm


def measurement_table(ids, pts, nrm, err, t=None) -> pa.Table:
    """A ``measurements`` table from arrays.

    Parameters
    ----------
    ids : (n,) int array-like
        Point ids.
    pts : (n, 3) ndarray
        Points (mm).
    nrm : (n, 3) ndarray
        Unit normals.
    err : (n,) ndarray
        Deviation along the normal (µm, + = material left).
    t : (n,) ndarray, optional
        Time stamps (s); NaN when None.

    Returns
    -------
    pa.Table
    """
    t = np.full(len(err), np.nan) if t is None else t
    return pa.table({"point_id": pa.array(np.asarray(ids).astype(np.int64)), "x_mm": pts[:, 0], "y_mm": pts[:, 1],
                     "z_mm": pts[:, 2], "nx": nrm[:, 0], "ny": nrm[:, 1], "nz": nrm[:, 2], "err_um": err, "t_s": t})
