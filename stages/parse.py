"""Stage ``parse``: one NC program file → its motion blocks with resolved modal state.

Writes the program's ``programs`` row (status, message, T number); ``split`` completes it.
The reading is :func:`stages.nc.reader.parse_program` (vectorised over the file's bytes). A program
that cannot be used yields status ``failed`` with ``file:line: what and why`` and no blocks; the
run goes on with the others. With ``correct.via_points`` long plain G1 lines and plain arcs are cut
at the split stage's pass ends (:func:`stages.nc.via.via_blocks`) so that each pass's end can be
corrected apart; the passes stay the same.
"""
from __future__ import annotations

import pyarrow as pa

from stages import InputError
from stages.nc.reader import empty_blocks, parse_program
from stages.nc.via import via_blocks

NAME = "parse"
VERSION = "2"
INPUTS = ("program_file",)
OUTPUTS = ("programs", "blocks")
PARAMS = ("correct.via_points", "correct.corner_via_mm", "split.max_pass_mm", "split.chord_tol_mm")


def used_params(params: dict) -> dict:
    """Without via points parsing uses no workflow value (its cache key stays that of the file)."""
    return params if params.get("correct", {}).get("via_points") else {}


def run(inputs: dict, params: dict) -> dict[str, pa.Table]:
    f = inputs["program_file"]
    path, program_id = f["path"], f["program_id"]
    status = {"program_id": program_id, "path": path, "sha256": f["sha256"], "tool": None,
              "n_lines": 0, "n_blocks": 0, "n_passes": 0, "cut_length_mm": 0.0, "duration_s": 0.0,
              "status": "ok", "message": ""}
    try:
        with open(path, "rb") as fh:
            data = fh.read()
        blocks, summary = parse_program(data, path, program_id)
        status.update(summary)
        if params.get("correct", {}).get("via_points"):
            blocks = via_blocks(data, blocks, float(params["split"]["max_pass_mm"]),
                                float(params["split"]["chord_tol_mm"]),
                                float(params["correct"].get("corner_via_mm") or 0.0))
    except InputError as e:
        blocks = empty_blocks()
        status.update(status="failed", message=str(e), n_lines=data.count(b"\n") + 1)
    except OSError as e:
        blocks = empty_blocks()
        status.update(status="failed", message=f"{path}: cannot read: {e.strerror}")
    return {"programs": pa.Table.from_pylist([status]), "blocks": blocks}
