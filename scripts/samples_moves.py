"""Moves of the sample programs (scripts/make_samples.py): stretches linked into a program as NC text,
with the ball-centre polyline of every feed move kept for the surface the program leaves.

Links between stretches never gouge: a straight feed link is used only where the checked ball stays
off the model all along it (exact distances to the model), else the tool lifts straight up (always free
on a part a 3-axis machine can cut), traverses at rapid over the part and plunges beside the next
stretch (free there, so free all the way down: nothing on such a part overhangs).
"""
from __future__ import annotations

import numpy as np

from samples_geom import Grid, closest_points
from samples_nc import SAFE_Z, NCWriter

CLEAR_MM = 1.0          # rapid moves stop this far above what they approach
TOP_Z = 0.0             # the part's top (the parting face): rapid traverses pass CLEAR_MM over it
LINK_SAMPLES_MM = 0.05  # ball positions along a link checked for gouging
LEAD_MM = (1.0, 0.5)    # lengths of the lead-in/out moves tried (along the air side's normal), longest first


class Toolpath:
    """A program being written: NC blocks through ``writer`` and the centre segments of its feed moves.

    Parameters
    ----------
    grid : the model's triangles (links are checked against them).
    diameter : the ball that must not gouge it: the tool, or the tool plus twice its allowance.
    radius : the tool's radius (its centre is the tip + radius·Z).
    writer : the NC writer; a semi-finishing path that is never written gets a throwaway one.
    feed, plunge : cutting and plunge feeds, mm/min.
    """

    def __init__(self, grid: Grid, diameter: float, radius: float, writer: NCWriter, feed: float, plunge: float):
        self.grid, self.diameter, self.radius = grid, float(diameter), float(radius)
        self.w, self.feed, self.plunge = writer, feed, plunge
        self.pos = None                       # tip, as written (3 decimals)
        self.segments: list[tuple[np.ndarray, np.ndarray]] = []
        self.links = {"feed": 0, "retract": 0}

    # ------------------------------------------------------------------------------------- moves
    def _at(self, x, y, z) -> np.ndarray:
        p = self.pos.copy() if self.pos is not None else np.full(3, np.nan)
        for i, v in enumerate((x, y, z)):
            if v is not None:
                p[i] = float(self.w.num(v))
        return p

    def rapid(self, x=None, y=None, z=None) -> None:
        end = self._at(x, y, z)
        self.w.move("G0", x=x, y=y, z=z)
        self.pos = end

    def cut(self, p, feed=None) -> None:
        end = self._at(*p)
        if self.w.move("G1", x=p[0], y=p[1], z=p[2], feed=feed or self.feed):
            self.segments.append((self.pos.copy(), end))
        self.pos = end

    def centre_segments(self) -> tuple[np.ndarray, np.ndarray]:
        """(a, b): the ball centres at the start and end of every feed move, (n, 3) each."""
        if not self.segments:
            return np.zeros((0, 3)), np.zeros((0, 3))
        a, b = (np.array(v) for v in zip(*self.segments))
        return a + [0, 0, self.radius], b + [0, 0, self.radius]

    # ------------------------------------------------------------------------------------- links
    def free(self, tips: np.ndarray) -> np.ndarray:
        """Whether the checked ball at each tip position stays off the model (1e-4 mm slack)."""
        r = self.diameter / 2
        _, d = closest_points(self.grid, np.asarray(tips, float).reshape(-1, 3) + [0, 0, r], r)
        return d >= r - 1e-4

    def free_line(self, a, b) -> bool:
        """Whether the straight feed move a → b keeps the checked ball off the model."""
        n = max(2, int(np.ceil(np.linalg.norm(np.subtract(b, a)) / LINK_SAMPLES_MM)) + 1)
        t = np.linspace(0, 1, n)[:, None]
        return bool(self.free(np.asarray(a, float) + t * (np.asarray(b, float) - a)).all())

    def retract_to(self, b) -> None:
        """Lift straight up to ``CLEAR_MM`` over the part's top, rapid over to ``b``, rapid down to
        ``CLEAR_MM`` above it and plunge to it."""
        if self.pos is None:
            self.rapid(x=b[0], y=b[1])
            self.rapid(z=SAFE_Z)
        else:
            self.rapid(z=max(TOP_Z, self.pos[2], b[2]) + CLEAR_MM)
            self.rapid(x=b[0], y=b[1])
            self.links["retract"] += 1
        self.rapid(z=b[2] + CLEAR_MM)
        self.cut(b, feed=self.plunge)

    def link(self, b, max_feed_link: float) -> None:
        """From the current point to ``b``: a straight feed move when short and free, else a retract."""
        a = self.pos
        if a is not None and np.linalg.norm(np.subtract(b, a)) <= max_feed_link and self.free_line(a, b):
            self.cut(b)
            self.links["feed"] += 1
        else:
            self.retract_to(b)
