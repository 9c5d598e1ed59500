"""The blind check's cases: random effects within the ranges real machines show, and pairs of
effects with distinct sizes on the part (DESIGN §8 step 5).
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

# drawn sizes of each effect (random_case): runout e µm, contour |a| µm, wear at the end µm, drift |a| µm,
# force scale s (and 1/s), servo lag |a| µm, machine geometry's largest tool offset µm
RANGES = {"runout": (4.0, 15.0), "tool_contour": (4.0, 12.0), "tool_wear": (5.0, 15.0), "thermal_drift": (8.0, 25.0),
          "force_scale": (2.0, 3.5), "servo_corner": (10.0, 30.0), "machine_geometry": (8.0, 20.0)}
_AMPLITUDES = {"runout": ("e_um",), "tool_contour": ("a_um",), "tool_wear": ("rate_um_per_m",),
               "thermal_drift": ("ax_um", "ay_um", "az_um"), "servo_corner": ("a_um",),
               "machine_geometry": ("sx", "sy", "sz", "exy", "exz", "eyz")}


def random_case(rng, kind: str, ctx: dict) -> dict:
    """Random physical parameters for one effect, within ranges set by the part (duration, size).

    Parameters
    ----------
    rng : numpy.random.Generator
    kind : str
        The effect (``stages.gap.effects.EFFECT_NAMES``).
    ctx : dict
        The part: ``duration_s`` (s), ``q_max_deg``, ``cut_len_mm``, ``tips`` (n, 3) mm, ``flutes``.

    Returns
    -------
    dict
        The effect's parameters as the virtual machine takes them.
    """
    T, qmax = ctx["duration_s"], ctx["q_max_deg"]
    sgn = lambda: rng.choice([-1.0, 1.0])
    if kind == "runout":
        # eccentricity within 45° of a flute (else with 2 flutes no flute stands out): e_eff ≥ e·cos 45°
        return {"e_um": rng.uniform(*RANGES["runout"]), "phase_deg": rng.uniform(-45, 45) + 360.0 / ctx["flutes"] * rng.integers(ctx["flutes"])}
    if kind == "tool_contour":
        return {"a_um": sgn() * rng.uniform(*RANGES["tool_contour"]), "q0_deg": rng.uniform(0.2 * qmax, 0.8 * qmax),
                "width_deg": rng.uniform(5, 15)}
    if kind == "tool_wear":
        return {"rate_um_per_m": rng.uniform(*RANGES["tool_wear"]) * 1000.0 / max(ctx["cut_len_mm"], 1e-6)}
    if kind == "thermal_drift":
        a = rng.normal(size=3)
        a = a / np.linalg.norm(a) * rng.uniform(*RANGES["thermal_drift"])
        return {"ax_um": a[0], "ay_um": a[1], "az_um": a[2], "tau_s": T * rng.uniform(0.1, 1.0)}
    if kind == "force_scale":
        return {"scale": float(np.exp(rng.uniform(*np.log(RANGES["force_scale"])) * sgn()))}
    if kind == "servo_corner":
        return {"a_um": sgn() * rng.uniform(*RANGES["servo_corner"]), "lambda_mm": rng.uniform(0.3, 1.5)}
    if kind == "machine_geometry":
        v = rng.normal(size=6)
        g = dict(zip(("sx", "sy", "sz", "exy", "exz", "eyz"), map(float, v)))
        disp = geometry_offsets(g, ctx["tips"])
        k = rng.uniform(*RANGES["machine_geometry"]) / max(float(np.linalg.norm(disp, axis=1).max()), 1e-9)
        return {key: val * k for key, val in g.items()}
    raise ValueError(kind)


def _scaled(name: str, params: dict, k: float) -> dict:
    out = dict(params)
    if name == "force_scale":
        out["scale"] = 1.0 + k * (params["scale"] - 1.0)
    else:
        for a in _AMPLITUDES[name]:
            out[a] = params[a] * k
    return out


def geometry_offsets(g: dict, tip: np.ndarray) -> np.ndarray:
    """Tool offsets of the machine-geometry effect at the tool tips.

    Parameters
    ----------
    g : dict
        ``sx, sy, sz, exy, exz, eyz`` (µm/mm).
    tip : (n, 3) ndarray
        Tool tips (mm).

    Returns
    -------
    (n, 3) ndarray
        µm.
    """
    return np.stack([g["sx"] * tip[:, 0] + g["exy"] * tip[:, 1] + g["exz"] * tip[:, 2],
                     g["sy"] * tip[:, 1] + g["eyz"] * tip[:, 2], g["sz"] * tip[:, 2]], 1)


def _amplitude_range(name: str, params: dict, ctx: Optional[dict]) -> tuple[float, float]:
    """By how much an effect's amplitude may be scaled (``_scaled``) and stay within the range
    ``random_case`` draws from: (smallest, largest) factor. Without the part's context only the
    force scale's range is known; the others may then shrink freely but not grow."""
    lo, hi = RANGES[name]
    if name == "force_scale":
        s = params["scale"]
        amp, lo, hi = (s - 1.0, lo - 1.0, hi - 1.0) if s > 1 else (1.0 - s, 1.0 - 1.0 / lo, 1.0 - 1.0 / hi)
    elif ctx is None:
        return 0.0, 1.0
    elif name == "runout":
        amp = params["e_um"]
    elif name in ("tool_contour", "servo_corner"):
        amp = abs(params["a_um"])
    elif name == "tool_wear":
        amp = params["rate_um_per_m"] * ctx["cut_len_mm"] * 1e-3
    elif name == "thermal_drift":
        amp = math.sqrt(params["ax_um"] ** 2 + params["ay_um"] ** 2 + params["az_um"] ** 2)
    elif name == "machine_geometry":
        amp = float(np.linalg.norm(geometry_offsets(params, ctx["tips"]), axis=1).max())   # µm/mm × mm
    else:
        return 0.0, 1.0
    amp = max(amp, 1e-12)
    return lo / amp, hi / amp


def distinct_sizes(truth: dict, vm, pts, nrm, ratio: float, ctx: Optional[dict] = None,
                    size: Optional[dict] = None) -> Optional[dict]:
    """The pair rescaled so that the second effect's RMS on the points is ``ratio`` × the first's,
    with both amplitudes kept inside the ranges ``random_case`` draws from (a second effect scaled
    below its range would be a different, smaller effect than the single-effect cases test; one
    scaled above it, a force scale below zero or a servo lag of 100+ µm): the second is scaled as
    far as its range allows and the first by the rest. None when the first would then leave its
    own range (the caller draws again).

    Parameters
    ----------
    truth : dict
        Two effects {name: parameters}, the first the larger.
    vm : object
        The virtual machine (``probe(pts, nrm, effects, noise)``).
    pts, nrm : (n, 3) ndarray
        Plan points (mm) and unit normals.
    ratio : float
        RMS of the second / RMS of the first.
    ctx : dict, optional
        The part (``random_case``); without it only the force scale may grow.
    size : dict, optional
        Each effect's RMS (µm), when known (``true_sizes``).

    Returns
    -------
    dict or None
    """
    size = size or true_sizes(truth, vm, pts, nrm)
    first, second = list(truth)
    if size[second] <= 0 or size[first] <= 0:
        return truth
    k = ratio * size[first] / size[second]
    lo2, hi2 = _amplitude_range(second, truth[second], ctx)
    lo1, hi1 = _amplitude_range(first, truth[first], ctx)
    g = min(max(k, min(lo2, 1.0)), max(hi2, 1.0))          # the second's share, within its range
    f = g / k                                              # the first's, for the rest
    if not min(lo1, 1.0) * (1 - 1e-9) <= f <= max(hi1, 1.0) * (1 + 1e-9):
        return None                                        # not possible within the drawn ranges
    return {first: _scaled(first, truth[first], f), second: _scaled(second, truth[second], g)}


def draw_pair(rng, kinds: list, pool: list, vm, pts, nrm, ctx: dict, tries: int = 20) -> dict:
    """Parameters of a two-effect case whose second effect's RMS on the points is 45-75 % of the
    first's, both within their drawn ranges (``_distinct_sizes``). The drawn kinds are tried in both
    orders (a corner effect is never the larger: it is small in RMS), with fresh parameters; when
    the part admits no such sizes for them (e.g. a force scale of at most 3.5 on a part with little
    deflection against a tool wear of at least 5 µm), another pair of kinds is drawn.

    Parameters
    ----------
    rng : numpy.random.Generator
    kinds : list of str
        The two kinds drawn.
    pool : list of str
        Kinds to draw again from.
    vm, pts, nrm, ctx
        As ``distinct_sizes``.
    tries : int

    Returns
    -------
    dict
        {name: parameters} of the two effects, the larger first.
    """
    base = vm.probe(pts, nrm, {}, 0.0)
    for _ in range(10):
        a, b = kinds
        for _ in range(tries):
            truth = {k: random_case(rng, k, ctx) for k in (a, b)}
            size = true_sizes(truth, vm, pts, nrm, base)
            ratio = float(rng.uniform(0.45, 0.75))
            for first, second in ((a, b), (b, a)):
                if first == "servo_corner":
                    continue
                pair = distinct_sizes({first: truth[first], second: truth[second]}, vm, pts, nrm, ratio, ctx, size)
                if pair is not None:
                    return pair
        a = str(rng.choice([k for k in pool if k != "servo_corner"]))
        kinds = [a, str(rng.choice([k for k in pool if k != a]))]
    raise RuntimeError("blind check: no pair of effects within the drawn ranges has distinct sizes on this part")


def true_sizes(truth: dict, vm, pts, nrm, base: Optional[np.ndarray] = None) -> dict:
    """RMS of each effect's own signature on the measured points (noise-free, alone).

    Parameters
    ----------
    truth : dict
        {name: parameters}.
    vm : object
        The virtual machine.
    pts, nrm : (n, 3) ndarray
    base : (n,) ndarray, optional
        The effect-free probe (µm), when known.

    Returns
    -------
    dict
        {name: µm}.
    """
    base = vm.probe(pts, nrm, {}, 0.0) if base is None else base
    return {k: float(np.sqrt(np.mean((vm.probe(pts, nrm, {k: v}, 0.0) - base) ** 2))) for k, v in truth.items()}


def true_order(truth: dict, vm, pts, nrm) -> list:
    """Effects of a case ordered by the RMS of their own signature on the measured points (noise-free).

    Parameters
    ----------
    truth : dict
    vm : object
    pts, nrm : (n, 3) ndarray

    Returns
    -------
    list of str
    """
    if len(truth) <= 1:
        return list(truth)
    size = true_sizes(truth, vm, pts, nrm)
    return sorted(size, key=lambda k: -size[k])


# errors outside the catalogue (issue 59): a periodic offset along a machine axis (a ballscrew's
# pitch error, a guide's waviness) of 2-6 µm, two to six periods over the points' span; a local
# bump of 3-10 µm whose width (σ of a Gaussian) is 1/25-1/10 of the part (wider ones are smooth
# fields the catalogue's own effects take)
OUTSIDE = ("periodic", "bump")
OUTSIDE_RANGES = {"periodic": (2.0, 6.0), "bump": (3.0, 10.0)}


def outside_case(rng, kind: str, pts: np.ndarray, nrm: np.ndarray) -> dict:
    """Random parameters of an error outside the catalogue (``outside_signature``).

    Parameters
    ----------
    rng : numpy.random.Generator
    kind : str
        ``periodic`` or ``bump``.
    pts, nrm : (n, 3) ndarray
        Plan points (mm) and unit normals.

    Returns
    -------
    dict
        periodic: ``axis`` (0-2, along which it varies), ``direction`` (0-2, of the offset; one the
        normals see), ``period_mm``, ``a_um``, ``phase_rad``; bump: ``centre_mm``, ``width_mm``, ``a_um``.
    """
    if kind == "periodic":
        axis = int(rng.integers(2))
        span = float(np.ptp(pts[:, axis]))
        seen = [j for j in range(3) if np.sqrt(np.mean(nrm[:, j] ** 2)) >= 0.3]
        return {"axis": axis, "direction": int(rng.choice(seen)), "period_mm": float(rng.uniform(span / 6, span / 2)),
                "a_um": float(rng.uniform(*OUTSIDE_RANGES["periodic"])), "phase_rad": float(rng.uniform(0, 2 * np.pi))}
    if kind == "bump":
        size = float(np.ptp(pts, axis=0).max())
        return {"centre_mm": pts[rng.integers(len(pts))].tolist(), "width_mm": float(rng.uniform(size / 25, size / 10)),
                "a_um": float(rng.choice([-1.0, 1.0]) * rng.uniform(*OUTSIDE_RANGES["bump"]))}
    raise ValueError(kind)


def outside_signature(kind: str, p: dict, pts: np.ndarray, nrm: np.ndarray) -> np.ndarray:
    """Deviation along the normals (µm) of an error outside the catalogue (``outside_case``)."""
    if kind == "periodic":
        return (p["a_um"] * nrm[:, p["direction"]]
                * np.sin(2 * np.pi * pts[:, p["axis"]] / p["period_mm"] + p["phase_rad"]))
    return p["a_um"] * np.exp(-np.sum((pts - np.asarray(p["centre_mm"])) ** 2, 1) / (2 * p["width_mm"] ** 2))
