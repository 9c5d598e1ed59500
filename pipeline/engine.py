"""The engine: stage graph over program partitions, on Dask, through the cache (DESIGN §3).

Execution is stage by stage. For each stage the engine computes, on the client and without
running anything, every partition's cache key from the stage version, its declared parameters and
its inputs' keys. Partitions already in the cache are not touched; the missing ones become Dask
tasks. A Dask cluster is only started when something is missing, so a fully cached nightly run
costs file hashing and a directory listing.

Tasks run ``execute_partition`` on the workers: read inputs from the cache, call the stage's pure
``run``, check every output against its schema, write the entry atomically, return a small record
(never the tables). Workers therefore need the output directory on a shared filesystem when the
cluster spans machines.

A stage that declares ``SHARDS = n`` (``generating``: one program's predictions are the night's
work) runs each partition as n tasks, ``run(inputs, params, shard=(i, n))``, each cached under its
own key; when all n are done the client joins them (``combine_shards``) into the partition's entry.
"""
from __future__ import annotations

import importlib
import logging
import json
import os
import shutil
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional


import schemas
from pipeline.cache import Cache, digest, file_sha256
from pipeline.config import WorkflowError, load_workflow, program_paths, resolve
from stages import InputError

# Stage modules in execution order. A stage runs once per program partition (or per shard of it).
STAGE_MODULES = ["stages.parse", "stages.split", "stages.cut_filter", "stages.angle_prune", "stages.generating",
                 "stages.forces", "stages.deflection", "stages.errors", "stages.correct"]


def load_stages() -> list:
    return [importlib.import_module(m) for m in STAGE_MODULES]


@dataclass
class Partition:
    program_id: str
    path: str
    sha256: str
    keys: dict[str, str] = field(default_factory=dict)   # stage → cache key
    failed: Optional[str] = None                         # first failure message (stops later stages)
    parse_failed: bool = False                           # still gets its `programs` row from split
    tool_t: Optional[int] = None


@dataclass
class StageReport:
    name: str
    partitions: int = 0
    cached: int = 0
    computed: int = 0
    failed: int = 0
    compute_s: float = 0.0
    wall_s: float = 0.0


def program_ids(paths: list[Path], base: Path) -> list[str]:
    """File stems; where two programs share a stem, their path relative to the base instead."""
    stems = [p.stem for p in paths]
    out = []
    for p, s in zip(paths, stems):
        if stems.count(s) > 1:
            try:
                rel = p.resolve().relative_to(base.resolve())
            except ValueError:
                rel = p
            s = str(rel.with_suffix("")).replace(os.sep, "__")
        out.append(s)
    return out


class Run:
    """One invocation of a workflow: config, partitions, cache, reports."""

    def __init__(self, workflow_path: str, out: Optional[str] = None, until: Optional[str] = None,
                 fresh: bool = False):
        self.wf, self.base = load_workflow(workflow_path)
        self.workflow_path = workflow_path
        self.out = Path(out) if out else resolve(self.base, self.wf.output)
        self.cache = Cache(self.out / "cache")
        self.stages = load_stages()
        names = [s.NAME for s in self.stages]
        until = until or self.wf.until
        if until is not None and until not in names:
            raise WorkflowError(f"--until {until!r}: not a stage; stages are {', '.join(names)}")
        if until is not None:
            self.stages = self.stages[: names.index(until) + 1]
        self.fresh = fresh
        self.producer = {t: s for s in self.stages for t in s.OUTPUTS}
        paths = program_paths(self.wf, self.base)
        ids = program_ids(paths, self.base)
        self.parts = [Partition(pid, str(p.resolve()), file_sha256(p)) for pid, p in zip(ids, paths)]
        self._static = self._static_inputs()

    # --- keys and inputs ---------------------------------------------------------------------------
    def _static_inputs(self) -> dict[str, tuple[Any, str]]:
        """Model inputs (stock, nominal): value handed to stages and its fingerprint."""
        out = {}
        for key in ("stock", "nominal"):
            v = getattr(self.wf, key)
            if v is None:
                out[key] = (None, "none")
            elif isinstance(v, str):
                p = resolve(self.base, v)
                if not p.is_file():
                    raise WorkflowError(f"{key}: file {p} does not exist")
                out[key] = (str(p.resolve()), file_sha256(p))
            else:
                out[key] = (v.model_dump(), digest(v.model_dump()))
        return out

    def params_for(self, stage, part: Partition) -> dict:
        """The workflow values a stage declares, per program (tool/material by its T number).

        A dotted name (``machine.rapid_mm_min``) takes one sub-key, so the stage's cache key does
        not change when unrelated values of the same section do.
        """
        params: dict[str, Any] = {}
        for name in stage.PARAMS:
            head, _, sub = name.partition(".")
            if head in ("tool", "material") and part.parse_failed:
                val = None  # nothing of the program is used: split only reports the parse failure
            elif head == "tool":
                val = self.wf.tool_for(part.tool_t).model_dump()
            elif head == "material":
                val = self.wf.material_for(part.tool_t).model_dump()
            else:
                val = getattr(self.wf, head)
                val = val.model_dump() if hasattr(val, "model_dump") else val
            val = self._resolve_files(val)
            if sub and val is not None:
                params.setdefault(head, {})[sub] = val[sub]
            else:
                params[head] = val
        # a stage may use some values only under a switch (parse: the split length only with
        # correct.via_points): the values it does not use do not change its cache key
        used = getattr(stage, "used_params", None)
        return used(params) if used is not None else params

    def _resolve_files(self, val):
        """Make file references in parameters absolute (tool.profile, machine.frf.table)."""
        if isinstance(val, dict):
            out = {}
            for k, v in val.items():
                if k in ("profile", "table") and isinstance(v, str):
                    p = resolve(self.base, v)
                    if not p.is_file():
                        raise WorkflowError(f"{k}: file {p} does not exist")
                    out[k] = str(p.resolve())
                else:
                    out[k] = self._resolve_files(v)
            return out
        return val

    def key_for(self, stage, part: Partition, params: dict) -> str:
        ins = {}
        for name in stage.INPUTS:
            if name == "program_file":
                ins[name] = [part.program_id, part.sha256]
            elif name in self._static:
                ins[name] = self._static[name][1]
            else:
                up = self.producer[name]
                ins[name] = part.keys[up.NAME]
        files = {}
        _collect_file_hashes(params, files)
        return digest({"stage": stage.NAME, "version": stage.VERSION, "params": params,
                       "files": files, "inputs": ins})

    def task_inputs(self, stage, part: Partition) -> dict:
        spec = {}
        for name in stage.INPUTS:
            if name == "program_file":
                spec[name] = ("value", {"path": part.path, "sha256": part.sha256, "program_id": part.program_id})
            elif name in self._static:
                spec[name] = ("value", self._static[name][0])
            else:
                up = self.producer[name]
                spec[name] = ("table", str(self.cache.table_path(up.NAME, part.keys[up.NAME], name)))
        return spec

    # --- execution ------------------------------------------------------------------------------------
    def execute(self, scheduler: Optional[str] = None, workers: Optional[int] = None,
                progress: bool = True) -> dict:
        t_run = time.perf_counter()
        if self.fresh and self.cache.root.exists():
            shutil.rmtree(self.cache.root)
        self.cache.sweep_temp(older_than_s=600)
        reports, failures = [], []
        client = None
        try:
            for stage in self.stages:
                t0 = time.perf_counter()
                rep = StageReport(stage.NAME)
                todo = []
                for part in self.parts:
                    if part.failed:
                        continue
                    try:
                        params = self.params_for(stage, part)
                    except WorkflowError as e:
                        part.failed = f"{part.path}: {e}"
                        failures.append({"program_id": part.program_id, "stage": stage.NAME, "message": part.failed})
                        rep.failed += 1
                        continue
                    key = self.key_for(stage, part, params)
                    part.keys[stage.NAME] = key
                    rep.partitions += 1
                    if self.cache.has(stage.NAME, key):
                        rep.cached += 1
                    else:
                        todo.append((part, key, params))
                if todo:
                    if client is None:
                        client = _connect(scheduler, workers)
                    for part, rec in _run_tasks(client, stage, todo, self, progress):
                        rep.compute_s += rec.get("elapsed_s", 0.0)
                        if rec["ok"]:
                            rep.computed += 1
                        else:
                            rep.failed += 1
                            part.failed = rec["message"]
                            part.keys.pop(stage.NAME, None)
                            failures.append({"program_id": part.program_id, "stage": stage.NAME,
                                             "message": rec["message"], "traceback": rec.get("traceback")})
                self._after_stage(stage, failures)
                rep.wall_s = time.perf_counter() - t0
                reports.append(rep)
            if any(s.NAME == "correct" for s in self.stages):   # rounds 2… of predict → correct
                from pipeline.iterate import iterate_corrections
                holder = [client]

                def get_client():
                    if holder[0] is None:
                        holder[0] = _connect(scheduler, workers)
                    return holder[0]
                try:
                    self.correct_rounds = iterate_corrections(self, get_client, reports, failures, progress)
                finally:
                    client = holder[0]
        finally:
            if client is not None:
                _close(client)
        tables = self.materialize()
        if "corrected" in tables:
            from pipeline.nc_output import write_corrected_programs
            for part in self.parts:
                if part.failed or "correct" not in part.keys:
                    continue
                try:
                    write_corrected_programs(self, part)
                except Exception as e:  # one program's output must not cost the others
                    failures.append({"program_id": part.program_id, "stage": "nc", "message": f"nc: {type(e).__name__}: {e}",
                                     "traceback": traceback.format_exc()})
        report = None
        if "errors" in tables:
            from pipeline.report import write_report
            try:
                report = write_report(self.out, self.wf.name)
            except Exception as e:  # a picture must never cost the tables
                failures.append({"program_id": None, "stage": "report", "message": f"report: {type(e).__name__}: {e}",
                                 "traceback": traceback.format_exc()})
        summary = self.summary(reports, failures, tables, time.perf_counter() - t_run)
        summary["report"] = str(report) if report else None
        summary["correct_rounds"] = getattr(self, "correct_rounds", None)
        (self.out / "run.json").write_text(json.dumps(summary, indent=2, default=str))
        return summary

    def _after_stage(self, stage, failures):
        """Learn what later stages need from this one: the T number (parse) and program status."""
        for part in self.parts:
            if part.failed or stage.NAME not in part.keys:
                continue
            if "parse_status" in stage.OUTPUTS:
                row = self.cache.read(stage.NAME, part.keys[stage.NAME], "parse_status").to_pylist()[0]
                part.tool_t, part.parse_failed = row["tool"], row["status"] != "ok"
            if "programs" in stage.OUTPUTS:
                row = self.cache.read(stage.NAME, part.keys[stage.NAME], "programs").to_pylist()[0]
                if row["status"] != "ok":
                    part.failed = row["message"]
                    failures.append({"program_id": part.program_id, "message": row["message"],
                                     "stage": "parse" if part.parse_failed else stage.NAME})

    def materialize(self) -> dict[str, int]:
        """Expose the current run's partitions as ``<out>/tables/<table>/<program_id>.parquet``.

        Files are hard links to cache entries (a copy where links are impossible), rebuilt every
        run so the tables hold exactly this workflow's programs.
        """
        root = self.out / "tables"
        staging = self.out / ".tables.tmp"
        shutil.rmtree(staging, ignore_errors=True)
        counts: dict[str, int] = {}
        for stage in self.stages:
            for tname in stage.OUTPUTS:
                d = staging / tname
                d.mkdir(parents=True, exist_ok=True)
                counts[tname] = 0
                for part in self.parts:
                    key = part.keys.get(stage.NAME)
                    if key is None or not self.cache.has(stage.NAME, key):
                        continue
                    src = self.cache.table_path(stage.NAME, key, tname)
                    dst = d / f"{part.program_id}.parquet"
                    try:
                        os.link(src, dst)
                    except OSError:
                        shutil.copyfile(src, dst)
                    counts[tname] += 1
        if root.exists():
            shutil.rmtree(root)
        staging.mkdir(parents=True, exist_ok=True)
        os.replace(staging, root)
        return counts

    def summary(self, reports, failures, tables, wall_s) -> dict:
        import pyarrow.parquet as pq
        n_passes = 0
        prog_dir = self.out / "tables" / "passes"
        if prog_dir.is_dir():
            n_passes = sum(pq.ParquetFile(p).metadata.num_rows for p in prog_dir.glob("*.parquet"))
        failed_ids = sorted({f["program_id"] for f in failures if f["program_id"] is not None})
        return {
            "workflow": str(self.workflow_path), "name": self.wf.name, "output": str(self.out),
            "finished_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "wall_s": round(wall_s, 3),
            "counts": {"programs": len(self.parts), "programs_ok": len(self.parts) - len(failed_ids),
                       "programs_failed": len(failed_ids), "passes": n_passes, "tables": tables},
            "stages": [vars(r) | {"compute_s": round(r.compute_s, 3), "wall_s": round(r.wall_s, 3)} for r in reports],
            "failures": failures,
        }

    # --- status ---------------------------------------------------------------------------------------
    def status(self) -> list[dict]:
        """Which stages and partitions are done, without computing anything."""
        rows = []
        for stage in self.stages:
            done = pending = blocked = 0
            for part in self.parts:
                if part.failed:
                    blocked += 1
                    continue
                try:
                    key = self.key_for(stage, part, self.params_for(stage, part))
                except (KeyError, WorkflowError):
                    pending += 1
                    continue
                if self.cache.has(stage.NAME, key):
                    done += 1
                    part.keys[stage.NAME] = key
                else:
                    pending += 1
            self._after_stage(stage, [])
            rows.append({"stage": stage.NAME, "done": done, "pending": pending, "blocked": blocked})
        return rows


def _collect_file_hashes(obj, out: dict, prefix: str = ""):
    if isinstance(obj, dict):
        for k, v in obj.items():
            if k in ("profile", "table") and isinstance(v, str) and os.path.isfile(v):
                out[f"{prefix}{k}"] = file_sha256(v)
            else:
                _collect_file_hashes(v, out, f"{prefix}{k}.")


# --- worker side ----------------------------------------------------------------------------------------
def execute_partition(stage_module: str, cache_root: str, key: str, inputs: dict, params: dict,
                      shard: Optional[tuple] = None) -> dict:
    """Run one stage on one partition, or one shard of it (on a Dask worker). Returns a small
    record, never tables."""
    import pyarrow.parquet as pq
    t0 = time.perf_counter()
    stage = importlib.import_module(stage_module)
    cache = Cache(cache_root)
    if cache.has(stage.NAME, key):  # a concurrent run (or a retried task) already made it
        return {"ok": True, "elapsed_s": 0.0}
    try:
        loaded = {n: (pq.read_table(v) if kind == "table" else v) for n, (kind, v) in inputs.items()}
        result = stage.run(loaded, params) if shard is None else stage.run(loaded, params, shard=tuple(shard))
        missing = set(stage.OUTPUTS) - set(result)
        if missing:
            raise RuntimeError(f"stage {stage.NAME} did not return tables {sorted(missing)}")
        checked = {name: schemas.check(name, result[name]) for name in stage.OUTPUTS}
        cache.write(stage.NAME, key, checked)
        return {"ok": True, "elapsed_s": time.perf_counter() - t0}
    except InputError as e:
        return {"ok": False, "message": str(e), "elapsed_s": time.perf_counter() - t0}
    except Exception as e:  # a bug or an unexpected input: this partition fails, the run goes on
        return {"ok": False, "message": f"{stage.NAME}: {type(e).__name__}: {e}",
                "traceback": traceback.format_exc(), "elapsed_s": time.perf_counter() - t0}


def _connect(scheduler: Optional[str], workers: Optional[int]):
    from distributed import Client, LocalCluster
    if scheduler:
        return Client(scheduler, timeout="30s")
    n = workers or os.cpu_count() or 1
    cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                           dashboard_address=None, silence_logs=logging.CRITICAL)
    return Client(cluster)


def _close(client):
    cluster = getattr(client, "cluster", None)
    client.close()
    if cluster is not None:
        cluster.close()


def shard_key(key: str, i: int, n: int) -> str:
    """Cache key of shard ``i`` of ``n`` of a partition's entry ``key``."""
    return f"{key}-shard{i}of{n}"


def _run_tasks(client, stage, todo, run: Run, progress: bool):
    """Run ``todo`` = [(partition, key, params)] on the cluster; yields (partition, record) as each
    partition finishes. A stage declaring ``SHARDS`` = n > 1 runs each partition as n tasks
    (``stage.run(..., shard=(i, n))``, each cached on its own, so a killed run keeps finished
    shards) and the partition's entry is ``stage.combine_shards`` of them."""
    from distributed import as_completed
    from tqdm import tqdm
    n_sh = max(1, int(getattr(stage, "SHARDS", 1)))
    futs, left, recs = {}, {}, {}
    for part, key, params in todo:
        inputs = run.task_inputs(stage, part)
        if n_sh == 1:
            f = client.submit(execute_partition, stage.__name__, str(run.cache.root), key, inputs, params,
                              key=f"{stage.NAME}-{key}", pure=False)
            futs[f] = (part, key)
            continue
        left[key], recs[key] = n_sh, []
        for i in range(n_sh):
            sk = shard_key(key, i, n_sh)
            f = client.submit(execute_partition, stage.__name__, str(run.cache.root), sk, inputs, params,
                              (i, n_sh), key=f"{stage.NAME}-{sk}", pure=False)
            futs[f] = (part, key)
    bar = tqdm(total=len(futs), desc=f"{stage.NAME:>12}", unit="task", disable=not progress or None,
               file=sys.stderr, leave=True)
    try:
        for fut in as_completed(futs):
            part, key = futs[fut]
            try:
                rec = fut.result()
            except Exception as e:  # the worker died (out of memory, crash): recorded, run goes on
                rec = {"ok": False, "message": f"{stage.NAME}: worker failed: {type(e).__name__}: {e}"}
            bar.update(1)
            if n_sh == 1:
                yield part, rec
                continue
            recs[key].append(rec)
            left[key] -= 1
            if left[key] == 0:
                yield part, _join_shards(stage, run.cache, key, n_sh, recs.pop(key))
    finally:
        bar.close()


def _join_shards(stage, cache: Cache, key: str, n: int, recs: list) -> dict:
    """The partition's record once all its shards are done: its entry written from theirs."""
    elapsed = sum(r.get("elapsed_s", 0.0) for r in recs)
    bad = [r for r in recs if not r["ok"]]
    if bad:
        return {**bad[0], "elapsed_s": elapsed}
    try:
        parts = [{name: cache.read(stage.NAME, shard_key(key, i, n), name) for name in stage.OUTPUTS}
                 for i in range(n)]
        joined = stage.combine_shards(parts)
        cache.write(stage.NAME, key, {name: schemas.check(name, joined[name]) for name in stage.OUTPUTS})
        for i in range(n):                     # the joined entry replaces them
            shutil.rmtree(cache.entry(stage.NAME, shard_key(key, i, n)), ignore_errors=True)
        return {"ok": True, "elapsed_s": elapsed}
    except Exception as e:
        return {"ok": False, "message": f"{stage.NAME}: joining shards: {type(e).__name__}: {e}",
                "traceback": traceback.format_exc(), "elapsed_s": elapsed}
