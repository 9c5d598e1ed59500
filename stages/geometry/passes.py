"""Passes of one program as arrays of tool-tip coordinates, and their bounds."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages import InputError
from stages.geometry.cutter import Cutter

# a move joined end to start to the next that turns less than this from it carries the same cut
# on: the split stage's pieces of one line, a corrected line's via pieces, a curve's CAM chords
# (see stages.surface.cut_passes.line_interior and stages.cutting.surface_error.deepest_passage)
CONTINUE_DEG = 10.0
# a line's pieces turn by float noise only
STRAIGHT_DEG = 0.01


@dataclass
class PassGeometry:
    """Passes of one program as arrays (tool tip coordinates)."""

    program_id: str
    pass_id: np.ndarray      # (n,) int
    motion: np.ndarray       # (n,) int8, 0 = rapid
    p0: np.ndarray           # (n, 3) tip at start
    p1: np.ndarray           # (n, 3) tip at end
    feed_mm_min: np.ndarray
    spindle_rpm: np.ndarray

    @property
    def length(self):
        return np.linalg.norm(self.p1 - self.p0, axis=1)

    @property
    def s0(self):
        """Path length at the start of each pass (cumulative over the program)."""
        return np.concatenate([[0.0], np.cumsum(self.length)[:-1]])

    @property
    def feed_deg(self):
        """Direction of the xy feed, degrees CCW from +X (0 for pure plunges)."""
        d = self.p1 - self.p0
        return np.degrees(np.arctan2(d[:, 1], d[:, 0]))

    def sweep_bounds(self, shape: Cutter):
        """(n, 2, 3) axis-aligned bounds of each pass's swept volume."""
        lo = np.minimum(self.p0, self.p1) - [shape.radius_mm, shape.radius_mm, 0.0]
        hi = np.maximum(self.p0, self.p1) + [shape.radius_mm, shape.radius_mm, shape.stickout_mm]
        return np.stack([lo, hi], axis=1)


def path_turning(pg: PassGeometry):
    """The program's path as joined chains and its turning.

    Returns
    -------
    chain_start, chain_end : (n,) int
        First and last pass of the chain each pass belongs to: passes joined end to start, no
        rapid between them.
    turned : (n,) float
        Cumulative turning (deg) along the path: the turn from pass j to pass i is
        ``turned[i] - turned[j]`` (non-decreasing; zero-length passes do not turn).
    """
    n = len(pg.pass_id)
    d = pg.p1 - pg.p0
    L = np.linalg.norm(d, axis=1)
    u = d / np.maximum(L, 1e-12)[:, None]
    turn = np.zeros(n)
    brk = np.ones(n, bool)
    if n > 1:
        ang = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", u[:-1], u[1:]), -1.0, 1.0)))
        turn[1:] = np.where((L[:-1] > 1e-9) & (L[1:] > 1e-9), ang, 0.0)
        brk[1:] = ((pg.motion[:-1] == 0) | (pg.motion[1:] == 0)
                   | (np.linalg.norm(pg.p0[1:] - pg.p1[:-1], axis=1) > 1e-6))
    start = np.maximum.accumulate(np.where(brk, np.arange(n), 0))
    last = np.r_[brk[1:], True]
    end = np.minimum.accumulate(np.where(last, np.arange(n), n)[::-1])[::-1]
    return start, end, np.cumsum(turn)


def straight_run(pg: PassGeometry, idx: np.ndarray, turn_deg: float = STRAIGHT_DEG):
    """First and last pass of the run around each pass ``idx`` that carries it straight on:
    joined to it and turning by at most ``turn_deg`` in all from it (one line split into pieces,
    or moved by a correction's float noise; a curve's chords turn, and a later chord of a concave
    curve does cut below an earlier one's contact)."""
    start, end, turned = path_turning(pg)
    idx = np.asarray(idx, np.int64)
    lo = np.searchsorted(turned, turned[idx] - turn_deg - 1e-9, side="left")
    hi = np.searchsorted(turned, turned[idx] + turn_deg + 1e-9, side="right") - 1
    return np.maximum(start[idx], lo), np.minimum(end[idx], hi)


def pass_geometry(passes, tool) -> PassGeometry:
    """Arrays of a ``passes`` table (one program). Converts ``control_point: center`` to tips."""
    cutter = Cutter.from_params(tool)
    cols = passes.column_names
    need = ["program_id", "pass_id", "motion", "x0_mm", "y0_mm", "z0_mm", "x1_mm", "y1_mm", "z1_mm"]
    missing = [c for c in need if c not in cols]
    if missing:
        raise InputError(f"passes: missing columns {missing}")
    col = {c: passes.column(c).to_numpy(zero_copy_only=False) for c in cols}
    p0 = np.stack([col["x0_mm"], col["y0_mm"], col["z0_mm"]], 1).astype(float)
    p1 = np.stack([col["x1_mm"], col["y1_mm"], col["z1_mm"]], 1).astype(float)
    p0 = p0 - [0, 0, cutter.control_offset_mm]
    p1 = p1 - [0, 0, cutter.control_offset_mm]
    if not (np.all(np.isfinite(p0)) and np.all(np.isfinite(p1))):
        bad = int(np.nonzero(~np.all(np.isfinite(p0) & np.isfinite(p1), axis=1))[0][0])
        raise InputError(f"passes: pass_id {col['pass_id'][bad]}: non-finite coordinates")
    pid = col["program_id"][0] if len(passes) else ""
    n = len(passes)
    return PassGeometry(str(pid), col["pass_id"].astype(np.int64), col["motion"].astype(np.int8),
                        p0, p1, col.get("feed_mm_min", np.zeros(n)).astype(float),
                        col.get("spindle_rpm", np.zeros(n)).astype(float))


def overlaps(lo_a, hi_a, lo_b, hi_b):
    """(na, nb) boolean: axis-aligned xy boxes a and b overlap."""
    return ((lo_a[:, None, 0] <= hi_b[None, :, 0]) & (hi_a[:, None, 0] >= lo_b[None, :, 0])
            & (lo_a[:, None, 1] <= hi_b[None, :, 1]) & (hi_a[:, None, 1] >= lo_b[None, :, 1]))


def window_xy_bounds(views):
    """(n, 2) lo, hi xy bounds of the footprint of each view (conservative for oblique views)."""
    lo, hi = [], []
    for v in views:
        right, up, d = v.basis()
        c = np.asarray(v.center, float)
        corners = []
        for sx in (-0.5, 0.5):
            for sy in (-0.5, 0.5):
                for s in (v.near_mm, v.far_mm):
                    corners.append(c + sx * v.width_mm * right + sy * v.height_mm * up + s * d)
        corners = np.array(corners)
        lo.append(corners.min(0))
        hi.append(corners.max(0))
    return np.array(lo), np.array(hi)
