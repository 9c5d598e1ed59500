"""Stages: pure functions table → table (DESIGN §2).

Every stage module exposes

- ``NAME``: the stage name used in workflows, the cache and ``--until``;
- ``VERSION``: bump it when the stage's output for the same input changes (invalidates its cache
  entries and everything downstream of them);
- ``INPUTS``: the names of the tables (or ``"program_file"``, ``"stock"``...) it reads;
- ``OUTPUTS``: the names of the tables it writes (each has a schema in ``schemas/``);
- ``PARAMS``: the workflow keys it depends on (``"split"``, ``"tool"``, ...); only these enter its
  cache key, so changing ``prune.min_contact_deg`` does not re-parse programs;
- ``run(inputs: dict, params: dict) -> dict[str, pa.Table]``.

A stage never imports Dask, never reads or writes the cache, and never opens output files: the
engine (``pipeline/``) does all of that. Bad input is reported by raising ``stages.InputError``
with a ``file:line: what and why`` message; the engine records it against the program and goes on.

Beside the stage modules, the computation lives in packages by concept: ``nc`` (reading, splitting
and writing NC text), ``geometry`` (the cutter, envelopes, sweeps, workpieces), ``render`` (the
depth-test back ends), ``scan`` (the render chain's kernels), ``cutting`` (forces, deflection,
surface error), ``correction`` (vertex moves), ``gap`` (the sim-to-real diagnosis),
``tool_measure`` (tool images and wear), ``thermal`` (the machine's drift), ``polygon`` (polygon cutting, the
``polygon`` job) and ``virtual_machine`` (the independent check).
"""


class InputError(ValueError):
    """Bad user input (a program, a model, a table). The message names the file/line/key."""
