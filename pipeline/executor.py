"""Running stage tasks on Dask: a LocalCluster sized to the machine, or an existing scheduler.

Tasks run :func:`execute_partition` on the workers: read inputs from the cache, call the stage's
pure ``run``, check every output against its schema, write the entry atomically, return a small
record (never the tables). Workers therefore need the output directory on a shared filesystem when
the cluster spans machines. A stage that declares ``SHARDS = n`` runs each partition as n tasks,
``run(inputs, params, shard=(i, n))``, each cached under its own key; when all n are done the client
joins them (the module's ``combine_shards``) into the partition's entry.

Progress: a bar per stage on a terminal; otherwise (a nightly job's log) a line per stage every
:data:`LOG_EVERY_S` seconds while it runs, with done/total, rate and the time left, and one at its end.
"""
from __future__ import annotations

import importlib
import logging
import os
import shutil
import sys
import threading
import time
import traceback
from typing import Optional

import schemas
from pipeline.cache import Cache
from stages import InputError

LOG_EVERY_S = 10.0

# Environment of the LocalCluster's worker processes: Dask's defaults without
# MALLOC_TRIM_THRESHOLD_. Fixing that threshold also fixes glibc's mmap threshold, so every large
# numpy temporary is a fresh mmap with its page faults: the scan stage ran 1.45x slower in a worker
# than in a plain process (28.1 s against 19.4 s on one tile of the 300,000-pass bench).
WORKER_ENV = {"OMP_NUM_THREADS": 1, "MKL_NUM_THREADS": 1, "OPENBLAS_NUM_THREADS": 1}


def execute_partition(stage_module: str, cache_root: str, key: str, inputs: dict, params: dict,
                      shard: Optional[tuple] = None) -> dict:
    """Run one stage on one partition, or one shard of it (on a Dask worker)."""
    t0 = time.perf_counter()
    stage = importlib.import_module(stage_module)
    cache = Cache(cache_root)
    if cache.has(stage.NAME, key):  # a concurrent run (or a retried task) already made it
        return {"ok": True, "elapsed_s": 0.0}
    try:
        loaded = {n: _load(kind, v) for n, (kind, v) in inputs.items()}
        result = stage.run(loaded, params) if shard is None else stage.run(loaded, params, shard=tuple(shard))
        missing = set(stage.OUTPUTS) - set(result)
        if missing:
            raise RuntimeError(f"stage {stage.NAME} did not return tables {sorted(missing)}")
        cache.write(stage.NAME, key, {name: schemas.check(name, result[name]) for name in stage.OUTPUTS})
        return {"ok": True, "elapsed_s": time.perf_counter() - t0}
    except InputError as e:
        return {"ok": False, "message": str(e), "elapsed_s": time.perf_counter() - t0}
    except Exception as e:  # a bug or an unexpected input: this partition fails, the run goes on
        return {"ok": False, "message": f"{stage.NAME}: {type(e).__name__}: {e}",
                "traceback": traceback.format_exc(), "elapsed_s": time.perf_counter() - t0}


def _load(kind: str, v):
    """A task's input from its spec: a table path, a list of (table path, parameters), or a value."""
    import pyarrow.parquet as pq
    if kind == "table":
        return pq.read_table(v)
    if kind == "tables":
        return [(pq.read_table(path), params) for path, params in v]
    return v


def shard_key(key: str, i: int, n: int) -> str:
    """Cache key of shard ``i`` of ``n`` of a partition's entry ``key``."""
    return f"{key}-shard{i}of{n}"


class Executor:
    """A Dask client opened on first use (a fully cached run starts no cluster)."""

    def __init__(self, scheduler: Optional[str] = None, workers: Optional[int] = None, progress: bool = True,
                 client=None):
        self.scheduler, self.workers, self.progress = scheduler, workers, progress
        self.client, self._own = client, client is None
        self.dashboard = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self.client is not None and self._own:
            cluster = getattr(self.client, "cluster", None)
            self.client.close()
            if cluster is not None:
                cluster.close()

    def _connect(self):
        from distributed import Client, LocalCluster
        if self.scheduler:
            self.client = Client(self.scheduler, timeout="30s")
        else:
            import dask
            n = self.workers or os.cpu_count() or 1
            # ":0" takes a free port: another Dask on this machine costs no warning
            with dask.config.set({"distributed.nanny.pre-spawn-environ": WORKER_ENV}):
                cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                       dashboard_address=":0", silence_logs=logging.CRITICAL)
            self.client = Client(cluster)
        self.dashboard = self.client.dashboard_link
        if self.progress and (self.scheduler or self.workers):
            print(f"Dask dashboard: {self.dashboard}", file=sys.stderr)
        return self.client

    def run(self, stage, todo: list, cache: Cache):
        """Run ``todo`` = [(partition, key, params, input specs)]; yields (partition, key, record) as
        each partition finishes."""
        if not todo:
            return
        from distributed import as_completed
        client = self.client or self._connect()
        futs, left, recs, n_of = {}, {}, {}, {}
        for part, key, params, specs in todo:
            n_sh = n_of[key] = stage.shard_count(specs, params)
            for i in range(n_sh):
                shard = None if n_sh == 1 else (i, n_sh)
                k = key if n_sh == 1 else shard_key(key, i, n_sh)
                f = client.submit(execute_partition, stage.module, str(cache.root), k, specs, params, shard,
                                  key=f"{stage.name}-{k}", pure=False)
                futs[f] = (part, key)
            left[key], recs[key] = n_sh, []
        meter = Progress(stage.name, len(futs), self.progress)
        try:
            for fut in as_completed(futs):
                part, key = futs[fut]
                try:
                    rec = fut.result()
                except Exception as e:  # the worker died (out of memory, crash): recorded, run goes on
                    rec = {"ok": False, "message": f"{stage.name}: worker failed: {type(e).__name__}: {e}"}
                meter.update()
                recs[key].append(rec)
                left[key] -= 1
                if left[key] == 0:
                    r = recs.pop(key)
                    yield part, key, (r[0] if n_of[key] == 1 else _join_shards(stage, cache, key, n_of[key], r))
        finally:
            meter.close()


def _join_shards(stage, cache: Cache, key: str, n: int, recs: list) -> dict:
    """The partition's record once all its shards are done: its entry written from theirs."""
    elapsed = sum(r.get("elapsed_s", 0.0) for r in recs)
    bad = [r for r in recs if not r["ok"]]
    if bad:
        return {**bad[0], "elapsed_s": elapsed}
    try:
        parts = [{name: cache.read(stage.name, shard_key(key, i, n), name) for name in stage.outputs}
                 for i in range(n)]
        joined = stage.load().combine_shards(parts)
        cache.write(stage.name, key, {name: schemas.check(name, joined[name]) for name in stage.outputs})
        for i in range(n):                     # the joined entry replaces them
            shutil.rmtree(cache.entry(stage.name, shard_key(key, i, n)), ignore_errors=True)
        return {"ok": True, "elapsed_s": elapsed}
    except Exception as e:
        return {"ok": False, "message": f"{stage.name}: joining shards: {type(e).__name__}: {e}",
                "traceback": traceback.format_exc(), "elapsed_s": elapsed}


class Progress:
    """A tqdm bar on a terminal; elsewhere (a nightly job's log) a line every ``every_s`` seconds
    while the stage runs, and one when it ends; nothing when off."""

    def __init__(self, name: str, total: int, enabled: bool, every_s: float = LOG_EVERY_S, stream=None):
        self.name, self.total, self.done = name, total, 0
        self.stream = stream or sys.stderr
        self.t0 = time.monotonic()
        self.bar, self._stop, self._thread = None, threading.Event(), None
        if enabled and self.stream.isatty():
            from tqdm import tqdm
            self.bar = tqdm(total=total, desc=f"{name:>12}", unit="task", file=self.stream, leave=True)
        elif enabled:
            self._thread = threading.Thread(target=self._log_every, args=(every_s,), daemon=True)
            self._thread.start()

    def _log_every(self, every_s: float):
        while not self._stop.wait(every_s):
            self.line()

    def line(self):
        el = time.monotonic() - self.t0
        rate = self.done / el if el > 0 else 0.0
        left = f"{(self.total - self.done) / rate:.0f} s left" if rate > 0 else "time left unknown"
        print(f"[{time.strftime('%H:%M:%S')}] {self.name}: {self.done}/{self.total} tasks, {rate:.2f}/s, {left}",
              file=self.stream, flush=True)

    def update(self):
        self.done += 1
        if self.bar is not None:
            self.bar.update(1)

    def close(self):
        if self.bar is not None:
            self.bar.close()
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
            self.line()
