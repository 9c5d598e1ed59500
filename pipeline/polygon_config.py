"""The polygon job's workflow (``job: polygon``, seed 004): keys, validation, the set-up it describes.

Errors name the file, the YAML line and the key (``pipeline.config_errors.format_error``); the
checks across keys (a cutter that never reaches the bar) are reported against the key to change.
"""
from __future__ import annotations

from pathlib import Path
from typing import Literal, Optional

from pydantic import Field, field_validator

from pipeline.config import _Strict, load_model, resolve
from stages.polygon.cut import Grid, make_grid
from stages.polygon.kinematics import Setup

# cells of the height map at most (rows × columns): beyond, a run takes many minutes
MAX_CELLS = 2_000_000_000


class PolygonWorkpiece(_Strict):
    """The bar before cutting, turning about its axis (ω1)."""

    radius_mm: float = Field(gt=0, le=500, description="radius of the round bar, mm")
    length_mm: float = Field(gt=0, le=2000, description="machined length along the axis, mm (cut over its whole length)")
    rpm: float = Field(description="ω1, rev/min, signed: + counter-clockwise seen from +z (the feed direction)")

    @field_validator("rpm")
    def _turning(cls, v):
        if v == 0:
            raise ValueError("the workpiece must turn: the speed ratio ω2/ω1 is undefined for ω1 = 0")
        return v


class PolygonCutter(_Strict):
    """The fly cutter: edges on a circle of radius R about an axis parallel to the bar's, ε away (ω2)."""

    rpm: float = Field(description="ω2, rev/min, signed as ω1 (opposite signs: opposite directions); "
                       "ω2/ω1 is the speed ratio")
    radius_mm: float = Field(gt=0, description="R, radius of the edge tips about the cutter axis, mm")
    eccentricity_mm: float = Field(ge=0, description="ε, distance between the bar's axis and the cutter's, mm")
    edges: int = Field(1, ge=1, le=24, description="number of edges")
    lag_deg: Optional[list[float]] = Field(None, description="lag of each edge behind the first, degrees of "
                                           "cutter rotation (the seed's φ; default: evenly spaced, 360·i/edges)")
    edge_width_mm: float = Field(gt=0, description="the edge's extent along the axis, mm (the seed's "
                                 "edge thickness; the feed per cutter revolution should be smaller)")

    @field_validator("rpm")
    def _ratio(cls, v):
        if v == 0:
            raise ValueError("the cutter must turn: a speed ratio ω2/ω1 of 0 cuts nothing")
        return v


class PolygonFeed(_Strict):
    """Axial feed of the cutter along the bar."""

    mm: float = Field(gt=0, description="axial advance per revolution, mm")
    per: Literal["tool", "workpiece"] = Field(description="the revolution `mm` is per: of the cutter (`tool`; "
                                              "the seed's machining times fit this) or of the bar (`workpiece`)")


class PolygonResolution(_Strict):
    """The height map r(θ, z)."""

    dz_mm: float = Field(0.02, gt=0, description="axial step, mm (rounded so the rows end on the length)")
    dtheta_deg: float = Field(0.2, gt=0, le=5, description="angular step, degrees (rounded to close the circle)")


class PolygonSections(_Strict):
    """The cross-sections written to the table and drawn."""

    count: int = Field(5, ge=1, le=50, description="sections, evenly spaced from z = 0 to the length")
    prominence_mm: float = Field(0.005, gt=0, description="two faces are told apart where the ridge between "
                                 "them rises this much above both, mm")


class PolygonStl(_Strict):
    """The solid written as STL: the height map thinned to these steps."""

    dz_mm: float = Field(0.1, gt=0, description="axial step of the mesh, mm (at least the map's)")
    dtheta_deg: float = Field(1.0, gt=0, description="angular step of the mesh, degrees (at least the map's)")


class PolygonWorkflow(_Strict):
    """A polygon-cutting job (`job: polygon`, seed 004): the machined bar, its sections and twist."""

    job: Literal["polygon"] = Field(description="`polygon`: this job (pipeline/jobs.py)")
    name: str = Field(description="job name: the table file, the STL and the report are named after it")
    output: str = Field("runs/polygon", description="output directory, relative to the project")
    workpiece: PolygonWorkpiece = Field(description="the bar")
    cutter: PolygonCutter = Field(description="the cutter")
    feed: PolygonFeed = Field(description="the axial feed")
    resolution: PolygonResolution = Field(PolygonResolution(), description="the height map's steps")
    sections: PolygonSections = Field(PolygonSections(), description="cross-sections")
    stl: PolygonStl = Field(PolygonStl(), description="the STL's steps")

    def lags_deg(self) -> tuple:
        c = self.cutter
        return tuple(c.lag_deg) if c.lag_deg is not None else tuple(360.0 * i / c.edges for i in range(c.edges))

    def setup(self) -> Setup:
        w, c = self.workpiece, self.cutter
        return Setup(w.radius_mm, w.length_mm, w.rpm, c.rpm, c.radius_mm, c.eccentricity_mm,
                     self.feed.mm, self.feed.per, self.lags_deg(), c.edge_width_mm)

    def grid(self) -> Grid:
        return make_grid(self.workpiece.length_mm, self.resolution.dz_mm, self.resolution.dtheta_deg)


def _problems(wf: PolygonWorkflow) -> list[tuple[tuple, str, object]]:
    """Checks across keys: (key path, what is wrong, the value)."""
    w, c = wf.workpiece, wf.cutter
    out = []
    if c.eccentricity_mm >= w.radius_mm + c.radius_mm:
        out.append((("cutter", "eccentricity_mm"), f"the edges never reach the bar: ε ≥ workpiece radius + R "
                    f"({w.radius_mm:g} + {c.radius_mm:g} mm)", c.eccentricity_mm))
    if c.radius_mm >= w.radius_mm + c.eccentricity_mm:
        out.append((("cutter", "radius_mm"), f"the edges pass round the bar without touching it: R ≥ workpiece "
                    f"radius + ε ({w.radius_mm:g} + {c.eccentricity_mm:g} mm)", c.radius_mm))
    if c.lag_deg is not None and len(c.lag_deg) != c.edges:
        out.append((("cutter", "lag_deg"), f"one lag angle per edge: {c.edges} edges, {len(c.lag_deg)} angles",
                    c.lag_deg))
    g = wf.grid()
    if g.nz * g.ntheta > MAX_CELLS:
        out.append((("resolution", "dz_mm"), f"{g.nz} × {g.ntheta} cells is over {MAX_CELLS:.0e}: coarsen "
                    "the steps", wf.resolution.dz_mm))
    return out


def load_polygon(path, overlays=()) -> tuple[PolygonWorkflow, Path]:
    """Read and validate a polygon workflow (overlays merged over it first, ``pipeline.overlay``).

    Returns the workflow and the project folder its relative paths are relative to.
    """
    return load_model(path, PolygonWorkflow, overlays, file_keys=(), problems=_problems)


def output_dir(wf: PolygonWorkflow, base: Path, out=None) -> Path:
    return Path(out) if out else resolve(base, wf.output)
