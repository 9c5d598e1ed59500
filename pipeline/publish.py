"""What a run leaves for its users: tables, written files, the report and ``run.json`` (DESIGN §3).

``<out>/tables/<table>/<program_id>.parquet`` are hard links to cache entries (copies where links are
impossible), rebuilt every run so they hold exactly this workflow's programs: each table from the
last stage that wrote it in the first round (the prediction of the programs as written), the
Repeat's ``kept_tables`` tables from the round it keeps (:meth:`Run.kept_round`). The graph's writers then make their files (the
corrected NC programs), each written to a temporary name and renamed.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
import traceback
from pathlib import Path

import numpy as np
import pyarrow.compute as pc
import pyarrow.parquet as pq

from pipeline import deviation_map
from pipeline import report as report_mod


def publish(run, reports: list, failures: list, wall_s: float) -> dict:
    tables = materialize(run)
    files = write_files(run, failures)
    kept = ({p.program_id: kept_summary(p.rounds, run.kept_round(p), p.stalled) for p in run.parts if p.rounds}
            if run.repeat is not None else {})
    nominal = run.source("nominal")
    report, report_error = None, None
    try:
        key = report_key(run, kept)
        stamp = run.out / "report" / ".inputs"
        if (not run.fresh and stamp.is_file() and stamp.read_text() == key
                and (run.out / "report" / "index.html").is_file()):
            report = run.out / "report" / "index.html"        # nothing it shows changed (--fresh: redrawn)
        else:
            stamp.unlink(missing_ok=True)
            report = report_mod.write_report(run.out, run.wf.name, nominal=nominal, kept=kept,
                                             overlays=run.overlays)
            if report is not None:
                stamp.write_text(key)
    except Exception as e:  # a picture never fails a run: the tables and programs are what it is for
        report_error = {"message": f"report: {type(e).__name__}: {e}", "traceback": traceback.format_exc()}
    from pipeline.duckdb_views import write_views
    views = write_views(run.out, run.wf.name)
    summary = summarize(run, reports, failures, tables, wall_s)
    summary["files"] = files
    summary["duckdb"] = str(views) if views else None
    summary["report"] = str(report) if report else None
    summary["report_error"] = report_error
    summary["dashboard"] = getattr(run, "dashboard", None)
    feeds = feed_summary(run.out)
    if feeds:
        summary["feeds"] = feeds
    summary["warnings"], summary["allowance"] = warning_summary(run.out)
    if run.repeat is not None:
        summary["rounds"] = {p.program_id: p.rounds for p in run.parts if p.rounds}
        summary["kept"] = kept
    (run.out / "run.json").write_text(json.dumps(summary, indent=2, default=str))
    return summary


def report_key(run, kept: dict) -> str:
    """Digest of what the report shows: every published table's cache key, the kept corrections,
    the design model and the report's own code."""
    from pipeline.cache import digest
    code = [hashlib.sha256(Path(m.__file__).read_bytes()).hexdigest() for m in (report_mod, deviation_map)]
    return digest({"tables": {p.program_id: sorted(final_tables(run, p).items()) for p in run.parts},
                   "failed": {p.program_id: p.failed for p in run.parts}, "kept": kept, "title": run.wf.name,
                   "nominal": run.fingerprint("nominal"), "code": code, "overlay": run.overlays})


def feed_summary(out: Path) -> dict:
    """Per program with scheduled feeds: machining time before and after, passes overloaded, and
    what set the feeds (``feeds`` table)."""
    d = Path(out) / "tables" / "feeds"
    res = {}
    for f in sorted(d.glob("*.parquet")) if d.is_dir() else []:
        t = pq.read_table(f, columns=["duration_s", "duration_new_s", "overloaded", "limited_by"])
        if t.num_rows == 0:
            continue
        limited = t.column("limited_by").value_counts().to_pylist()
        res[f.stem] = {"duration_s": round(float(pc.sum(t.column("duration_s")).as_py()), 3),
                       "duration_new_s": round(float(pc.sum(t.column("duration_new_s")).as_py()), 3),
                       "overloaded": int(pc.sum(t.column("overloaded")).as_py() or 0),
                       "limited_by": {x["values"]: x["counts"] for x in limited}}
    return res


def warning_summary(out: Path) -> tuple[dict, dict]:
    """Per program: the warnings by reason with their first NC lines, and the stock along the normal
    its predicted passes meet (median, P95, max, mm)."""
    warns, allowance = {}, {}
    d = Path(out) / "tables"
    for f in sorted((d / "warnings").glob("*.parquet")) if (d / "warnings").is_dir() else []:
        t = pq.read_table(f, columns=["reason", "line_no"]).to_pandas()
        if len(t):
            warns[f.stem] = {r: {"passes": int(len(g)), "lines": sorted({int(x) for x in g.line_no})[:5]}
                             for r, g in t.groupby("reason")}
    for f in sorted((d / "allowance").glob("*.parquet")) if (d / "allowance").is_dir() else []:
        s = pq.read_table(f, columns=["stock_mm"]).column("stock_mm").to_numpy(zero_copy_only=False).astype(float)
        s = s[np.isfinite(s)]
        if s.size:
            allowance[f.stem] = {"median_mm": round(float(np.median(s)), 4), "p95_mm": round(float(np.percentile(s, 95)), 4),
                                 "max_mm": round(float(s.max()), 4)}
    return warns, allowance


def kept_summary(records: list, kept: int, stalled: bool) -> dict:
    """Which round's output a partition publishes and what its rounds predicted, for ``run.json``.

    ``rms_dev_um`` of round k + 1 is the prediction of round k's output (None: not predicted, the
    last round's output).
    """
    dev = lambda k: records[k]["rms_dev_um"] if k < len(records) else None  # noqa: E731
    return {"rounds": len(records), "kept_round": kept, "stalled": stalled,
            "first_rms_dev_um": dev(0), "kept_rms_dev_um": dev(kept) if kept else None}


def final_tables(run, part) -> dict:
    """table → (stage, key) of what a partition publishes."""
    out = dict(part.tables[1])
    if run.repeat is not None:
        kept = run.kept_round(part)
        for t in run.repeat.kept_tables:
            out.pop(t, None)
            if kept and t in part.tables[kept]:
                out[t] = part.tables[kept][t]
    return out


def materialize(run) -> dict[str, int]:
    root, staging = run.out / "tables", run.out / ".tables.tmp"
    shutil.rmtree(staging, ignore_errors=True)
    counts: dict[str, int] = {}
    for part in run.parts:
        for name, (stage, key) in final_tables(run, part).items():
            if not run.cache.has(stage, key):
                continue
            d = staging / name
            d.mkdir(parents=True, exist_ok=True)
            src, dst = run.cache.table_path(stage, key, name), d / f"{part.program_id}.parquet"
            try:
                os.link(src, dst)
            except OSError:
                shutil.copyfile(src, dst)
            counts[name] = counts.get(name, 0) + 1
    if root.exists():
        shutil.rmtree(root)
    staging.mkdir(parents=True, exist_ok=True)
    os.replace(staging, root)
    return counts


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def write_files(run, failures: list) -> int:
    """The graph's writers over every partition that has their inputs; returns how many files.

    A writer's directory holds this run's files only, as ``tables/`` does: a file of an earlier run
    whose partition has no output now (a failed program, a correction not kept) is removed.
    """
    n = 0
    for writer in run.graph.writers:
        written = set()
        for part in run.parts:
            if part.failed:
                continue
            have = final_tables(run, part)
            if not all(i.endswith("?") or i.partition("@")[0] in have or run.graph.sources.get(i)
                       for i in writer.inputs):
                continue
            try:
                inputs = {}
                for spec in writer.inputs:
                    name = spec.rstrip("?")
                    base, _, qual = name.partition("@")
                    if qual == "first":          # the first round's table, whichever round is kept
                        loc = part.tables[1].get(base) if part.tables else None
                        inputs[name] = run.cache.read(loc[0], loc[1], base) if loc else None
                    elif run.graph.sources.get(name) == "partition":
                        inputs[name] = {"path": part.path, "sha256": part.sha256, "program_id": part.program_id}
                    elif name in have:
                        stage, key = have[name]
                        inputs[name] = run.cache.read(stage, key, name)
                    else:
                        inputs[name] = None
                files = writer.fn(inputs, run.wf.params(writer.params, part.tool_t, run.base))
                outdir = run.out / writer.directory
                outdir.mkdir(parents=True, exist_ok=True)
                for fname, data in files.items():
                    _atomic_write(outdir / fname, data)
                    written.add(fname)
                    n += 1
            except Exception as e:  # one program's output must not cost the others
                failures.append({"program_id": part.program_id, "stage": writer.name,
                                 "message": f"{writer.name}: {type(e).__name__}: {e}",
                                 "traceback": traceback.format_exc()})
        outdir = run.out / writer.directory
        if outdir.is_dir():
            for old in outdir.iterdir():
                if old.is_file() and old.name not in written:
                    old.unlink()
    return n


def summarize(run, reports, failures, tables, wall_s) -> dict:
    n_passes = 0
    prog_dir = run.out / "tables" / "passes"
    if prog_dir.is_dir():
        n_passes = sum(pq.ParquetFile(p).metadata.num_rows for p in prog_dir.glob("*.parquet"))
    failed_ids = sorted({f["program_id"] for f in failures if f["program_id"] is not None})
    return {
        "workflow": str(run.workflow_path), "overlay": list(run.overlays),
        "name": run.wf.name, "output": str(run.out),
        "finished_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "wall_s": round(wall_s, 3),
        "counts": {"programs": len(run.parts), "programs_ok": len(run.parts) - len(failed_ids),
                   "programs_failed": len(failed_ids), "passes": n_passes, "tables": tables},
        "stages": [vars(r) | {"compute_s": round(r.compute_s, 3), "wall_s": round(r.wall_s, 3)} for r in reports],
        "failures": failures,
    }
