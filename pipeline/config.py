"""Workflow file (DESIGN §4): load, validate, and hand stages plain dicts.

Every key is declared; an unknown key or a bad value is an error that names the file and the key
path (``tool.diameter_mm``), so a typo in a nightly workflow fails loudly before any work starts.
Relative paths are resolved against the workflow file's directory's project root (the directory
the workflow is run from is irrelevant: a workflow always means the same files).
"""
from __future__ import annotations

import glob
from pathlib import Path
from typing import Literal, Optional, Union

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from pipeline.config_errors import read_yaml
from stages.geometry.cutter import DEFAULT_FLUTES, DEFAULT_HELIX_DEG, DEFAULT_STICKOUT_MM


class WorkflowError(ValueError):
    """A workflow file that cannot be used; the message names the file and key."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Tool(_Strict):
    """One cutter: ball, bull-nose or flat end mill (one axisymmetric shape, DESIGN §7)."""

    t: Optional[int] = Field(None, ge=0, description="T number this entry applies to (when `tool` is a list)")
    type: Literal["ball", "bull", "flat"] = Field(description="cutter shape")
    diameter_mm: float = Field(gt=0, le=100, description="cutting diameter, mm")
    flutes: int = Field(DEFAULT_FLUTES, ge=1, le=12, description="number of cutting edges")
    helix_deg: float = Field(DEFAULT_HELIX_DEG, ge=0, lt=80, description="helix angle of the edges, degrees")
    stickout_mm: float = Field(DEFAULT_STICKOUT_MM, gt=0, description="length from the tip to the holder, mm")
    corner_radius_mm: Optional[float] = Field(None, ge=0, description="corner radius of a bull-nose tool, mm "
                                              "(ball: diameter/2, flat: 0; leave it out for those)")
    runout_um: float = Field(0.0, ge=0, le=200, description="axis eccentricity towards flute 0, µm")
    profile: Optional[str] = Field(None, description="measured contour error table (claim 2): CSV "
                                   "`contact_deg,error_um`, + = tool smaller than nominal")
    control_point: Literal["tip", "center"] = Field("tip", description="what the NC coordinates are: the tool "
                                                    "tip (CAM's usual output) or the corner's centre")

    @model_validator(mode="after")
    def _corner(self):
        r = self.diameter_mm / 2
        if self.type == "bull":
            if self.corner_radius_mm is None or not (0 < self.corner_radius_mm < r):
                raise ValueError("corner_radius_mm must be given and 0 < corner_radius_mm < diameter_mm/2 for a bull-nose tool")
        elif self.type == "ball" and self.corner_radius_mm not in (None, r):
            raise ValueError("corner_radius_mm of a ball tool is diameter_mm/2 (leave it out)")
        elif self.type == "flat" and self.corner_radius_mm not in (None, 0):
            raise ValueError("corner_radius_mm of a flat tool is 0 (leave it out)")
        if self.control_point == "center" and self.type == "flat":
            raise ValueError("control_point: center only makes sense for tools with a corner radius")
        return self


class Material(_Strict):
    """Mechanistic cutting coefficients (Altintas): cutting terms N/mm², edge terms N/mm."""

    t: Optional[int] = Field(None, ge=0, description="T number this entry applies to (when `material` is a list)")
    name: str = Field(description="material name, for the reports")
    ktc: float = Field(ge=0, description="tangential cutting coefficient, N/mm²")
    krc: float = Field(ge=0, description="radial cutting coefficient, N/mm²")
    kac: float = Field(ge=0, description="axial cutting coefficient, N/mm²")
    kte: float = Field(0.0, ge=0, description="tangential edge coefficient, N/mm")
    kre: float = Field(0.0, ge=0, description="radial edge coefficient, N/mm")
    kae: float = Field(0.0, ge=0, description="axial edge coefficient, N/mm")


class Mode(_Strict):
    """One vibration mode of the tool-tip compliance."""

    fn_hz: float = Field(gt=0, description="natural frequency, Hz")
    zeta: float = Field(gt=0, lt=1, description="damping ratio")
    k_n_per_um: float = Field(gt=0, description="modal stiffness, N/µm")


class Frf(_Strict):
    """Tool-tip compliance: modes for x and y, or a measured FRF table."""

    x: Optional[list[Mode]] = Field(None, description="modes along x")
    y: Optional[list[Mode]] = Field(None, description="modes along y")
    table: Optional[str] = Field(None, description="measured FRF: CSV `freq_hz,xx_re,xx_im,yy_re,yy_im` in µm/N")

    @model_validator(mode="after")
    def _one_source(self):
        if self.table is None and (not self.x or not self.y):
            raise ValueError("give modes for both x and y, or a measured FRF table")
        return self


class Machine(_Strict):
    """The machine tool."""

    rapid_mm_min: float = Field(30000.0, gt=0, description="rapid traverse rate: G0 moves are timed at it, mm/min")
    frf: Optional[Frf] = Field(None, description="tool-tip compliance (needed from `deflection` on)")


class Render(_Strict):
    """The depth-test renders (seed 000)."""

    backend: Literal["auto", "gl", "cpu"] = Field("auto", description="gl (headless EGL; llvmpipe without a GPU), "
                                                  "cpu (numpy z-buffer), auto (gl if an EGL context opens)")
    px_per_mm: float = Field(20.0, gt=0, le=1000, description="render resolution, pixels per mm")
    passes_per_task: int = Field(4000, ge=1, description="a program's scan is split into tasks of about this "
                                 "many passes (its tiles dealt out; at most 16 tasks)")


class Prune(_Strict):
    """Claim 8: passes that cannot matter are not predicted."""

    min_contact_deg: float = Field(45.0, ge=0, le=90, description="predict a pass only where its surface's largest "
                                   "contact angle reaches this, degrees")


class Split(_Strict):
    """How NC motion becomes passes (seed para 0051)."""

    chord_tol_mm: float = Field(0.001, gt=0, le=1.0, description="arcs become chords, and short moves merge, "
                                "within this deviation, mm")
    max_pass_mm: float = Field(5.0, gt=0, description="cutting moves longer than this (by 0.5 %) are cut into "
                               "equal pieces, mm")
    merge_max_mm: float = Field(0.5, ge=0, description="runs of short moves merge into passes up to this long, mm")


class Correct(_Strict):
    """Corrected NC programs (seed 000 para 0084; rounds of seed 003)."""

    max_move_um: float = Field(50.0, gt=0, description="a vertex moves at most this far in all; larger moves are "
                               "clipped and flagged, µm")
    tol_um: float = Field(0.1, gt=0, description="rounds stop when no vertex changes by this much, µm")
    max_iter: int = Field(5, ge=1, le=50, description="most rounds of predict → correct")
    relax: float = Field(1.0, gt=0, le=1, description="largest fraction of its step a vertex takes in rounds 2…; "
                         "a vertex whose change does not shrink takes half as much, again and again")
    gouge_limit: bool = Field(True, description="keep the moved tool off the surfaces other passes generate")
    normal_tol_deg: Optional[float] = Field(None, gt=0, lt=30, description="normals of a vertex's two passes closer "
                                            "than this are one normal (default 2°), degrees")
    ln_normals: bool = Field(False, description="also write Heidenhain-style LN blocks with surface normals")
    comp_table: bool = Field(False, description="also write a contact-angle compensation table (.3dtc.csv)")
    via_points: bool = Field(False, description="cut long straight moves and arcs at the pass ends and write the "
                             "moved ends as inserted G1 lines (the program then has more lines than the source)")
    corner_via_mm: float = Field(0.5, ge=0, description="with via_points: a via point this far from each path "
                                 "corner of a G1 line (0: none), mm")


class Feed(_Strict):
    """Scheduled feeds (stage ``feed``): where a path offset cannot cancel a deflection, lower the feed."""

    max_deflection_um: float = Field(gt=0, description="largest predicted tool deflection over a revolution, µm")
    max_chip_mm: float = Field(gt=0, description="largest feed per tooth (the thickest chip), mm")
    max_mm_min: float = Field(gt=0, description="no feed above this (passes that cut nothing get it), mm/min")
    min_mm_min: float = Field(gt=0, description="no feed below this; a pass over the limit even there is "
                              "flagged overloaded, mm/min")
    max_change: float = Field(0.3, gt=0, description="neighbouring passes' feeds differ by at most this "
                              "fraction (feeds are lowered to meet it)")

    @model_validator(mode="after")
    def _order(self):
        if self.min_mm_min > self.max_mm_min:
            raise ValueError(f"min_mm_min {self.min_mm_min:g} is above max_mm_min {self.max_mm_min:g}")
        return self


class Drift(_Strict):
    """Thermal drift compensation (stage ``correct``): vertices move against the drift a fitted model predicts."""

    model: str = Field(description="drift model written by `pipeline thermal-fit` (drift.yaml)")
    start_s: float = Field(0.0, ge=0, description="time on the model's clock (since the machine's cold start) "
                           "at which the job's first program starts, s; later programs follow the earlier "
                           "ones' machining times")


class Warnings(_Strict):
    """Which passes are listed as ones a correction cannot help (table ``warnings``)."""

    allowance_mm: Optional[float] = Field(None, gt=0, description="the finishing allowance the programs are "
                                          "meant to meet (default: each program's median stock along the normal), mm")
    rest_factor: float = Field(3.0, gt=1, description="stock along the normal over this many allowances is "
                               "rest material")


class Measurements(_Strict):
    """Measured points for the gap diagnosis (DESIGN §8): a CMM export or Parquet, with a column mapping."""

    file: str = Field(description="CSV (x y z i j k deviation, like a CMM export) or Parquet of measured points")
    columns: dict[str, str] = Field({}, description="our column name (x_mm, nx, err_um, …) → the file's")
    length_unit: Literal["mm", "um", "inch"] = Field("mm", description="unit of the coordinates in the file")
    deviation_unit: Optional[Literal["um", "mm", "inch"]] = Field(None, description="unit of the deviations "
                                                                  "(default: µm unless the header says)")
    noise_um: Optional[float] = Field(None, gt=0, description="probe noise σ if known (else estimated), µm")
    off_part_mm: float = Field(0.05, gt=0, description="points farther than this from every tool envelope are "
                               "off the part, mm")


class Box(_Strict):
    """A box-shaped stock."""

    box: list[float] = Field(description="[x0, y0, z0, x1, y1, z1], mm")

    @field_validator("box")
    @classmethod
    def _six(cls, v):
        if len(v) != 6 or not all(a < b for a, b in zip(v[:3], v[3:])):
            raise ValueError("box is [x0, y0, z0, x1, y1, z1] with x0<x1, y0<y1, z0<z1 (mm)")
        return v


class Workflow(_Strict):
    """A workflow file (DESIGN §4)."""

    job: Literal["mould"] = Field("mould", description="what `pipeline run` does (pipeline/jobs.py): `mould` "
                                  "predicts and corrects NC programs; other jobs have their own keys")
    name: str = Field(description="job name, for reports")
    programs: Union[str, list[str]] = Field(description="NC programs: a glob, or an ordered list of files or globs")
    stock: Union[str, Box, None] = Field(None, description="the surface before the programs: a mesh (STL/OBJ/PLY) "
                                         "or {box: [...]}")
    nominal: Optional[str] = Field(None, description="the design model (mesh), for the generating points and reports")
    tool: Union[Tool, list[Tool]] = Field(description="the cutter, or a list keyed by T number (`t`)")
    material: Union[Material, list[Material]] = Field(description="cutting coefficients, or a list keyed by T number")
    machine: Machine = Field(Machine(), description="the machine tool")
    render: Render = Field(Render(), description="the renders")
    prune: Prune = Field(Prune(), description="which passes are predicted")
    split: Split = Field(Split(), description="how NC motion becomes passes")
    correct: Correct = Field(Correct(), description="corrected programs")
    feed: Optional[Feed] = Field(None, description="scheduled feeds (off without this section)")
    drift: Optional[Drift] = Field(None, description="thermal drift compensation (off without this section)")
    warnings: Warnings = Field(Warnings(), description="passes a correction cannot help")
    measurements: Union[str, Measurements, None] = Field(None, description="measured points for the gap diagnosis "
                                                         "(a file, or a mapping with `file`)")
    output: str = Field("runs/out", description="output directory, relative to the project")
    until: Optional[str] = Field(None, description="stop after this stage (the CLI's --until overrides it)")

    @model_validator(mode="after")
    def _lists_keyed(self):
        for key in ("tool", "material"):
            v = getattr(self, key)
            if isinstance(v, list):
                ts = [e.t for e in v]
                if any(t is None for t in ts):
                    raise ValueError(f"{key}: every entry of a list needs its T number as 't'")
                if len(set(ts)) != len(ts):
                    raise ValueError(f"{key}: T numbers repeat: {ts}")
        return self

    # --- lookups -----------------------------------------------------------------------------
    def tool_for(self, t: Optional[int]) -> Tool:
        return _pick(self.tool, t, "tool")

    def material_for(self, t: Optional[int]) -> Material:
        return _pick(self.material, t, "material")

    def value(self, dotted: str):
        """One workflow value by its dotted key (``correct.max_iter``)."""
        v = self
        for part in dotted.split("."):
            v = getattr(v, part)
        return v

    def params(self, names, tool_t: Optional[int], base: Path) -> dict:
        """The values of the workflow keys ``names`` as plain dicts, for one program.

        ``tool`` and ``material`` are the program's entry (by its T number ``tool_t``); a dotted
        name (``machine.rapid_mm_min``) takes one sub-key, so a stage's cache key does not change
        when unrelated values of the same section do; file references (``tool.profile``,
        ``machine.frf.table``) become absolute paths.
        """
        out: dict = {}
        for name in names:
            head, _, sub = name.partition(".")
            if head == "tool":
                val = self.tool_for(tool_t).model_dump()
            elif head == "material":
                val = self.material_for(tool_t).model_dump()
            else:
                val = getattr(self, head)
                val = val.model_dump() if hasattr(val, "model_dump") else val
            val = _absolute_files(val, base)
            if sub and val is not None:
                out.setdefault(head, {})[sub] = val[sub]
            else:
                out[head] = val
        return out


# keys whose string values name files (relative to the project); their content enters cache keys
FILE_KEYS = ("profile", "table", "model")


def _absolute_files(val, base: Path):
    if isinstance(val, dict):
        out = {}
        for k, v in val.items():
            if k in FILE_KEYS and isinstance(v, str):
                p = resolve(base, v)
                if not p.is_file():
                    raise WorkflowError(f"{k}: file {p} does not exist")
                out[k] = str(p.resolve())
            else:
                out[k] = _absolute_files(v, base)
        return out
    return val


def _pick(v, t, key):
    if not isinstance(v, list):
        return v
    if t is None:
        raise WorkflowError(f"{key}: the program calls no tool (no T word with M6) and the workflow lists several")
    for e in v:
        if e.t == t:
            return e
    raise WorkflowError(f"{key}: no entry for T{t} (the workflow has T{', T'.join(str(e.t) for e in v)})")


def load_workflow(path: str | Path, overlays=()) -> tuple[Workflow, Path]:
    """Read and validate a workflow file; return it and the base directory for relative paths.

    The base directory is the one holding ``workflows/`` (the project root) when the file sits in
    a ``workflows`` folder, else the file's own directory. ``overlays`` (files of workflow keys,
    ``pipeline.overlay``) are merged over the file in order before validation; a bad value they
    bring in is reported against the overlay that gave it.
    """
    return load_model(path, Workflow, overlays)


def load_model(path: str | Path, model, overlays=(), file_keys=FILE_KEYS, problems=None):
    """:func:`load_workflow` for the workflow model ``model`` of any job (``pipeline.jobs``).

    ``file_keys`` are the keys whose values in an overlay are paths relative to it; ``problems``,
    given the validated workflow, lists ``(key path, message, value)`` of what no single field can
    check (one key against another), reported like a field's error with the file, line and key.
    """
    path = Path(path)
    raw, text = read_yaml(path, "workflow", WorkflowError)
    if not isinstance(raw, dict):
        raise WorkflowError(f"{path}: a workflow is a mapping of keys (DESIGN §4), got {type(raw).__name__}")
    read = []
    for ov in overlays:
        from pipeline.overlay import OverlayError, apply_overlay, read_overlay
        try:
            over, ov_text = read_overlay(ov, model, file_keys)
            raw = apply_overlay(raw, over, ov)
        except OverlayError as e:
            raise WorkflowError(str(e)) from None
        read.append((Path(ov), over, ov_text))
    try:
        wf = model.model_validate(raw)
        found = problems(wf) if problems else []
        if found:
            raise ValidationError.from_exception_data(model.__name__, [
                {"type": "value_error", "loc": loc, "input": val, "ctx": {"error": ValueError(msg)}}
                for loc, msg, val in found])
    except ValidationError as e:
        from pipeline.config_errors import format_error
        where, where_text = _blame(path, text, read, e)
        raise WorkflowError(format_error(where, e, where_text, model)) from None
    base = path.resolve().parent
    if base.name == "workflows":
        base = base.parent
    return wf, base


def _blame(path: Path, text: str, overlays: list, err: ValidationError) -> tuple[Path, str]:
    """(file, text) to report a validation error against: the last overlay that sets the first
    bad key (its top-level section), else the workflow file."""
    head = next((str(e["loc"][0]) for e in err.errors() if e["loc"]), None)
    for ov, over, ov_text in reversed(overlays):
        if head in over:
            return ov, ov_text
    return path, text


def resolve(base: Path, p: str) -> Path:
    q = Path(p)
    return q if q.is_absolute() else base / q


def program_paths(wf: Workflow, base: Path) -> list[Path]:
    pats = [wf.programs] if isinstance(wf.programs, str) else list(wf.programs)
    out: list[Path] = []
    for pat in pats:
        hits = sorted(glob.glob(str(resolve(base, pat)), recursive=True))
        if not hits:
            raise WorkflowError(f"programs: pattern {pat!r} matches no file (relative to {base})")
        out.extend(Path(h) for h in hits if Path(h).is_file())
    # one program listed twice by overlapping globs is processed once
    seen, uniq = set(), []
    for p in out:
        if p.resolve() not in seen:
            seen.add(p.resolve())
            uniq.append(p)
    return uniq
