"""The corrected NC programs of one program, as files: the source with moved coordinates, reverse-
checked by parsing it back, and on request Heidenhain LN blocks and a compensation table."""
from __future__ import annotations

from pathlib import Path

from stages.nc.heidenhain import write_comp_table, write_ln_program
from stages.nc.writer import reverse_check, write_program


def corrected_programs(inputs: dict, params: dict) -> dict[str, bytes]:
    """{file name: bytes} for the ``<out>/nc/`` directory.

    Parameters
    ----------
    inputs : {"program_file": {path, sha256, program_id}, "blocks", "corrected", "errors"}
    params : {"correct": {max_move_um, ln_normals, comp_table, ...}}
    """
    f = inputs["program_file"]
    src = Path(f["path"])
    blocks, corrected = inputs["blocks"], inputs["corrected"]
    opts = params.get("correct") or {}
    text = write_program(src.read_bytes(), blocks, corrected, source_sha256=f["sha256"],
                         max_move_um=opts.get("max_move_um"))
    check = reverse_check(text, blocks, corrected, path=str(src), program_id=f["program_id"])
    if not check.get("ok", False):
        raise RuntimeError(f"{src}: corrected program failed its reverse check: {check}")
    out = {src.name: text}
    if opts.get("ln_normals"):
        out[f"{src.stem}_ln.h"] = write_ln_program(blocks, corrected, name=src.stem).encode()
    if opts.get("comp_table"):
        out[f"{src.stem}.3dtc.csv"] = write_comp_table(inputs["errors"]).encode()
    return out
