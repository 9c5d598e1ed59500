"""Stage ``correct_blocks``: the program as corrected so far, for the next prediction round.

Seed 003 / DESIGN §7: predict again on the corrected path. The previous round's ``corrected`` table
becomes a ``blocks`` table of the original program with the new end points, start points following
them and refitted arc centres (:func:`stages.correction.rounds.apply_corrected`); the rounds then
split, render and predict it like any program. It opens the repeated part of the stage graph.
"""
from __future__ import annotations

import pyarrow as pa

from stages.correction.rounds import apply_corrected

NAME = "correct_blocks"
VERSION = "1"
INPUTS = ("blocks@first", "corrected@previous")
OUTPUTS = ("blocks",)
PARAMS = ()


def run(inputs: dict, params: dict) -> dict[str, pa.Table]:
    """``blocks`` of the original program with the coordinates of the last round's ``corrected``."""
    return {"blocks": apply_corrected(inputs["blocks@first"], inputs["corrected@previous"])}
