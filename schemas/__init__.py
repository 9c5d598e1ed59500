"""One Arrow schema per table (DESIGN §6), checked by the engine whenever a stage writes.

Each table lives in its own module ``schemas/<table>.py`` exposing ``SCHEMA``. Units are in the
column names (``_mm``, ``_um``, ``_deg``, ``_n``, ``_s``, ``_hz``).
"""
from __future__ import annotations

import importlib

import pyarrow as pa

TABLES = ("programs", "problems", "blocks", "passes", "cut_filter", "angle_prune", "generating", "engagement", "forces", "feeds", "allowance", "warnings",
          "deflection", "errors", "corrected", "measurements", "gap_points", "gap_effects", "tool_wear",
          "polygon_sections", "posture", "posture_cover")


def endpoints() -> list[pa.Field]:
    """A move's start and end (x0_mm … z1_mm), absolute, mm."""
    return [pa.field(f"{a}{e}_mm", pa.float64(), nullable=False) for e in "01" for a in "xyz"]


def surface_point() -> list[pa.Field]:
    """A point on the part (x_mm, y_mm, z_mm) and the unit normal out of the material there."""
    return [pa.field(c, pa.float64()) for c in ("x_mm", "y_mm", "z_mm", "nx", "ny", "nz")]


class SchemaError(ValueError):
    """A table that does not match its declared schema."""


def get(name: str) -> pa.Schema:
    try:
        return importlib.import_module(f"schemas.{name}").SCHEMA
    except ModuleNotFoundError:
        raise KeyError(f"no schema declared for table {name!r}") from None


def check(name: str, table: pa.Table) -> pa.Table:
    """Return ``table`` cast to the schema of ``name``; raise SchemaError naming what is wrong.

    Columns must all be present (extra columns are an error too: a schema is the contract analysts
    query against). Types are cast safely (int32 → int64 is fine, float → int is not).
    """
    schema = get(name)
    have, want = set(table.column_names), set(schema.names)
    if have != want:
        missing, extra = sorted(want - have), sorted(have - want)
        raise SchemaError(f"table {name}: missing columns {missing}, unexpected columns {extra}")
    table = table.select(schema.names)
    try:
        table = table.cast(schema, safe=True)
    except (pa.ArrowInvalid, pa.ArrowNotImplementedError) as e:
        raise SchemaError(f"table {name}: {e}") from None
    for field in schema:
        if not field.nullable and table.column(field.name).null_count:
            raise SchemaError(f"table {name}: column {field.name} has nulls")
    return table


def empty(name: str) -> pa.Table:
    return get(name).empty_table()
