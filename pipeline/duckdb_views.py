"""``<out>/<workflow name>.duckdb``: views over a run's Parquet tables, rebuilt after every run.

An analyst opens the file (``duckdb runs/mould/mould.duckdb``) and queries the tables by name
(``passes``, ``errors``, …) or the joined per-pass view ``pass_errors``: program, pass, NC line,
the motion as text, the move, whether it cuts and is predicted, the contact angle q and rotation
angle φ, the generating point and normal, the error and its parts, and the correction of the
pass's end vertex. The views read the Parquet files by absolute path, so the file works from any
directory as long as the run's output stays where it is.
"""
from __future__ import annotations

import os
from pathlib import Path

MOTION = "case p.motion when 0 then 'rapid' when 1 then 'linear' when 2 then 'arc_cw' when 3 then 'arc_ccw' end"

# the joined view: (table, alias, join condition, its columns in the view)
JOINED = (
    ("cut_filter", "cf", "cf.program_id = p.program_id and cf.pass_id = p.pass_id", "cf.is_cutting"),
    ("angle_prune", "ap", "ap.program_id = p.program_id and ap.pass_id = p.pass_id", "ap.predict"),
    ("generating", "g", "g.program_id = p.program_id and g.pass_id = p.pass_id",
     "g.contact_deg, g.rotation_deg, g.gen_x_mm, g.gen_y_mm, g.gen_z_mm, g.nx, g.ny, g.nz"),
    ("errors", "e", "e.program_id = p.program_id and e.pass_id = p.pass_id",
     "e.err_um, e.err_deflection_um, e.err_shape_um, e.err_runout_um, e.err2_um"),
    ("corrected", "c", "c.program_id = p.program_id and c.block_no = p.block_end",
     "c.move_um, c.x_new_mm, c.y_new_mm, c.z_new_mm, c.clipped, c.drift_x_um, c.drift_y_um, c.drift_z_um"),
)


def write_views(out: Path, name: str) -> Path | None:
    """(Re)write ``<out>/<name>.duckdb`` with a view per table in ``<out>/tables`` and ``pass_errors``.

    Returns the file, None when the run has no tables yet. The file is built aside and moved in
    place, so a reader never sees half of it.
    """
    import duckdb
    tables = sorted(d.name for d in (Path(out) / "tables").glob("*") if d.is_dir() and any(d.glob("*.parquet")))
    if not tables:
        return None
    path = Path(out) / f"{name}.duckdb"
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.unlink(missing_ok=True)
    con = duckdb.connect(str(tmp))
    try:
        for t in tables:
            files = str((Path(out) / "tables" / t).resolve() / "*.parquet").replace("'", "''")
            con.execute(f"create view {t} as select * from read_parquet('{files}', union_by_name = true)")
        if "passes" in tables:
            cols = [f"p.program_id, p.pass_id, p.line_no, {MOTION} as motion, p.x0_mm, p.y0_mm, p.z0_mm, "
                    "p.x1_mm, p.y1_mm, p.z1_mm, p.feed_mm_min"]
            joins = []
            for table, alias, on, columns in JOINED:
                if table in tables:
                    cols.append(columns)
                    joins.append(f"left join {table} {alias} on {on}")
            con.execute(f"create view pass_errors as select {', '.join(cols)} from passes p {' '.join(joins)}")
    finally:
        con.close()
    os.replace(tmp, path)
    return path
