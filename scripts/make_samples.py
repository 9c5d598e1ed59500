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
``models/semi.stl``
    Semi-finished stock over the machined region X12–90, Y21–71: the surface left by a
    semi-finishing ball pass (Ø10 ball, zig-zag along X, step-over 0.8 mm, 0.2 mm stock
    allowance = the finishing depth), computed exactly as the lower envelope of the ball
    swept along its OpenCAMLib drop-cutter path, sampled on a 0.3 mm grid and closed into a
    watertight solid (bottom at the part's bottom, Z-41.275). Everywhere at least 0.2 mm from
    the nominal surface; exactly 0.2 mm under each semi-finishing row; cusps of
    0.8² / (8·5) = 16 µm on flat areas; more in concave corners the ball cannot reach and on
    walls parallel to X (rest material a real semi-finishing pass leaves). Limit: sampled at
    0.3 mm, the 0.2 mm rounds over sharp convex edges are cut by chords (locally thinner).
``nc/mould_finish_t1.nc``
    Finishing program O1001: Ø10 ball end mill T1 dropped by OpenCAMLib's BatchDropCutter on
    the nominal model, parallel zig-zag along X over X14–88, Y33–64.8, step-over 0.6 mm
    (cusp 9 µm), samples every 0.05 mm along a row (steep stretches refined to 3-D steps
    ≤ 0.05 mm), collinear points removed within 0.002 mm (Douglas–Peucker), row links as
    G2/G3 semicircles (I J) or, where the surface differs, as lift/traverse/lower G1 moves. Coordinates are the tool TIP (OpenCAMLib's CL point is the tip: checked here on a
    flat and a tilted facet before anything is written).
``nc/mould_contour_t1.nc``
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

from samples_cam import (  # noqa: E402 (scripts/ is on sys.path when run as a script)
    ARC_TOL, BALL_D, BALL_R, BOSS_CENTRE, BOSS_LEVELS, CAM_TOL, CLEAR_Z, DEFAULT_SOURCE, FIN_STEP, FIN_X,
    FIN_Y, LEAD_R, NCWriter, SAFE_Z, SAMPLE, SEMI_STEP, STOCK_GRID, STOCK_MM, STOCK_X, STOCK_Y, WALL_LEVELS,
    check_cl_is_tip, crop_surface, densify_rows, douglas_peucker, drop_tips, footer, header,
    heightfield_solid, load_nominal, ocl_surface, roundtrip_stl, semi_surface, signed_area, waterline_loops)


# ---------------------------------------------------------------------------- finishing program
def finishing_program(surf) -> tuple[str, dict]:
    """Parallel zig-zag finishing along X with a ball cutter dropped on the nominal."""
    xs = np.round(np.arange(FIN_X[0], FIN_X[1] + 1e-9, SAMPLE), 6)
    ys = np.round(np.arange(FIN_Y[0], FIN_Y[1] + 1e-9, FIN_STEP), 6)
    X, Y = np.meshgrid(xs, ys)
    Z = drop_tips(surf, BALL_D, np.column_stack([X.ravel(), Y.ravel()])).reshape(X.shape)

    rows_x, rows_z = densify_rows(surf, BALL_D, ys, [xs] * len(ys), list(Z), SAMPLE)
    rows = []
    for r, (y, x, z) in enumerate(zip(ys, rows_x, rows_z)):
        keep = douglas_peucker(np.column_stack([x, z]), CAM_TOL)
        pts = np.column_stack([x[keep], np.full(keep.size, y), z[keep]])
        rows.append(pts if r % 2 == 0 else pts[::-1])

    w = NCWriter(n_step=2)
    header(w, 1001, "MOULD FINISH T1", [
        "PARALLEL FINISHING ZIGZAG ALONG X - MOULD INSERT KTOOLCAV",
        "CAM OPENCAMLIB BATCHDROPCUTTER - SAMPLING 0.05 - TOLERANCE 0.002",
        "MODEL MOULD.STL MM - WORK ZERO X0 Y0 PART MIN CORNER - Z0 PARTING FACE",
        f"T1 BALL D{BALL_D:.3f} R{BALL_R:.3f} - COORDINATES = TOOL TIP",
        f"AREA X{FIN_X[0]:.3f}-{FIN_X[1]:.3f} Y{FIN_Y[0]:.3f}-{FIN_Y[1]:.3f} "
        f"STEPOVER {FIN_STEP:.3f} ROWS {len(rows)} - STOCK TO LEAVE 0.000",
    ])
    first = rows[0][0]
    w.move("G0", x=first[0], y=first[1])
    w.move("G0", z=SAFE_Z)
    w.move("G0", z=first[2] + CLEAR_Z)
    w.move("G1", z=first[2], feed=1000)
    # row links: test every candidate link against the model in one drop-cutter batch
    ends = np.array([(rows[r][-1], rows[r + 1][0]) for r in range(len(rows) - 1)])  # (n, 2, 3)
    t = np.linspace(-np.pi / 2, np.pi / 2, 13)
    side = np.where(ends[:, 0, 0] > (FIN_X[0] + FIN_X[1]) / 2, 1.0, -1.0)
    cy = (ends[:, 0, 1] + ends[:, 1, 1]) / 2
    rad = np.abs(ends[:, 1, 1] - ends[:, 0, 1]) / 2
    arc_xy = np.stack([ends[:, 0, 0, None] + side[:, None] * rad[:, None] * np.cos(t),
                       cy[:, None] + rad[:, None] * np.sin(t)], -1)
    line_xy = np.stack([np.repeat(ends[:, 0, 0, None], t.size, 1),
                        ends[:, 0, 1, None] + (ends[:, 1, 1] - ends[:, 0, 1])[:, None]
                        * np.linspace(0, 1, t.size)], -1)
    z_link = drop_tips(surf, BALL_D, np.vstack([arc_xy.reshape(-1, 2), line_xy.reshape(-1, 2)]))
    z_arc, z_line = z_link.reshape(2, len(ends), t.size)
    n_arc_links = n_line_links = 0
    for r, pts in enumerate(rows):
        for p in pts[1:]:
            w.move("G1", x=p[0], y=p[1], z=p[2], feed=3000)
        if r + 1 == len(rows):
            break
        a, b = ends[r]
        if abs(a[2] - b[2]) < 5e-4 and z_arc[r].max() <= a[2] + 1e-4:
            # semicircle in XY through the row end, bulging outward, tangent to both rows
            w.arc("G3" if side[r] > 0 else "G2", b[0], b[1], i=0.0, j=cy[r] - a[1], feed=3000)
            n_arc_links += 1
        else:
            # lift to the highest CL on the link line, traverse, lower (gouge-free link)
            z_top = max(z_line[r].max(), a[2], b[2])
            w.move("G1", z=z_top, feed=3000)
            w.move("G1", y=b[1])
            w.move("G1", z=b[2])
            n_line_links += 1
    footer(w)
    info = {
        "rows": len(rows), "cut_points": int(sum(len(p) for p in rows)),
        "arc_links": n_arc_links, "line_links": n_line_links, "moves": dict(w.moves),
        "blocks": w.n // w.n_step, "tip_z_range": (float(Z.min()), float(Z.max())),
    }
    return w.text(), info


def contour_program(surf, tris: np.ndarray) -> tuple[str, dict]:
    """Waterline contours of the pocket walls and of the boss, with arcs."""
    w = NCWriter(n_step=10)
    header(w, 1002, "MOULD CONTOUR T1", [
        "WATERLINE CONTOURS - POCKET WALLS AND BOSS - CLIMB",
        "CAM OPENCAMLIB WATERLINE - SAMPLING 0.1 - TOLERANCE 0.002 - ARC FIT 0.02",
        f"T1 BALL D{BALL_D:.3f} R{BALL_R:.3f} - COORDINATES = TOOL TIP",
    ])
    w.block("M8")
    info = {"wall_loops": [], "boss_loops": []}
    cx0, cy0 = BOSS_CENTRE
    pocket_surf = crop_surface(tris, (15.0, 15.0, 87.0, 70.0))
    approach = []  # non-cutting tool positions, checked against the full model below
    boss_surf = crop_surface(tris, (cx0 - 16, cy0 - 16, cx0 + 16, cy0 + 16))
    first = True
    # ---- pocket walls: counter-clockwise (climb inside a pocket with M3)
    for z in WALL_LEVELS:
        loops = waterline_loops(pocket_surf, z)
        # the pocket loop: encloses the boss centre, inside the relief
        cand = [L for L in loops
                if L[:, 0].min() < cx0 < L[:, 0].max() and L[:, 1].min() < cy0 < L[:, 1].max()
                and L[:, 0].min() > 20 and L[:, 0].max() < 82 and L[:, 1].min() > 24]
        L = max(cand, key=lambda a: abs(signed_area(a[:, :2])))
        P = L[:, :2]
        if signed_area(P) < 0:
            P = P[::-1]
        # start on the bottom wall (direction +X) near x = 45
        bottom = np.flatnonzero(P[:, 1] < P[:, 1].min() + 0.01)
        s = bottom[np.argmin(np.abs(P[bottom, 0] - 45.0))]
        P = np.roll(P, -s, axis=0)
        P = np.vstack([P, P[:1]])
        keep = douglas_peucker(P, CAM_TOL)
        Q = P[keep]
        # overlap 1 mm along the bottom wall before leaving
        x_end = Q[0, 0] + 1.0
        xs, ys = Q[0]
        w.raw(f"; WALL LEVEL Z{w.num(z)}  {len(Q) - 1} MOVES")
        w.move("G0", x=xs - LEAD_R, y=ys)
        if first:
            w.move("G0", z=SAFE_Z)
            first = False
        w.move("G0", z=z + LEAD_R + CLEAR_Z)
        ang = np.linspace(0, np.pi / 2, 7)
        approach += [(xs - LEAD_R, ys, z + LEAD_R + CLEAR_Z)]
        approach += [(xs - LEAD_R + LEAD_R * np.sin(t), ys, z + LEAD_R * np.cos(t)) for t in ang]
        approach += [(x_end + LEAD_R * np.sin(t), ys, z + LEAD_R - LEAD_R * np.cos(t))
                     for t in ang]
        w.move("G1", z=z + LEAD_R, feed=1000)
        # vertical lead-in arc in the ZX plane, tangent to the +X start direction
        w.arc("G3", xs, None, z, i=0.0, k=-LEAD_R, feed=3000, plane="G18")
        w.block("G17")
        w.motion = None
        for x, y in Q[1:]:
            w.move("G1", x=x, y=y)
        w.move("G1", x=x_end)
        w.arc("G2", x_end + LEAD_R, None, z + LEAD_R, i=0.0, k=LEAD_R, plane="G18")
        w.block("G17")
        w.motion = None
        w.move("G0", z=SAFE_Z)
        info["wall_loops"].append({"z": z, "points": int(len(P)), "moves": int(len(Q) - 1)})
    # ---- boss: clockwise (climb outside a boss with M3), circle fitted to the waterline
    for lvl, z in enumerate(BOSS_LEVELS):
        loops = waterline_loops(boss_surf, z)
        L = min(loops, key=lambda a: np.hypot(a[:, 0].mean() - cx0, a[:, 1].mean() - cy0))
        P = L[:, :2]
        # least-squares circle (Kasa): x² + y² = 2ax + 2by + c
        A = np.column_stack([2 * P[:, 0], 2 * P[:, 1], np.ones(len(P))])
        a, b, c = np.linalg.lstsq(A, (P ** 2).sum(1), rcond=None)[0]
        dist = np.hypot(P[:, 0] - a, P[:, 1] - b)
        # the model's boss is a polygon: take the circumscribed circle (touches the facet
        # vertices, never gouges) and accept it within the arc-fit tolerance
        rad = float(dist.max())
        dev = float(rad - dist.min())
        if dev > ARC_TOL:
            raise RuntimeError(f"boss waterline at z={z} is not a circle (dev {dev:.4f} mm)")
        w.raw(f"; BOSS LEVEL Z{w.num(z)}  CIRCLE R{rad:.3f} ABOUT X{a:.3f} Y{b:.3f}")
        # start at the -Y point, plunge in the air beside the boss
        xs, ys = a, b - rad
        w.move("G0", x=xs, y=ys)
        w.move("G0", z=z + CLEAR_Z)
        w.move("G1", z=z, feed=1000)
        if lvl == 0:
            # two half circles, I J form
            w.arc("G2", a, b + rad, i=0.0, j=rad, feed=3000)
            w.arc("G2", a, b - rad, i=0.0, j=-rad)
            n_arcs = 2
        else:
            # four quarter circles, R form (clockwise from -Y: -X, +Y, +X, -Y)
            for px, py in ((a - rad, b), (a, b + rad), (a + rad, b), (a, b - rad)):
                w.arc("G2", px, py, r=rad, feed=3000)
            n_arcs = 4
        w.motion = None
        if lvl + 1 < len(BOSS_LEVELS):
            w.move("G0", z=SAFE_Z)
        else:
            w.block(f"G0 G90 Z{w.num(SAFE_Z)} M9")  # a block with several words
            w.pos["Z"] = w.num(SAFE_Z)
            w.motion = "G0"
            w.moves["G0"] += 1
        approach.append((xs, ys, z + CLEAR_Z))
        info["boss_loops"].append({"z": z, "radius": rad, "centre": (float(a), float(b)),
                                   "max_dev_mm": dev, "arcs": n_arcs})
    # gouge check of the approach, plunge and lead moves (drop-cutter CL must be below the tool)
    A = np.array(approach)
    cl = drop_tips(surf, BALL_D, A[:, :2])
    if (cl > A[:, 2] + 1e-3).any():
        raise RuntimeError(f"contour approach gouges: {A[cl > A[:, 2] + 1e-3]}")
    footer(w)
    info["moves"] = dict(w.moves)
    info["blocks"] = w.n // w.n_step
    return w.text(), info


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

Small, real-shaped inputs for the pipeline (`workflows/mould.yaml`). Everything here is made by
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
| `models/semi.stl` | semi-finished stock over X{sx0:g}–{sx1:g}, Y{sy0:g}–{sy1:g}: the surface left by a semi-finishing Ø10 ball pass (zig-zag along X, step-over {semi_step} mm) with {stock} mm allowance, closed into a watertight solid down to Z-41.275; {semi_faces} faces | mm, machine frame; bounds {semi_bounds} | exact lower envelope of the swept ball over its OpenCAMLib drop-cutter path (ball R+0.2), sampled on a {grid} mm grid |
| `nc/mould_finish_t1.nc` | O1001, finishing: Ø10 ball T1, parallel zig-zag along X over X{fx0:g}–{fx1:g} Y{fy0:g}–{fy1:g}, step-over {fin_step} mm (cusp {fin_cusp_um:.0f} µm), {fin_rows} rows, {fin_g1} G1 + {fin_arcs} G2/G3 moves, {fin_blocks} N blocks | Fanuc/ISO, mm, G90, tool tip | OpenCAMLib BatchDropCutter (samples every 0.05 mm, steep stretches refined to 3-D steps ≤ 0.05 mm), collinear points removed within 0.002 mm, row links as I J semicircles where the surface allows, else lift/traverse/lower G1 |
| `nc/mould_contour_t1.nc` | O1002, contours with the same tool: pocket walls at Z{wall_levels} (counter-clockwise, climb; vertical G18 lead-in/out arcs with I K), boss at Z{boss_levels} (clockwise circles: I J half circles, R quarter circles); {con_g1} G1 + {con_arcs} G2/G3 moves; `;` comments, a multi-word block | as above | OpenCAMLib Waterline loops, Douglas–Peucker 0.002 mm, boss loops written as circles circumscribing the faceted boss's waterline (the model's Ø12.7 boss is a 46-gon: the arc touches its vertices and stands off its facets by at most {boss_dev:.3f} mm) |
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
ball's depth of cut into `semi.stl` at its program points: median 0.199 mm, 5th percentile 0.12 mm,
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
    args = ap.parse_args(argv)
    out = Path(args.out)
    t0 = time.time()

    check_cl_is_tip()
    nominal = roundtrip_stl(load_nominal(args.source), out / "models" / "mould.stl")
    tris = np.asarray(nominal.triangles, dtype=np.float64)
    surf = ocl_surface(tris)
    print(f"nominal: {len(nominal.faces)} faces, bounds {fmt_bounds(nominal.bounds)}")

    gx, gy, S, rows_y = semi_surface(surf)
    stock = heightfield_solid(gx, gy, S, z_bottom=float(nominal.bounds[0, 2]))
    stock = roundtrip_stl(stock, out / "models" / "semi.stl")
    print(f"semi: {len(stock.faces)} faces, bounds {fmt_bounds(stock.bounds)}, "
          f"{len(rows_y)} semi rows")

    fin_text, fin = finishing_program(surf)
    (out / "nc").mkdir(parents=True, exist_ok=True)
    (out / "nc" / "mould_finish_t1.nc").write_text(fin_text)
    print("finish:", fin)

    con_text, con = contour_program(surf, tris)
    (out / "nc" / "mould_contour_t1.nc").write_text(con_text)
    print("contour:", con)

    (out / "tools").mkdir(parents=True, exist_ok=True)
    np.savetxt(out / "tools" / "t1_profile.csv", tool_profile(), fmt=["%.1f", "%.4f"],
               delimiter=",", header="contact_deg,error_um", comments="")
    (out / "machine").mkdir(parents=True, exist_ok=True)
    np.savetxt(out / "machine" / "frf_xy.csv", frf_table(), fmt=["%.0f"] + ["%.6e"] * 4,
               delimiter=",", header="freq_hz,xx_re,xx_im,yy_re,yy_im", comments="")

    (out / "README.md").write_text(README.format(
        nominal_faces=len(nominal.faces), nominal_bounds=fmt_bounds(nominal.bounds),
        sx0=STOCK_X[0], sx1=STOCK_X[1], sy0=STOCK_Y[0], sy1=float(gy[-1]),
        semi_step=SEMI_STEP, stock=STOCK_MM, semi_faces=len(stock.faces),
        semi_bounds=fmt_bounds(stock.bounds), grid=STOCK_GRID,
        fx0=FIN_X[0], fx1=FIN_X[1], fy0=FIN_Y[0], fy1=FIN_Y[1], fin_step=FIN_STEP,
        fin_cusp_um=1000 * (BALL_R - np.sqrt(BALL_R ** 2 - (FIN_STEP / 2) ** 2)),
        fin_rows=fin["rows"], fin_g1=fin["moves"]["G1"],
        fin_arcs=fin["moves"]["G2"] + fin["moves"]["G3"], fin_blocks=fin["blocks"],
        wall_levels=", ".join(f"{z:g}" for z in WALL_LEVELS),
        boss_levels=", ".join(f"{z:g}" for z in BOSS_LEVELS),
        con_g1=con["moves"]["G1"], con_arcs=con["moves"]["G2"] + con["moves"]["G3"],
        boss_dev=max(b["max_dev_mm"] for b in con["boss_loops"]),
    ))
    ours = ["models/mould.stl", "models/semi.stl", "nc/mould_finish_t1.nc",
            "nc/mould_contour_t1.nc", "tools/t1_profile.csv", "machine/frf_xy.csv", "README.md"]
    sizes = {k: (out / k).stat().st_size for k in ours}
    for k, v in sizes.items():
        print(f"  {k:28s} {v / 1e6:8.3f} MB")
    print(f"total {sum(sizes.values()) / 1e6:.2f} MB in {time.time() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
