"""Stage ``correct_blocks``: the program as corrected so far, for the next prediction round.

Seed 003 / DESIGN §7: predict again on the corrected path. This stage turns the ``corrected`` table
of the previous round back into a ``blocks`` table (new end points, start points following them,
refitted arc centres) with :func:`stages.correct.apply_corrected`; the engine then runs the same
split → render → physics → errors chain on it and ``correct`` again with the previous round's
table (see ``pipeline/iterate.py``). Used only from the second round on.
"""
from __future__ import annotations

import pyarrow as pa

from stages.correct import apply_corrected

NAME = "correct_blocks"
VERSION = "1"
INPUTS = ("blocks", "corrected")
OUTPUTS = ("blocks",)
PARAMS = ()


def run(inputs: dict, params: dict) -> dict[str, pa.Table]:
    """``blocks`` of the original program with the coordinates of ``corrected``.

    Parameters
    ----------
    inputs : {"blocks": the original program's ``blocks``, "corrected": the last round's ``corrected``}
    params : unused

    Returns
    -------
    {"blocks": blocks table of the corrected program (same rows, block numbers and lines)}
    """
    return {"blocks": apply_corrected(inputs["blocks"], inputs["corrected"])}
