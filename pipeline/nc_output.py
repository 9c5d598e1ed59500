"""Corrected NC programs: ``<out>/nc/<program file name>`` (and LN / compensation-table variants).

The engine calls this after the ``correct`` stage; the text itself is made by the pure
``stages.nc_writer`` from the source bytes, its blocks and the ``corrected`` table. Files are written
to a temporary name and renamed, so a killed run never leaves half a program for the machine.
"""
from __future__ import annotations

import os
from pathlib import Path

from stages import nc_writer


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def write_corrected_programs(run, part) -> list[Path]:
    """Write the corrected program of one partition (and the optional variants). Returns the paths."""
    src = Path(part.path)
    data = src.read_bytes()
    blocks = run.cache.read("parse", part.keys["parse"], "blocks")
    corrected = run.cache.read("correct", part.keys["correct"], "corrected")
    opts = run.wf.correct
    outdir = run.out / "nc"
    outdir.mkdir(parents=True, exist_ok=True)
    written = []
    text = nc_writer.write_program(data, blocks, corrected, source_sha256=part.sha256, max_move_um=opts.max_move_um)
    check = nc_writer.reverse_check(text, blocks, corrected, path=str(src), program_id=part.program_id)
    if not check.get("ok", False):
        raise RuntimeError(f"{src}: corrected program failed its reverse check: {check}")
    _atomic_write(outdir / src.name, text)
    written.append(outdir / src.name)
    if opts.ln_normals:
        p = outdir / f"{src.stem}_ln.h"
        _atomic_write(p, nc_writer.write_ln_program(blocks, corrected, name=src.stem).encode())
        written.append(p)
    if opts.comp_table:
        errors = run.cache.read("errors", part.keys["errors"], "errors")
        p = outdir / f"{src.stem}.3dtc.csv"
        _atomic_write(p, nc_writer.write_comp_table(errors).encode())
        written.append(p)
    return written
