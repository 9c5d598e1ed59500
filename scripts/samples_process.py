"""The sample mould's finishing process (scripts/make_samples.py): semi-finishing that leaves an even
allowance, then three finishing programs machined in this order on that stock.

Both stages are steep-and-shallow with rest machining: Z-level contours of a Ø10 ball on walls
steeper than ``STEEP_DEG``, a raster along X on the shallow areas (overlapping the steep ones by
``OVERLAP_MM`` of path), and a Ø4 ball wherever the Ø10's sweeps leave more than ``REST_MM`` over the
model (concave corners and the feet of walls). Semi-finishing runs the same strategies with each ball
kept ``ALLOWANCE_MM`` off the model (its paths are those of a ball ``2·ALLOWANCE_MM`` larger, same
centre) and coarser steps.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from samples_envelope import Sweeps, gap
from samples_geom import Grid
from samples_moves import Toolpath
from samples_nc import NCWriter
from samples_cam import SAMPLE, drop_tips
from samples_paths import (climb, contacts, dilate, floor_levels, in_box, level_loops, min_length, raster_rows,
                           resample, runs, simplify)

BOX = (54.0, 15.0, 90.0, 62.0)   # machined area (contact points) and the semi-finished stock's extent
TOP_Z = 0.0                      # the parting face
FLOOR_Z = -26.67                 # pocket floor, the lowest level (ktoolcav: 1.05 in)
ALLOWANCE_MM = 0.2               # stock the semi-finishing leaves for the finishing programs
STEEP_DEG = 60.0                 # contact slope from which Z-level contours take over from the raster
OVERLAP_MM = 0.5                 # the raster runs on into the steep areas by this much path
REST_MM = 0.02                   # a Ø4 rest pass where a Ø10 leaves more than this (Ø10 cusps: 9 µm)
REST_BAND_MM = 5.2               # rest rings on a floor reach this far from its walls (the Ø10's radius)
CAM_TOL = 0.005                  # chordal tolerance of the programs (Douglas–Peucker), mm
MIN_STRETCH_MM = 1.0             # shorter contour stretches are dropped


@dataclass(frozen=True)
class Tool:
    """A ball cutter of the process and how finely each strategy steps with it."""

    t: int
    diameter: float
    raster_step: float           # between raster rows, mm
    level_step: float            # between Z levels, mm
    rpm: int
    feed: float
    plunge: float

    @property
    def radius(self) -> float:
        return self.diameter / 2.0


T1 = Tool(1, 10.0, raster_step=0.6, level_step=0.5, rpm=12000, feed=3000.0, plunge=1000.0)
T2 = Tool(2, 4.0, raster_step=0.4, level_step=0.4, rpm=20000, feed=1500.0, plunge=600.0)
SEMI_T1 = Tool(1, 10.0, raster_step=0.8, level_step=0.3, rpm=10000, feed=3000.0, plunge=1000.0)
SEMI_T2 = Tool(2, 4.0, raster_step=0.4, level_step=0.25, rpm=16000, feed=1500.0, plunge=600.0)


def cusp_um(radius: float, step: float) -> float:
    """Scallop height of a ball of ``radius`` between passes ``step`` apart on a plane, µm."""
    return 1000.0 * (radius - np.sqrt(radius ** 2 - (step / 2) ** 2))


# ------------------------------------------------------------------------------ the stretches
def raster_stretches(rows, grid: Grid, radius: float, keep, overlap: float) -> tuple[list, int]:
    """Per row, the stretches whose contact ``keep(points, normals, slopes)`` accepts, grown by
    ``overlap`` mm of path onto points of the region (the slope limit relaxed), simplified. Returns
    them and the points looked at."""
    tips = np.vstack(rows)
    cp, n, slope = contacts(grid, tips, radius)
    mask = keep(cp, n, slope)
    region = keep(cp, n, np.zeros_like(slope))
    out, k = [], 0
    for r in rows:
        m = dilate(mask[k:k + len(r)], r, overlap, False) & region[k:k + len(r)]
        out.append([simplify(r[i], CAM_TOL) for i in runs(m, False) if len(i) > 1])
        k += len(r)
    return out, len(tips)


def level_stretches(levels, grid: Grid, radius: float, keep) -> list[list[np.ndarray]]:
    """Per level, the stretches of its loops whose contact ``keep`` accepts, climb, simplified; a loop
    kept whole is closed (its first point repeated at the end)."""
    loops = [L for ls in levels for L in ls]
    if not loops:
        return [[] for _ in levels]
    tips = np.vstack(loops)
    cp, n, slope = contacts(grid, tips, radius)
    mask = keep(cp, n, slope)
    out, k = [], 0
    for ls in levels:
        level = []
        for L in ls:
            m, nn = mask[k:k + len(L)], n[k:k + len(L)]
            for i in runs(m, True):
                if len(i) < 2:
                    continue
                if len(i) == len(L):
                    s = climb(np.vstack([L, L[:1]]), np.vstack([nn, nn[:1]]))
                else:
                    s = climb(L[i], nn[i])
                level += min_length([simplify(s, CAM_TOL)], MIN_STRETCH_MM)
            k += len(L)
        out.append(level)
    return out


def levels_of(tool: Tool) -> np.ndarray:
    """Tip heights of the Z levels: every ``level_step`` from half a step under the parting face down
    to just above the pocket floor's allowance (the deepest contour touches the walls there and does
    not plough the floor's stock: the raster and the floor rings finish the floor)."""
    z = np.arange(-tool.level_step / 2, FLOOR_Z + ALLOWANCE_MM, -tool.level_step)
    return np.round(np.append(z, FLOOR_Z + ALLOWANCE_MM + 0.05), 4)


def rows_of(tool: Tool, offset: float = 0.0, margin: float = 0.0) -> np.ndarray:
    """Y of the raster rows across ``BOX`` (± ``margin``), ``raster_step`` apart from ``BOX``'s edge + offset."""
    return np.round(np.arange(BOX[1] - margin + offset, BOX[3] + margin + 1e-9, tool.raster_step), 6)


# ------------------------------------------------------------------------------------ a tool
def _region(cp: np.ndarray, cover: bool) -> np.ndarray:
    """Contacts a pass of the stage keeps: in ``BOX`` and, finishing, under the parting face (that is
    face-milled, not ball-finished); semi-finishing (``cover``) also keeps every contact off ``BOX``."""
    ok = np.isfinite(cp).all(1)
    inside = ok & in_box(np.nan_to_num(cp), BOX)
    return (inside | ~in_box(np.nan_to_num(cp), BOX)) & ok if cover else inside & (cp[:, 2] < TOP_Z - 0.01)


def stretches(surf, tris: np.ndarray, grid: Grid, tool: Tool, allowance: float,
              rest_of: Sweeps | None = None, cover: bool = False) -> tuple[list, list, Sweeps | None, dict]:
    """One tool's steep and shallow stretches, and its reach.

    Parameters
    ----------
    surf, tris, grid : the nominal model (OpenCAMLib surface, triangles, closest-point grid).
    allowance : stock left on the model, mm (the paths are those of a ball 2·allowance larger).
    rest_of : a larger tool's reach: only where it leaves more than ``allowance + REST_MM``, the
        shallow part as rings offset from the walls on the floors (a raster would cross the narrow
        bands along the walls in short pieces).
    cover : semi-finishing: keep the raster over everything outside ``BOX`` too (the stock's margins).

    Returns
    -------
    steep : per Z level, its contour stretches (climb); shallow : per raster row (or offset ring),
        its stretches.
    reach : without ``rest_of``, the balls along every row and loop whatever their slope: what this
        tool can reach (the rest machining's reference); else None.
    info : counts for the console and the README.
    """
    r_path = tool.radius + allowance
    d_path = 2 * r_path

    def rest(cp):
        out = np.zeros(len(cp), bool)
        if rest_of is None:
            return ~out
        ok = np.isfinite(cp).all(1)
        out[ok] = gap(rest_of, cp[ok]) > allowance + REST_MM
        return out

    def shallow_keep(cp, n, slope):
        return (slope <= STEEP_DEG) & rest(cp) & _region(cp, cover)

    def steep_keep(cp, n, slope):
        return (slope >= STEEP_DEG) & rest(cp) & _region(cp, cover)

    zs = levels_of(tool)
    box = (BOX[0] - r_path - 1, BOX[1] - r_path - 1, BOX[2] + r_path + 1, BOX[3] + r_path + 1)
    loops = [level_loops(tris, d_path, z, box) for z in zs]
    steep = level_stretches(loops, grid, r_path, steep_keep)
    info = {"levels": len(zs)}
    if rest_of is not None:
        shallow = []
        for zf in floor_levels(tris, BOX):
            for rho in np.arange(tool.raster_step, REST_BAND_MM + 1e-9, tool.raster_step):
                rings = [resample(L, SAMPLE) for L in level_loops(tris, 2 * rho, zf + 0.005, box, flat=True)]
                rings = [np.column_stack([q, drop_tips(surf, d_path, q)]) for q in rings]
                shallow.append([s for s in level_stretches([rings], grid, r_path, shallow_keep)[0]])
        info["rings"] = sum(len(x) for x in shallow)
        return steep, shallow, None, info
    ys = rows_of(tool, offset=tool.raster_step / 2, margin=r_path if cover else 0.0)
    rows = raster_rows(surf, d_path, ys, BOX[0] - r_path, BOX[2] + r_path)
    shallow, info["raster_points"] = raster_stretches(rows, grid, r_path, shallow_keep, OVERLAP_MM)
    info["rows"] = len(ys)
    # a loop round the edge of the cropped model touches nothing of the model: not part of the reach
    real = [L for ls in loops for L in ls if np.isfinite(contacts(grid, L[::50], r_path)[2]).all()]
    lines = [simplify(r, CAM_TOL) for r in rows] + [simplify(np.vstack([L, L[:1]]), CAM_TOL) for L in real]
    a = np.vstack([q[:-1] for q in lines]) + [0, 0, r_path]
    b = np.vstack([q[1:] for q in lines]) + [0, 0, r_path]
    return steep, shallow, Sweeps(a, b, np.full(len(a), tool.radius)), info


def toolpath(grid: Grid, tool: Tool, allowance: float, writer: NCWriter | None = None) -> Toolpath:
    """A :class:`Toolpath` of ``tool`` kept ``allowance`` off the model (a throwaway writer if None)."""
    r_path = tool.radius + allowance
    return Toolpath(grid, 2 * r_path, r_path, writer or NCWriter(), tool.feed, tool.plunge)


def sweeps_of(tool: Tool, *paths: Toolpath) -> Sweeps:
    """The capsules the tool's ball sweeps along the feed moves of ``paths``."""
    a, b = (np.vstack(v) for v in zip(*(p.centre_segments() for p in paths)))
    return Sweeps(a, b, np.full(len(a), tool.radius))
