"""The engine: a declared stage graph over program partitions, on Dask, through the cache (DESIGN §3).

Execution is stage by stage. For each stage the engine computes, on the client and without running
anything, every partition's cache key from the stage's version, its declared parameters and its
inputs' keys. Partitions already in the cache are not touched; the missing ones become Dask tasks
(:mod:`pipeline.executor`). A cluster is only started when something is missing, so a fully cached
nightly run costs file hashing and a directory listing.

After the graph's main chain, its ``Repeat`` runs rounds of its sub-chain for every partition that
has not converged, each round's entries ordinary cache entries keyed by the round's inputs and the
round number. The engine knows no stage by name: inputs are resolved by the rules of
:mod:`pipeline.graph`, and the graph's ``status`` table says when a partition failed.
"""
from __future__ import annotations

import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

from pipeline.cache import Cache, digest, file_sha256
from pipeline.config import FILE_KEYS, WorkflowError, load_workflow, program_paths, resolve
from pipeline.executor import Executor
from pipeline.graph import Graph, Stage


@dataclass
class Partition:
    program_id: str
    path: str
    sha256: str
    # round → table name → (stage name, cache key) of the stage that wrote it that round
    tables: dict = field(default_factory=lambda: {1: {}})
    failed: Optional[str] = None          # first failure message (stops later stages)
    tool_t: Optional[int] = None
    rounds: list = field(default_factory=list)   # per-round records of the graph's Repeat
    stalled: bool = False                 # the Repeat stopped because its rounds stopped paying

    def located(self, name: str, rnd: int):
        """(stage, key) of input ``name`` (with its @first / @previous qualifier) in round ``rnd``."""
        base, _, qual = name.partition("@")
        if qual == "first":
            return self.tables[1].get(base)
        if qual == "previous":
            return self.tables.get(rnd - 1, {}).get(base) if rnd > 1 else None
        return self.tables.get(rnd, {}).get(base) or self.tables[1].get(base)


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

    def __init__(self, workflow_path: str, graph: Graph, out: Optional[str] = None, until: Optional[str] = None,
                 fresh: bool = False, overlays=()):
        # overlays change the workflow's values before validation; they reach the cache keys as
        # those values (a stage recomputes only when a key it declares changed)
        self.overlays = [str(o) for o in overlays]
        self.wf, self.base = load_workflow(workflow_path, self.overlays)
        self.workflow_path = workflow_path
        self.graph = graph
        self.out = Path(out) if out else resolve(self.base, self.wf.output)
        self.cache = Cache(self.out / "cache")
        names = graph.names()
        until = until or self.wf.until
        if until is not None and until not in names:
            raise WorkflowError(f"--until {until!r}: not a stage; stages are {', '.join(names)}")
        self.stages = list(graph.stages[: names.index(until) + 1] if until else graph.stages)
        self.repeat = graph.repeat if graph.repeat and len(self.stages) == len(graph.stages) else None
        self.fresh = fresh
        paths = program_paths(self.wf, self.base)
        self.parts = [Partition(pid, str(p.resolve()), file_sha256(p))
                      for pid, p in zip(program_ids(paths, self.base), paths)]
        self._static = self._workflow_sources()

    # --- inputs and keys ------------------------------------------------------------------------------
    def _workflow_sources(self) -> dict[str, tuple[Any, str]]:
        """Workflow-level sources (stock, nominal model): the value handed to stages, its fingerprint."""
        out = {}
        for name, key in self.graph.sources.items():
            if key == "partition":
                continue
            v = getattr(self.wf, key)
            if v is None:
                out[name] = (None, "none")
            elif isinstance(v, str):
                p = resolve(self.base, v)
                if not p.is_file():
                    raise WorkflowError(f"{key}: file {p} does not exist")
                out[name] = (str(p.resolve()), file_sha256(p))
            else:
                out[name] = (v.model_dump(), digest(v.model_dump()))
        return out

    def source(self, name: str):
        """The value a workflow-level source hands to stages (a resolved file path), None if unset."""
        return self._static.get(name, (None,))[0]

    def fingerprint(self, name: str) -> str:
        """The content fingerprint of a workflow-level source (a file's sha256)."""
        return self._static.get(name, (None, "none"))[1]

    def display_path(self, path: str) -> str:
        """A program's path as users read it: relative to the workflow's directory (absolute when
        it lies elsewhere). Not part of any cache key: moving a project re-uses its cache."""
        rel = os.path.relpath(path, Path(self.base).resolve())
        return path if Path(rel).parts[0] == ".." else rel

    def params_for(self, stage: Stage, part: Partition) -> dict:
        params = self.wf.params(stage.params, part.tool_t, self.base)
        used = getattr(stage.load(), "used_params", None)   # values a stage uses only under a switch
        return used(params) if used is not None else params

    def _input(self, name: str, part: Partition, rnd: int, stage: Stage):
        """(fingerprint for the key, spec for the task) of one declared input."""
        base, _, qual = name.partition("@")
        if qual == "earlier":
            return self._earlier(base, part, stage)
        if self.graph.sources.get(base) == "partition":
            return ([part.program_id, part.sha256],
                    ("value", {"path": part.path, "sha256": part.sha256, "program_id": part.program_id,
                               "name": self.display_path(part.path)}))
        if base in self._static:
            value, fp = self._static[base]
            return fp, ("value", value)
        loc = part.located(name, rnd)
        if loc is None:
            if name.endswith("@previous"):
                return None, ("value", None)
            raise KeyError(f"input {name!r}: no stage before it writes {base!r}")
        return loc[1], ("table", str(self.cache.table_path(loc[0], loc[1], base)))

    def _earlier(self, base: str, part: Partition, stage: Stage):
        """Table ``base`` of every partition before ``part``, with the stage's parameters for each."""
        fps, specs = [], []
        for other in self.parts[:self.parts.index(part)]:
            loc = other.tables[1].get(base)
            if loc is None:
                raise WorkflowError(f"machined after {other.program_id}, which failed ({other.failed or 'no ' + base}): "
                                    "the stock this program meets is unknown")
            params = self.params_for(stage, other)
            fps.append([other.program_id, loc[1], digest(params)])
            specs.append((str(self.cache.table_path(loc[0], loc[1], base)), params))
        return fps, ("tables", specs)

    def plan(self, stage: Stage, part: Partition, rnd: int):
        """Cache key, parameters and input specs of ``stage`` on ``part`` in round ``rnd``."""
        params = self.params_for(stage, part)
        fps, specs = {}, {}
        for name in stage.inputs:
            fps[name], specs[name] = self._input(name, part, rnd, stage)
        files = {}
        _collect_file_hashes(params, files)
        spec = {"stage": stage.name, "version": stage.version, "params": params, "files": files, "inputs": fps}
        if rnd > 1:
            spec["round"] = rnd
        return digest(spec), params, specs

    # --- execution ---------------------------------------------------------------------------------------
    def execute(self, scheduler: Optional[str] = None, workers: Optional[int] = None,
                progress: bool = True) -> dict:
        from pipeline.publish import publish
        t_run = time.perf_counter()
        if self.fresh and self.cache.root.exists():
            shutil.rmtree(self.cache.root)
        self.cache.sweep_temp(older_than_s=600)
        reports, failures = [], []
        with Executor(scheduler, workers, progress) as ex:
            for stage in self.stages:
                reports.append(self._run_stage(ex, stage, self.parts, 1, failures))
            if self.repeat is not None:
                self._run_rounds(ex, reports, failures)
            self.dashboard = ex.dashboard
        return publish(self, reports, failures, time.perf_counter() - t_run)

    def _run_stage(self, ex: Executor, stage: Stage, parts: list, rnd: int, failures: list) -> StageReport:
        t0 = time.perf_counter()
        rep = StageReport(stage.name if rnd == 1 else f"{stage.name}@{rnd}")
        todo = []
        for part in parts:
            if part.failed:
                continue
            try:
                key, params, specs = self.plan(stage, part, rnd)
            except WorkflowError as e:
                self._fail(part, f"{self.display_path(part.path)}: {e}", rep.name, failures)
                rep.failed += 1
                continue
            rep.partitions += 1
            if self.cache.has(stage.name, key):
                rep.cached += 1
                self._done(stage, part, key, rnd, failures)
            else:
                todo.append((part, key, params, specs))
        for part, key, rec in ex.run(stage, todo, self.cache):
            rep.compute_s += rec.get("elapsed_s", 0.0)
            if rec["ok"]:
                rep.computed += 1
                self._done(stage, part, key, rnd, failures)
            else:
                rep.failed += 1
                self._fail(part, rec["message"], rep.name, failures, rec.get("traceback"))
        rep.wall_s = time.perf_counter() - t0
        return rep

    def _done(self, stage: Stage, part: Partition, key: str, rnd: int, failures: list) -> None:
        """Record where the stage's tables are, and what the graph's status table says."""
        for name in stage.outputs:
            part.tables.setdefault(rnd, {})[name] = (stage.name, key)
        if self.graph.status in stage.outputs:
            row = self.cache.read(stage.name, key, self.graph.status).to_pylist()[0]
            part.tool_t = row.get("tool")
            if row.get("status", "ok") != "ok":
                self._fail(part, row.get("message") or "failed", stage.name, failures)

    @staticmethod
    def _fail(part: Partition, message: str, stage: str, failures: list, tb: Optional[str] = None) -> None:
        part.failed = message
        failures.append({"program_id": part.program_id, "stage": stage, "message": message, "traceback": tb})

    def _run_rounds(self, ex: Executor, reports: list, failures: list) -> None:
        """Rounds 2 … max of the graph's Repeat, for the partitions whose last round did not converge."""
        rep = self.repeat
        done = [p for p in self.parts if not p.failed and rep.until_table in p.tables[1]]
        for part in done:
            part.rounds.append(self._round_record(part, 1))
        for rnd in range(2, int(self.wf.value(rep.max_rounds)) + 1):
            active = [p for p in done if not p.failed and not p.stalled and not self._converged(p, rnd - 1)]
            if not active:
                break
            for stage in rep.stages:
                reports.append(self._run_stage(ex, stage, active, rnd, failures))
            for part in active:
                if not part.failed:
                    part.rounds.append(self._round_record(part, rnd))
                    part.stalled = bool(rep.stalled(part.rounds))

    def _converged(self, part: Partition, rnd: int) -> bool:
        stage_name, key = part.tables[rnd][self.repeat.until_table]
        stage = next(s for s in self.repeat.stages if s.name == stage_name)
        table = self.cache.read(stage_name, key, self.repeat.until_table)
        return bool(self.repeat.until(table, self.params_for(stage, part)))

    def _round_record(self, part: Partition, rnd: int) -> dict:
        tables = {}
        for name in self.repeat.record_inputs:
            stage_name, key = part.located(name, rnd)
            tables[name] = self.cache.read(stage_name, key, name.partition("@")[0])
        return {"round": rnd, **self.repeat.record(tables)}

    def kept_round(self, part: Partition) -> int:
        """The round whose ``kept_tables`` tables a partition publishes (0: none)."""
        if not part.rounds:
            return max(part.tables)
        return int(self.repeat.keep(part.rounds, part.stalled))

    # --- status ------------------------------------------------------------------------------------------
    def status(self) -> list[dict]:
        """Which stages and partitions are done (main chain), without computing anything."""
        rows = []
        for stage in self.stages:
            done = pending = blocked = 0
            for part in self.parts:
                if part.failed:
                    blocked += 1
                    continue
                try:
                    key = self.plan(stage, part, 1)[0]
                except (KeyError, WorkflowError):
                    pending += 1
                    continue
                if self.cache.has(stage.name, key):
                    done += 1
                    self._done(stage, part, key, 1, [])
                else:
                    pending += 1
            rows.append({"stage": stage.name, "done": done, "pending": pending, "blocked": blocked})
        return rows


def _collect_file_hashes(obj, out: dict, prefix: str = ""):
    """Content hashes of the files parameters name (a changed tool profile invalidates its stages)."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            if k in FILE_KEYS and isinstance(v, str) and os.path.isfile(v):
                out[f"{prefix}{k}"] = file_sha256(v)
            else:
                _collect_file_hashes(v, out, f"{prefix}{k}.")
