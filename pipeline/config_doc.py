"""``docs/config.md``: every workflow key with its type, default and meaning, from the config models.

    python3 -m pipeline.config_doc > docs/config.md

``tests/test_docs.py`` regenerates it and compares it with the committed file, so it never drifts.
"""
from __future__ import annotations

import typing

from pydantic import BaseModel
from pydantic.fields import PydanticUndefined

from pipeline.config import Workflow
from pipeline.config_errors import models_in
from pipeline.polygon_config import PolygonWorkflow
from pipeline.posture_config import PostureWorkflow

HEADER = """# Workflow keys

Generated from the configuration models (`pipeline/config.py`) by `python3 -m pipeline.config_doc`;
a test checks this file against them. A workflow is a YAML file (DESIGN §4); an unknown key or a
bad value is an error naming the file, the line and the key. Relative paths are relative to the
project (the folder holding `workflows/`). `tool` and `material` may be lists keyed by T number `t`.
"""

OVERLAYS = """
## Overlays (`pipeline run WORKFLOW --overlay FILE`)

An overlay is a YAML file of workflow keys, in the workflow's shape, merged over the workflow before
it is validated (`pipeline diagnose` writes one: `gap/model_update.yaml`). `--overlay` may be given
several times; later overlays win. `pipeline status` takes the same option.

- Mappings merge key by key, recursively; any other value (a number, a string, a list, `null`)
  replaces the workflow's (`drift: null` turns drift compensation off; a `machine.frf.x` list replaces
  the workflow's modes).
- `tool` / `material` as a list keyed by `t` in the workflow: an overlay mapping with a `t` merges into
  the entry with that `t` (a `t` the workflow lacks adds an entry, which must then be complete); a
  mapping without `t` merges into every entry; an overlay list merges entry by entry by `t`. Where the
  workflow has one mapping, an overlay mapping merges into it and an overlay list replaces it.
- Relative paths in an overlay (`tool.profile`, `machine.frf.table`, `drift.model`, and the top-level
  `programs`, `stock`, `nominal`, `measurements`, `output`) are relative to the overlay file's folder.
- An unknown key is an error naming the overlay file, its line and the key; a bad value an overlay
  brings in is reported against the overlay.
- The merged values enter the cache keys as workflow values do: a stage recomputes when a key it
  declares changed (every stage that declares `tool` for a `tool.runout_um` overlay; `parse` not).
  `run.json` `overlay` lists the files and the report names them.
"""


def _type_name(annotation) -> str:
    origin = typing.get_origin(annotation)
    if origin is typing.Union:
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        return " or ".join(_type_name(a) for a in args) + (", optional" if len(args) < len(typing.get_args(annotation)) else "")
    if origin is typing.Literal:
        return " \\| ".join(f"`{a}`" for a in typing.get_args(annotation))
    if origin in (list, tuple):
        return "list of " + ", ".join(_type_name(a) for a in typing.get_args(annotation))
    if origin is dict:
        return "mapping"
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return f"[{annotation.__name__.lower()}](#{annotation.__name__.lower()})"
    return getattr(annotation, "__name__", str(annotation))


def _default(field) -> str:
    if field.default is PydanticUndefined:
        return "required"
    if isinstance(field.default, BaseModel):
        return "see below"
    return "`null`" if field.default is None else f"`{field.default}`"


POLYGON = """
# Polygon workflow (`job: polygon`)

A workflow with `job: polygon` machines a round bar by polygon (2-axis) cutting (seed 004,
`docs/polygon.md`): `pipeline run` takes these keys instead of the ones above (overlays work the
same way).
"""


POSTURE = """
# Posture workflows (`job: posture`)

Generated from `pipeline/posture_config.py`. A workflow with `job: posture` evaluates fixed tool
orientations of a ball end mill on a part (seed 001; the method, the angles and the outputs are in
`docs/posture.md`). Its keys are checked like the mould workflow's; `--overlay` merges the same way.
"""


def _tables(root, top: str) -> list[str]:
    """One table per model reachable from ``root``, breadth first."""
    out, seen, queue = [], set(), [root]
    while queue:
        model = queue.pop(0)
        if model in seen:
            continue
        seen.add(model)
        title = top if model is root else model.__name__.lower()
        out.append(f"\n## {title}\n\n{(model.__doc__ or '').strip()}\n")
        out.append("| key | type | default | meaning |\n|---|---|---|---|")
        for name, field in model.model_fields.items():
            out.append(f"| `{name}` | {_type_name(field.annotation)} | {_default(field)} | {field.description or ''} |")
            queue.extend(m for m in models_in(field.annotation) if m not in seen)
    return out


def render() -> str:
    out = [HEADER, *_tables(Workflow, "workflow (top level)")]
    polygon = [POLYGON, *_tables(PolygonWorkflow, "polygon workflow (top level)")]
    posture = [POSTURE, *_tables(PostureWorkflow, "posture workflow (top level)")]
    return "\n".join(out) + "\n" + OVERLAYS + "\n".join(polygon) + "\n" + "\n".join(posture) + "\n"


if __name__ == "__main__":
    print(render(), end="")
