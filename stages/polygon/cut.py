"""The machined solid as a radial height map r(θ, z) over the workpiece-fixed frame.

Material at (θ, z) is removed down to the least radius at which an edge's tip passes polar angle θ
while the edge, ``edge_width_mm`` wide along the axis, covers z. One passage's cut is a fixed
profile (``kinematics.event_profile``) shifted in θ and z, so a chunk of rows is

1. every passage gathered at the grid columns its profile spans and scattered (min) to the row
   its tip is at: a map of tip points, O(passages × columns spanned);
2. a running minimum along z over the edge width (``scipy.ndimage.minimum_filter1d``, O(cells)).

Memory is the chunk's rows plus half an edge width each side, times the columns.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import numpy as np

from stages.polygon.kinematics import Profile, Setup, event_profile, passages

# gathered (passage, column) pairs per batch: bounds the scatter's temporaries (~100 MB)
BATCH_CELLS = 2_000_000
# cells of one chunk's tip-point map (rows incl. the edge-width margins × columns): ~64 MB of float64
CHUNK_CELLS = 8_000_000


@dataclass(frozen=True)
class Grid:
    """Rows z_i = i·dz (i < nz, from 0 to the part's length) and columns θ_j = j·2π/ntheta."""

    nz: int
    ntheta: int
    dz: float

    @property
    def z(self) -> np.ndarray:
        return np.arange(self.nz) * self.dz

    @property
    def theta(self) -> np.ndarray:
        return np.arange(self.ntheta) * (2 * np.pi / self.ntheta)

    @property
    def dtheta(self) -> float:
        return 2 * np.pi / self.ntheta


def make_grid(length_mm: float, dz_mm: float, dtheta_deg: float) -> Grid:
    """The grid nearest the asked resolution that ends exactly on the part's length and closes the circle."""
    nz = max(2, int(round(length_mm / dz_mm)) + 1)
    return Grid(nz, max(8, int(round(360.0 / dtheta_deg))), length_mm / (nz - 1))


def half_width_rows(setup: Setup, grid: Grid) -> int:
    """Rows each side of the tip that the edge covers (its width over 2, to the nearest row)."""
    return int(round(0.5 * setup.edge_width_mm / grid.dz))


def _scatter(P: np.ndarray, row_base: int, T: np.ndarray, setup: Setup, prof: Profile, grid: Grid) -> None:
    """Min the tip points of passages starting at ``T`` into the tip-point map ``P`` (rows from ``row_base``)."""
    nt, dth = grid.ntheta, grid.dtheta
    K = int(np.floor(prof.span / dth)) + 2             # columns one passage spans
    shift = np.mod(-setup.w * T, 2 * np.pi)             # θ shift of each passage
    j0 = np.ceil((prof.theta0 + shift) / dth).astype(np.int64)
    zt = setup.feed_per_tool_mm * T / (2 * np.pi)       # axial position at each passage's start
    batch = max(1, BATCH_CELLS // K)
    k = np.arange(K)
    for b in range(0, len(T), batch):
        j = j0[b:b + batch, None] + k                   # (passages, K) unwrapped column numbers
        m = np.floor((j * dth - shift[b:b + batch, None] - prof.theta0) / prof.h).astype(np.int64)
        ok = (m >= 0) & (m < prof.r.size)
        m = np.where(ok, m, 0)
        r = np.where(ok, prof.r[m], np.inf)
        row = np.rint((zt[b:b + batch, None] + prof.dz[m]) / grid.dz).astype(np.int64) - row_base
        ok &= np.isfinite(r) & (row >= 0) & (row < P.shape[0])
        np.minimum.at(P.ravel(), (row * nt + np.mod(j, nt))[ok], r[ok])


def height_map_chunks(setup: Setup, grid: Grid, oversample: int = 4, chunk_rows: int | None = None
                      ) -> Iterator[tuple[int, np.ndarray]]:
    """The machined radius r(θ, z), chunk by chunk along z.

    Parameters
    ----------
    setup : Setup
    grid : Grid
    oversample : int
        Bins of the passage profile per grid column (the θ error of a tip point is half a bin).
    chunk_rows : int, optional
        Rows per chunk (default: as many as ``CHUNK_CELLS`` allows beside the edge-width margins).

    Yields
    ------
    i0 : int
        The chunk's first row.
    r : ndarray, shape (rows, grid.ntheta)
        mm, at most the workpiece radius (uncut).
    """
    from scipy.ndimage import minimum_filter1d
    prof = event_profile(setup, grid.dtheta / oversample)
    mh = half_width_rows(setup, grid)
    rows = chunk_rows or max(16, CHUNK_CELLS // grid.ntheta - 2 * mh)
    rw = setup.workpiece_radius_mm
    for i0 in range(0, grid.nz, rows):
        i1 = min(grid.nz, i0 + rows)
        base = i0 - mh
        P = np.full((i1 - i0 + 2 * mh, grid.ntheta), np.inf)
        T = passages(setup, prof, (base - 0.5) * grid.dz, (i1 + mh - 0.5) * grid.dz)
        if T.size:
            _scatter(P, base, T, setup, prof, grid)
        if mh:
            P = minimum_filter1d(P, 2 * mh + 1, axis=0, mode="constant", cval=np.inf)
        yield i0, np.minimum(P[mh:mh + i1 - i0], rw)


def height_map(setup: Setup, grid: Grid, **kw) -> np.ndarray:
    """The whole height map (nz, ntheta), mm: for tests and small grids."""
    return np.concatenate([h for _, h in height_map_chunks(setup, grid, **kw)], axis=0)
