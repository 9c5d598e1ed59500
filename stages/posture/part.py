"""The required surface as micro-regions: a triangle mesh read with trimesh, checked, and cut into
triangles no longer than a given size (seed eq. 1: the surface divided into micro-regions i)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stages import InputError


@dataclass
class Part:
    """The required surface (mm): the file's triangles, and the micro-regions cut from them.

    vertices : (nv, 3); faces : (nf, 3) vertex indices, counter-clockwise seen from outside;
    face_normals : (nf, 3) unit normals out of the material. Micro-regions (n of them): centroids
    (n, 3), areas (n,) mm², parent (n,) the face each lies in, bary (n, 3) the barycentric
    coordinates of its centroid in that face, whole (n,) True where the region is its whole face,
    triangles (n, 3, 3) its corners (for pictures).
    """

    vertices: np.ndarray
    faces: np.ndarray
    face_normals: np.ndarray
    centroids: np.ndarray
    areas: np.ndarray
    parent: np.ndarray
    bary: np.ndarray
    whole: np.ndarray
    triangles: np.ndarray
    path: str = ""

    @property
    def n(self) -> int:
        """Number of micro-regions."""
        return len(self.parent)

    @property
    def normals(self) -> np.ndarray:
        """(n, 3) unit normal of each micro-region (its face's)."""
        return self.face_normals[self.parent]

    @property
    def area(self) -> float:
        return float(self.areas.sum())


def read_mesh(path) -> "trimesh.Trimesh":  # noqa: F821
    """The mesh of an STL/OBJ/PLY file, checked: ``InputError`` naming the file when it is missing,
    unreadable, empty, non-manifold (an edge of more than two faces) or inconsistently wound.

    A closed mesh wound inside out (negative volume, a common export slip) is turned outside out.
    """
    import trimesh
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such mesh file")
    try:
        mesh = trimesh.load(str(path), force="mesh", process=True)
    except Exception as e:  # trimesh raises many kinds on a broken file
        raise InputError(f"{path}: cannot read the mesh: {type(e).__name__}: {e}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError(f"{path}: the mesh is empty (no triangles)")
    mesh.update_faces(mesh.nondegenerate_faces())
    if len(mesh.faces) == 0 or mesh.area <= 0:
        raise InputError(f"{path}: the mesh is empty (every triangle has zero area)")
    counts = np.unique(mesh.edges_unique_inverse, return_counts=True)[1]
    if (counts > 2).any():
        bad = mesh.edges_unique[np.nonzero(counts > 2)[0][0]]
        raise InputError(f"{path}: the mesh is not manifold: {int((counts > 2).sum())} edges are shared by more "
                         f"than two triangles (the first between the points {mesh.vertices[bad[0]].round(3).tolist()} "
                         f"and {mesh.vertices[bad[1]].round(3).tolist()}); a required surface is one sheet")
    if not mesh.is_winding_consistent:
        raise InputError(f"{path}: the triangles are not wound consistently: the normals must all point out of "
                         "the material (fix the orientation in the CAD export)")
    if mesh.is_watertight and mesh.volume < 0:
        mesh.invert()
    return mesh


def micro_regions(vertices, faces, region_mm: float, path: str = "") -> Part:
    """Cut the triangles until no edge is longer than ``region_mm`` (midpoint subdivision).

    Parameters
    ----------
    vertices : (nv, 3) float; faces : (nf, 3) int; region_mm : largest edge of a micro-region, mm.
    """
    import trimesh
    vertices, faces = np.asarray(vertices, float), np.asarray(faces, np.int64)
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    fn = cross / np.linalg.norm(cross, axis=1, keepdims=True)
    v, f, parent = trimesh.remesh.subdivide_to_size(vertices, faces, max_edge=float(region_mm), max_iter=20,
                                                    return_index=True)
    sub = v[f]
    areas = 0.5 * np.linalg.norm(np.cross(sub[:, 1] - sub[:, 0], sub[:, 2] - sub[:, 0]), axis=1)
    keep = areas > 0
    sub, areas, parent = sub[keep], areas[keep], np.asarray(parent, np.int64)[keep]
    centroids = sub.mean(1)
    bary = trimesh.triangles.points_to_barycentric(tri[parent], centroids)
    whole = np.bincount(parent, minlength=len(faces))[parent] == 1
    return Part(vertices, faces, fn, centroids, areas, parent, bary, whole, sub, str(path))


def load_part(path, region_mm: float) -> Part:
    """:func:`read_mesh` then :func:`micro_regions`."""
    mesh = read_mesh(path)
    return micro_regions(mesh.vertices, mesh.faces, region_mm, str(path))
