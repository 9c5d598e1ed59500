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
"""


class InputError(ValueError):
    """Bad user input (a program, a model, a table). The message names the file/line/key."""


def read_numeric_csv(path, columns, what: str):
    """Named numeric columns of a small CSV table (force records, FRF tables, ...).

    Returns an (n, len(columns)) float array in the order of ``columns``. Blank lines and lines
    starting with ``#`` are skipped; a missing column or a non-number is an ``InputError`` naming
    the file and line, ``what`` saying which input it is.
    """
    from pathlib import Path

    import numpy as np

    try:
        lines = Path(path).read_text().splitlines()
    except OSError as e:
        raise InputError(f"{what}: cannot read {path}: {e.strerror or e}") from None
    header = [h.strip().lower() for h in lines[0].split(",")] if lines else []
    missing = [c for c in columns if c not in header]
    if missing:
        raise InputError(f"{path}:1: {what} header lacks {missing} (expected {','.join(columns)}), "
                         f"got {lines[0] if lines else ''!r}")
    cols = [header.index(c) for c in columns]
    rows = []
    for n, line in enumerate(lines[1:], start=2):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.split(",")
        try:
            rows.append([float(parts[c]) for c in cols])
        except (ValueError, IndexError):
            raise InputError(f"{path}:{n}: expected numbers {','.join(columns)}, got {line!r}") from None
    return np.array(rows, dtype=float).reshape(-1, len(columns))
