"""The stock the virtual machine cuts into, as a height field z_top(x, y) (3-axis machining)."""
from __future__ import annotations

import os

import numpy as np

from stages import InputError


def stock_height_fn(stock, cell_mm: float = 0.05):
    """The stock's top surface as a function z_top(x, y).

    Parameters
    ----------
    stock : dict or path
        ``{"box": [x0, y0, z0, x1, y1, z1]}`` (mm) or the path of a mesh (STL...) of the stock.
    cell_mm : float
        Grid spacing of the height field rasterised from a mesh.

    Returns
    -------
    callable
        ``h(x, y)`` over arrays of equal shape (mm): the highest up-facing surface above (x, y),
        bilinear between grid cells; ``-inf`` outside the stock.

    Raises
    ------
    stages.InputError
        The mesh file does not exist.
    """
    if isinstance(stock, dict) and "box" in stock:
        x0, y0, z0, x1, y1, z1 = [float(v) for v in stock["box"]]

        def box_h(x, y):
            inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
            return np.where(inside, z1, -np.inf)
        return box_h
    import trimesh
    path = os.fspath(stock)
    if not os.path.exists(path):
        raise InputError(f"{path}: stock model not found")
    m = trimesh.load(path, force="mesh")
    tris = np.asarray(m.triangles, float)
    nz = np.asarray(m.face_normals)[:, 2]
    tris = tris[nz > 1e-6]
    lo = tris.min(axis=(0, 1))
    hi = tris.max(axis=(0, 1))
    nx = int(np.ceil((hi[0] - lo[0]) / cell_mm)) + 1
    ny = int(np.ceil((hi[1] - lo[1]) / cell_mm)) + 1
    H = _rasterise_top(tris, lo, cell_mm, nx, ny)

    def mesh_h(x, y):
        fi = (np.asarray(x) - lo[0]) / cell_mm
        fj = (np.asarray(y) - lo[1]) / cell_mm
        i = np.clip(np.floor(fi).astype(np.int64), 0, nx - 2)
        j = np.clip(np.floor(fj).astype(np.int64), 0, ny - 2)
        tx, ty = np.clip(fi - i, 0, 1), np.clip(fj - j, 0, 1)
        with np.errstate(invalid="ignore"):
            h = ((1 - tx) * (1 - ty) * H[j, i] + tx * (1 - ty) * H[j, i + 1]
                 + (1 - tx) * ty * H[j + 1, i] + tx * ty * H[j + 1, i + 1])
        out = (fi < 0) | (fi > nx - 1) | (fj < 0) | (fj > ny - 1)
        return np.where(out | ~np.isfinite(h), -np.inf, h)
    return mesh_h


def _rasterise_top(tris: np.ndarray, lo: np.ndarray, cell_mm: float, nx: int, ny: int) -> np.ndarray:
    """Highest z of the triangles ``tris`` (k, 3, 3) at each grid cell centre: (ny, nx), -inf where none.

    The cells whose centre lies in a triangle's bounding box are tested by barycentric coordinates,
    20,000 triangles at a time.
    """
    H = np.full(nx * ny, -np.inf)
    i0 = np.floor((tris[:, :, 0].min(1) - lo[0]) / cell_mm).astype(np.int64)
    i1 = np.ceil((tris[:, :, 0].max(1) - lo[0]) / cell_mm).astype(np.int64)
    j0 = np.floor((tris[:, :, 1].min(1) - lo[1]) / cell_mm).astype(np.int64)
    j1 = np.ceil((tris[:, :, 1].max(1) - lo[1]) / cell_mm).astype(np.int64)
    wi, wj = i1 - i0 + 1, j1 - j0 + 1
    cnt = wi * wj
    for start in range(0, len(tris), 20000):
        sl = slice(start, start + 20000)
        c = cnt[sl]
        t = np.repeat(np.arange(start, min(start + 20000, len(tris))), c)
        loc = np.arange(c.sum()) - np.repeat(np.cumsum(c) - c, c)
        ii = i0[t] + loc % wi[t]
        jj = j0[t] + loc // wi[t]
        ok = (ii >= 0) & (ii < nx) & (jj >= 0) & (jj < ny)
        t, ii, jj = t[ok], ii[ok], jj[ok]
        px, py = lo[0] + ii * cell_mm, lo[1] + jj * cell_mm
        a, b, cc = tris[t, 0], tris[t, 1], tris[t, 2]
        v0x, v0y = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
        v1x, v1y = cc[:, 0] - a[:, 0], cc[:, 1] - a[:, 1]
        v2x, v2y = px - a[:, 0], py - a[:, 1]
        den = v0x * v1y - v1x * v0y
        den = np.where(np.abs(den) > 1e-15, den, np.nan)
        l1 = (v2x * v1y - v1x * v2y) / den
        l2 = (v0x * v2y - v2x * v0y) / den
        inside = (l1 >= -1e-9) & (l2 >= -1e-9) & (l1 + l2 <= 1 + 1e-9)
        z = a[:, 2] + l1 * (b[:, 2] - a[:, 2]) + l2 * (cc[:, 2] - a[:, 2])
        np.maximum.at(H, (jj * nx + ii)[inside], z[inside])
    return H.reshape(ny, nx)
