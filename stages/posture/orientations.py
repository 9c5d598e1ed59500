"""Tool orientations: the grid the postures are evaluated on, and the view frame of each.

The tool axis θ is the unit vector from the tool tip towards the spindle, in the part's frame.
``rxry``: θ = R_y(ry) · R_x(rx) · ẑ (the part seen from the tool after tilting the tool by rx about X,
then by ry about Y, as in the seed's Fig. 3: rx = ry = 0 is the vertical axis), rx, ry in [−90°, 90°].
``polar``: θ = (sin t cos a, sin t sin a, cos t), tilt t in [0°, 90°] from +Z, azimuth a from +X.
"""
from __future__ import annotations

import numpy as np

KINDS = ("rxry", "polar")


def steps(lo: float, hi: float, step: float) -> np.ndarray:
    """``lo, lo + step, …`` up to ``hi`` inclusive (within 1e-9 of a step), degrees."""
    n = int(np.floor((hi - lo) / step + 1e-9)) + 1
    return lo + step * np.arange(max(n, 1))


def axes_rxry(rx_deg, ry_deg):
    """Tool axes and the image's up vectors for tilts ``rx_deg`` about X then ``ry_deg`` about Y.

    Returns
    -------
    axis, up : (n, 3) unit vectors; up = R ŷ, so the image turns with the tilt (no jump at the poles).
    """
    a, b = np.radians(np.asarray(rx_deg, float)), np.radians(np.asarray(ry_deg, float))
    axis = np.stack([np.cos(a) * np.sin(b), -np.sin(a), np.cos(a) * np.cos(b)], -1)
    up = np.stack([np.sin(a) * np.sin(b), np.cos(a), np.sin(a) * np.cos(b)], -1)
    return axis, up


def axes_polar(tilt_deg, azimuth_deg):
    """Tool axes and up vectors for polar tilt from +Z and azimuth from +X (degrees); up = R_z(a) ŷ."""
    t, a = np.radians(np.asarray(tilt_deg, float)), np.radians(np.asarray(azimuth_deg, float))
    axis = np.stack([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)], -1)
    up = np.stack([-np.sin(a), np.cos(a), 0 * a], -1)
    return axis, up


def grid(kind: str, first: tuple, second: tuple) -> dict:
    """The orientation grid: every pair of the two angle ranges ``(lo, hi, step)`` in degrees.

    Parameters
    ----------
    kind : ``"rxry"`` (first = rx, second = ry) or ``"polar"`` (first = tilt, second = azimuth).

    Returns
    -------
    dict of (n,) arrays ``rx_deg, ry_deg, tilt_deg, azimuth_deg`` (the same axes in both spellings),
    (n, 3) ``axis`` and ``up``, and ``shape`` (n_first, n_second): row-major over (first, second).
    """
    u, v = steps(*first), steps(*second)
    A, B = (g.ravel() for g in np.meshgrid(u, v, indexing="ij"))
    axis, up = (axes_rxry if kind == "rxry" else axes_polar)(A, B)
    rx, ry, tilt, azim = angles_of(axis)
    if kind == "rxry":
        rx, ry = A, B
    else:
        tilt, azim = A, B
    return dict(rx_deg=rx, ry_deg=ry, tilt_deg=tilt, azimuth_deg=azim, axis=axis, up=up, shape=(len(u), len(v)),
                first=u, second=v)


def angles_of(axis):
    """(rx, ry, tilt, azimuth) in degrees of unit tool axes (n, 3); azimuth 0 for the vertical axis."""
    axis = np.asarray(axis, float)
    rx = -np.degrees(np.arcsin(np.clip(axis[:, 1], -1, 1)))
    ry = np.degrees(np.arctan2(axis[:, 0], axis[:, 2]))
    tilt = np.degrees(np.arccos(np.clip(axis[:, 2], -1, 1)))
    az = np.where(tilt > 1e-9, np.degrees(np.arctan2(axis[:, 1], axis[:, 0])) % 360.0, 0.0)
    return rx, ry, tilt, az


def frames(axis, up):
    """Image frames looking down the tool axis: (n, 3, 3) rows right, up, view direction.

    The view direction is −θ (rays travel from the spindle towards the part: nearer = higher along
    θ); right = up × view, as :meth:`stages.render.View.basis` builds it, so both back ends agree.
    """
    d = -np.asarray(axis, float)
    u = np.asarray(up, float)
    u = u - np.sum(u * d, -1, keepdims=True) * d
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    return np.stack([np.cross(u, d), u, d], 1)
