"""Workpiece models: the stock (a closed mesh or a box) and the design surface (distance queries)."""
from __future__ import annotations

import os
from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np

from stages import InputError
from stages.geometry.passes import overlaps, window_xy_bounds
from stages.render import Scene
from stages.render.base import N_ATTR


@dataclass(frozen=True)
class Workpiece:
    """Closed triangle mesh of the stock. ``normals`` point out of the material."""

    tris: np.ndarray      # (n, 3, 3)
    normals: np.ndarray   # (n, 3)
    bounds: np.ndarray    # (2, 3)

    @cached_property
    def top(self) -> "StockTop":
        """The stock's top at any xy (:class:`StockTop`), built on first use."""
        return StockTop(self)


def box_workpiece(box) -> Workpiece:
    import trimesh
    b = np.asarray(box, float).reshape(2, 3)
    if not np.all(b[1] > b[0]):
        raise InputError(f"stock.box: need x0<x1, y0<y1, z0<z1, got {list(box)}")
    m = trimesh.creation.box(bounds=b)
    return _from_trimesh(m)


def _from_trimesh(m) -> Workpiece:
    tris = np.asarray(m.triangles, dtype=float)
    n = np.asarray(m.face_normals, dtype=float)
    return Workpiece(tris, n, np.asarray(m.bounds, float))


class StockTop:
    """The stock's top at any xy, exact between pixels: the highest of its triangles over the point
    (the stock as 3-axis machining sees it; a vertical face has no top and a wall is where the top
    drops). The triangles are binned by their xy bounds into square cells of ``cell_mm``."""

    def __init__(self, wp: Workpiece, cell_mm: float = 0.5):
        t = wp.tris
        a, b = t[:, 1, :2] - t[:, 0, :2], t[:, 2, :2] - t[:, 0, :2]
        det = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
        keep = np.abs(det) > 1e-12
        self._t0, self._a, self._b, self._det = t[keep, 0], a[keep], b[keep], det[keep]
        self._dz = np.stack([t[keep, 1, 2] - t[keep, 0, 2], t[keep, 2, 2] - t[keep, 0, 2]], 1)
        self._lo, self._cell = wp.bounds[0, :2].astype(float), float(cell_mm)
        c0 = np.floor((t[keep, :, :2].min(1) - self._lo) / cell_mm).astype(np.int64)
        c1 = np.floor((t[keep, :, :2].max(1) - self._lo) / cell_mm).astype(np.int64)
        self._shape = (int(c1[:, 0].max(initial=0)) + 1, int(c1[:, 1].max(initial=0)) + 1)
        nx, ny = c1[:, 0] - c0[:, 0] + 1, c1[:, 1] - c0[:, 1] + 1
        k = np.repeat(np.arange(len(c0)), nx * ny)
        off = np.arange(k.size) - np.repeat(np.cumsum(nx * ny) - nx * ny, nx * ny)
        cx, cy = c0[k, 0] + off % nx[k], c0[k, 1] + off // nx[k]
        # keep the cells the triangle itself covers, not only its bounds (a long diagonal sliver's
        # bounds hold many cells): no edge of it separates the cell from it
        xy = t[keep, :, :2][k]
        centre = self._lo + (np.stack([cx, cy], 1) + 0.5) * cell_mm
        meets = np.ones(len(k), bool)
        for e in range(3):
            d = xy[:, (e + 1) % 3] - xy[:, e]
            n = np.stack([-d[:, 1], d[:, 0]], 1)
            proj = np.einsum("kvi,ki->kv", xy, n)
            c = np.einsum("ki,ki->k", centre, n)
            half = 0.5 * cell_mm * (np.abs(n[:, 0]) + np.abs(n[:, 1]))
            meets &= (c + half >= proj.min(1)) & (c - half <= proj.max(1))
        k, cells = k[meets], (cx * self._shape[1] + cy)[meets]
        order = np.argsort(cells, kind="stable")
        self._cells, self._tri = cells[order], k[order]

    def z(self, xy: np.ndarray) -> np.ndarray:
        """Top of the stock at points ``xy`` (n, 2); -inf off the stock."""
        xy = np.asarray(xy, float).reshape(-1, 2)
        c = np.floor((xy - self._lo) / self._cell).astype(np.int64)
        ok = (c >= 0).all(1) & (c[:, 0] < self._shape[0]) & (c[:, 1] < self._shape[1])
        key = np.where(ok, c[:, 0] * self._shape[1] + c[:, 1], -1)
        lo = np.searchsorted(self._cells, key, side="left")
        n = np.where(ok, np.searchsorted(self._cells, key, side="right") - lo, 0)
        pt = np.repeat(np.arange(len(xy)), n)
        tri = self._tri[np.repeat(lo - np.cumsum(n) + n, n) + np.arange(pt.size)]
        v = xy[pt] - self._t0[tri, :2]
        a, b, det = self._a[tri], self._b[tri], self._det[tri]
        l1 = (v[:, 0] * b[:, 1] - v[:, 1] * b[:, 0]) / det
        l2 = (a[:, 0] * v[:, 1] - a[:, 1] * v[:, 0]) / det
        inside = (l1 >= -1e-9) & (l2 >= -1e-9) & (l1 + l2 <= 1.0 + 1e-9)
        z = self._t0[tri, 2] + l1 * self._dz[tri, 0] + l2 * self._dz[tri, 1]
        top = np.full(len(xy), -np.inf)
        np.maximum.at(top, pt[inside], z[inside])
        return top

    def under(self, points: np.ndarray, margin: float) -> np.ndarray:
        """Whether points (n, 3) lie more than ``margin`` under the stock's top."""
        points = np.asarray(points, float).reshape(-1, 3)
        return self.z(points[:, :2]) > points[:, 2] + margin


class DesignSurface:
    """Distance of points to the nominal (design) model (no spatial-index extra needed).

    Candidate faces are those of the ``k`` nearest random surface samples (about ``spacing_mm``
    apart); the distance to each candidate is exact (closest point on the triangle), so the result
    is never under the true distance. Where the random samples miss the nearest face, a neighbour
    gives it: within a sample spacing of a 1 mm-faceted sphere at most 10 µm over (the test),
    against the 80 µm the generating stage asks of it. :meth:`signed_distance` signs it by the
    nearest face's normal (the file's winding; a closed model wound inside out is turned).
    """

    def __init__(self, mesh, spacing_mm: float = 0.2, k: int = 16):
        import trimesh
        from scipy.spatial import cKDTree
        count = int(min(max(mesh.area / spacing_mm ** 2, 1000), 2_000_000))
        pts, face = trimesh.sample.sample_surface(mesh, count, seed=0)
        self._tree = cKDTree(pts)
        self._face = np.asarray(face, np.int64)
        self._tris = np.asarray(mesh.triangles, float)
        normals = np.asarray(mesh.face_normals, float)
        if mesh.is_watertight and mesh.volume < 0:
            normals = -normals
        self._normals = normals
        self._k = min(k, count)

    def _closest(self, points):
        """Per point: distance to the model, the nearest face and the closest point on it."""
        import trimesh
        points = np.asarray(points, float).reshape(-1, 3)
        if len(points) == 0:
            return np.zeros(0), np.zeros(0, np.int64), np.zeros((0, 3))
        _, nb = self._tree.query(points, k=self._k)
        faces = self._face[nb]                                          # (n, k), with repeats
        rep = np.repeat(points, faces.shape[1], axis=0)
        cp = trimesh.triangles.closest_point(self._tris[faces.reshape(-1)], rep)
        d = np.linalg.norm(cp - rep, axis=1).reshape(faces.shape)
        best = d.argmin(axis=1)
        rows = np.arange(len(points))
        return d[rows, best], faces[rows, best], cp.reshape(*faces.shape, 3)[rows, best]

    def distance(self, points) -> np.ndarray:
        return self._closest(points)[0]

    def samples(self, lo=None, hi=None) -> tuple[np.ndarray, np.ndarray]:
        """The surface samples (about ``spacing_mm`` apart) and their faces' unit normals, those
        within the box ``lo`` … ``hi`` (mm) when given."""
        pts = self._tree.data
        keep = np.ones(len(pts), bool) if lo is None else np.all((pts >= lo) & (pts <= hi), axis=1)
        return np.asarray(pts[keep]), self._normals[self._face[keep]]

    def signed_distance(self, points) -> np.ndarray:
        """:meth:`distance`, negative inside the material (behind the nearest face's normal)."""
        points = np.asarray(points, float).reshape(-1, 3)
        d, face, cp = self._closest(points)
        side = np.einsum("ij,ij->i", points - cp, self._normals[face])
        return np.where(side < 0, -d, d)


def _read_mesh(path, what: str):
    """A mesh file as a trimesh, with an InputError naming the file and ``what`` it is for."""
    import trimesh
    path = os.fspath(path)
    if not os.path.exists(path):
        raise InputError(f"{path}: {what} not found")
    try:
        m = trimesh.load(path, force="mesh")
    except Exception as e:  # trimesh raises many types for bad files
        raise InputError(f"{path}: cannot read {what}: {e}") from None
    if len(m.faces) == 0:
        raise InputError(f"{path}: {what} has no faces")
    return m


@lru_cache(maxsize=4)
def _design_surface_cached(path: str, mtime: float) -> DesignSurface:
    return DesignSurface(_read_mesh(path, "nominal model"))


def load_design_surface(nominal) -> DesignSurface | None:
    """The workflow's ``nominal`` model (a mesh path) as a :class:`DesignSurface`; None without one."""
    if nominal is None or isinstance(nominal, DesignSurface):
        return nominal
    path = os.fspath(nominal)
    if not os.path.exists(path):
        raise InputError(f"{path}: nominal model not found")
    return _design_surface_cached(os.path.abspath(path), os.path.getmtime(path))


def load_workpiece(stock) -> Workpiece:
    """Stock from the engine's ``inputs['stock']``: a mesh path (STL/OBJ/PLY), ``{'box': [...]}`` or
    a trimesh."""
    if stock is None:
        raise InputError("stock: a stock model (mesh path or {box: [...]}) is required")
    if isinstance(stock, Workpiece):
        return stock
    if hasattr(stock, "triangles") and hasattr(stock, "face_normals"):
        return _from_trimesh(stock)
    if isinstance(stock, dict):
        if "box" not in stock:
            raise InputError(f"stock: dict must have key 'box', got {sorted(stock)}")
        return box_workpiece(stock["box"])
    path = os.path.abspath(os.fspath(stock))
    if not os.path.exists(path):
        raise InputError(f"{path}: stock model not found")
    return _workpiece_cached(path, os.path.getmtime(path))


@lru_cache(maxsize=4)
def _workpiece_cached(path: str, mtime: float) -> Workpiece:
    m = _read_mesh(path, "stock model")
    if m.is_volume and m.volume < 0:
        m.invert()
    return _from_trimesh(m)


def workpiece_scene(wp: Workpiece, views, tri_id=0.0):
    """Workpiece faces a viewer inside the material leaves through (normal . view_dir > 0).

    Seen from below this is the top surface of the stock (the seed draws W without its lower
    face, para 0044); seen along a surface normal it is the face the ray exits through.
    """
    lo_w, hi_w = window_xy_bounds(views)
    tlo, thi = wp.tris.min(1), wp.tris.max(1)
    d = np.array([np.asarray(v.view_dir, float) / np.linalg.norm(v.view_dir) for v in views])
    win, tri = np.nonzero(overlaps(lo_w, hi_w, tlo, thi) & ((d @ wp.normals.T) > 1e-9))
    attrs = np.zeros((len(tri), 3, N_ATTR), np.float32)
    attrs[:, :, 0] = tri_id
    attrs[:, :, 2] = -1.0
    return Scene(wp.tris[tri], attrs, np.zeros(len(tri)), win.astype(np.int64))
