"""Unmodelled effects the virtual machine can switch on (DESIGN §8.5), and what each does to the cut.

Name, parameters and signature on the measured deviation r:

- ``runout``: ``e_um`` (radial runout of the largest flute), ``phase_deg``: ρ_j = e·cos(2πj/N + phase);
  the largest flute cuts the surface: r ≈ −ρ_max·sin q; also changes the chip of each flute.
- ``tool_contour``: ``a_um``, ``q0_deg``, ``width_deg``: profile error w(q) = a·exp(−½((q−q0)/width)²),
  positive = tool smaller there (seed 002 sign): r = +w(q).
- ``tool_wear``: ``rate_um_per_m``: radius loss = rate·L (L = cut length so far, m): r = +rate·L.
- ``thermal_drift``: ``ax_um``, ``ay_um``, ``az_um``, ``tau_s``: tool offset A·(1 − exp(−t/τ)):
  r = n·A·(1 − exp(−t/τ)).
- ``force_scale``: ``scale``: every cutting coefficient × scale (mis-calibrated material): the
  deflection part of the error scales by it.
- ``servo_corner``: ``a_um``, ``lambda_mm``: near a path corner of angle θ the tool lags towards the
  inside of the turn (unit bisector b) by a·sin(θ/2)/sin(45°)·exp(−d/λ), d = path distance to the
  corner: r = (b·n)·that.
- ``machine_geometry``: ``sx``, ``sy``, ``sz`` (scale, µm/mm), ``exy``, ``exz``, ``eyz`` (squareness,
  µm/mm): tool offset dx = sx·x + exy·y + exz·z, dy = sy·y + eyz·z, dz = sz·z at the tool tip
  position (machine frame): r = n·offset.

``runout`` and ``force_scale`` act through the forces and deflection (``machine.py``); the others
through :func:`radius_loss` and :func:`machine_offsets` at every tooth passage.
"""
from __future__ import annotations

import math

import numpy as np

from stages import InputError
from stages.geometry.paths import Path3, corner_features

EFFECTS = {
    "runout": ("e_um", "phase_deg"),
    "tool_contour": ("a_um", "q0_deg", "width_deg"),
    "tool_wear": ("rate_um_per_m",),
    "thermal_drift": ("ax_um", "ay_um", "az_um", "tau_s"),
    "force_scale": ("scale",),
    "servo_corner": ("a_um", "lambda_mm"),
    "machine_geometry": ("sx", "sy", "sz", "exy", "exz", "eyz"),
}
DEFAULTS = {
    "runout": {"e_um": 5.0, "phase_deg": 0.0},
    "tool_contour": {"a_um": 5.0, "q0_deg": 30.0, "width_deg": 10.0},
    "tool_wear": {"rate_um_per_m": 20.0},
    "thermal_drift": {"ax_um": 0.0, "ay_um": 0.0, "az_um": -10.0, "tau_s": 600.0},
    "force_scale": {"scale": 1.5},
    "servo_corner": {"a_um": 10.0, "lambda_mm": 0.5},
    "machine_geometry": {"sx": 0.0, "sy": 0.0, "sz": 0.0, "exy": 0.0, "exz": 0.0, "eyz": 0.0},
}


def parse_effect(text: str) -> tuple[str, dict]:
    """An effect given on the command line, ``NAME:key=value,...``.

    Returns
    -------
    (name, params) : the parameters with :data:`DEFAULTS` filled in.

    Raises
    ------
    stages.InputError
        Unknown effect or key, a value that is not a number, or one outside its range.
    """
    name, _, rest = text.partition(":")
    name = name.strip()
    if name not in EFFECTS:
        raise InputError(f"--effect {text!r}: unknown effect {name!r} (known: {', '.join(EFFECTS)})")
    params = dict(DEFAULTS[name])
    for item in filter(None, (s.strip() for s in rest.split(","))):
        k, eq, v = item.partition("=")
        if not eq or k.strip() not in EFFECTS[name]:
            raise InputError(f"--effect {text!r}: {item!r} is not key=value with key in {EFFECTS[name]}")
        try:
            params[k.strip()] = float(v)
        except ValueError:
            raise InputError(f"--effect {text!r}: {k.strip()}={v!r} is not a number") from None
    if name == "force_scale" and not params["scale"] > 0:
        raise InputError(f"--effect {text!r}: scale must be > 0")
    if name == "thermal_drift" and not params["tau_s"] > 0:
        raise InputError(f"--effect {text!r}: tau_s must be > 0")
    if name == "servo_corner" and not params["lambda_mm"] > 0:
        raise InputError(f"--effect {text!r}: lambda_mm must be > 0")
    if name == "runout" and params["e_um"] < 0:
        raise InputError(f"--effect {text!r}: e_um must be >= 0")
    return name, params


def radius_loss(effects: dict, q_deg: np.ndarray, cut_len_mm: np.ndarray, profile=None) -> np.ndarray:
    """How much smaller than nominal the cutting radius is at contact angle q (µm).

    Parameters
    ----------
    effects : dict
        Effect name → parameters; ``tool_contour`` and ``tool_wear`` act here.
    q_deg : (n,) float
        Contact angle of each tooth passage.
    cut_len_mm : (n,) float
        Cut length of the tool when it makes the passage (what ``tool_wear`` grows with).
    profile : (contact_deg, error_um) arrays, optional
        The tool's measured shape error (+ = smaller), interpolated at q.

    Returns
    -------
    (n,) float
    """
    out = np.zeros(len(q_deg)) if profile is None else np.interp(q_deg, *profile)
    if "tool_contour" in effects:
        e = effects["tool_contour"]
        out += e["a_um"] * np.exp(-0.5 * ((q_deg - e["q0_deg"]) / e["width_deg"]) ** 2)
    if "tool_wear" in effects:
        out += effects["tool_wear"]["rate_um_per_m"] * cut_len_mm * 1e-3
    return out


def machine_offsets(effects: dict, path: Path3, centres: np.ndarray, rows: np.ndarray, frac: np.ndarray,
                    t: np.ndarray, radius_mm: float) -> np.ndarray:
    """Tool offset from the machine at each tooth passage (mm): thermal drift, servo lag, axis geometry.

    Parameters
    ----------
    effects : dict
        Effect name → parameters; ``thermal_drift``, ``servo_corner`` and ``machine_geometry`` act here.
    path : Path3
        The program's cutting passes.
    centres : (n, 3) float
        Nominal ball centre of each passage (mm).
    rows, frac : (n,) int, (n,) float
        The pass the passage belongs to and where along it (0 … 1, beyond for a passage past its end).
    t : (n,) float
        Time of the passage (s from the program's start).
    radius_mm : float
        Ball radius (the tip is the centre less it).

    Returns
    -------
    (n, 3) float
    """
    off = np.zeros((len(centres), 3))
    if "thermal_drift" in effects:
        e = effects["thermal_drift"]
        g = 1 - np.exp(-np.maximum(t, 0) / e["tau_s"])
        off += np.stack([e["ax_um"] * g, e["ay_um"] * g, e["az_um"] * g], 1) * 1e-3
    if "servo_corner" in effects:
        e = effects["servo_corner"]
        # distance along the path from the passage's own position (beyond the pass's end it is
        # on the neighbour: clipping it to the end put every such passage at the corner itself)
        dist, ang, b = corner_features(path, rows, frac)
        mag = e["a_um"] * np.sin(np.radians(ang) / 2) / math.sin(math.pi / 4) * np.exp(-dist / e["lambda_mm"])
        off += b * mag[:, None] * 1e-3
    if "machine_geometry" in effects:
        e = effects["machine_geometry"]
        tip = centres - [0.0, 0.0, radius_mm]
        x, y, z = tip[:, 0], tip[:, 1], tip[:, 2]
        off += np.stack([e["sx"] * x + e["exy"] * y + e["exz"] * z, e["sy"] * y + e["eyz"] * z, e["sz"] * z], 1) * 1e-3
    return off
