"""CAM helpers of scripts/make_samples.py: the model, OpenCAMLib drop-cutter and waterline paths, the
semi-finished stock as a height field, and an NC writer (OpenCAMLib computes the paths, not our code).
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


STOCK_MM = 0.2  # semi-finishing allowance = finishing depth


# finishing raster
FIN_X = (14.0, 88.0)


FIN_Y = (33.0, 64.8)


FIN_STEP = 0.6


SAMPLE = 0.05


CAM_TOL = 0.002


ARC_TOL = 0.02  # arc fit tolerance: the model's Ø12.7 boss is a 46-gon, chord error 0.015 mm


SAFE_Z = 25.0


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


# ---------------------------------------------------------------------------------- NC writer
class NCWriter:
    """Fanuc/ISO-style block writer: N numbers, modal G/F and coordinates, 3 decimals."""

    def __init__(self, n_step: int = 2):
        self.lines: list[str] = []
        self.n = 0
        self.n_step = n_step
        self.pos = {"X": None, "Y": None, "Z": None}
        self.motion = None
        self.feed = None
        self.moves = {"G0": 0, "G1": 0, "G2": 0, "G3": 0}

    @staticmethod
    def num(v: float) -> str:
        s = f"{v:.3f}"
        return "0.000" if s == "-0.000" else s

    def raw(self, text: str) -> None:
        self.lines.append(text)

    def block(self, text: str) -> None:
        self.n += self.n_step
        self.lines.append(f"N{self.n} {text}")

    def _coords(self, words: list, x, y, z) -> bool:
        """Append the coordinates that change (modal); whether any did."""
        changed = False
        for ax, v in (("X", x), ("Y", y), ("Z", z)):
            if v is None:
                continue
            s = self.num(v)
            if s != self.pos[ax]:
                words.append(ax + s)
                self.pos[ax] = s
                changed = True
        return changed

    def _emit(self, g: str, words: list, feed) -> None:
        if feed is not None and feed != self.feed:
            words.append(f"F{feed:g}")
            self.feed = feed
        self.motion = g
        self.block(" ".join(words))
        self.moves[g] += 1

    def move(self, g: str, x=None, y=None, z=None, feed=None, extra: str = "", force=False):
        words = [g] if g != self.motion or force else []
        changed = self._coords(words, x, y, z)
        if extra:
            words.append(extra)
            changed = True
        if not changed:
            return False
        self._emit(g, words, None if g == "G0" else feed)
        return True

    def arc(self, g: str, x, y, z=None, i=None, j=None, k=None, r=None, feed=None, plane=""):
        """Circular move; I J K incremental centre or R. ``plane`` prefixes e.g. 'G18'."""
        words = ([plane] if plane else []) + [g]
        self._coords(words, x, y, z)
        for ax, v in (("I", i), ("J", j), ("K", k), ("R", r)):
            if v is not None:
                words.append(ax + self.num(v))
        self._emit(g, words, feed)

    def text(self) -> str:
        return "\n".join(self.lines) + "\n"


def header(w: NCWriter, number: int, title: str, comments: list[str]) -> None:
    w.raw("%")
    w.raw(f"O{number} ({title})")
    for c in comments:
        w.raw(f"({c})")
    w.block("G90 G17 G21 G40 G49 G80")
    w.block("T1 M6")
    w.block("S12000 M3")


def footer(w: NCWriter) -> None:
    w.move("G0", z=SAFE_Z)
    w.block("M5")
    w.block("M30")
    w.raw("%")


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


# -------------------------------------------------------------------------------- contour program
def waterline_loops(surf, z: float, sampling: float = 0.1) -> list[np.ndarray]:
    """OpenCAMLib Waterline loops (tip z = ``z``) as (n, 3) arrays."""
    from opencamlib import ocl

    cutter = ocl.BallCutter(BALL_D, FLUTE_LEN)  # keep a reference: OCL stores a pointer
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
