"""Stage ``parse``: one NC program file → its motion blocks with resolved modal state.

Writes the program's ``programs`` row (status, message, T number); ``split`` completes it.
The reading is :func:`stages.nc.reader.parse_program` (vectorised over the file's bytes). A program
that cannot be used yields status ``failed`` with ``file:line: what and why``, every problem found
in ``problems`` (line, column, message) and no blocks; the run goes on with the others. Paths are
shown relative to the workflow's directory (``program_file["name"]``). With ``correct.via_points`` long plain G1 lines and plain arcs are cut
at the split stage's pass ends (:func:`stages.nc.via.via_blocks`) so that each pass's end can be
corrected apart; the passes stay the same.
"""
from __future__ import annotations

import pyarrow as pa

from stages import InputError
from stages.nc.lexer import ProgramError
from stages.nc.reader import empty_blocks, parse_program
from stages.nc.via import via_blocks

NAME = "parse"
VERSION = "3"
INPUTS = ("program_file",)
OUTPUTS = ("programs", "problems", "blocks")
PARAMS = ("correct.via_points", "correct.corner_via_mm", "split.max_pass_mm", "split.chord_tol_mm")


def used_params(params: dict) -> dict:
    """Without via points parsing uses no workflow value (its cache key stays that of the file)."""
    return params if params.get("correct", {}).get("via_points") else {}


def run(inputs: dict, params: dict) -> dict[str, pa.Table]:
    from schemas.problems import SCHEMA as PROBLEMS
    f = inputs["program_file"]
    path, program_id = f["path"], f["program_id"]
    name = f.get("name") or path
    status = {"program_id": program_id, "path": name, "sha256": f["sha256"], "tool": None,
              "n_lines": 0, "n_blocks": 0, "n_passes": 0, "cut_length_mm": 0.0, "duration_s": 0.0,
              "status": "ok", "message": ""}
    problems = []
    try:
        with open(path, "rb") as fh:
            data = fh.read()
        blocks, summary = parse_program(data, name, program_id)
        status.update(summary)
        if params.get("correct", {}).get("via_points"):
            blocks = via_blocks(data, blocks, float(params["split"]["max_pass_mm"]),
                                float(params["split"]["chord_tol_mm"]),
                                float(params["correct"].get("corner_via_mm") or 0.0))
    except InputError as e:
        blocks = empty_blocks()
        status.update(status="failed", message=str(e), n_lines=data.count(b"\n") + 1)
        found = e.problems if isinstance(e, ProgramError) else [(_line_of(str(e), name), None, str(e))]
        problems = [{"program_id": program_id, "path": name, "line": ln, "column": c,
                     "message": m if isinstance(e, ProgramError) else m.split(": ", 1)[-1]} for ln, c, m in found]
    except OSError as e:
        blocks = empty_blocks()
        status.update(status="failed", message=f"{name}: cannot read: {e.strerror}")
        problems = [{"program_id": program_id, "path": name, "line": 1, "column": None,
                     "message": f"cannot read: {e.strerror}"}]
    return {"programs": pa.Table.from_pylist([status]),
            "problems": pa.Table.from_pylist(problems, schema=PROBLEMS), "blocks": blocks}


def _line_of(message: str, name: str) -> int:
    """The line of a ``name:line: ...`` message (1 when it names none)."""
    head = message[len(name) + 1:].split(":", 1)[0] if message.startswith(name + ":") else ""
    return int(head) if head.isdigit() else 1
