"""Make the bundled sample data under ``data_samples/`` (deterministic).

Run from the project root::

    python scripts/make_samples.py [--source PATH_TO/ktoolcav.stl] [--out data_samples]

Uses ``opencamlib`` (one of the project's dependencies) for the drop-cutter toolpaths.
It takes well under a minute on two cores.

What it writes (all lengths mm, machine frame: tool axis +Z; the part's min corner at
X0 Y0, its parting face, the finished top of the insert, at Z0, the part below it down to
Z-41.275):

``models/mould.stl``
    Nominal (design) model: the cavity insert ``ktoolcav.stl`` of the OpenCAMLib repository
    (folder ``stl/``, LGPL-2.1), in inches, scaled ×25.4 and rotated so that its cavity face
    (the face at y=0 of the source, facing −y) looks up (+Z): machine (X, Y, Z) = 25.4 ·
    (x + 2, z + 1.5, −y) of the source. 101.6 × 84.1 × 41.3 mm, watertight, 4,090 faces.
    The cavity is a 26.7 mm deep pocket (drafted walls) with a Ø12.7 mm boss on its floor, a
    runner channel and a 1.27 mm deep relief around it.
``rest_overload/semi.stl``
    Semi-finished stock over the machined region X12–90, Y21–71: the surface left by a
    semi-finishing ball pass (Ø10 ball, zig-zag along X, step-over 0.8 mm, 0.2 mm stock
    allowance = the finishing depth), computed exactly as the lower envelope of the ball
    swept along its OpenCAMLib drop-cutter path, sampled on a 0.3 mm grid and closed into a
    watertight solid (bottom at the part's bottom, Z-41.275). Everywhere at least 0.2 mm from
    the nominal surface; exactly 0.2 mm under each semi-finishing row; cusps of
    0.8² / (8·5) = 16 µm on flat areas; more in concave corners the ball cannot reach and on
    walls parallel to X (rest material a real semi-finishing pass leaves). Limit: sampled at
    0.3 mm, the 0.2 mm rounds over sharp convex edges are cut by chords (locally thinner).
``rest_overload/nc/mould_finish_t1.nc``
    Finishing program O1001: Ø10 ball end mill T1 dropped by OpenCAMLib's BatchDropCutter on
    the nominal model, parallel zig-zag along X over X14–88, Y33–64.8, step-over 0.6 mm
    (cusp 9 µm), samples every 0.05 mm along a row (steep stretches refined to 3-D steps
    ≤ 0.05 mm), collinear points removed within 0.002 mm (Douglas–Peucker), row links as
    G2/G3 semicircles (I J) or, where the surface differs, as lift/traverse/lower G1 moves. Coordinates are the tool TIP (OpenCAMLib's CL point is the tip: checked here on a
    flat and a tilted facet before anything is written).
``rest_overload/nc/mould_contour_t1.nc``
    Contour program O1002, same tool: OpenCAMLib Waterline loops around the pocket walls at
    three Z levels (climb, counter-clockwise, vertical G18 lead-in/lead-out arcs with I K), and
    around the boss at two Z levels written as circular arcs (one level in I J form, one in R
    form). Contains ';' comments and multi-word blocks.
``tools/t1_profile.csv``
    Measured contour error of the ball cutter T1 per contact angle: ``contact_deg, error_um``,
    0–90° in 0.1° steps; positive = tool smaller than nominal there. A synthetic but
    realistic measurement: slight undersize growing toward the equator, a bump near 55°,
    0.05 µm noise (seed 2), low-pass filtered as seed 002 prescribes.
``machine/frf_xy.csv``
    Tool-tip compliance FRF ``freq_hz, xx_re, xx_im, yy_re, yy_im`` in µm/N, 0–5000 Hz in 2 Hz
    steps: two modes per axis (x: 850 Hz ζ0.03 k2.0 N/µm and 2300 Hz ζ0.05 k6.0 N/µm;
    y: 910 Hz ζ0.035 k2.3 N/µm and 2450 Hz ζ0.045 k6.5 N/µm), receptance
    G = Σ 1/(k(1 − r² + 2iζr)), r = f/fn, plus measurement noise (seed 1).
``README.md``
    The above, for users of the samples.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

# scripts/ is on sys.path when run as a script
import samples_rest_overload as rest  # noqa: E402
from samples_cam import BALL_R, DEFAULT_SOURCE, check_cl_is_tip, load_nominal, ocl_surface, roundtrip_stl  # noqa: E402


# ------------------------------------------------------------------------- tool and machine data
def tool_profile() -> np.ndarray:
    """Measured contour error of the ball cutter per contact angle (µm, + = undersize)."""
    q = np.round(np.arange(0, 900 + 1) * 0.1, 1)
    s = q / 90.0
    err = 0.6 + 2.4 * s ** 2 + 0.9 * np.exp(-0.5 * ((q - 55.0) / 6.0) ** 2)
    rng = np.random.default_rng(2)
    noisy = err + rng.normal(0.0, 0.05, q.size)
    # low-pass (seed 002): Gaussian kernel, sigma 1 deg, edges mirrored
    k = np.exp(-0.5 * (np.arange(-30, 31) * 0.1 / 1.0) ** 2)
    k /= k.sum()
    padded = np.concatenate([noisy[30:0:-1], noisy, noisy[-2:-32:-1]])
    return np.column_stack([q, np.convolve(padded, k, mode="valid")])


FRF_MODES = {
    "xx": [(850.0, 0.03, 2.0), (2300.0, 0.05, 6.0)],
    "yy": [(910.0, 0.035, 2.3), (2450.0, 0.045, 6.5)],
}


def frf_table() -> np.ndarray:
    """Compliance FRF of the tool tip, µm/N, from modal parameters plus noise."""
    f = np.arange(0, 5000 + 1, 2, dtype=np.float64)
    rng = np.random.default_rng(1)
    cols = [f]
    for axis in ("xx", "yy"):
        G = np.zeros(f.size, complex)
        for fn, zeta, k in FRF_MODES[axis]:
            r = f / fn
            G += 1.0 / (k * (1.0 - r ** 2 + 2j * zeta * r))
        noise = (rng.normal(0, 1, f.size) + 1j * rng.normal(0, 1, f.size))
        G = G + noise * (0.002 + 0.005 * np.abs(G))
        cols += [G.real, G.imag]
    return np.column_stack(cols)


# ------------------------------------------------------------------------------------ README
README = """# Sample data

Small, real-shaped inputs for the pipeline (`workflows/mould.yaml`, `workflows/rest_overload.yaml`). Everything here is made by
`python scripts/make_samples.py` (deterministic; `opencamlib` makes the toolpaths) from the
OpenCAMLib reference mesh `ktoolcav.stl`.

## Frame and units

Machine frame, millimetres, tool axis +Z (3-axis). Work zero: the insert's min corner at X0 Y0,
its parting face (the finished top of the insert, around the cavity) at Z0; the insert occupies
X0–101.6, Y0–84.1, Z-41.275–0. NC coordinates are the tool TIP (lowest point of the ball).

## Files

| file | what | frame / units | made by |
|---|---|---|---|
| `models/mould.stl` | nominal (design) model: a real injection-mould cavity insert, {nominal_faces} faces, watertight; 26.7 mm deep pocket with drafted walls, a Ø12.7 mm boss on its floor, a runner channel and a 1.27 mm relief around it | mm, machine frame; bounds {nominal_bounds} | `ktoolcav.stl` (inches) × 25.4, rotated so its cavity face looks up: (X, Y, Z) = 25.4·(x+2, z+1.5, −y) |
| `rest_overload/semi.stl` | semi-finished stock over X{sx0:g}–{sx1:g}, Y{sy0:g}–{sy1:g}: the surface left by a semi-finishing Ø10 ball pass (zig-zag along X, step-over {semi_step} mm) with {stock} mm allowance, closed into a watertight solid down to Z-41.275; {semi_faces} faces | mm, machine frame; bounds {semi_bounds} | exact lower envelope of the swept ball over its OpenCAMLib drop-cutter path (ball R+0.2), sampled on a {grid} mm grid |
| `rest_overload/nc/mould_finish_t1.nc` | O1001, finishing: Ø10 ball T1, parallel zig-zag along X over X{fx0:g}–{fx1:g} Y{fy0:g}–{fy1:g}, step-over {fin_step} mm (cusp {fin_cusp_um:.0f} µm), {fin_rows} rows, {fin_g1} G1 + {fin_arcs} G2/G3 moves, {fin_blocks} N blocks | Fanuc/ISO, mm, G90, tool tip | OpenCAMLib BatchDropCutter (samples every 0.05 mm, steep stretches refined to 3-D steps ≤ 0.05 mm), collinear points removed within 0.002 mm, row links as I J semicircles where the surface allows, else lift/traverse/lower G1 |
| `rest_overload/nc/mould_contour_t1.nc` | O1002, contours with the same tool: pocket walls at Z{wall_levels} (counter-clockwise, climb; vertical G18 lead-in/out arcs with I K), boss at Z{boss_levels} (clockwise circles: I J half circles, R quarter circles); {con_g1} G1 + {con_arcs} G2/G3 moves; `;` comments, a multi-word block | as above | OpenCAMLib Waterline loops, Douglas–Peucker 0.002 mm, boss loops written as circles circumscribing the faceted boss's waterline (the model's Ø12.7 boss is a 46-gon: the arc touches its vertices and stands off its facets by at most {boss_dev:.3f} mm) |
| `tools/t1_profile.csv` | measured contour error of the ball cutter T1: `contact_deg, error_um`, 0–90° in 0.1° steps; positive = tool smaller than nominal (undersize) | deg, µm | synthetic: 0.6 + 2.4 (q/90)² + 0.9 exp(−½((q−55)/6)²) µm + 0.05 µm noise (seed 2), Gaussian low-pass σ = 1° |
| `machine/frf_xy.csv` | tool-tip compliance FRF `freq_hz, xx_re, xx_im, yy_re, yy_im`, 0–5000 Hz in 2 Hz steps | Hz, µm/N | modal sum G = Σ 1/(k(1 − r² + 2iζr)), r = f/fn; x: 850 Hz ζ0.03 k2.0 N/µm + 2300 Hz ζ0.05 k6.0 N/µm; y: 910 Hz ζ0.035 k2.3 N/µm + 2450 Hz ζ0.045 k6.5 N/µm; noise (0.002 + 0.5 %·|G|) µm/N (seed 1) |

The semi-finished stock is at least 0.2 mm from the nominal surface everywhere, exactly 0.2 mm
under each semi-finishing row, 0.2 mm + up to 16 µm of cusp on flat areas, and thicker where a
real semi-finishing pass leaves rest material: concave corners tighter than the ball and walls
parallel to X (the finishing raster runs the same way and also rides over those walls; the
contour program finishes them).

Limits, measured: the stock mesh is a height field sampled every 0.3 mm (size), so the 0.2 mm
round it has over the model's sharp convex edges (pocket rim, boss top, runner edges) is cut by
chords: within ~0.3 mm of those edges the stock is locally thinner than 0.2 mm (the finishing
ball's depth of cut into `rest_overload/semi.stl` at its program points: median 0.199 mm, 5th percentile 0.12 mm,
minimum 0.05 mm). Between its points the finishing path stays within 2.5 µm of the surface
(CAM tolerance 2 µm + 3-decimal rounding); the contour chords across the pocket's inner corners
stand off by up to 25 µm; the boss arcs stand off the 46-gon facets by up to 15 µm.

`tests/test_samples.py` checks the meshes, that every checked
finishing and contour point puts the ball exactly on the nominal surface, and the stock offset.

## Source and licence

`ktoolcav.stl` comes from the OpenCAMLib repository (https://github.com/aewallin/opencamlib,
folder `stl/`), LGPL-2.1; the toolpaths are computed with the `opencamlib` package (LGPL-2.1),
independent CAM code, not ours.
"""


def fmt_bounds(b) -> str:
    return "[" + ", ".join(f"{v:.2f}" for v in np.asarray(b).ravel()) + "]"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--source", default=DEFAULT_SOURCE, help="path of ktoolcav.stl (inches)")
    ap.add_argument("--out", default="data_samples", help="output folder")
    ap.add_argument("--only", choices=("all", "rest_overload"), default="all",
                    help="rest_overload: only the heavy-rest case under OUT/rest_overload/ (and the nominal)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    t0 = time.time()

    check_cl_is_tip()
    nominal = roundtrip_stl(load_nominal(args.source), out / "models" / "mould.stl")
    tris = np.asarray(nominal.triangles, dtype=np.float64)
    surf = ocl_surface(tris)
    print(f"nominal: {len(nominal.faces)} faces, bounds {fmt_bounds(nominal.bounds)}")
    ours = ["models/mould.stl"]

    ro = rest.make(out / "rest_overload", surf, tris, z_bottom=float(nominal.bounds[0, 2]))
    print("rest_overload:", ro)
    ours += ["rest_overload/semi.stl", "rest_overload/nc/mould_finish_t1.nc", "rest_overload/nc/mould_contour_t1.nc"]

    if args.only == "all":
        (out / "tools").mkdir(parents=True, exist_ok=True)
        np.savetxt(out / "tools" / "t1_profile.csv", tool_profile(), fmt=["%.1f", "%.4f"],
                   delimiter=",", header="contact_deg,error_um", comments="")
        (out / "machine").mkdir(parents=True, exist_ok=True)
        np.savetxt(out / "machine" / "frf_xy.csv", frf_table(), fmt=["%.0f"] + ["%.6e"] * 4,
                   delimiter=",", header="freq_hz,xx_re,xx_im,yy_re,yy_im", comments="")
        fin, con = ro["finish"], ro["contour"]
        (out / "README.md").write_text(README.format(
            nominal_faces=len(nominal.faces), nominal_bounds=fmt_bounds(nominal.bounds),
            sx0=rest.STOCK_X[0], sx1=rest.STOCK_X[1], sy0=rest.STOCK_Y[0], sy1=71.1,
            semi_step=rest.SEMI_STEP, stock=rest.STOCK_MM, semi_faces=ro["semi_faces"],
            semi_bounds=fmt_bounds(trimesh_bounds(out / "rest_overload" / "semi.stl")), grid=rest.STOCK_GRID,
            fx0=rest.FIN_X[0], fx1=rest.FIN_X[1], fy0=rest.FIN_Y[0], fy1=rest.FIN_Y[1], fin_step=rest.FIN_STEP,
            fin_cusp_um=1000 * (BALL_R - np.sqrt(BALL_R ** 2 - (rest.FIN_STEP / 2) ** 2)),
            fin_rows=fin["rows"], fin_g1=fin["moves"]["G1"],
            fin_arcs=fin["moves"]["G2"] + fin["moves"]["G3"], fin_blocks=fin["blocks"],
            wall_levels=", ".join(f"{z:g}" for z in rest.WALL_LEVELS),
            boss_levels=", ".join(f"{z:g}" for z in rest.BOSS_LEVELS),
            con_g1=con["moves"]["G1"], con_arcs=con["moves"]["G2"] + con["moves"]["G3"],
            boss_dev=max(b["max_dev_mm"] for b in con["boss_loops"]),
        ))
        ours += ["tools/t1_profile.csv", "machine/frf_xy.csv", "README.md"]
    sizes = {k: (out / k).stat().st_size for k in ours}
    for k, v in sizes.items():
        print(f"  {k:40s} {v / 1e6:8.3f} MB")
    print(f"total {sum(sizes.values()) / 1e6:.2f} MB in {time.time() - t0:.1f} s")
    return 0


def trimesh_bounds(path: Path) -> np.ndarray:
    import trimesh
    return trimesh.load(str(path), force="mesh").bounds


if __name__ == "__main__":
    sys.exit(main())
