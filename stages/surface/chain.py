"""The stock a program meets: the workflow's stock less what the earlier programs of its job cut.

The programs of a workflow are machined in order on one stock (DESIGN §3). A program's scans draw
the earlier programs' sweeps, in their execution order, right after the stock and before its own
(``Renderer.scan(before=...)``): they shape the stock's top the program meets and are neither
counted nor logged. Where the engagement decides exactly whether a point is in material (a wall of
the stock between pixels), :meth:`Earlier.removed` tells whether an earlier sweep took it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.geometry.clearance import inside_sweep
from stages.geometry.cutter import Cutter
from stages.geometry.envelope import EnvelopeMesh, envelope_mesh
from stages.geometry.passes import PassGeometry
from stages.geometry.sweeps import ordered_sweep_scene, ragged_ranges
from stages.geometry.workpiece import Workpiece
from stages.surface.tiles import PASSES_PER_DRAW, cutting_candidates

EARLIER_ID = -2          # scan id of the earlier programs' sweeps (negative: drawn, not counted)
CELL_MM = 1.0            # bins of :meth:`Earlier.removed`


@dataclass
class EarlierProgram:
    passes: PassGeometry
    cutter: Cutter
    mesh: EnvelopeMesh
    cutting: np.ndarray       # pass indices that can reach the stock, in execution order
    bounds: np.ndarray        # (n_cutting, 2, 3) their sweeps' bounds


class Earlier:
    """The earlier programs of a job, in machining order (none: the program meets the stock)."""

    def __init__(self, programs: list[tuple[PassGeometry, Cutter]], wp: Workpiece, tol_mm: float):
        self.programs = []
        for pg, cutter in programs:
            k = cutting_candidates(pg, cutter, wp)
            self.programs.append(EarlierProgram(pg, cutter, envelope_mesh(cutter, tol_mm), k,
                                                pg.sweep_bounds(cutter)[k]))

    def __len__(self):
        return len(self.programs)

    def _reaching(self, e: EarlierProgram, lo, hi) -> np.ndarray:
        """Positions in ``e.cutting`` (and ``e.bounds``) of the passes whose sweeps reach the xy window."""
        b = e.bounds
        return np.flatnonzero(np.all(b[:, 0, :2] <= hi, axis=1) & np.all(b[:, 1, :2] >= lo, axis=1))

    def scenes(self, lo, hi):
        """The sweeps of the earlier programs' passes that reach into the xy window ``lo``–``hi``,
        in machining order, as scan scenes (id :data:`EARLIER_ID`, no depth bias: a pass of the
        program that repeats an earlier cut ties with it and does not count)."""
        for e in self.programs:
            k = e.cutting[self._reaching(e, lo, hi)]
            for a in range(0, len(k), PASSES_PER_DRAW):
                kk = k[a:a + PASSES_PER_DRAW]
                yield ordered_sweep_scene(e.mesh, e.passes.p0[kk], e.passes.p1[kk], np.full(len(kk), EARLIER_ID))

    def removed(self, points: np.ndarray, margin: float) -> np.ndarray:
        """Whether each point (n, 3) lies more than ``margin`` inside a sweep of an earlier program."""
        P = np.asarray(points, float).reshape(-1, 3)
        out = np.zeros(len(P), bool)
        if not len(P):
            return out
        lo, hi = P[:, :2].min(0), P[:, :2].max(0)
        shape = np.floor((hi - lo) / CELL_MM).astype(np.int64) + 1
        cell = np.floor((P[:, :2] - lo) / CELL_MM).astype(np.int64)
        pkey = cell[:, 0] * shape[1] + cell[:, 1]
        order = np.argsort(pkey, kind="stable")
        pkey_sorted = pkey[order]
        for e in self.programs:
            j = self._reaching(e, lo, hi)
            if not len(j):
                continue
            k, b = e.cutting[j], e.bounds[j]
            c0 = np.clip(np.floor((b[:, 0, :2] - lo) / CELL_MM).astype(np.int64), 0, shape - 1)
            c1 = np.clip(np.floor((b[:, 1, :2] - lo) / CELL_MM).astype(np.int64), 0, shape - 1)
            nx, ny = c1[:, 0] - c0[:, 0] + 1, c1[:, 1] - c0[:, 1] + 1
            rep = np.repeat(np.arange(len(k)), nx * ny)
            off = ragged_ranges(np.zeros(len(k), np.int64), nx * ny)
            ckey = (c0[rep, 0] + off % nx[rep]) * shape[1] + c0[rep, 1] + off // nx[rep]
            first = np.searchsorted(pkey_sorted, ckey, side="left")
            count = np.searchsorted(pkey_sorted, ckey, side="right") - first
            pt = order[ragged_ranges(first, count)]
            pk = np.repeat(rep, count)
            # the cells are 1 mm: the sweep's own bounds (shank included) drop most pairs at once
            q = P[pt]
            todo = ~out[pt] & np.all(q >= b[pk, 0], axis=1) & np.all(q <= b[pk, 1], axis=1)
            pt, ps = pt[todo], k[pk[todo]]
            hit = inside_sweep(P[pt], e.passes.p0[ps], e.passes.p1[ps], e.cutter, eps=margin)
            out[pt[hit]] = True
        return out


class ChainedStock:
    """The stock's top less the earlier programs' sweeps, for exact material tests."""

    def __init__(self, top, earlier: Earlier):
        self.top, self.earlier = top, earlier

    def under(self, points: np.ndarray, margin: float) -> np.ndarray:
        """Whether points (n, 3) lie more than ``margin`` in the material the program meets."""
        out = self.top.under(points, margin)
        if out.any():
            out[out] = ~self.earlier.removed(np.asarray(points, float).reshape(-1, 3)[out], margin)
        return out
