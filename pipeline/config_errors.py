"""Workflow validation errors as users read them: the file, the YAML line, the key path as written
(``tool.diameter_mm``), what is wrong and, for an unknown key, the nearest valid one."""
from __future__ import annotations

from pathlib import Path

import yaml
from pydantic import BaseModel, ValidationError


def read_yaml(path: Path, what: str, error: type[Exception]) -> tuple[object, str]:
    """The parsed document of the YAML file ``path`` and its text; ``error`` (naming the file and
    ``what`` it should be) when it is missing or not YAML."""
    if not path.is_file():
        raise error(f"{path}: no such {what} file")
    text = path.read_text()
    try:
        return yaml.safe_load(text), text
    except yaml.YAMLError as e:
        raise error(f"{path}: not valid YAML: {e}") from None


def _yaml_lines(text: str) -> dict:
    """Line (1-based) of every key and list item of a YAML document, by key path."""
    lines: dict = {}

    def walk(node, prefix):
        if isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                key = prefix + (str(k.value),)
                lines[key] = k.start_mark.line + 1
                walk(v, key)
        elif isinstance(node, yaml.SequenceNode):
            for i, v in enumerate(node.value):
                lines[prefix + (str(i),)] = v.start_mark.line + 1
                walk(v, prefix + (str(i),))
    try:
        walk(yaml.compose(text), ())
    except yaml.YAMLError:
        pass
    return lines


def models_in(annotation) -> list:
    """The config models an annotation may hold (through Optional, Union and list)."""
    import typing
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    return [m for a in typing.get_args(annotation) for m in models_in(a)]


def _valid_keys(root, path: tuple) -> list[str]:
    """The keys a mapping at ``path`` (list indices skipped) of the model ``root`` may have."""
    models = [root]
    for key in path:
        if key.isdigit():
            continue
        models = [m for model in models if key in model.model_fields
                  for m in models_in(model.model_fields[key].annotation)]
    return sorted({k for m in models for k in m.model_fields})


def format_error(path: Path, err: ValidationError, text: str, root) -> str:
    """One line per problem: file, YAML line, the key path as the user wrote it (``tool.diameter_mm``),
    what is wrong and, for an unknown key, the nearest valid one.

    Pydantic reports every branch of a union (``tool`` may be one tool or a list); the branch that
    only says "wrong container type" is dropped when another branch says something specific.
    """
    import difflib
    lines_of = _yaml_lines(text)
    items = []
    for e in err.errors():
        parts = tuple(str(p) for p in e["loc"] if not (isinstance(p, str) and ("[" in p or "(" in p)))
        msg = e["msg"]
        if e["type"] == "extra_forbidden":
            valid = _valid_keys(root, parts[:-1])
            near = difflib.get_close_matches(parts[-1], valid, n=1, cutoff=0.5)
            msg = f"unknown key {parts[-1]!r}" + (f"; did you mean {near[0]!r}?" if near else
                                                   f"; valid keys here: {', '.join(valid)}")
        items.append((parts, msg, e["type"], e.get("input")))
    loc_of = lambda parts: ".".join(parts) or "<top>"  # noqa: E731
    specific = {loc_of(p) for p, _, typ, _ in items if not typ.endswith(("_type", "union_tag_invalid"))}
    out, seen = [f"{path}: invalid workflow"], set()
    for parts, msg, typ, inp in items:
        loc = loc_of(parts)
        if typ.endswith("_type") and any(s == loc or s.startswith(loc + ".") for s in specific):
            continue
        if (loc, msg) in seen:
            continue
        seen.add((loc, msg))
        line = next((lines_of[parts[:k]] for k in range(len(parts), 0, -1) if parts[:k] in lines_of), None)
        where = f"{path}:{line}: " if line else "  "
        got = "" if typ == "extra_forbidden" else f" (got {inp!r})"
        out.append(f"  {where}{loc}: {msg}{got}")
    return "\n".join(out)
