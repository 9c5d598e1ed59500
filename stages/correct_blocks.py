"""Stage ``correct_blocks``: the program as corrected so far, for the next prediction round.

Seed 003 / DESIGN §7: predict again on the corrected path. The previous round's ``corrected`` table
becomes a ``blocks`` table of the original program with the new end points, start points following
them and refitted arc centres (:func:`stages.correction.rounds.apply_corrected`); the rounds then
split, render and predict it like any program. It opens the repeated part of the stage graph.

With scheduled feeds (``feeds@first``, a ``feed:`` section) the blocks also get the feeds the
written program will run at (:func:`stages.nc.feed_words.block_feeds`): the rounds predict the error
the machine leaves at those feeds, so the offsets do not cancel a deflection the lower feed no
longer causes.
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa

from stages.correction.rounds import apply_corrected
from stages.nc.feed_words import block_feeds
from stages.tables import col

NAME = "correct_blocks"
VERSION = "2"
INPUTS = ("blocks@first", "corrected@previous", "passes@first", "feeds@first")
OUTPUTS = ("blocks",)
PARAMS = ()


def run(inputs: dict, params: dict) -> dict[str, pa.Table]:
    """``blocks`` of the original program with the coordinates of the last round's ``corrected``
    and the scheduled feeds."""
    blocks = apply_corrected(inputs["blocks@first"], inputs["corrected@previous"])
    feeds = inputs.get("feeds@first")
    if feeds is None or feeds.num_rows == 0:
        return {"blocks": blocks}
    f = block_feeds(inputs["blocks@first"], inputs["passes@first"], feeds)
    i = blocks.schema.get_field_index("feed_mm_min")
    new = np.where(np.isfinite(f), f, col(blocks, "feed_mm_min"))
    field = blocks.schema.field(i)
    return {"blocks": blocks.set_column(i, field, pa.array(new, field.type, mask=np.isnan(new)))}
