"""Iterated correction inside ``pipeline run`` (DESIGN §7, seed 003: predict again on the corrected path).

After the stage loop has run the chain once (round 1: parse → … → errors → correct), and when
``correct.max_iter`` > 1, every program whose last correction still changed a vertex by
``correct.tol_um`` or more goes through another round:

    correct_blocks (original blocks + last corrected → blocks of the corrected program)
    → split → cut_filter → angle_prune → generating → forces → deflection → errors
    → correct (the move for the errors predicted on the corrected path, applied to the original
      program: the fixed point P = P0 − e(P)·n, see stages.correct.run; ``iteration`` counts rounds;
      a pass this round does not predict keeps its round-1 error, ``first_errors``)

until the largest change is below the tolerance or ``max_iter`` rounds have run. Each round's
partitions are ordinary cache entries of the same stages, keyed by stage, version, params, the
keys of this round's inputs (so, through the chain, by the previous round's corrections) and the
round number: a rerun is served from the cache round by round, and a changed program or parameter
recomputes exactly the rounds that depend on it. Stages stay pure; only this module knows rounds.

The tables under ``<out>/tables`` keep the prediction of the original program (round 1); the
``corrected`` table and ``<out>/nc`` are the last round's (``iteration`` = rounds run). ``run.json``
lists per program and round the predicted error of the path that round predicted on (round 1: the
program as written, round k: the program after k − 1 corrections), the same as deviation from the
original surface, and the largest change made (:func:`round_record`).
"""
from __future__ import annotations

import importlib

import numpy as np

from pipeline.cache import digest

ROUND_CHAIN = ("stages.correct_blocks", "stages.split", "stages.cut_filter", "stages.angle_prune",
               "stages.generating", "stages.forces", "stages.deflection", "stages.errors", "stages.correct")


class _RoundView:
    """The two things the task runner needs from a Run (cache, task inputs), for one round."""

    def __init__(self, run, specs: dict):
        self.cache = run.cache
        self._specs = specs

    def task_inputs(self, stage, part) -> dict:
        return self._specs[(stage.NAME, part.program_id)]


def round_record(run, rnd: int, errors_key: str, correct_key: str, split_key: str | None = None,
                 split0_key: str | None = None) -> dict:
    """What a round predicted and changed.

    ``rms_err_um``: predicted error of the path this round predicted on, relative to that path (round
    1: the program as written). ``rms_dev_um``: the same prediction as deviation from the ORIGINAL
    program's surface, e + (P − P0)·n with the path shift at each pass midpoint (= ``rms_err_um`` in
    round 1; None when the corrected program was split into different passes). ``max_change_um``:
    the largest vertex change this round made (the iteration stops below ``correct.tol_um``).
    """
    errors = run.cache.read("errors", errors_key, "errors")
    err = errors.column("err_um").to_numpy(zero_copy_only=False)
    fin = np.isfinite(err)
    dev = err.copy()
    if split_key is not None:
        p = run.cache.read("split", split_key, "passes").sort_by("pass_id")
        p0 = run.cache.read("split", split0_key, "passes").sort_by("pass_id")
        col = lambda t, c: t.column(c).to_numpy(zero_copy_only=False)  # noqa: E731
        if p.num_rows == p0.num_rows and np.array_equal(col(p, "block_no"), col(p0, "block_no")):
            mid = lambda t: np.stack([(col(t, f"{a}0_mm") + col(t, f"{a}1_mm")) / 2 for a in "xyz"], 1)  # noqa: E731
            shift = (mid(p) - mid(p0))[np.searchsorted(col(p, "pass_id"), col(errors, "pass_id"))]
            n = np.stack([col(errors, c) for c in ("nx", "ny", "nz")], 1)
            dev = err + 1000.0 * np.einsum("ij,ij->i", shift, n)
        else:
            dev = None
    cor = run.cache.read("correct", correct_key, "corrected")
    change = cor.column("change_um").to_numpy(zero_copy_only=False)
    move = cor.column("move_um").to_numpy(zero_copy_only=False)
    rms = lambda x: float(np.sqrt(np.mean(x ** 2))) if x.size else 0.0  # noqa: E731
    return {"round": rnd, "n_errors": int(fin.sum()),
            "rms_err_um": rms(err[fin]), "max_abs_err_um": float(np.abs(err[fin]).max()) if fin.any() else 0.0,
            "rms_dev_um": None if dev is None else rms(dev[fin & np.isfinite(dev)]),
            "max_change_um": float(change.max()) if change.size else 0.0,
            "max_move_um": float(move.max()) if move.size else 0.0,
            "clipped": int(np.count_nonzero(cor.column("clipped").to_numpy(zero_copy_only=False)))}


def _source(run, stage, name: str, part, rkeys: dict, prev_correct: str):
    """(stage, key, table) that ``stage`` reads as input ``name`` in this round; None for static inputs."""
    if name in run._static:
        return None
    if name == "parse_status":
        return "parse", part.keys["parse"], name
    if stage.NAME == "correct":
        # the move for this round's errors is applied to the original program (stages.correct.run)
        if name == "blocks":
            return "parse", part.keys["parse"], "blocks"
        if name == "passes":
            return "split", part.keys["split"], "passes"
        if name == "round_passes":
            return "split", rkeys["split"], "passes"
        if name == "first_errors":
            return "errors", part.keys["errors"], "errors"
        if name == "generating":
            # the moves are from the original program: the gouge limit checks its surface
            return "generating", part.keys["generating"], "generating"
        if name == "corrected":
            return "correct", prev_correct, "corrected"
    if name == "blocks":
        if stage.NAME == "correct_blocks":
            return "parse", part.keys["parse"], "blocks"      # the original program
        return "correct_blocks", rkeys["correct_blocks"], "blocks"
    if name == "corrected":
        return "correct", prev_correct, "corrected"
    up = run.producer[name].NAME
    return up, rkeys[up], name


def iterate_corrections(run, get_client, reports: list, failures: list, progress: bool) -> dict:
    """Run correction rounds 2 … ``max_iter`` (see the module docstring).

    Parameters
    ----------
    run : pipeline.engine.Run after its stage loop (``part.keys`` hold round 1's keys)
    get_client : callable returning a Dask client (started only when something is missing)
    reports, failures : the run's lists, extended with one report per round stage (``split@2``, …)
        and with the failures of any round
    progress : show progress bars

    Returns
    -------
    {program_id: [round record, …]} (see :func:`round_record`); ``part.keys["correct"]`` is left on
    the last round's entry.
    """
    from pipeline.engine import StageReport, _collect_file_hashes, _run_tasks
    opts = run.wf.correct
    parts = [p for p in run.parts if not p.failed and "correct" in p.keys and "errors" in p.keys]
    history = {p.program_id: [round_record(run, 1, p.keys["errors"], p.keys["correct"])] for p in parts}
    if opts.max_iter <= 1 or not parts:
        return history
    chain = [importlib.import_module(m) for m in ROUND_CHAIN]
    prev = {p.program_id: p.keys["correct"] for p in parts}
    for rnd in range(2, opts.max_iter + 1):
        active = [p for p in parts if not p.failed and history[p.program_id][-1]["max_change_um"] >= opts.tol_um]
        if not active:
            break
        rkeys = {p.program_id: {} for p in active}
        for stage in chain:
            rep = StageReport(f"{stage.NAME}@{rnd}")
            todo, specs = [], {}
            names = stage.INPUTS + (("round_passes", "corrected", "first_errors") if stage.NAME == "correct" else ())
            for part in active:
                if part.failed:
                    continue
                params = run.params_for(stage, part)
                ins, spec = {}, {}
                for name in names:
                    src = _source(run, stage, name, part, rkeys[part.program_id], prev[part.program_id])
                    if src is None:
                        ins[name] = run._static[name][1]
                        spec[name] = ("value", run._static[name][0])
                    else:
                        ins[name] = src[1]
                        spec[name] = ("table", str(run.cache.table_path(*src)))
                files: dict = {}
                _collect_file_hashes(params, files)
                key = digest({"stage": stage.NAME, "version": stage.VERSION, "params": params, "files": files,
                              "inputs": ins, "round": rnd})
                rkeys[part.program_id][stage.NAME] = key
                specs[(stage.NAME, part.program_id)] = spec
                rep.partitions += 1
                if run.cache.has(stage.NAME, key):
                    rep.cached += 1
                else:
                    todo.append((part, key, params))
            if todo:
                import time
                t0 = time.perf_counter()
                for part, rec in _run_tasks(get_client(), stage, todo, _RoundView(run, specs), progress):
                    rep.compute_s += rec.get("elapsed_s", 0.0)
                    if rec["ok"]:
                        rep.computed += 1
                    else:
                        rep.failed += 1
                        part.failed = f"round {rnd}: {rec['message']}"
                        failures.append({"program_id": part.program_id, "stage": f"{stage.NAME}@{rnd}",
                                         "message": part.failed, "traceback": rec.get("traceback")})
                rep.wall_s = time.perf_counter() - t0
            reports.append(rep)
        for part in active:
            if part.failed:
                continue
            k = rkeys[part.program_id]
            prev[part.program_id] = k["correct"]
            history[part.program_id].append(round_record(run, rnd, k["errors"], k["correct"], k["split"],
                                                         part.keys["split"]))
    for part in parts:
        if not part.failed:
            part.keys["correct"] = prev[part.program_id]
    return history
