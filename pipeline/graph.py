"""The stage graph: which stages run, in which order, what they read and write (DESIGN §2, §3).

Each stage module declares itself once (``NAME``, ``VERSION``, ``INPUTS``, ``OUTPUTS``, ``PARAMS``,
``run``; see :mod:`stages`); this module only lists them. The engine builds the Dask tasks, the
cache keys and the correction rounds from these declarations and never names a stage.

Inputs are resolved by name: a source (``SOURCES``: the program file of the partition, or a
workflow file such as the stock), else the table of the nearest earlier stage that outputs it.
In a repeated sub-chain (``Repeat``) a plain name means this round's table when a stage earlier
in the round wrote it, else the first round's; ``name@first`` is always the first round's and
``name@previous`` the previous round's (absent in the first round). ``name@earlier`` is the list of
that table of every earlier partition of the job, in machining order (the workflow's program order),
each with the stage's parameters for it: ``[(table, params), ...]`` — the programs are machined on
one stock, and a partition whose input names them is recomputed when an earlier one changes. It is
always the first round's (the programs as written).
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Callable, Optional


@dataclass(frozen=True)
class Stage:
    """One node: a pure ``run(inputs, params) -> {table: pa.Table}`` and its declaration."""

    name: str
    module: str                      # import path; workers import it by name
    version: str
    inputs: tuple
    outputs: tuple
    params: tuple
    # tasks per partition, joined with the module's combine_shards: a number, or the module's
    # ``shards(rows, params)`` given the row counts of the partition's input tables and its parameters
    shards: object = 1

    @classmethod
    def of(cls, module) -> "Stage":
        return cls(module.NAME, module.__name__, str(module.VERSION), tuple(module.INPUTS),
                   tuple(module.OUTPUTS), tuple(module.PARAMS), getattr(module, "shards", None)
                   or int(getattr(module, "SHARDS", 1)))

    def load(self):
        return importlib.import_module(self.module)

    def shard_count(self, specs: dict, params: dict) -> int:
        """Tasks for one partition whose inputs are ``specs`` (name → (kind, path or value))."""
        if not callable(self.shards):
            return max(1, int(self.shards))
        import pyarrow.parquet as pq
        rows = {name.partition("@")[0]: pq.ParquetFile(v).metadata.num_rows
                for name, (kind, v) in specs.items() if kind == "table"}
        return max(1, int(self.shards(rows, params)))


@dataclass(frozen=True)
class Repeat:
    """Repeat ``stages`` (the tail of the graph, plus stages that only run in later rounds) until
    ``until(table, params)`` says the round converged, ``stalled(records)`` says the rounds stopped
    paying, or ``max_rounds`` (a workflow key) rounds ran.

    ``record(tables) -> dict`` summarises each round for ``run.json`` from the tables it names in
    ``record_inputs``; ``kept_tables`` tables are published from the round ``keep(records, stalled)``
    names (0: not published), the others from the first (the prediction of the program as written).
    """

    stages: tuple
    until: Callable
    until_table: str
    max_rounds: str
    record: Callable
    record_inputs: tuple
    kept_tables: tuple
    stalled: Callable = lambda records: False
    keep: Callable = lambda records, stalled: len(records)


@dataclass(frozen=True)
class Writer:
    """A file output made after the run from one partition's tables (e.g. corrected NC programs).

    ``fn(inputs, params) -> {file name: bytes}``; the engine writes the files atomically into
    ``<out>/<directory>/`` for every partition that has all ``inputs`` (a name ending in ``?`` may be
    missing: it is then None). Inputs are the published tables; ``name@first`` is the first
    round's table of a repeated stage even when another round (or none) is published.
    """

    name: str
    fn: Callable
    inputs: tuple
    params: tuple
    directory: str


@dataclass(frozen=True)
class Graph:
    sources: dict                     # input name → "partition" (the program file) or a workflow key
    stages: tuple
    repeat: Optional[Repeat] = None
    status: str = ""                  # table whose one row per partition says status, message, tool
    writers: tuple = field(default_factory=tuple)

    def names(self) -> list[str]:
        return [s.name for s in self.stages]


def mould_graph() -> Graph:
    """The main job: predict every finishing pass and correct the programs (workflows/mould.yaml)."""
    from stages import correct, correct_blocks, deflection, errors, feed, forces, parse, scan, split, warn
    from stages.nc.output import corrected_programs
    main = tuple(Stage.of(m) for m in (parse, split, scan, forces, deflection, feed, errors, warn, correct))
    # the rounds predict the corrected path again; feeds and warnings are of the program as written
    again = tuple(s for s in main[1:] if s.name not in ("feed", "warn"))
    rounds = Repeat(stages=(Stage.of(correct_blocks),) + again, until=correct.converged,
                    until_table="corrected", max_rounds="correct.max_iter", record=correct.round_record,
                    record_inputs=("errors", "corrected", "passes", "passes@first"), kept_tables=("corrected",),
                    stalled=correct.stalled, keep=correct.kept_round)
    nc = Writer("nc", corrected_programs, inputs=("program_file", "blocks", "corrected?", "corrected@first?", "errors", "passes", "feeds"),
                params=("correct",), directory="nc")
    return Graph(sources={"program_file": "partition", "stock": "stock", "nominal": "nominal"},
                 stages=main, repeat=rounds, status="programs", writers=(nc,))
