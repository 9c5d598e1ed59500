"""Cutting efficiency λ of the edge point in contact (seed §2, §5).

On a ball end mill the surface point with normal n is cut by the edge point at angle ψ from the tool
tip, ψ the angle between the tool axis θ and n (0°: the tip, where the cutting speed is zero; 90°:
the equator). The seed's default is λ = sin 2ψ; a shop's own λ is a table of efficiency per edge
angle from cutting tests, interpolated linearly, which must cover 0–90°.
"""
from __future__ import annotations

import numpy as np

from stages import InputError


def psi_deg(normals, axis) -> np.ndarray:
    """ψ, degrees: the angle between the tool axis ``axis`` (3,) and unit normals (n, 3)."""
    return np.degrees(np.arccos(np.clip(np.asarray(normals, float) @ np.asarray(axis, float), -1, 1)))


def sin2psi(psi):
    """The seed's λ(ψ) = sin 2ψ (ψ in degrees), 0 beyond 90°."""
    psi = np.asarray(psi, float)
    return np.where(psi <= 90.0, np.sin(np.radians(2 * psi)), 0.0)


class Table:
    """λ from a table of (edge angle in degrees, efficiency), linear in between.

    ``where`` names the table in errors (``file.csv`` or ``workflow.yaml:12: efficiency.points``).
    """

    def __init__(self, angles, values, where: str):
        a, v = np.asarray(angles, float), np.asarray(values, float)
        if a.ndim != 1 or a.shape != v.shape or len(a) < 2:
            raise InputError(f"{where}: an efficiency table needs at least two rows of (edge angle, efficiency)")
        if not (np.isfinite(a).all() and np.isfinite(v).all()):
            raise InputError(f"{where}: the efficiency table has values that are not numbers")
        if np.any(np.diff(a) <= 0):
            raise InputError(f"{where}: the edge angles of the efficiency table must increase")
        if a[0] > 0 or a[-1] < 90:
            raise InputError(f"{where}: the efficiency table covers {a[0]:g}–{a[-1]:g}°; it must cover the "
                             "edge angles 0–90° of the ball")
        if np.any(v < 0):
            raise InputError(f"{where}: efficiencies must not be negative")
        self.angles, self.values, self.where = a, v, where

    def __call__(self, psi):
        psi = np.asarray(psi, float)
        return np.where(psi <= 90.0, np.interp(psi, self.angles, self.values), 0.0)


def read_table(path) -> Table:
    """A CSV of two columns, edge angle (degrees) and efficiency, with or without a header line."""
    from pathlib import Path
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such efficiency table")
    rows = []
    for no, line in enumerate(path.read_text().splitlines(), 1):
        cells = [c.strip() for c in line.replace(";", ",").split(",") if c.strip()]
        if not cells or line.lstrip().startswith("#"):
            continue
        try:
            rows.append((float(cells[0]), float(cells[1])))
        except (ValueError, IndexError):
            if rows or no > 1:
                raise InputError(f"{path}:{no}: expected two numbers, edge angle (deg) and efficiency; "
                                 f"got {line.strip()!r}") from None
    if not rows:
        raise InputError(f"{path}: the efficiency table has no rows")
    a, v = np.array(rows).T
    return Table(a, v, str(path))
