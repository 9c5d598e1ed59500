"""What the measurement plan can observe (issue 59): the amplitudes of each catalogue effect the
points determine, and the nonlinear values the final fit pins.

An amplitude is observable when the largest value real machines show of it (``SCALES``), in the
part of its signature the effect's other amplitudes cannot take, would change the fit by more than
the selection's per-parameter test needs: (R_jj·P_j/σ)² ≥ χ²(1 − ``ALPHA``, 1), R from the QR
decomposition with column pivoting of the effect's signature columns scaled by P (the Jacobian of
its fit, relative to the noise). The others are held at nominal (0: no effect) in every fit
(``Effect.keep``) and reported as not observable, so an effect is selected and judged on its
observable part.

An amplitude that moves the tool along one machine axis (the drift's ax, ay, az; the geometry's
coefficients) is seen only through the points whose normal leans at least ``MIN_LEAN_DEG`` towards
that axis (|n_axis| ≥ sin ``MIN_LEAN_DEG``): the test above takes its signature on those points alone
(the other amplitudes still fitted on all). A point leaning less reads the axis through a lever
under 0.17, so any error of the model along the normal's main axis (probe radius, form, a drift's
other part) reaches the estimate amplified more than 5.8×: on a floor plan a fraction of a µm along
z would be reported as µm of x. A floor-only plan therefore sees a thermal drift's z part and not
its x/y parts, whatever its number of points; a handful of wall points makes x observable.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from scipy.linalg import qr
from scipy.stats import chi2

from stages.gap.effects import Effect

# the largest the seeds measured on real machines (``stages.gap.effects.LIMITS`` / 4; seed 003) or,
# where they give none, the largest the blind check draws (``stages.gap.cases.RANGES``)
SCALES = {"thermal_drift": 50.0, "machine_geometry": 2.5, "runout": 10.0, "tool_contour": 10.0,
          "force_scale": 2.5, "servo_corner": 30.0}
WEAR_AT_END_UM = 15.0
MIN_LEAN_DEG = 10.0
# the normal component through which each amplitude of an axis-wise effect acts
_AXIS = {"thermal_drift": ("nx", "ny", "nz"), "machine_geometry": ("nx", "ny", "nz", "nx", "nx", "ny")}
UNITS = {"ax_um": "µm", "ay_um": "µm", "az_um": "µm", "tau_s": "s", "e_um": "µm", "e_force_um": "µm", "a_um": "µm",
         "q0_deg": "°", "width_deg": "°", "rate_um_per_m": "µm/m", "scale": "", "lambda_mm": "mm",
         "sx": "µm/mm", "sy": "µm/mm", "sz": "µm/mm", "exy": "µm/mm", "exz": "µm/mm", "eyz": "µm/mm"}


def _scale(F, e: Effect) -> float:
    if e.name == "tool_wear":
        return WEAR_AT_END_UM / max(float(np.max(F["cut_len_mm"])) * 1e-3, 1e-9)
    return SCALES[e.name]


def _sample(grid: list, k: int = 12) -> list:
    return [grid[i] for i in np.unique(np.linspace(0, len(grid) - 1, min(k, len(grid))).astype(int))]


def _own_gain(X: np.ndarray, j: int, m: np.ndarray) -> float:
    """Squared norm of column j of X on the rows ``m`` (0 elsewhere) outside the span of the other
    columns on all rows: what amplitude j does through the points that see it, less what the
    others, held by every point, could take of it."""
    xj = np.where(m, X[:, j], 0.0)
    others = np.delete(X, j, axis=1)
    if others.shape[1]:
        xj = xj - others @ np.linalg.lstsq(others, xj, rcond=None)[0]
    return float(xj @ xj)


def _lean_masks(F, e: Effect) -> list:
    """Per amplitude, the points that see it (normal leaning ≥ ``MIN_LEAN_DEG`` towards its axis);
    None for an amplitude not tied to one axis."""
    if e.name not in _AXIS:
        return [None] * e.n_lin
    s = math.sin(math.radians(MIN_LEAN_DEG))
    return [np.abs(F[a]) >= s for a in _AXIS[e.name]]


def _reason(k: str, P: float, gain: float, need: float, axis, lean_n: int) -> str:
    if axis is not None and lean_n == 0:
        return (f"not observable on these points: no point's normal leans {MIN_LEAN_DEG:g}° or more towards "
                f"{axis[1]}, so {k} is read only through a lever under "
                f"{math.sin(math.radians(MIN_LEAN_DEG)):.2f}; held at 0")
    where = "" if axis is None else f" on the {lean_n} points leaning ≥ {MIN_LEAN_DEG:g}° towards {axis[1]}"
    return (f"not observable on these points: its largest real value ({P:.3g} {UNITS.get(k, '')}) in the part "
            f"of its signature the effect's other amplitudes cannot take gains {gain:.2g} σ² of fit{where}, "
            f"below the {need:.3g} a claim needs; held at 0")


def restrict(cat: list, F: dict, sigma: float, alpha: float = 1e-3) -> tuple[list, dict]:
    """The catalogue restricted to what the points observe, and why.

    Parameters
    ----------
    cat : list of Effect
        ``stages.gap.effects.catalogue``.
    F : dict
        Features of the n points.
    sigma : float
        Probe noise σ (µm).
    alpha : float
        False-claim rate of the per-parameter test.

    Returns
    -------
    cat : list of Effect
        Effects with at least one observable amplitude, ``keep`` set where some are not.
    report : dict
        {effect: {amplitude: None (observable) or the reason it is not}}.
    """
    need = float(chi2.ppf(1 - alpha, 1))
    out, report = [], {}
    for e in cat:
        P = _scale(F, e)
        ths = _sample(e.grid) if e.grid and e.grid[0] else [()]
        keys = e.linear_keys(ths[0])
        masks = _lean_masks(F, e)
        gain = np.zeros(e.n_lin)            # best χ² gain of each amplitude's own part over the grid
        for th in ths:
            X = e.basis(F, th) * P
            if e.n_lin == 1:
                g = np.array([float(X[:, 0] @ X[:, 0])])
            else:
                _, R, piv = qr(X, mode="economic", pivoting=True)
                g = np.zeros(e.n_lin)
                g[piv] = np.abs(np.diag(R)) ** 2
            for j, m in enumerate(masks):
                if m is not None:
                    g[j] = _own_gain(X, j, m)
            gain = np.maximum(gain, g / sigma ** 2)
        ok = gain >= need
        report[e.name] = {k: None if o else
                          _reason(k, P, gain[j], need, None if masks[j] is None else _AXIS[e.name][j],
                                  0 if masks[j] is None else int(masks[j].sum()))
                          for j, (k, o) in enumerate(zip(keys, ok))}
        if not ok.any():
            continue
        out.append(e if ok.all() else replace(e, keep=tuple(int(j) for j in np.flatnonzero(ok)), n_lin=int(ok.sum()),
                                             n_full=e.n_lin))
    return out, report


def nonlinear_observability(F, chosen: list, params: dict, se: dict) -> dict:
    """The nonlinear values of the chosen effects the final fit does not pin: a stated standard
    error missing, or 2·SE beyond the interval the value may take (the contour's centre: the
    measured contact angles within 0–90°; its width: ``CONTOUR_WIDTH_DEG``; τ, λ: the value itself).

    Parameters
    ----------
    F : dict
    chosen : list of (Effect, tuple)
    params, se : dict
        {effect: {parameter: value}} and {effect: {parameter: SE or None}} of the final fit.

    Returns
    -------
    dict
        {effect: {parameter: reason}} of the values not observable.
    """
    from stages.gap.effects import CONTOUR_WIDTH_DEG
    q = F["q_deg"]
    span = {"q0_deg": (max(float(np.min(q)), 0.0), min(float(np.max(q)), 90.0)), "width_deg": CONTOUR_WIDTH_DEG}
    out = {}
    for e, th in chosen:
        keys = list(params.get(e.name, {}))[(e.n_full or e.n_lin):]
        if e.name == "servo_corner":
            keys = ["lambda_mm"]
        for k in keys:
            v, s = params[e.name].get(k), se.get(e.name, {}).get(k)
            if not isinstance(v, (int, float)):
                continue
            lo, hi = span.get(k, (0.0, abs(v)))
            width = hi - lo
            if s is None or not math.isfinite(s) or 2 * s > width:
                out.setdefault(e.name, {})[k] = (f"not observable on these points: ±2 SE "
                                                 f"({'none stated' if s is None else f'{2 * s:.3g}'}) spans more than "
                                                 f"{'the value itself' if k not in span else f'{lo:.3g}–{hi:.3g}'}")
    return out
