"""Fit a :class:`~stages.thermal.model.DriftModel` to on-machine drift measurements.

The drift is linear in every coefficient once the time constants are fixed, so the fit is a
variable projection: the outer least squares moves log τ only, each of its evaluations solves the
three axes' linear problems exactly. The outer search starts from the best of a grid of time
constants (from a tenth of the shortest sampling step to ten times the history), so it does not
depend on a guess. Uncertainties come from the full Jacobian at the optimum (every parameter, the
residual's variance from its degrees of freedom).
"""
from __future__ import annotations

import itertools

import numpy as np
from scipy.optimize import least_squares

from stages.thermal.model import AXES, DriftModel

GRID_PER_DECADE = 6


def _solve(model: DriftModel, data: dict, Y: np.ndarray, taus: np.ndarray):
    """Linear coefficients (m, 3) for fixed ``taus`` and the residuals (n, 3)."""
    X = model.design(data, taus)
    coef, *_ = np.linalg.lstsq(X, Y, rcond=None)
    return coef, Y - X @ coef, X


def _start(model: DriftModel, data: dict, Y: np.ndarray, lo: float, hi: float, K: int) -> np.ndarray:
    """The grid point (K distinct time constants, ascending) with the smallest residual."""
    grid = np.logspace(np.log10(lo), np.log10(hi), int(np.ceil(np.log10(hi / lo) * GRID_PER_DECADE)) + 1)
    best, best_taus = np.inf, None
    for taus in itertools.combinations(grid, K):
        taus = np.asarray(taus)
        sse = float((_solve(model, data, Y, taus)[1] ** 2).sum())
        if sse < best:
            best, best_taus = sse, taus
    return best_taus


def fit_drift(data: dict, sources: int = 2, heat_column: str | None = None,
              positions: tuple = (), temperatures: tuple = ()) -> tuple[DriftModel, dict]:
    """Fit the drift model to measurements.

    Parameters
    ----------
    data : dict of (n,) arrays: ``time_s`` (increasing), ``dx_um``, ``dy_um``, ``dz_um`` and the
        columns named below.
    sources : number of first-order heat sources (time constants).
    heat_column : column of the machine's heat input (e.g. ``spindle_rpm``), None for a machine
        running from t = 0.
    positions : position columns (``x_mm``...) for the cross terms.
    temperatures : temperature columns entering linearly.

    Returns
    -------
    model : the fitted :class:`DriftModel`.
    report : residual RMS per axis, parameter standard errors, degrees of freedom.
    """
    t = np.asarray(data["time_s"], float)
    Y = np.column_stack([np.asarray(data[f"d{a}_um"], float) for a in AXES])
    ref = float(np.max(np.abs(data[heat_column]))) if heat_column else 1.0
    model = DriftModel(np.ones(sources), {}, heat_column, ref if ref > 0 else 1.0, tuple(positions),
                       np.array([np.mean(data[p]) for p in positions]), tuple(temperatures),
                       np.array([np.asarray(data[c], float)[0] for c in temperatures]))
    m = len(model.columns())
    dt = np.diff(t)
    lo = max(float(dt[dt > 0].min()) / 10 if (dt > 0).any() else 1.0, 1e-3)
    hi = 10.0 * max(float(t.max()), lo * 100)
    x0 = np.log(_start(model, data, Y, lo, hi, sources))

    def resid(logtau):
        return _solve(model, data, Y, np.exp(logtau))[1].ravel()

    sol = least_squares(resid, x0, bounds=(np.log(lo), np.log(hi)), x_scale=1.0, xtol=1e-12, ftol=1e-12)
    order = np.argsort(sol.x)
    logtau = sol.x[order]
    taus = np.exp(logtau)
    coef, res, X = _solve(model, data, Y, taus)
    model.taus_s = taus
    model.coef = {a: coef[:, i] for i, a in enumerate(AXES)}
    # full Jacobian of the stacked residuals in (log τ, every axis's coefficients)
    n = len(t)
    P = sources + 3 * m
    J = np.zeros((3 * n, P))
    for k in range(sources):
        h = 1e-6
        step = logtau.copy()
        step[k] += h
        dX = (model.design(data, np.exp(step)) - X) / h
        J[:, k] = -(dX @ coef).ravel()
    for i in range(3):
        J[i::3, sources + i * m: sources + (i + 1) * m] = -X
    dof = 3 * n - P
    s2 = float((res ** 2).sum()) / max(dof, 1)
    cov = s2 * np.linalg.pinv(J.T @ J)
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    names = model.columns()
    report = {
        "points": int(n), "parameters": int(P), "dof": int(dof),
        "rms_um": {a: float(np.sqrt(np.mean(res[:, i] ** 2))) for i, a in enumerate(AXES)},
        "sigma_um": float(np.sqrt(s2)),
        "time_constants_s": [{"value": float(taus[k]), "se": float(taus[k] * se[k])} for k in range(sources)],
        "se": {a: {nm: float(se[sources + i * m + j]) for j, nm in enumerate(names)} for i, a in enumerate(AXES)},
        "bounds_s": [lo, hi],
        "at_bound": bool(np.any(np.isclose(logtau, np.log(lo))) or np.any(np.isclose(logtau, np.log(hi)))),
    }
    return model, report
