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

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator


class WorkflowError(ValueError):
    """A workflow file that cannot be used; the message names the file and key."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Tool(_Strict):
    """One cutter. Axisymmetric envelope: ball, bull-nose (corner radius) or flat end mill."""

    t: Optional[int] = Field(None, ge=0, description="T number this entry applies to (list form)")
    type: Literal["ball", "bull", "flat"]
    diameter_mm: float = Field(gt=0, le=100)
    flutes: int = Field(2, ge=1, le=12)
    helix_deg: float = Field(30.0, ge=0, lt=80)
    stickout_mm: float = Field(40.0, gt=0)
    corner_radius_mm: Optional[float] = Field(None, ge=0)
    runout_um: float = Field(0.0, ge=0, le=200)
    profile: Optional[str] = None  # CSV contact_deg,error_um (claim 2 table)
    control_point: Literal["tip", "center"] = "tip"

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

    @property
    def corner_mm(self) -> float:
        if self.type == "ball":
            return self.diameter_mm / 2
        if self.type == "flat":
            return 0.0
        return float(self.corner_radius_mm)


class Material(_Strict):
    """Mechanistic cutting coefficients: cutting (N/mm²) and edge (N/mm) terms."""

    t: Optional[int] = Field(None, ge=0)
    name: str
    ktc: float = Field(ge=0)
    krc: float = Field(ge=0)
    kac: float = Field(ge=0)
    kte: float = Field(0.0, ge=0)
    kre: float = Field(0.0, ge=0)
    kae: float = Field(0.0, ge=0)


class Mode(_Strict):
    fn_hz: float = Field(gt=0)
    zeta: float = Field(gt=0, lt=1)
    k_n_per_um: float = Field(gt=0)


class Frf(_Strict):
    x: Optional[list[Mode]] = None
    y: Optional[list[Mode]] = None
    table: Optional[str] = None  # CSV: freq_hz, xx_re, xx_im, yy_re, yy_im (m/N → µm/N stated in header)

    @model_validator(mode="after")
    def _one_source(self):
        if self.table is None and (not self.x or not self.y):
            raise ValueError("give modes for both x and y, or a measured FRF table")
        return self


class Machine(_Strict):
    rapid_mm_min: float = Field(30000.0, gt=0)
    frf: Optional[Frf] = None


class Render(_Strict):
    backend: Literal["auto", "gl", "cpu"] = "auto"
    px_per_mm: float = Field(20.0, gt=0, le=1000)


class Prune(_Strict):
    min_contact_deg: float = Field(45.0, ge=0, le=90)


class Split(_Strict):
    """Seed para 0051: how NC motion becomes passes."""

    chord_tol_mm: float = Field(0.001, gt=0, le=1.0)  # arcs → chords, and merges, within this deviation
    max_pass_mm: float = Field(5.0, gt=0)             # longer cutting moves (> 0.5 % over) are split
    merge_max_mm: float = Field(0.5, ge=0)            # short moves merged into passes up to this long


class Correct(_Strict):
    """Corrected NC programs (seed 000 para 0084, seed 003 iteration)."""

    max_move_um: float = Field(50.0, gt=0)   # larger vertex moves are clipped and listed
    tol_um: float = Field(0.1, gt=0)         # iterate until the largest change is below this
    max_iter: int = Field(5, ge=1, le=50)
    # rounds 2…: largest fraction of the way a vertex goes from its last move to the move the new
    # prediction asks for (1 = the plain fixed point P = P0 − e(P)·n); a vertex whose change does
    # not shrink from round to round has its fraction halved (see stages.correct.correct_once)
    relax: float = Field(1.0, gt=0, le=1)
    # limit vertex moves so that the tool does not cut into the surface other passes generate
    # (a heavy corner pass moved sideways into the wall beside it; stages.correct.gouge_limit)
    gouge_limit: bool = True
    # normals of a vertex's two passes closer than this are one normal for the least-squares
    # refinement of its move (None: stages.correct.NORMAL_TOL_DEG, 2°). Realising two errors Δe apart
    # along normals θ apart takes Δe / sin θ sideways: on the sample's corner climb, its passes' normals
    # 2.95° apart in round 2 (+75.8, +87.0 µm) moved a vertex 159 µm towards the other wall
    normal_tol_deg: Optional[float] = Field(None, gt=0, lt=30)
    ln_normals: bool = False                 # also write Heidenhain-style LN blocks with normals
    comp_table: bool = False                 # also write a contact-angle compensation table
    # cut long straight cuts at the split stage's pass ends, and plain arcs at their chords, and
    # write the moved ends as inserted G1 lines (stages.nc_writer.via_blocks): the passes of one
    # long cut or arc can be corrected apart. Off by default: the corrected program then differs
    # from the source by more than coordinates
    via_points: bool = False
    # with via_points: a G1 line meeting another at a path corner (a turn over 30°) gets a via point
    # this far from the corner inside its pass (0: none; stages.nc_writer.via_blocks). The corner
    # vertex moves for both passes, and the line's body does not follow the other pass's move: on
    # the sample a wall climb's corner vertex moved 289 µm towards the other wall for the row
    # along it, which dragged the climb's body into that wall's rest material and more than
    # doubled its deflection on the virtual machine (−72 → −166 µm). The whole sample program with
    # via points: 39.1 / 34.5 % after one / three rounds against 39.8 / 37.7 % without
    corner_via_mm: float = Field(0.5, ge=0)


class Measurements(_Strict):
    """Measured points for the gap diagnosis (DESIGN §8): a CMM export or Parquet, with a column mapping."""

    file: str
    columns: dict[str, str] = {}                                 # our name (x_mm, nx, err_um, ...) → file's
    length_unit: Literal["mm", "um", "inch"] = "mm"
    deviation_unit: Optional[Literal["um", "mm", "inch"]] = None   # None: µm unless the header says
    noise_um: Optional[float] = Field(None, gt=0)                 # probe noise σ if known (else estimated)
    off_part_mm: float = Field(0.05, gt=0)                        # farther from every tool envelope = off the part


class Box(_Strict):
    box: list[float]

    @field_validator("box")
    @classmethod
    def _six(cls, v):
        if len(v) != 6 or not all(a < b for a, b in zip(v[:3], v[3:])):
            raise ValueError("box is [x0, y0, z0, x1, y1, z1] with x0<x1, y0<y1, z0<z1 (mm)")
        return v


class Workflow(_Strict):
    name: str
    programs: Union[str, list[str]]
    stock: Union[str, Box, None] = None
    nominal: Optional[str] = None
    tool: Union[Tool, list[Tool]]
    material: Union[Material, list[Material]]
    machine: Machine = Machine()
    render: Render = Render()
    prune: Prune = Prune()
    split: Split = Split()
    correct: Correct = Correct()
    measurements: Union[str, Measurements, None] = None
    output: str = "runs/out"
    until: Optional[str] = None  # stop after this stage (the CLI's --until overrides it)

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


def _pick(v, t, key):
    if not isinstance(v, list):
        return v
    if t is None:
        raise WorkflowError(f"{key}: the program calls no tool (no T word with M6) and the workflow lists several")
    for e in v:
        if e.t == t:
            return e
    raise WorkflowError(f"{key}: no entry for T{t} (the workflow has T{', T'.join(str(e.t) for e in v)})")


def _format_error(path: Path, err: ValidationError) -> str:
    """One line per problem, with the key path as the user wrote it (``tool.diameter_mm``).

    Pydantic reports every branch of a union (``tool`` may be one tool or a list); the branch that
    only says "wrong container type" is dropped when another branch says something specific.
    """
    items = []
    for e in err.errors():
        loc = ".".join(str(p) for p in e["loc"] if not (isinstance(p, str) and ("[" in p or "(" in p)))
        msg = "unknown key" if e["type"] == "extra_forbidden" else e["msg"]
        items.append((loc or "<top>", msg, e["type"], e.get("input")))
    specific = {loc for loc, _, typ, _ in items if not typ.endswith(("_type", "union_tag_invalid"))}
    lines, seen = [f"{path}: invalid workflow"], set()
    for loc, msg, typ, inp in items:
        generic = typ.endswith("_type")
        if generic and any(s == loc or s.startswith(loc + ".") for s in specific):
            continue
        if (loc, msg) not in seen:
            seen.add((loc, msg))
            lines.append(f"  {loc}: {msg} (got {inp!r})")
    return "\n".join(lines)


def load_workflow(path: str | Path) -> tuple[Workflow, Path]:
    """Read and validate a workflow file; return it and the base directory for relative paths.

    The base directory is the one holding ``workflows/`` (the project root) when the file sits in
    a ``workflows`` folder, else the file's own directory.
    """
    path = Path(path)
    if not path.is_file():
        raise WorkflowError(f"{path}: no such workflow file")
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise WorkflowError(f"{path}: not valid YAML: {e}") from None
    if not isinstance(raw, dict):
        raise WorkflowError(f"{path}: a workflow is a mapping of keys (DESIGN §4), got {type(raw).__name__}")
    try:
        wf = Workflow.model_validate(raw)
    except ValidationError as e:
        raise WorkflowError(_format_error(path, e)) from None
    base = path.resolve().parent
    if base.name == "workflows":
        base = base.parent
    return wf, base


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
