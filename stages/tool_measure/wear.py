"""Tool wear per contact angle between two profiles, and the wear rate per metre of cut.

Seed 003 measures wear from in-machine images (to ~0.7 µm); issue 6 asks for it per contact angle
with the cut length of the job so the wear rate per metre is a table analysts query
(``pipeline tool-wear``). The profiles are two ``pipeline tool-profile`` CSVs of the same tool
(contact_deg, error_um), measured in a common frame (``--centre-z-px`` of the first measurement for
the second). The cut length is given or summed from a run's tables (:func:`run_cut_length_m`): the
passes that cut (``cut_filter.is_cutting``) or, for a run stopped before the render stages, every
feed move (G1–G3), said in ``cut_length_source``. The table (schema ``schemas/tool_wear.py``) is
written to a temporary name and renamed, so a failure leaves nothing behind.

    import duckdb
    duckdb.sql("select contact_deg, wear_um, wear_rate_um_per_m from 'wear.parquet' where contact_deg in (30, 45, 60)")
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

import schemas
from stages import InputError
from stages.tool_measure.grid import CONTACT_DEG, on_grid


def wear_profile(before, after, cut_length_m=None) -> pd.DataFrame:
    """Wear per contact angle between two profiles of the same tool.

    Parameters
    ----------
    before, after : DataFrame
        Profiles (contact_deg, error_um) measured before and after a job.
    cut_length_m : float, optional
        Cutting length of the job (see :func:`cut_length_m`); gives the wear rate.

    Returns
    -------
    DataFrame
        contact_deg, wear_um (after − before; positive = the tool lost material there),
        wear_rate_um_per_m (NaN without a cut length), cut_length_m.
    """
    wear = on_grid(after, "error_um", "after") - on_grid(before, "error_um", "before")
    L = float(cut_length_m) if cut_length_m else np.nan
    return pd.DataFrame({"contact_deg": CONTACT_DEG.copy(), "wear_um": wear,
                         "wear_rate_um_per_m": wear / L if L > 0 else np.full_like(wear, np.nan),
                         "cut_length_m": np.full_like(wear, L)})


def cut_length_m(passes, cut_filter=None) -> float:
    """Length of the feed moves of a program, metres (DESIGN §6 passes table).

    Parameters
    ----------
    passes : pyarrow Table or DataFrame
        The passes table (motion, x0_mm..z1_mm).
    cut_filter : pyarrow Table or DataFrame, optional
        The cut_filter table; when given only passes with ``is_cutting`` count.
    """
    df = passes.to_pandas() if hasattr(passes, "to_pandas") else pd.DataFrame(passes)
    feed = df["motion"].to_numpy() != 0
    if cut_filter is not None:
        cf = cut_filter.to_pandas() if hasattr(cut_filter, "to_pandas") else pd.DataFrame(cut_filter)
        cutting = dict(zip(cf["pass_id"], cf["is_cutting"]))
        feed &= df["pass_id"].map(cutting).fillna(False).to_numpy(dtype=bool)
    return _feed_length_m(df, feed)


def _feed_length_m(df: pd.DataFrame, feed: np.ndarray) -> float:
    """Summed length (m) of the passes of ``df`` (x0_mm..z1_mm) where ``feed`` is true."""
    d = np.column_stack([df[f"{a}1_mm"] - df[f"{a}0_mm"] for a in "xyz"])
    return float(np.linalg.norm(d[feed], axis=1).sum() / 1000.0)


def read_profile(path) -> pd.DataFrame:
    """A tool-profile CSV (contact_deg, error_um); errors name the file."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: no such profile file")
    try:
        df = pd.read_csv(p, comment="#")
    except Exception as e:  # empty, binary, ragged
        raise InputError(f"{p}: not a profile CSV ({type(e).__name__}: {e})") from None
    for c in ("contact_deg", "error_um"):
        if c not in df.columns:
            raise InputError(f"{p}: column {c} missing (columns: {', '.join(map(str, df.columns))})")
    for c in ("contact_deg", "error_um"):
        v = pd.to_numeric(df[c], errors="coerce")
        bad = np.flatnonzero(~np.isfinite(v.to_numpy(dtype=float)))
        if bad.size:
            raise InputError(f"{p}:{int(bad[0]) + 2}: {c} is not a finite number ({df[c].iloc[bad[0]]!r})")
        df[c] = v.astype(float)
    q = df["contact_deg"].to_numpy()
    if np.any(np.diff(q) <= 0):
        k = int(np.flatnonzero(np.diff(q) <= 0)[0]) + 1
        raise InputError(f"{p}:{k + 2}: contact_deg must increase (row {k + 1}: {q[k]} after {q[k - 1]})")
    if q[0] > 0.0 + 1e-9 or q[-1] < 90.0 - 1e-9:
        raise InputError(f"{p}: contact_deg covers {q[0]}–{q[-1]}°, the profile must cover 0–90°")
    return df


def run_cut_length_m(passes: pa.Table | None, cut_filter: pa.Table | None = None, programs=None, tool=None,
                     where="run") -> tuple[float, str, list[str]]:
    """Cutting length (m) of a run's programs, the source of it, and the programs counted.

    Parameters
    ----------
    passes : pyarrow Table or None
        The run's passes table (None: the run has not written it).
    cut_filter : pyarrow Table, optional
        The run's cut_filter table; it decides which passes cut when it covers every selected program.
    programs : optional program ids to count (default: all of the run)
    tool : optional T number; only passes of that tool count
    where : str
        The run directory, for the error messages.

    Returns
    -------
    (length_m, source, programs) : source "cut_filter" or "feed_moves" (every G1–G3 move).
    """
    if passes is None:
        raise InputError(f"{where}: no tables/passes in this run directory (run `pipeline run` first)")
    passes = passes.to_pandas()
    have = set(passes["program_id"].unique())
    if programs:
        missing = sorted(set(programs) - have)
        if missing:
            raise InputError(f"{where}: program(s) {', '.join(missing)} not in this run (it has {', '.join(sorted(have))})")
        passes = passes[passes["program_id"].isin(programs)]
    if tool is not None:
        passes = passes[passes["tool"] == tool]
        if passes.empty:
            raise InputError(f"{where}: no passes of tool T{tool} in the selected programs")
    feed = passes["motion"].to_numpy() != 0
    source = "feed_moves"
    if cut_filter is not None:
        cf = cut_filter.select(["program_id", "pass_id", "is_cutting"]).to_pandas()
        m = passes[["program_id", "pass_id"]].merge(cf, on=["program_id", "pass_id"], how="left")
        covered = set(cf["program_id"].unique())
        if set(passes["program_id"].unique()) <= covered:
            feed &= m["is_cutting"].fillna(False).to_numpy(dtype=bool)
            source = "cut_filter"
    return _feed_length_m(passes, feed), source, sorted(passes["program_id"].unique())


def wear_table(before_path, after_path, *, cut_length_m=None, run_dir=None, run_tables=None, programs=None,
               tool=None, tool_id=None) -> pa.Table:
    """The ``tool_wear`` table (see ``schemas/tool_wear.py``).

    Parameters
    ----------
    before_path, after_path : path
        Tool-profile CSVs (:func:`read_profile`) before and after the job.
    cut_length_m : float, optional
        The job's cut length; or else
    run_dir : path, optional
        the run it was cut in, with ``run_tables`` = (passes, cut_filter or None) read from it
        (:func:`run_cut_length_m`, ``programs`` and ``tool`` select the passes).
    tool_id : str, optional
        Name of the tool in the table (default: the after file's stem).

    Raises
    ------
    stages.InputError
        Both or a bad cut length, a bad profile, or a run without the selected passes.
    """
    if cut_length_m is not None and run_dir is not None:
        raise InputError("give either --cut-length-m or --run, not both")
    before, after = read_profile(before_path), read_profile(after_path)
    prog_list = None
    if run_dir is not None:
        passes, cut_filter = run_tables if run_tables is not None else (None, None)
        L, source, prog_list = run_cut_length_m(passes, cut_filter, programs, tool, where=run_dir)
        if L <= 0:
            raise InputError(f"{run_dir}: the selected programs have no cutting length")
    elif cut_length_m is not None:
        if not np.isfinite(cut_length_m) or cut_length_m <= 0:
            raise InputError(f"--cut-length-m {cut_length_m}: must be a positive length in metres")
        L, source = float(cut_length_m), "given"
    else:
        L, source = None, "none"
    w = wear_profile(before, after, cut_length_m=L)
    n = len(w)
    grid = w["contact_deg"].to_numpy()
    b = np.interp(grid, before["contact_deg"].to_numpy(), before["error_um"].to_numpy())
    a = np.interp(grid, after["contact_deg"].to_numpy(), after["error_um"].to_numpy())
    rate = w["wear_rate_um_per_m"].to_numpy()
    table = pa.table({
        "tool_id": [tool_id or Path(after_path).stem] * n,
        "contact_deg": grid, "wear_um": w["wear_um"].to_numpy(),
        "wear_rate_um_per_m": pa.array(rate, mask=~np.isfinite(rate)),
        "cut_length_m": pa.array(np.full(n, np.nan if L is None else L), mask=np.full(n, L is None)),
        "cut_length_source": [source] * n,
        "before_error_um": b, "after_error_um": a,
        "before_path": [str(Path(before_path).resolve())] * n, "after_path": [str(Path(after_path).resolve())] * n,
        "run": pa.array([str(Path(run_dir).resolve()) if run_dir else None] * n, pa.string()),
        "programs": pa.array([prog_list] * n, pa.list_(pa.string())),
    })
    return schemas.check("tool_wear", table)


def write_wear(table: pa.Table, out) -> Path:
    """Write atomically (temporary name, rename)."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    try:
        pq.write_table(table, tmp)
        os.replace(tmp, out)
    finally:
        if tmp.exists():
            tmp.unlink()
    return out
