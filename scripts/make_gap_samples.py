"""Make the small sample job of the gap diagnosis (``workflows/gap.yaml``), deterministic.

A ball-nose finishing raster (Ø6, 2 flutes) over a smooth 3-D surface
``z = 2.4·sin(x/2)·cos(y/3) − 2.5`` on X0–8, Y0–6: rows along X at 0.4 mm step-over joined by
short cutting moves along Y on the part (90° corners), tool-tip coordinates computed exactly from
the surface (centre = p + R·n, tip = centre − R·z). The stock is the same surface 0.15 mm higher
(a height-field STL, closed down to Z-10). ``plan.csv`` is a CMM measurement plan: the contact
points of the ball at 0.3, 0.5, 0.7 of every cutting chord, with their normals.

``--part floors`` writes ``data_samples/gap_floors/`` (``workflows/gap_floors.yaml``): the same
raster over X0–10, Y0–5 of a part that is mostly floor, a lower floor Z-2.5 (X < 3) and an upper
one Z-1.9 (X > 7) joined by a cosine ramp (slope ≤ 13°, concave radius ≥ 5.4 mm > the ball's 3 mm):
the plan's normals are within 5° of +z on ~70 % of its points, and have no Y part anywhere.

    python scripts/make_gap_samples.py [--part floors]      # writes data_samples/gap/ (gap_floors/)
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

R = 3.0
PART = "gap"
OUT = Path(__file__).resolve().parent.parent / "data_samples" / "gap"
X0, X1, Y0, Y1, DX, STEP = 0.0, 8.0, 0.0, 6.0, 0.4, 0.4


RAMP = (3.0, 7.0, 0.6)          # the floors part: ramp from X3 to X7, 0.6 mm high


def surface(x, y):
    if PART == "floors":
        x0, x1, h = RAMP
        u = np.clip((x - x0) / (x1 - x0), 0.0, 1.0)
        return -2.5 + h * 0.5 * (1.0 - np.cos(np.pi * u)) + 0.0 * y
    return 2.4 * np.sin(x / 2.0) * np.cos(y / 3.0) - 2.5


def normal(x, y):
    if PART == "floors":
        x0, x1, h = RAMP
        u = (x - x0) / (x1 - x0)
        fx = np.where((u > 0) & (u < 1), h * 0.5 * np.pi / (x1 - x0) * np.sin(np.pi * np.clip(u, 0, 1)), 0.0)
        fy = np.zeros_like(fx)
    else:
        fx = 2.4 / 2.0 * np.cos(x / 2.0) * np.cos(y / 3.0)
        fy = -2.4 / 3.0 * np.sin(x / 2.0) * np.sin(y / 3.0)
    n = np.stack([-fx, -fy, np.ones_like(fx)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def contact_points():
    """Rows of surface points (zig-zag order) whose ball centres make the path."""
    rows = []
    ys = np.arange(Y0, Y1 + 1e-9, STEP)
    xs = np.arange(X0, X1 + 1e-9, DX)
    for k, y in enumerate(ys):
        x = xs if k % 2 == 0 else xs[::-1]
        rows.append(np.stack([x, np.full_like(x, y), surface(x, y)], axis=1))
    return rows


def program_text(rows) -> str:
    title = "O3002 (GAP FLOORS RASTER D6 BALL)" if PART == "floors" else "O3001 (GAP SAMPLE RASTER D6 BALL)"
    lines = ["%", title, "G90 G17 G21", "T1 M6", "S8000 M3"]
    pts = []
    for k, row in enumerate(rows):
        n = normal(row[:, 0], row[:, 1])
        tip = row + R * n - [0.0, 0.0, R]
        pts.append(tip)
    first = pts[0][0]
    lead = first[0] - 6.0                                   # lead in along X from outside the stock
    lines += [f"G0 X{lead:.4f} Y{first[1]:.4f} Z{first[2] + 5:.4f}", f"G1 Z{first[2]:.4f} F400"]
    feed = " F800"
    for row in pts:
        for p in row:
            lines.append(f"G1 X{p[0]:.4f} Y{p[1]:.4f} Z{p[2]:.4f}{feed}")
            feed = ""
    lines += ["G0 Z10.", "M5", "M30", "%"]
    return "\n".join(lines) + "\n"


def plan_rows(rows, fractions=(0.3, 0.5, 0.7)):
    """Contact points of the ball at fractions of every cutting chord (rows and row changes).

    Vertices are left out: where the path turns, the chords' balls overlap the next chord's and a
    convex path is cut a few µm deeper there (chordal error of the CL points, not a machine effect).
    The plan point is where the chord's swept ball touches the part: p = c − R·n with n the surface
    normal at p (fixed-point iteration on the analytic surface) made square to the chord: the nominal
    is the CAM path's envelope (its chordal deviation from the CAD surface is the CAM's tolerance).
    """
    pts = np.vstack(rows)
    n = normal(pts[:, 0], pts[:, 1])
    c = pts + R * n
    out = []
    for u in fractions:
        cm = c[:-1] + u * (c[1:] - c[:-1])
        nm = (1 - u) * n[:-1] + u * n[1:]
        nm /= np.linalg.norm(nm, axis=1, keepdims=True)
        for _ in range(4):
            pm = cm - R * nm
            nm = normal(pm[:, 0], pm[:, 1])
        # the chord's envelope (a cylinder around it) touches where the normal is square to the chord
        tdir = (c[1:] - c[:-1]) / np.linalg.norm(c[1:] - c[:-1], axis=1, keepdims=True)
        nm = nm - np.sum(nm * tdir, axis=1, keepdims=True) * tdir
        nm /= np.linalg.norm(nm, axis=1, keepdims=True)
        out.append(np.hstack([cm - R * nm, nm]))
    # path order: chord by chord, fractions inside each chord
    plan = np.stack(out, axis=1).reshape(-1, 6)
    # keep the points the nominal path's envelope really touches: where the path turns sharply
    # (convex top, coarse CL points) a neighbouring chord's ball passes deeper than this one
    cen = plan[:, :3] + R * plan[:, 3:]
    a, ab = c[:-1], c[1:] - c[:-1]
    u = np.clip(np.einsum("pkj,kj->pk", cen[:, None, :] - a[None], ab) / np.sum(ab * ab, 1), 0, 1)
    d = np.linalg.norm(a[None] + u[..., None] * ab[None] - plan[:, None, :3], axis=2).min(axis=1)
    return plan[d > R - 1e-4]


def stock_stl(path: Path, allowance: float = 0.15, h: float = 0.2) -> None:
    import trimesh
    xs = np.arange(X0 - 2.0, X1 + 2.0 + 1e-9, h)
    ys = np.arange(Y0 - 2.0, Y1 + 2.0 + 1e-9, h)
    gx, gy = np.meshgrid(xs, ys, indexing="xy")
    top = surface(gx, gy) + allowance
    ny, nx = top.shape
    bottom = -10.0
    v_top = np.stack([gx, gy, top], -1).reshape(-1, 3)
    v_bot = np.stack([gx, gy, np.full_like(top, bottom)], -1).reshape(-1, 3)
    verts = np.vstack([v_top, v_bot])
    off = len(v_top)
    idx = np.arange(ny * nx).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = [np.stack([a, b, d], 1), np.stack([a, d, c], 1),                 # top (normal up)
             np.stack([a, d, b], 1) + off, np.stack([a, c, d], 1) + off]     # bottom (normal down)
    for edge in (idx[0, :], idx[:, -1], idx[-1, ::-1], idx[::-1, 0]):      # walls, boundary loop order
        e0, e1 = edge[:-1], edge[1:]
        faces += [np.stack([e0, e1 + off, e1], 1), np.stack([e0, e0 + off, e1 + off], 1)]
    m = trimesh.Trimesh(verts, np.vstack(faces), process=True)
    m.fix_normals()
    m.export(path)


def main():
    global PART, OUT, X1, Y1
    import argparse
    ap = argparse.ArgumentParser()
    ap.add_argument("--part", choices=("gap", "floors"), default="gap")
    PART = ap.parse_args().part
    if PART == "floors":
        OUT, X1, Y1 = OUT.parent / "gap_floors", 10.0, 5.0
    OUT.mkdir(parents=True, exist_ok=True)
    rows = contact_points()
    (OUT / "gap_t1.nc").write_text(program_text(rows))
    plan = plan_rows(rows)
    hdr = "point_id,x_mm,y_mm,z_mm,nx,ny,nz"
    body = "\n".join(f"{i},{p[0]:.5f},{p[1]:.5f},{p[2]:.5f},{p[3]:.6f},{p[4]:.6f},{p[5]:.6f}" for i, p in enumerate(plan))
    (OUT / "plan.csv").write_text(hdr + "\n" + body + "\n")
    stock_stl(OUT / "stock.stl")
    print(f"{sum(len(r) for r in rows)} path points, {len(plan)} plan points -> {OUT}")


if __name__ == "__main__":
    main()
