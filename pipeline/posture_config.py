"""The posture job's workflow (``job: posture``, issue 61, seed 001): keys, checks and loading.

Errors name the file, the YAML line and the key (:func:`pipeline.config_errors.format_error`), as
the mould workflow's do; overlays (``--overlay``) merge over it the same way.
"""
from __future__ import annotations

from pathlib import Path
from typing import Literal, Optional, Union

from pydantic import Field, field_validator, model_validator

from pipeline.config import _Strict, load_model, resolve

# keys whose strings name files, relative to the project (the folder holding workflows/)
FILE_KEYS = ("part", "table")
LIMITS = {"rx_deg": (-90.0, 90.0), "ry_deg": (-90.0, 90.0), "tilt_deg": (0.0, 90.0), "azimuth_deg": (-360.0, 360.0)}
MAX_ORIENTATIONS = 100_000


class Orientations(_Strict):
    """The orientation grid: each range is `[first, last, step]` in degrees (see docs/posture.md)."""

    kind: Literal["rxry", "polar"] = Field("rxry", description="`rxry`: tilt about X then about Y (the seed's "
                                           "Rx, Ry); `polar`: tilt from +Z and azimuth from +X")
    rx_deg: Optional[list[float]] = Field([-90.0, 90.0, 5.0], description="rxry: tilt about X, [first, last, step] "
                                          "within −90…90°")
    ry_deg: Optional[list[float]] = Field([-90.0, 90.0, 5.0], description="rxry: then tilt about Y, [first, last, "
                                          "step] within −90…90°")
    tilt_deg: Optional[list[float]] = Field(None, description="polar: tilt from +Z, [first, last, step] within 0…90°")
    azimuth_deg: Optional[list[float]] = Field(None, description="polar: azimuth from +X towards +Y, [first, last, "
                                               "step] within −360…360°")

    @field_validator("rx_deg", "ry_deg", "tilt_deg", "azimuth_deg")
    @classmethod
    def _range(cls, v, info):
        if v is None:
            return v
        lo_ok, hi_ok = LIMITS[info.field_name]
        if len(v) != 3:
            raise ValueError("a range is [first, last, step] in degrees")
        first, last, step = v
        if not (lo_ok <= first <= last <= hi_ok):
            raise ValueError(f"out of range: need {lo_ok:g} ≤ first ≤ last ≤ {hi_ok:g} degrees")
        if step <= 0:
            raise ValueError("the step must be positive")
        return v

    @model_validator(mode="after")
    def _kind(self):
        if self.kind == "polar" and (self.tilt_deg is None or self.azimuth_deg is None):
            raise ValueError("kind polar needs tilt_deg and azimuth_deg")
        if self.kind == "rxry" and (self.tilt_deg is not None or self.azimuth_deg is not None):
            raise ValueError("tilt_deg and azimuth_deg are for kind: polar")
        ranges = self.ranges()
        n = 1
        for first, last, step in ranges:
            n *= int((last - first) / step + 1e-9) + 1
        if n > MAX_ORIENTATIONS:
            raise ValueError(f"{n} orientations; at most {MAX_ORIENTATIONS} (use a larger step)")
        return self

    def ranges(self):
        return (self.rx_deg, self.ry_deg) if self.kind == "rxry" else (self.tilt_deg, self.azimuth_deg)


class Efficiency(_Strict):
    """λ from cutting tests: efficiency per edge angle ψ (0° the tip, 90° the equator), linear in between."""

    table: Optional[str] = Field(None, description="CSV of `edge_deg,efficiency` rows (a header line is allowed)")
    points: Optional[list[tuple[float, float]]] = Field(None, description="the same inline: [[edge_deg, "
                                                        "efficiency], …], covering 0…90°")

    @field_validator("points")
    @classmethod
    def _covers(cls, v):
        if v is None:
            return v
        from stages import InputError
        from stages.posture.efficiency import Table
        try:
            Table([a for a, _ in v], [e for _, e in v], "points")
        except InputError as e:
            raise ValueError(str(e).removeprefix("points: ")) from None
        return v

    @model_validator(mode="after")
    def _one(self):
        if (self.table is None) == (self.points is None):
            raise ValueError("give either table (a CSV file) or points")
        return self


class PostureRender(_Strict):
    """The z-maps along the tool axes."""

    backend: Literal["auto", "gl", "cpu"] = Field("auto", description="gl (headless EGL; llvmpipe without a GPU), "
                                                  "cpu (numpy z-buffer), auto (gl if an EGL context opens)")
    cell_mm: float = Field(0.4, gt=0, le=10, description="z-map cell, mm")
    tile_px: int = Field(2048, ge=64, le=8192, description="largest z-map tile side, pixels (bounds the memory)")


class Cover(_Strict):
    """The greedy union of postures (seed §6)."""

    max_postures: int = Field(20, ge=1, le=1000, description="choose at most this many postures")
    tolerance: float = Field(0.0, ge=0, lt=1, description="stop when the union is within this fraction of the "
                             "upper bound")


class PostureWorkflow(_Strict):
    """A posture workflow (`job: posture`): evaluate fixed tool orientations of a ball end mill on a part."""

    job: Literal["posture"] = Field(description="`posture`")
    name: str = Field(description="job name: the tables' file name and the report's title")
    part: str = Field(description="the required surface: a mesh (STL/OBJ/PLY), normals out of the material, mm")
    ball_radius_mm: float = Field(gt=0, le=50, description="radius of the ball end mill (its shank: the same radius)")
    orientations: Orientations = Field(Orientations(), description="the orientation grid")
    alpha: float = Field(0.5, ge=0, le=1, description="E = (1 − alpha)·Φ1 + alpha·Φ2 (0: efficiency only, 1: area only)")
    efficiency: Union[Literal["sin2psi"], Efficiency] = Field("sin2psi", description="λ of the edge point in "
                                                              "contact: `sin2psi` (the seed's) or a table")
    micro_region_mm: float = Field(1.0, gt=0, le=100, description="triangles are cut until no edge is longer: the "
                                   "micro-regions, mm")
    render: PostureRender = Field(PostureRender(), description="the z-maps")
    cover: Cover = Field(Cover(), description="the greedy union of postures")
    output: str = Field("runs/posture", description="output directory, relative to the project")


def load_posture(path, overlays=()) -> tuple[PostureWorkflow, Path]:
    """Read and validate a posture workflow (and overlays); return it and the project folder."""
    return load_model(path, PostureWorkflow, overlays, file_keys=FILE_KEYS)


def key_line(path, text_keys: tuple) -> str:
    """``file:line`` of a key path in a workflow file (``file`` alone when the key is not found)."""
    from pipeline.config_errors import _yaml_lines
    path = Path(path)
    line = _yaml_lines(path.read_text()).get(tuple(text_keys)) if path.is_file() else None
    return f"{path}:{line}" if line else str(path)


def part_path(wf: PostureWorkflow, base: Path) -> Path:
    return resolve(base, wf.part)
