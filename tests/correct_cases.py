"""Shared fixtures of the correction tests: the sample programs, a split, error tables, stage inputs.
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa

from stages.nc.moves import split_blocks
from stages.nc.reader import parse_program

SAMPLES = ("data_samples/rest_overload/nc/mould_contour_t1.nc", "data_samples/rest_overload/nc/mould_finish_t1.nc")


SPLIT = {"split": {"chord_tol_mm": 0.001, "max_pass_mm": 5.0, "merge_max_mm": 0.5},
         "machine": {"rapid_mm_min": 30000.0},
         "tool": {"type": "ball", "diameter_mm": 10.0, "control_point": "tip"}}


def stage_inputs(blocks, passes, errors, *, previous=None, round_passes=None, first=None, generating=None):
    """The ``correct`` stage's declared inputs for one round on ``passes`` of the original program."""
    return {"blocks@first": blocks, "passes@first": passes,
            "passes": passes if round_passes is None else round_passes, "errors": errors,
            "errors@first": first, "generating@first": generating, "corrected@previous": previous}


def load(path):
    data = open(path, "rb").read()
    blocks, _ = parse_program(data, path, "p")
    return data, blocks, split_blocks(blocks, SPLIT)


def errors_table(passes, err, normals):
    n = np.asarray(normals, float)
    return pa.table({"program_id": ["p"] * len(err), "pass_id": passes.column("pass_id"),
                     "err_um": np.asarray(err, float), "nx": n[:, 0], "ny": n[:, 1], "nz": n[:, 2]})


def random_errors(passes, seed, scale=15.0):
    rng = np.random.default_rng(seed)
    n = passes.num_rows
    nn = rng.normal(size=(n, 3))
    nn /= np.linalg.norm(nn, axis=1)[:, None]
    keep = rng.random(n) < 0.8          # some passes pruned
    err = errors_table(passes, rng.normal(0, scale, n), nn)
    return err.filter(pa.array(keep))


def code_words(line: bytes) -> bytes:
    import re
    return re.sub(rb"\([^)]*\)|;.*", b"", line)
