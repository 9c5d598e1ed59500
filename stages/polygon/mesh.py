"""The machined bar as a closed triangle mesh (STL for CAD) from its height map."""
from __future__ import annotations

import numpy as np


def solid_mesh(r, theta, z):
    """A watertight mesh of the solid r(θ, z): the side surface and a flat end cap at each end.

    Parameters
    ----------
    r : ndarray, shape (nz, ntheta)
        Radius, mm, at rows ``z`` and columns ``theta`` (the full circle, not repeating 2π).
    theta : ndarray, shape (ntheta,)
        Polar angles, rad, increasing.
    z : ndarray, shape (nz,)
        Axial positions, mm, increasing.

    Returns
    -------
    trimesh.Trimesh
        Faces wound outward (normals out of the material).
    """
    import trimesh
    r = np.asarray(r, dtype=float)
    nz, nt = r.shape
    ring = np.column_stack([(r * np.cos(theta)).ravel(), (r * np.sin(theta)).ravel(), np.repeat(z, nt)])
    ends = np.array([[0.0, 0.0, z[0]], [0.0, 0.0, z[-1]]])
    verts = np.vstack([ring, ends])
    i, j = np.meshgrid(np.arange(nz - 1), np.arange(nt), indexing="ij")
    a = (i * nt + j).ravel()
    b = (i * nt + (j + 1) % nt).ravel()
    c, d = b + nt, a + nt
    # e_θ × e_z = e_r: (a, b, c) and (a, c, d) face out of the side
    side = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    k = np.arange(nt)
    bottom = np.column_stack([np.full(nt, nz * nt), (k + 1) % nt, k])
    top = np.column_stack([np.full(nt, nz * nt + 1), (nz - 1) * nt + k, (nz - 1) * nt + (k + 1) % nt])
    return trimesh.Trimesh(verts, np.vstack([side, bottom, top]), process=False)


def write_stl(mesh, path) -> None:
    """Binary STL, written under a temporary name and renamed."""
    import os
    tmp = f"{path}.tmp"
    with open(tmp, "wb") as fh:
        fh.write(mesh.export(file_type="stl"))
    os.replace(tmp, path)
