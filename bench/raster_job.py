"""The synthetic raster program of the parse and correction benchmarks, and their options."""
from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
from tests.ncprograms import raster_program  # noqa: E402

PARAMS = {"split": {"chord_tol_mm": 0.001, "max_pass_mm": 5.0, "merge_max_mm": 0.5},
          "machine": {"rapid_mm_min": 30000.0}, "tool": {"type": "ball", "diameter_mm": 6.0, "control_point": "tip"}}


def options_and_program(description: str):
    """(parsed ``--blocks``/``--repeat`` options, program bytes, the split parameters)."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--blocks", type=int, default=300_000)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    return a, raster_program(a.blocks), PARAMS
