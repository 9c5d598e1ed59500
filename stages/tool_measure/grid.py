"""The contact-angle grid every tool profile is given on (DESIGN §5).

Contact angle q at the ball (or corner) centre between the downward tool axis and the contour
point: 0° at the tip, 90° at the equator, 0–90° in 0.1° steps. ``error_um`` positive = tool smaller
than nominal there (it leaves material on the part).
"""
from __future__ import annotations

import numpy as np

from stages import InputError

STEP_DEG = 0.1
CONTACT_DEG = np.round(np.arange(0, 901) * STEP_DEG, 1)


def on_grid(df, column: str, name: str) -> np.ndarray:
    """A profile's ``column`` interpolated onto :data:`CONTACT_DEG`.

    Parameters
    ----------
    df : DataFrame or mapping
        Needs ``contact_deg`` (increasing) and ``column`` (finite).
    column : str
    name : str
        What the profile is, for the error message.

    Returns
    -------
    (901,) float

    Raises
    ------
    stages.InputError
        A column is missing, contact_deg does not increase or a value is not finite.
    """
    if "contact_deg" not in df or column not in df:
        raise InputError(f"{name}: needs columns contact_deg and {column}")
    q = np.asarray(df["contact_deg"], dtype=float)
    v = np.asarray(df[column], dtype=float)
    if q.size < 2 or np.any(np.diff(q) <= 0) or not np.all(np.isfinite(v)):
        raise InputError(f"{name}: contact_deg must increase and {column} be finite")
    return np.interp(CONTACT_DEG, q, v)
