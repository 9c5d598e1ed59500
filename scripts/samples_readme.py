"""``data_samples/README.md``, the users' manual of the sample files, filled in by scripts/make_samples.py."""
from __future__ import annotations

import numpy as np

from samples_process import (ALLOWANCE_MM, BOX, CAM_TOL, OVERLAP_MM, REST_BAND_MM, REST_MM, SEMI_T1, SEMI_T2,
                             STEEP_DEG, T1, T2, cusp_um, levels_of)
from samples_programs import PROGRAMS

HEAD = """# Sample data

Small, real-shaped inputs for the pipeline's jobs. `python scripts/make_samples.py` makes `models/`, `nc/`,
`rest_overload/`, `tools/t1_profile.csv`, `machine/` and this file (deterministic, {minutes:.0f} min on two cores;
`opencamlib` computes the toolpaths) from the OpenCAMLib reference mesh `ktoolcav.stl`;
`scripts/make_tool_images.py` makes `tool_images/` and `tools/t1_profile_measured.*`, `scripts/make_gap_samples.py`
makes `gap/` (`workflows/gap.yaml`).

## Frame and units

Machine frame, millimetres, tool axis +Z (3-axis). Work zero: the insert's min corner at X0 Y0,
its parting face (the finished top of the insert, around the cavity) at Z0; the insert occupies
X0–101.6, Y0–84.1, Z-41.275–0. NC coordinates are the tool TIP (lowest point of the ball).

## The finishing process (`workflows/mould.yaml`)

A semi-finished insert and the three programs that finish it, machined in the order of their file
names on that one stock (the workflow's `programs:` glob is sorted; that order is the machining
order). They finish the cavity inside the machining boundary X{bx0:g}–{bx1:g}, Y{by0:g}–{by1:g}, under
the parting face (which is face-milled, not ball-finished): the pocket's right wall and both its
corners, the right part of its long walls, its floor and the Ø12.7 boss on it, the right side of
the runner and of the 1.27 mm relief.

| file | what | frame / units | made by |
|---|---|---|---|
| `models/mould.stl` | nominal (design) model: the cavity insert, {nominal_faces} faces, watertight | mm, machine frame | `ktoolcav.stl` (inches) × 25.4, cavity up |
| `models/semi.stl` | semi-finished stock over the boundary: {allow} mm over the model where the programs cut | mm, machine frame | semi-finishing sweeps (below) |
| `nc/10_steep_t1.nc` | O1010: Z-level contours on walls steeper than {steep:.0f}°, Ø10 ball T1, climb; {g1_10} G1 | Fanuc/ISO, mm, tool tip | OpenCAMLib AdaptiveWaterline |
| `nc/20_shallow_t1.nc` | O1020: zig-zag raster along X on the shallow areas, Ø10 ball T1; {g1_20} G1 | as above | OpenCAMLib BatchDropCutter |
| `nc/30_pencil_t2.nc` | O1030: rest finishing where a Ø10 cannot reach, Ø4 ball T2; {g1_30} G1 | as above | both, from a Ø10's reach |
| `tools/t1_profile.csv` | contour error of T1 per contact angle `contact_deg, error_um` (+ = undersize) | deg, µm | synthetic (below) |
| `tools/t1_profile_measured.csv` | T1's profile measured by `pipeline tool-profile` on `tool_images/t1/` (`.json`, `.png`) | deg, µm | `make_tool_images.py` |
| `machine/frf_xy.csv` | tool-tip compliance FRF `freq_hz, xx_re, xx_im, yy_re, yy_im`, 0–5000 Hz, 2 Hz steps | Hz, µm/N | modal sum (below) |

`models/mould.stl`: `ktoolcav.stl` rotated so its cavity face looks up, (X, Y, Z) = 25.4·(x+2, z+1.5, −y);
bounds {nominal_bounds}: a 26.7 mm deep pocket with walls drafted 1–3°, a foot fillet and corners of about
2.7 mm radius, a Ø12.7 × 1.27 mm boss on its floor, a runner channel and a 1.27 mm relief around it.

### The finishing programs

All three leave no stock; OpenCAMLib's points (every {sample} mm along a row, adaptive along a contour)
are thinned to a chordal tolerance of {tol} mm and written to 3 decimals. A link between two stretches
is a straight feed move where it is short and the ball stays off the model all along it (exact
distances to the model), else the tool lifts to Z1, traverses at rapid and plunges (G1 at the plunge
feed) in the air. No arcs. A ball's contact is the model's closest point to its centre; its slope is
the angle of the contact normal from +Z.

- `10_steep_t1.nc`: levels every {dz1} mm from Z{z1a:g} down to Z{z1b:g} ({allow} mm + 0.05 over the pocket floor:
  the floor is the raster's), kept where the slope is {steep:.0f}° or more: scallops {w1v:.0f} µm on a vertical
  wall, {w1s:.0f} µm at {steep:.0f}°. Climb (the material on the tool's right, M3), one way: a 1 mm lead move
  square to the wall in the air at each end of a level's stretch, a retract between; level by level, top
  first (a lower level never meets a higher level's stock on its flutes). F{f1:g}, S{s1}.
- `20_shallow_t1.nc`: rows along X every {st1} mm (scallop {c1:.0f} µm on a flat) kept where the slope is at
  most {steep:.0f}°, and {ov} mm of path on beyond (the overlap with the contours); a row runs into the next
  where the link is free. F{f1:g}, S{s1}.
- `30_pencil_t2.nc`: the rest of a Ø10 ball: wherever a Ø10 put anywhere on the model (every row and every
  level above, whatever the slope) leaves more than {rest} mm over it — the pocket's corners, the feet of
  its walls, round the boss, along the relief's wall. Contours every {dz2} mm on the steep part, chained
  down each corner back and forth; rings on each floor {st2}–{band} mm out from its walls, {st2} mm apart
  (the waterline of a flat cutter just above the floor, a Ø4 dropped on its points). Scallops
  {c2:.0f} µm. F{f2:g}, S{s2}.

| program | stretches | G1 moves | G0 moves | N blocks | retracts |
|---|---|---|---|---|---|
{program_rows}

### The semi-finished stock

The same strategies, each ball kept {allow} mm off the model (the paths of a ball {allow2} mm larger,
same centre), coarser: Ø10 contours every {dzs1} mm and a raster every {sts1} mm (scallops {ws1:.0f} µm on a
wall, {cs1:.0f} µm on a flat; the raster also covers the margins), then the Ø4 rest passes where a Ø10 leaves
more than {rest_semi} mm (contours every {dzs2} mm, floor rings every {sts2} mm). Its surface is exact: the
lowest point over (x, y) of the capsules the balls sweep along their {semi_moves} feed moves. The mesh
samples it in rectangular cells ({bc0} × {bc1} mm on a flat, their edges on the raster's rows and ridges;
split along the axis across which the surface bends while it departs from the cell's two triangles
by more than 5 µm along the normal, down to {fine0} × {fine1} mm at vertical steps), {semi_faces} faces,
closed into a watertight solid down to Z-41.275; bounds {semi_bounds}. At the finishing contact points
its thickness along the normal is within {mesh_max:.0f} µm of the exact surface's (99 % within {mesh_p99:.0f} µm:
cells across the vertical steps, and contour scallops between samples). On the model's sharp edges,
where the contact normal is any of a fan, the stock read along the fan's directions across the cells' chords
is down to 18 µm under the allowance (`tests/test_samples.py`).

### The allowance the finishing tools meet

The stock's thickness along the model's normal from each contact point of a program (every G1 end point;
points within 1 mm of the stock's cut sides left out), to the stock mesh, by brute force:
`python scripts/measure_samples.py`.

| program | contact points | median | 5 % | 95 % | max |
|---|---|---|---|---|---|
{allowance_rows}

The pipeline measures the same per predicted pass (`run.json` `allowance`, table `allowance`): from
the pass's generating point, the farthest engaged point of the tool along the normal; its tails are
longer (beside a wall the tool's side meets the wall's stock too). The largest values above are at the
model's corners tighter than the semi-finishing Ø4's 2.2 mm (it leaves them thicker) and on the
relief's sharp top edge, where the contact normal runs along the parting face's 0.2 mm.

Limits: the pencil does not reach corners tighter than 2 mm (the feet of the relief and of the boss
are sharp: what a Ø4 leaves there is for another tool). The cusps of the finishing passes are the
surface's; the programs' chords depart from the model by up to {tol} mm between their points.

`tests/test_samples.py` checks the meshes, that every checked finishing point puts its ball on the
nominal surface, the stock's thickness there, and that the programs parse.

## The heavy-rest case (`workflows/rest_overload.yaml`)

`rest_overload/` keeps the first sample files: a semi-finished stock that leaves ~0.6 mm of rest
material on the walls parallel to X, and a finishing raster along X that rides over those walls.

| file | what | frame / units | made by |
|---|---|---|---|
| `rest_overload/semi.stl` | stock over X12–90, Y21–71.1: a Ø10 semi-finishing raster along X, step-over 0.8 mm, 0.2 mm allowance | mm | lower envelope on a 0.3 mm grid |
| `rest_overload/nc/mould_finish_t1.nc` | O1001: Ø10 ball T1, zig-zag along X over X14–88 Y33–64.8, step-over 0.6 mm | Fanuc/ISO, mm, tool tip | BatchDropCutter |
| `rest_overload/nc/mould_contour_t1.nc` | O1002: pocket wall contours at Z-8, -14, -20 (G18 I K leads), boss circles | as above | Waterline |

The stock is 0.2 mm + up to 16 µm of cusp on flat areas, thicker in concave corners tighter than the
ball and on walls parallel to X; as a height field sampled every 0.3 mm it is cut by chords within
0.3 mm of the model's sharp convex edges (the finishing ball's depth of cut at its program points:
median 0.199 mm, 5th percentile 0.12 mm, minimum 0.05 mm). The raster has {ro_g1} G1 and {ro_arcs} G2/G3
moves (row links as I J semicircles); the contour program {ro_con_g1} G1 and {ro_con_arcs} G2/G3 moves, `;`
comments and a multi-word block; its boss arcs circumscribe the 46-gon boss (standing off its facets by
at most 15 µm).

## Tool and machine data

`tools/t1_profile.csv`: 0.6 + 2.4 (q/90)² + 0.9 exp(−½((q−55)/6)²) µm + 0.05 µm noise (seed 2), Gaussian
low-pass σ = 1°, 0–90° in 0.1° steps. `machine/frf_xy.csv`: G = Σ 1/(k(1 − r² + 2iζr)), r = f/fn; x: 850 Hz
ζ0.03 k2.0 N/µm + 2300 Hz ζ0.05 k6.0 N/µm; y: 910 Hz ζ0.035 k2.3 N/µm + 2450 Hz ζ0.045 k6.5 N/µm;
noise (0.002 + 0.5 %·|G|) µm/N (seed 1).

## Source and licence

`ktoolcav.stl` comes from the OpenCAMLib repository (https://github.com/aewallin/opencamlib,
folder `stl/`), LGPL-2.1; the toolpaths are computed with the `opencamlib` package (LGPL-2.1),
independent CAM code, not ours.
"""


def _bounds(b) -> str:
    return "[" + ", ".join(f"{v:.2f}" for v in np.asarray(b).ravel()) + "]"


def render(nominal, proc: dict, rest_overload: dict, minutes: float) -> str:
    """The README's text from the nominal mesh and what :func:`samples_build.make_process` and
    :func:`samples_rest_overload.make` report."""
    fin = proc["finishing"]
    rows = []
    for name in PROGRAMS:
        i = fin[name]
        stretches = sum(v.get("closed", 0) + v.get("open", 0) + v.get("stretches", 0)
                        for v in [i] + [x for x in i.values() if isinstance(x, dict)])
        rows.append(f"| `{name}` | {stretches} | {i['moves']['G1']} | {i['moves']['G0']} | {i['blocks']} | "
                    f"{i['links']['retract']} |")
    met = proc["allowance"]
    arows = [f"| {k} | {v['points']} | {v['median_mm']:.3f} | {v['p5_mm']:.3f} | {v['p95_mm']:.3f} | "
             f"{v['max_mm']:.3f} |" for k, v in met.items()]
    mesh = proc["mesh_vs_exact"].values()
    z1 = levels_of(T1)
    ro_f, ro_c = rest_overload["finish"], rest_overload["contour"]
    fine = (proc["base_cell"][0] / 32, proc["base_cell"][1] / 32)
    return HEAD.format(
        minutes=minutes, bx0=BOX[0], bx1=BOX[2], by0=BOX[1], by1=BOX[3], nominal_faces=len(nominal.faces),
        nominal_bounds=_bounds(nominal.bounds), allow=ALLOWANCE_MM, allow2=2 * ALLOWANCE_MM, steep=STEEP_DEG,
        g1_10=fin[PROGRAMS[0]]["moves"]["G1"], g1_20=fin[PROGRAMS[1]]["moves"]["G1"],
        g1_30=fin[PROGRAMS[2]]["moves"]["G1"], sample=0.05, tol=CAM_TOL, dz1=T1.level_step, z1a=z1[0],
        z1b=z1[-1], w1v=cusp_um(T1.radius, T1.level_step), w1s=cusp_um(T1.radius, T1.level_step / np.sin(np.radians(STEEP_DEG))),
        f1=T1.feed, s1=T1.rpm, st1=T1.raster_step, c1=cusp_um(T1.radius, T1.raster_step), ov=OVERLAP_MM,
        rest=REST_MM, dz2=T2.level_step, st2=T2.raster_step, band=REST_BAND_MM, c2=cusp_um(T2.radius, T2.raster_step),
        f2=T2.feed, s2=T2.rpm, program_rows="\n".join(rows), dzs1=SEMI_T1.level_step, sts1=SEMI_T1.raster_step,
        ws1=cusp_um(SEMI_T1.radius, SEMI_T1.level_step), cs1=cusp_um(SEMI_T1.radius, SEMI_T1.raster_step),
        rest_semi=ALLOWANCE_MM + REST_MM, dzs2=SEMI_T2.level_step, sts2=SEMI_T2.raster_step,
        semi_moves=proc["semi_moves"], bc0=proc["base_cell"][0], bc1=proc["base_cell"][1],
        fine0=f"{fine[0]:.4f}", fine1=f"{fine[1]:.5f}", semi_faces=proc["semi_faces"],
        semi_bounds=_bounds(proc["semi_bounds"]), mesh_max=max(m["max_diff_um"] for m in mesh),
        mesh_p99=max(m["p99_diff_um"] for m in mesh), allowance_rows="\n".join(arows),
        ro_g1=ro_f["moves"]["G1"], ro_arcs=ro_f["moves"]["G2"] + ro_f["moves"]["G3"],
        ro_con_g1=ro_c["moves"]["G1"], ro_con_arcs=ro_c["moves"]["G2"] + ro_c["moves"]["G3"])
