"""Machining a bar: the height map chunk by chunk, and what the job keeps of it.

The full map (rows × columns) is never held: each chunk gives its rows' depth harmonics (twist),
the analysed sections, and the rows and columns of the mesh.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from stages.polygon.cut import Grid, height_map_chunks
from stages.polygon.kinematics import Setup
from stages.polygon.sections import SectionStats

# sections analysed for sides and thickness, evenly spaced along the part (beside the stations)
ANALYSED_SECTIONS = 200
# harmonics of the depth kept per row: the face orientation of p-gons up to this p
MAX_SIDES = 128


@dataclass
class Machined:
    """The machined bar: figures, the station sections and a thinned height map for the mesh."""

    grid: Grid
    stations: np.ndarray          # row indices of the written sections
    sections: np.ndarray          # (stations, ntheta) r, mm
    mesh_rows: np.ndarray         # row indices of the thinned map
    mesh_cols: np.ndarray         # column indices of the thinned map
    mesh_r: np.ndarray            # (mesh rows, mesh cols) r, mm
    figures: dict
    seconds: float


def station_rows(grid: Grid, count: int) -> np.ndarray:
    """``count`` rows evenly spaced from one end of the part to the other."""
    return np.unique(np.rint(np.linspace(0, grid.nz - 1, max(1, count))).astype(int))


def thinned(n: int, stride: int, closed: bool) -> np.ndarray:
    """Every ``stride``-th index of ``n``, with the last one when ``closed`` (the part's far end)."""
    idx = np.arange(0, n, max(1, stride))
    return np.append(idx, n - 1) if closed and idx[-1] != n - 1 else idx


def machine(setup: Setup, grid: Grid, stations: int, prominence_mm: float,
            mesh_stride: tuple[int, int] = (1, 1)) -> Machined:
    """Machine the bar described by ``setup`` on ``grid``.

    Parameters
    ----------
    setup : Setup
    grid : Grid
    stations : int
        Cross-sections kept for the table and pictures.
    prominence_mm : float
        Least ridge between two faces (``sections.face_minima``).
    mesh_stride : (int, int)
        Rows and columns of the map kept for the mesh: every n-th.

    Returns
    -------
    Machined
    """
    t0 = time.perf_counter()
    st = station_rows(grid, stations)
    analysed = np.union1d(st, station_rows(grid, min(grid.nz, ANALYSED_SECTIONS)))
    pmax = min(MAX_SIDES, grid.ntheta // 2)
    stats = SectionStats(grid.nz, setup.workpiece_radius_mm, analysed, pmax)
    mr, mc = thinned(grid.nz, mesh_stride[0], True), thinned(grid.ntheta, mesh_stride[1], False)
    parts = []
    for i0, r in height_map_chunks(setup, grid):
        stats.add(i0, r)
        sel = mr[(mr >= i0) & (mr < i0 + len(r))]
        parts.append(r[sel - i0][:, mc])
    figures = stats.figures(grid.z, grid.theta, prominence_mm)
    return Machined(grid, st, np.array([stats.rows[i] for i in st]), mr, mc, np.concatenate(parts),
                    figures, time.perf_counter() - t0)
