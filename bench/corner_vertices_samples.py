"""Hand variants of the measured loop's program at one pocket corner of the sample finishing program
(issue 5; a bench, not a CI test: 30 min of the virtual machine for four whole programs).

The corner: the heavy row along the y 53 wall (y 48, the pocket floor) ends at x 28.2 and climbs the
x wall; pass 4832's fillet points below the ball's equator there keep more mean square than ≤ 20 %
allows the whole part after every round fed the machine's error (``docs/closed_loop_samples.md``).
This replays ``bench/closed_loop_vm_samples.py --secant`` on RUN_DIR (its ``points_secant_*`` files
must exist for ``--rounds``), then sets only the y of the corner's three vertices (the row's via point
at x 28.7, the corner at x 28.2, the climb's first via point 0.5 mm up; blocks 4982–4984 of the
sample's blocks with via points) in four ways, machines the programs whole and reports the part, the
pass and the corner's box.

With ``--blend`` the variants are a rule instead: at every path corner with a via point on both
sides (``correct.corner_via_mm``), the via point before, the corner and the via point after all take
the mean of the two via points' moves (the row's and the climb's), at all such corners, at those
whose two via points' moves differ by more than 100 µm, and at the heavy row's two corners
(blocks 4971 and 4983) only.

    python3 bench/corner_vertices_samples.py RUN_DIR [--rounds 4] [--vm-step-mm 0.5] [--blend]
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

CORNER_BLOCKS = (4982, 4983, 4984)        # via point x 28.7, corner x 28.2, the climb's via point
CORNER_PASS = 4832
CORNER_BOX = (22.0, 34.0, 46.0, 54.0)     # x0, x1, y0, y1 (mm)
Y0 = 48.0                                  # the row's y in the original program


NEW = ["x_new_mm", "y_new_mm", "z_new_mm"]


def blend_variants(blocks, corrected) -> dict:
    """name → (b, 3) new coordinates: the corners (a turn over 30° between G1 lines, with a via point
    on both sides) blended, each corner's three vertices at the mean of its via points' moves."""
    from stages.split import corner_ends
    blocks = blocks.to_pandas()
    blocks = blocks[blocks.motion <= 3]                     # the corrected table's rows
    if not np.array_equal(blocks.block_no.to_numpy(), corrected.block_no.to_numpy()):
        raise SystemExit("the corrected table's rows are not the program's motion blocks")
    g = lambda c: blocks[c].to_numpy()  # noqa: E731
    p0 = np.stack([g("x0_mm"), g("y0_mm"), g("z0_mm")], 1)
    p1 = np.stack([g("x1_mm"), g("y1_mm"), g("z1_mm")], 1)
    via = g("via_only")
    _, at_end = corner_ends(p0, p1, g("motion") == 1)
    i = np.flatnonzero(at_end[1:-1]) + 1
    tri = np.stack([i - 1, i, i + 1], 1)[via[i - 1] & via[i + 1]]
    orig = corrected[["x_mm", "y_mm", "z_mm"]].to_numpy()
    new = corrected[NEW].to_numpy()
    move = new - orig
    apart = np.linalg.norm(move[tri[:, 0]] - move[tri[:, 2]], axis=1) > 0.1
    heavy = np.isin(g("block_no")[tri[:, 1]], HEAVY_ROW_CORNERS)

    def blend(sel):
        out = new.copy()
        t = tri[sel]
        out[t] = orig[t] + ((move[t[:, 0]] + move[t[:, 2]]) / 2)[:, None, :]
        return out
    print(f"{len(tri)} corners with via points on both sides; {int(apart.sum())} whose via points' moves "
          f"differ by more than 100 um (blocks {g('block_no')[tri[apart, 1]].tolist()})")
    return {"blend all": blend(slice(None)), "blend over 100 um": blend(apart), "blend heavy row": blend(heavy)}


HEAVY_ROW_CORNERS = (4971, 4983)          # the heavy row's corners at x 73.4 and x 28.2


def main():
    import pandas as pd
    import pyarrow as pa
    import pyarrow.parquet as pq
    import yaml

    import closed_loop_pipeline_samples as bench
    from closed_loop_vm_samples import errors_from_points, measured_round
    from stages.geometry import tool_from_params
    from stages.nc_writer import reverse_check, write_program

    ap = argparse.ArgumentParser()
    ap.add_argument("run", type=Path, help="a run directory of bench/closed_loop_pipeline_samples.py --whole")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--vm-step-mm", type=float, default=0.5)
    ap.add_argument("--blend", action="store_true", help="the corner-blend rule's variants instead of the hand ones")
    args = ap.parse_args()
    run = args.run.resolve()
    wf = yaml.safe_load((run / "wf1.yaml").read_text())
    params = {"correct": {**wf["correct"]}, "tool": wf["tool"]}
    shape = tool_from_params(wf["tool"]) if params["correct"].get("gouge_limit", True) else None
    table = lambda name: pq.read_table(run / "out" / "tables" / name)  # noqa: E731
    blocks, passes, generating = table("blocks"), table("passes").sort_by("pass_id"), table("generating")
    pts = pd.read_parquet(run / "points.parquet")
    normals = pts[["nx", "ny", "nz"]].to_numpy()
    err, corrected = pts.err_original_um.to_numpy(), None
    tag = f"secant_vm{args.vm_step_mm:g}_"
    for k in range(1, args.rounds + 1):          # the bench's rounds, from its machined errors
        corrected = measured_round(blocks, passes, errors_from_points(pts.pass_id.to_numpy(), err, normals),
                                   corrected, params, True, generating=generating, tool_shape=shape)
        m = pd.read_parquet(run / f"points_{tag}measured_{k}.parquet")
        err = m[[c for c in m.columns if c.startswith("err_") and "measured" in c][0]].to_numpy()
    src = (run / "nc" / "band.nc").read_bytes()
    last = write_program(src, blocks, corrected)
    if last != (run / f"{tag}measured_{args.rounds}.nc").read_bytes():
        raise SystemExit("the replayed rounds do not give the bench's program; run it with the same code first")
    d = corrected.to_pandas()
    rows = [int(np.flatnonzero(d.block_no.to_numpy() == b)[0]) for b in CORNER_BLOCKS]
    y_row = float(d.y_new_mm.to_numpy()[rows[1]])
    half = Y0 + (y_row - Y0) / 2
    programs = {"original": src, f"round {args.rounds}": last}
    if args.blend:
        variants = {name: d.assign(**dict(zip(NEW, xyz.T))) for name, xyz in blend_variants(blocks, d).items()}
    else:
        variants = {}
        for name, ys in {"the climb's via point follows": (None, None, y_row),
                         "the last piece and the corner not moved": (Y0, Y0, None),
                         "only the corner not moved": (None, Y0, None),
                         "all three at half": (half, half, half)}.items():
            v = variants[name] = d.copy()
            for r, y in zip(rows, ys):
                if y is not None:
                    v.loc[r, "y_new_mm"] = y
    for name, v in variants.items():
        t = pa.Table.from_pandas(v, preserve_index=False)
        text = write_program(src, blocks, t)
        if not reverse_check(text, blocks, t)["ok"]:
            raise SystemExit(f"{name}: the written program does not parse back")
        programs[name] = text
    dump = run / ("points_corner_blend.parquet" if args.blend else "points_corner_vertices.parquet")
    bench.vm_errors((-1e9, 1e9, -1e9, 1e9), programs, wf, cache=run.parent / "vm_cache", dump=dump,
                    vm_step_mm=args.vm_step_mm)
    p = pd.read_parquet(dump)
    n = len(p)
    base = float(np.mean(p.err_original_um ** 2))
    x0, x1, y0, y1 = CORNER_BOX
    box = (p.x_mm > x0) & (p.x_mm < x1) & (p.y_mm > y0) & (p.y_mm < y1)
    own = p.pass_id == CORNER_PASS
    print(f"corner vertices' y moves (um) as round {args.rounds} left them: "
          + " / ".join(f"{1000 * (d.y_new_mm[r] - Y0):.0f}" for r in rows))
    for name in programs:
        e = p[f"err_{name.replace(' ', '_')}_um"].to_numpy()
        print(f"  {name:42s} part {100 * np.sqrt(np.mean(e ** 2) / base):5.1f} % of before; mean square of the part: "
              f"pass {CORNER_PASS} {np.sum(e[own] ** 2) / n:6.2f} um^2, box {np.sum(e[box] ** 2) / n:6.2f} um^2")


if __name__ == "__main__":
    os.chdir(ROOT)
    main()
