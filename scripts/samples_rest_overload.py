"""The heavy-rest sample case (``data_samples/rest_overload/``, workflows/rest_overload.yaml).

A semi-finished stock from a raster along X only, which leaves ~0.6 mm of rest material on the
walls parallel to X, and two finishing programs: a raster along X over everything and waterline
contours at three levels. Kept byte for byte as first made: :func:`make` writes the same files.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from samples_cam import (BALL_D, BALL_R, CAM_TOL, SAMPLE, crop_surface, densify_rows, douglas_peucker,
                         drop_tips, roundtrip_stl, signed_area, waterline_loops)
from samples_nc import SAFE_Z, NCWriter, footer, header


STOCK_MM = 0.2  # semi-finishing allowance = finishing depth


# finishing raster
FIN_X = (14.0, 88.0)


FIN_Y = (33.0, 64.8)


FIN_STEP = 0.6


ARC_TOL = 0.02  # arc fit tolerance: the model's Ø12.7 boss is a 46-gon, chord error 0.015 mm


CLEAR_Z = 2.0


# semi-finishing pass and stock mesh
SEMI_STEP = 0.8


SEMI_SAMPLE = 0.1  # along a semi row; sphere-envelope error between samples 0.1²/(8R) = 0.25 µm


SEMI_Y0 = 15.3  # first semi row (rows cover the stock grid ± the ball radius)

STOCK_X = (12.0, 90.0)


STOCK_Y = (21.0, 71.1)


STOCK_GRID = 0.3


# contour program
WALL_LEVELS = (-8.0, -14.0, -20.0)


BOSS_LEVELS = (-26.3, -25.9)


BOSS_CENTRE = (63.5, 38.1)  # nominal boss axis (source: x=0.5 in, z=0 in)


LEAD_R = 2.0


# -------------------------------------------------------------------------------- semi stock
def semi_surface(surf) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Height of the surface left by the semi-finishing ball pass on the stock grid.

    The semi-finishing ball (radius R) leaves ``STOCK_MM``: its path is the drop-cutter path of
    a ball of radius R + STOCK_MM (same centre), so the ball itself stays STOCK_MM off the
    nominal along the contact normal. The surface left is the lower envelope of the ball's
    sphere over all sampled centres: S(x, y) = min_k c_z,k − sqrt(R² − |p − c_k|²).

    Returns
    -------
    gx, gy : grid coordinates; S : (ny, nx) heights; rows_y : y of the semi rows.
    """
    R = BALL_R
    xs = np.round(np.arange(STOCK_X[0] - R - SEMI_SAMPLE * 2, STOCK_X[1] + R + SEMI_SAMPLE * 2 + 1e-9,
                            SEMI_SAMPLE), 6)
    rows_y = np.round(np.arange(SEMI_Y0, STOCK_Y[1] + R + SEMI_STEP, SEMI_STEP), 6)
    X, Y = np.meshgrid(xs, rows_y)
    tip = drop_tips(surf, 2 * (R + STOCK_MM), np.column_stack([X.ravel(), Y.ravel()]))
    centre_z = tip.reshape(X.shape) + R + STOCK_MM

    nx = int(round((STOCK_X[1] - STOCK_X[0]) / STOCK_GRID)) + 1
    ny = int(round((STOCK_Y[1] - STOCK_Y[0]) / STOCK_GRID)) + 1
    gx = np.round(STOCK_X[0] + STOCK_GRID * np.arange(nx), 6)
    gy = np.round(STOCK_Y[0] + STOCK_GRID * np.arange(ny), 6)
    col = np.rint((gx - xs[0]) / SEMI_SAMPLE).astype(int)  # grid x is on the sample lattice
    assert np.allclose(xs[col], gx)
    M = int(np.floor(R / SEMI_SAMPLE))
    du = SEMI_SAMPLE * np.arange(-M, M + 1)
    S = np.full((ny, nx), np.inf)
    for j, yj in enumerate(rows_y):
        sel = np.flatnonzero(np.abs(gy - yj) < R)
        if sel.size == 0:
            continue
        r2 = R * R - (gy[sel] - yj) ** 2  # squared radius of the ball's section at each grid y
        best = np.full((sel.size, nx), np.inf)
        for m, u in zip(range(-M, M + 1), du):
            h2 = r2 - u * u
            ok = h2 >= 0
            if not ok.any():
                continue
            cand = centre_z[j, col + m][None, :] - np.sqrt(np.where(ok, h2, 0.0))[:, None]
            cand[~ok] = np.inf
            np.minimum(best, cand, out=best)
        S[sel] = np.minimum(S[sel], best)
    # steep stretches of the semi path (the ball pivoting over edges): extra centres so that
    # consecutive ball positions are at most SEMI_SAMPLE apart in 3-D, swept here one by one
    rows_x, rows_z = densify_rows(surf, 2 * (R + STOCK_MM), rows_y, [xs] * len(rows_y),
                                  list(centre_z - R - STOCK_MM), SEMI_SAMPLE)
    GX, GY = np.meshgrid(gx, gy)
    for yj, x, z in zip(rows_y, rows_x, rows_z):
        extra = ~np.isin(np.round(x, 6), xs)
        for xc, zc in zip(x[extra], z[extra] + R + STOCK_MM):
            i0, i1 = np.searchsorted(gx, [xc - R, xc + R])
            j0, j1 = np.searchsorted(gy, [yj - R, yj + R])
            if i1 <= i0 or j1 <= j0:
                continue
            h2 = R * R - (GX[j0:j1, i0:i1] - xc) ** 2 - (GY[j0:j1, i0:i1] - yj) ** 2
            cand = np.where(h2 >= 0, zc - np.sqrt(np.clip(h2, 0, None)), np.inf)
            np.minimum(S[j0:j1, i0:i1], cand, out=S[j0:j1, i0:i1])
    if not np.isfinite(S).all():
        raise RuntimeError("semi-finishing rows do not cover the stock grid")
    return gx, gy, S, rows_y


def heightfield_solid(gx, gy, S, z_bottom: float) -> trimesh.Trimesh:
    """Watertight solid: top = height field S on the grid, vertical sides, flat bottom."""
    ny, nx = S.shape
    GX, GY = np.meshgrid(gx, gy)
    top = np.column_stack([GX.ravel(), GY.ravel(), S.ravel()])
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    faces = [np.column_stack([a.ravel(), b.ravel(), c.ravel()]),
             np.column_stack([a.ravel(), c.ravel(), d.ravel()])]  # counter-clockwise from above
    # boundary loop of the top, counter-clockwise seen from above
    ring = np.concatenate([idx[0, :], idx[1:, -1], idx[-1, -2::-1], idx[-2:0:-1, 0]])
    nb = ring.size
    bottom = top[ring].copy()
    bottom[:, 2] = z_bottom
    base = nx * ny
    centre = base + nb
    verts = np.vstack([top, bottom, [[gx.mean(), gy.mean(), z_bottom]]])
    k = np.arange(nb)
    k1 = (k + 1) % nb
    # sides: outward normals for a CCW ring
    faces.append(np.column_stack([ring[k], base + k, base + k1]))
    faces.append(np.column_stack([ring[k], base + k1, ring[k1]]))
    # bottom fan, normals down
    faces.append(np.column_stack([np.full(nb, centre), base + k1, base + k]))
    mesh = trimesh.Trimesh(verts, np.vstack(faces), process=False)
    if not (mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0):
        raise RuntimeError("stock mesh is not a valid closed solid")
    return mesh


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


# ------------------------------------------------------------------------------------- files
def make(out: Path, surf, tris: np.ndarray, z_bottom: float) -> dict:
    """Write ``semi.stl`` and ``nc/mould_finish_t1.nc``, ``nc/mould_contour_t1.nc`` under ``out``.

    Parameters
    ----------
    out : the case's folder (``data_samples/rest_overload``).
    surf : OpenCAMLib surface of the nominal model; tris : its (n, 3, 3) triangles, mm.
    z_bottom : the part's bottom, where the stock solid is closed, mm.

    Returns
    -------
    info : what each file holds (faces, rows, moves), for the console.
    """
    gx, gy, S, rows_y = semi_surface(surf)
    stock = roundtrip_stl(heightfield_solid(gx, gy, S, z_bottom=z_bottom), out / "semi.stl")
    fin_text, fin = finishing_program(surf)
    (out / "nc").mkdir(parents=True, exist_ok=True)
    (out / "nc" / "mould_finish_t1.nc").write_text(fin_text)
    con_text, con = contour_program(surf, tris)
    (out / "nc" / "mould_contour_t1.nc").write_text(con_text)
    return {"semi_faces": len(stock.faces), "semi_rows": len(rows_y), "finish": fin, "contour": con}
