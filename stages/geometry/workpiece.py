"""Workpiece models: the stock (a closed mesh or a box) and the design surface (distance queries)."""
from __future__ import annotations

import os
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from stages import InputError
from stages.geometry.passes import overlaps, window_xy_bounds
from stages.render import Scene


@dataclass(frozen=True)
class Workpiece:
    """Closed triangle mesh of the stock. ``normals`` point out of the material."""

    tris: np.ndarray      # (n, 3, 3)
    normals: np.ndarray   # (n, 3)
    bounds: np.ndarray    # (2, 3)


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
    m = _read_mesh(stock, "stock model")
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
    attrs = np.zeros((len(tri), 3, 3), np.float32)
    attrs[:, :, 0] = tri_id
    attrs[:, :, 2] = -1.0
    return Scene(wp.tris[tri], attrs, np.zeros(len(tri)), win.astype(np.int64))
