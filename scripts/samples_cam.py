"""CAM helpers of scripts/make_samples.py: the model in the machine frame and OpenCAMLib's drop-cutter and
waterline paths (OpenCAMLib computes the paths, not our code), polyline simplification.
"""
from __future__ import annotations

import contextlib
import os
import sys
from pathlib import Path

import numpy as np
import trimesh


INCH_MM = 25.4


DEFAULT_SOURCE = "/work/shared/reference/models/ktoolcav.stl"


# finishing tool T1 (also the semi-finishing tool)
BALL_D = 10.0


BALL_R = BALL_D / 2.0


FLUTE_LEN = 40.0


SAMPLE = 0.05   # drop-cutter sampling along a row, mm


CAM_TOL = 0.002  # CAM tolerance: collinear points removed within this, mm


# ----------------------------------------------------------------------------------- geometry
def load_nominal(source: str | Path) -> trimesh.Trimesh:
    """Load the K-tool cavity (inches) and place it in the machine frame (mm).

    Parameters
    ----------
    source : path of ``ktoolcav.stl`` (OpenCAMLib ``stl/`` folder).

    Returns
    -------
    mesh : the insert, cavity face up (+Z), min corner at X0 Y0, parting face at Z0.
    """
    src = trimesh.load(str(source), force="mesh")
    v = np.asarray(src.vertices, dtype=np.float64)
    # rotation about X by -90 deg (det +1, no mirror): (x, y, z) -> (x, z, -y)
    placed = np.column_stack([v[:, 0], v[:, 2], -v[:, 1]]) * INCH_MM
    placed -= [placed[:, 0].min(), placed[:, 1].min(), placed[:, 2].max()]
    mesh = trimesh.Trimesh(placed, np.asarray(src.faces), process=True)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def roundtrip_stl(mesh: trimesh.Trimesh, path: Path) -> trimesh.Trimesh:
    """Write ``mesh`` as binary STL and load it back (float32 vertices, as users will see it)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    mesh.export(str(path))
    return trimesh.load(str(path), force="mesh")


@contextlib.contextmanager
def quiet_fds():
    """Silence C++ chatter (OpenCAMLib's waterline prints to stdout/stderr)."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, 1)
        os.dup2(null, 2)
        yield
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in saved + [null]:
            os.close(fd)


def ocl_surface(triangles: np.ndarray):
    """OpenCAMLib STLSurf from an (n, 3, 3) array of triangles."""
    from opencamlib import ocl

    surf = ocl.STLSurf()
    for t in np.asarray(triangles, dtype=np.float64):
        surf.addTriangle(ocl.Triangle(*(ocl.Point(*map(float, p)) for p in t)))
    return surf


def drop_tips(surf, diameter: float, xy: np.ndarray, zmin: float = -100.0) -> np.ndarray:
    """Drop a ball cutter on ``surf`` at each (x, y); return OpenCAMLib's CL z per point."""
    from opencamlib import ocl

    cutter = ocl.BallCutter(float(diameter), FLUTE_LEN)  # keep a reference: OCL stores a pointer
    bdc = ocl.BatchDropCutter()
    bdc.setSTL(surf)
    bdc.setCutter(cutter)
    for x, y in np.asarray(xy, dtype=np.float64):
        bdc.appendPoint(ocl.CLPoint(float(x), float(y), zmin))
    bdc.run()
    pts = bdc.getCLPoints()
    out = np.array([[p.x, p.y, p.z] for p in pts])
    # BatchDropCutter keeps the order of appendPoint; check rather than trust
    if not np.allclose(out[:, :2], xy):
        raise RuntimeError("BatchDropCutter changed the point order")
    return out[:, 2]


def check_cl_is_tip() -> None:
    """Verify OpenCAMLib's drop-cutter CL point is the tool tip (not the ball centre).

    A ball of radius R on the plane z = 0 must give CL z = 0 if CL is the tip (R if the
    centre); on the plane z = x/2 at x = 0 the tip sits at R/cos(atan(1/2)) − R.
    """
    flat = np.array([[[-20, -20, 0], [20, -20, 0], [0, 20, 0]]], float)
    tilt = np.array([[[-20, -20, -10], [20, -20, 10], [0, 20, 0]]], float)
    z_flat = drop_tips(ocl_surface(flat), BALL_D, np.array([[0.0, 0.0], [1.0, 2.0]]))
    z_tilt = drop_tips(ocl_surface(tilt), BALL_D, np.array([[0.0, 0.0]]))
    expect = BALL_R / np.cos(np.arctan(0.5)) - BALL_R
    if not (np.allclose(z_flat, 0.0, atol=1e-9) and abs(z_tilt[0] - expect) < 1e-9):
        raise RuntimeError(f"OpenCAMLib CL is not the tool tip: {z_flat}, {z_tilt} vs {expect}")


def douglas_peucker(points: np.ndarray, tol: float) -> np.ndarray:
    """Indices of the points kept by Douglas–Peucker simplification of a polyline.

    Parameters
    ----------
    points : (n, d) polyline.
    tol : largest allowed distance of a dropped point from the kept chord.
    """
    p = np.asarray(points, dtype=np.float64)
    keep = np.zeros(len(p), dtype=bool)
    keep[[0, -1]] = True
    stack = [(0, len(p) - 1)]
    while stack:
        i, j = stack.pop()
        if j <= i + 1:
            continue
        a, b = p[i], p[j]
        ab = b - a
        L2 = float(ab @ ab)
        rel = p[i + 1 : j] - a
        if L2 == 0.0:
            d = np.linalg.norm(rel, axis=1)
        else:
            t = np.clip(rel @ ab / L2, 0.0, 1.0)
            d = np.linalg.norm(rel - t[:, None] * ab, axis=1)
        k = int(np.argmax(d))
        if d[k] > tol:
            k += i + 1
            keep[k] = True
            stack += [(i, k), (k, j)]
    return np.flatnonzero(keep)


def densify_rows(surf, diameter: float, ys, rows_x, rows_z, max_step: float, rounds: int = 6):
    """Add drop-cutter samples where consecutive CL points of a row are farther than ``max_step``.

    A fixed x step under-samples steep CL stretches (the ball pivoting over a sharp edge): the
    chord between two samples 0.05 mm apart in x may span 0.7 mm in z and cut 10 µm under the
    true CL arc. Real CAM refines adaptively; here each long segment is split evenly in x and
    dropped again, until every 3-D step is at most ``max_step`` (or ``rounds`` passes).
    """
    rows_x = [np.asarray(x, float) for x in rows_x]
    rows_z = [np.asarray(z, float) for z in rows_z]
    for _ in range(rounds):
        new_xy, owner = [], []
        for r, (y, x, z) in enumerate(zip(ys, rows_x, rows_z)):
            seg = np.hypot(np.diff(x), np.diff(z))
            for i in np.flatnonzero(seg > max_step):
                n = int(np.ceil(seg[i] / max_step))
                xi = x[i] + (x[i + 1] - x[i]) * np.arange(1, n) / n
                new_xy.append(np.column_stack([xi, np.full(xi.size, y)]))
                owner.append(np.full(xi.size, r))
        if not new_xy:
            break
        xy = np.vstack(new_xy)
        owner = np.concatenate(owner)
        z_new = drop_tips(surf, diameter, xy)
        for r in np.unique(owner):
            sel = owner == r
            x = np.concatenate([rows_x[r], xy[sel, 0]])
            z = np.concatenate([rows_z[r], z_new[sel]])
            o = np.argsort(x, kind="stable")
            rows_x[r], rows_z[r] = x[o], z[o]
    return rows_x, rows_z


# ------------------------------------------------------------------------------- waterline
def waterline_loops(surf, z: float, sampling: float = 0.1, diameter: float = None) -> list[np.ndarray]:
    """OpenCAMLib Waterline loops of a ball (default T1) at tip z = ``z``, as (n, 3) arrays."""
    from opencamlib import ocl

    cutter = ocl.BallCutter(float(diameter or BALL_D), FLUTE_LEN)  # keep a reference: OCL stores a pointer
    wl = ocl.Waterline()
    wl.setSTL(surf)
    wl.setCutter(cutter)
    wl.setZ(float(z))
    wl.setSampling(float(sampling))
    with quiet_fds():
        wl.run()
        loops = wl.getLoops()
    return [np.array([[p.x, p.y, p.z] for p in L]) for L in loops if len(L) > 2]


def signed_area(xy: np.ndarray) -> float:
    x, y = xy[:, 0], xy[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def crop_surface(tris: np.ndarray, box) -> object:
    """OpenCAMLib surface of the triangles whose bounding box meets ``box`` (x0, y0, x1, y1).

    Waterline cost grows with the model's extent; the loops inside the box do not depend on
    triangles far outside it (farther than the tool radius).
    """
    lo, hi = tris.min(1), tris.max(1)
    sel = (hi[:, 0] > box[0]) & (lo[:, 0] < box[2]) & (hi[:, 1] > box[1]) & (lo[:, 1] < box[3])
    return ocl_surface(tris[sel])
