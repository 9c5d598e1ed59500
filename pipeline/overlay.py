"""Workflow overlays (``pipeline run WORKFLOW --overlay FILE``): YAML mappings of workflow keys
merged over the workflow file before it is validated.

An overlay has the workflow's shape (``gap/model_update.yaml`` of ``pipeline diagnose`` is one).
Its keys are checked on their own, so a typo names the overlay file and its line; its relative
paths are relative to the overlay's own folder (they are made absolute before the merge, so the
workflow's project-relative paths and the overlay's never mix). The merged values enter the cache
keys as any workflow value does: a stage recomputes only when a key it declares changed.

Merge rules (``docs/config.md``):

- mappings merge key by key, recursively; any other value (a number, a string, a list, ``null``)
  replaces the workflow's;
- ``tool`` / ``material`` given as a list keyed by ``t`` in the workflow: an overlay mapping with a
  ``t`` merges into the entry with that ``t`` (a ``t`` the workflow lacks is a new entry), an
  overlay mapping without ``t`` merges into every entry, an overlay list merges entry by entry by
  ``t``.
"""
from __future__ import annotations

from pathlib import Path

from pipeline.config_errors import read_yaml

KEYED_LISTS = ("tool", "material")
# top-level keys whose strings name files or folders (relative to the project in a workflow)
TOP_PATHS = ("programs", "stock", "nominal", "measurements", "output")


class OverlayError(ValueError):
    """An overlay that cannot be used; the message names the overlay file (and line, key)."""


def read_overlay(path, root, file_keys) -> tuple[dict, str]:
    """The overlay's mapping, its relative paths made absolute against its folder, and its text.

    Parameters
    ----------
    path : str or Path
        The overlay YAML file.
    root : pydantic model class
        The workflow model whose keys the overlay may set (``pipeline.config.Workflow``).
    file_keys : tuple of str
        Keys whose string values name files at any depth (``pipeline.config.FILE_KEYS``).

    Returns
    -------
    mapping : dict
    text : str
        The file's text (for line numbers in error messages).
    """
    path = Path(path)
    raw, text = read_yaml(path, "overlay", OverlayError)
    if raw is None:
        raw = {}                                  # an empty overlay (nothing diagnosed) changes nothing
    if not isinstance(raw, dict):
        raise OverlayError(f"{path}: an overlay is a mapping of workflow keys, got {type(raw).__name__}")
    check_keys(raw, path, text, root)
    return absolute_paths(raw, path.resolve().parent, file_keys), text


def check_keys(raw: dict, path: Path, text: str, root) -> None:
    """Refuse a key the workflow model ``root`` does not declare, naming the overlay file, its line and the key."""
    import difflib

    from pipeline.config_errors import _valid_keys, _yaml_lines
    lines = _yaml_lines(text)

    def walk(node, where: tuple):
        if isinstance(node, list):
            for i, v in enumerate(node):
                walk(v, where + (str(i),))
            return
        if not isinstance(node, dict):
            return
        valid = _valid_keys(root, where)
        if not valid:                            # a free mapping (measurements.columns)
            return
        for k, v in node.items():
            if str(k) not in valid:
                near = difflib.get_close_matches(str(k), valid, n=1, cutoff=0.5)
                line = lines.get(where + (str(k),))
                loc = ".".join(p for p in where + (str(k),) if not p.isdigit())
                raise OverlayError(f"{path}:{line}: {loc}: unknown key {k!r}"
                                   + (f"; did you mean {near[0]!r}?" if near else f"; valid keys here: {', '.join(valid)}"))
            walk(v, where + (str(k),))
    walk(raw, ())


def absolute_paths(raw: dict, folder: Path, file_keys) -> dict:
    """``raw`` with every relative file reference (``file_keys`` at any depth, the top-level
    paths of ``TOP_PATHS``) made absolute against ``folder``."""

    def absolute(v):
        if isinstance(v, str):
            return v if Path(v).is_absolute() else str(folder / v)
        if isinstance(v, list):
            return [absolute(x) for x in v]
        return v

    def walk(node):
        if isinstance(node, list):
            return [walk(v) for v in node]
        if isinstance(node, dict):
            return {k: (absolute(v) if k in file_keys and isinstance(v, str) else walk(v)) for k, v in node.items()}
        return node
    out = walk(raw)
    for k in TOP_PATHS:
        v = out.get(k)
        if isinstance(v, (str, list)):
            out[k] = absolute(v)
        elif k == "measurements" and isinstance(v, dict) and isinstance(v.get("file"), str):
            out[k] = dict(v, file=absolute(v["file"]))
    return out


def merge(base, over):
    """``over`` merged over ``base``: mappings key by key, anything else replaced."""
    if isinstance(base, dict) and isinstance(over, dict):
        out = dict(base)
        for k, v in over.items():
            out[k] = merge(base[k], v) if k in base else v
        return out
    return over


def merge_keyed(base: list, over, key: str, path) -> list:
    """An overlay value merged into a workflow list keyed by ``t`` (``tool``, ``material``)."""
    if isinstance(over, dict) and over.get("t") is None:
        return [merge(e, over) for e in base]            # no T number: every entry
    items = [over] if isinstance(over, dict) else over
    if not isinstance(items, list):
        raise OverlayError(f"{path}: {key}: give a mapping or a list of mappings keyed by 't' "
                           f"(the workflow's {key} is a list), got {type(over).__name__}")
    out = list(base)
    for o in items:
        if not isinstance(o, dict) or o.get("t") is None:
            raise OverlayError(f"{path}: {key}: every entry of an overlay list needs its T number as 't'")
        hit = [i for i, e in enumerate(out) if isinstance(e, dict) and e.get("t") == o["t"]]
        if hit:
            out[hit[0]] = merge(out[hit[0]], o)
        else:
            out.append(o)
    return out


def apply_overlay(raw: dict, over: dict, path) -> dict:
    """The workflow mapping ``raw`` with the overlay mapping ``over`` (from file ``path``) merged over it."""
    out = dict(raw)
    for k, v in over.items():
        if k in KEYED_LISTS and isinstance(raw.get(k), list):
            out[k] = merge_keyed(raw[k], v, k, path)
        else:
            out[k] = merge(raw[k], v) if k in raw else v
    return out
