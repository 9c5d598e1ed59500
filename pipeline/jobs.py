"""Jobs of the product: a workflow's ``job`` key chooses what ``pipeline run`` does with it.

``mould`` (the default) is the stage graph of :mod:`pipeline.graph` over NC programs, run by the
engine. The seed systems that are not chains of NC programs are jobs with their own workflow
schema and runner module (``JOBS``). A runner module exposes

- ``run(path, *, out=None, overlays=(), fresh=False, workers=None, quiet=False) -> dict``: read and
  validate the workflow (``WorkflowError`` naming the file, line and key), compute, write its
  tables under ``<out>/tables/<table>/``, its report and ``<out>/run.json`` (the returned summary,
  with ``name``, ``job``, ``output``, ``wall_s`` and ``failures``); bad input raises ``InputError``;
- ``echo_summary(summary)``: the lines ``pipeline run`` prints;
- ``load(path, overlays=())``: the validated workflow and its project folder (:func:`load_any`).
"""
from __future__ import annotations

import importlib
from pathlib import Path

from pipeline.config_errors import _yaml_lines, read_yaml

# job name → runner module (None: the engine's stage graph)
JOBS = {"mould": None, "polygon": "pipeline.polygon_job", "posture": "pipeline.posture_job"}


class JobError(ValueError):
    """A workflow naming a job the product does not have."""


def job_name(path) -> str:
    """The ``job`` of the workflow file ``path`` (``mould`` when absent)."""
    path = Path(path)
    raw, text = read_yaml(path, "workflow", JobError)
    job = raw.get("job", "mould") if isinstance(raw, dict) else "mould"
    if job not in JOBS:
        line = _yaml_lines(text).get(("job",))
        raise JobError(f"{path}:{line}: job: unknown job {job!r}; the jobs are {', '.join(sorted(JOBS))}")
    return job


def runner(job: str):
    """The runner module of a job that is not the stage graph."""
    return importlib.import_module(JOBS[job])


def load_any(path, overlays=()):
    """Any job's workflow file read and validated by its job's reader: (workflow, project folder)."""
    job = job_name(path)
    if JOBS[job] is None:
        from pipeline.config import load_workflow
        return load_workflow(path, overlays)
    return runner(job).load(path, overlays)
