"""Fitting the effects to the residual: grid and joint fits, held-out folds over spatial blocks,
held-out predictions, the probe noise.

Parameters shared by the functions of the fit, the diagnosis and the uncertainty modules
(``stages.gap.fit``, ``collinearity``, ``diagnose``, ``uncertainty``, ``servo``)::

    F : dict                 features of n measured points ((n,) arrays, ``stages.gap.associate.associate``)
    y : (n,) ndarray         the residual being explained (µm)
    train, mask : (n,) bool  the points fitted on
    fold : (n,) int          held-out fold of each point (``folds``)
    chosen, effects : list   [(Effect, th)]: effects with their nonlinear values (``stages.gap.effects``)
    beta : (p,) ndarray      their amplitudes, concatenated in the same order
    sigma : float            probe noise σ (µm)
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from stages.gap.effects import Effect, effect_bounds
from stages.gap.servo import refine_servo

ALPHA = 1e-3          # false-claim rate of the per-effect test (a priori, not tuned)
K_FOLDS = 5


def bounds_of(F, effects: list) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of the linear parameters of ``effects`` [(Effect, th)], concatenated
    (``stages.gap.effects.effect_bounds``)."""
    if not effects:
        return np.zeros(0), np.zeros(0)
    b = [effect_bounds(F, e, th) for e, th in effects]
    return np.concatenate([x[0] for x in b]), np.concatenate([x[1] for x in b])


def solve_bounded(G: np.ndarray, g: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """min βᵀGβ − 2gᵀβ within lo ≤ β ≤ hi (bounded least squares from the normal equations).

    The unconstrained solution when it is inside the box; else ``scipy.optimize.lsq_linear`` on
    ‖Lᵀβ − L⁻¹g‖² (G = LLᵀ, a relative ridge of 1e-12 keeping L finite where G is singular).

    Parameters
    ----------
    G : (p, p) ndarray
    g : (p,) ndarray
    lo, hi : (p,) ndarray
        Bounds (±inf: none).

    Returns
    -------
    (p,) ndarray
    """
    if len(g) == 0:
        return np.zeros(0)
    beta = np.linalg.lstsq(G, g, rcond=None)[0]
    if np.all(beta >= lo) and np.all(beta <= hi):
        return beta
    from scipy.optimize import lsq_linear
    ridge = 1e-12 * max(float(np.trace(G)), 1e-300) / len(g)
    L = np.linalg.cholesky(G + ridge * np.eye(len(g)))
    return lsq_linear(L.T, np.linalg.solve(L, g), bounds=(lo, hi), method="bvls").x


def lstsq_bounded(X: np.ndarray, y: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Least squares of ``y`` on the columns of ``X`` within the bounds: the unconstrained solution
    when inside them, else ``scipy.optimize.lsq_linear`` (BVLS) on X itself."""
    if X.shape[1] == 0:
        return np.zeros(0)
    beta = np.linalg.lstsq(X, y, rcond=None)[0]
    if np.all(beta >= lo) and np.all(beta <= hi):
        return beta
    from scipy.optimize import lsq_linear
    return lsq_linear(X, y, bounds=(lo, hi), method="bvls").x


def fit_effects(F, y, train, chosen: list, cand: Effect):
    """Fit ``chosen`` (fixed nonlinear params) + ``cand`` on ``train``: best grid value, betas.

    Grid search over the candidate's nonlinear parameters, then one coordinate-wise refinement
    between the best value's grid neighbours (9 values per parameter). Linear parameters by bounded
    least squares (normal equations, ``solve_bounded``: the physical limits of
    ``stages.gap.effects.effect_bounds``).

    Parameters
    ----------
    F, y, train, chosen
        As in the module docstring.
    cand : Effect
        The candidate.

    Returns
    -------
    th : tuple
        The candidate's nonlinear value.
    beta : (p,) ndarray
        Linear parameters of ``chosen`` then ``cand``.
    """
    base = np.hstack([e.basis(F, th) for e, th in chosen])[train] if chosen else np.zeros((int(train.sum()), 0))
    yt = y[train]
    Gbb = base.T @ base
    gb = base.T @ yt
    yy = float(yt @ yt)
    lo_b, hi_b = bounds_of(F, chosen)

    def solve(th):
        Xc = cand.basis(F, th)[train]
        G = np.block([[Gbb, base.T @ Xc], [Xc.T @ base, Xc.T @ Xc]])
        g = np.concatenate([gb, Xc.T @ yt])
        lo_c, hi_c = effect_bounds(F, cand, th)
        beta = solve_bounded(G, g, np.concatenate([lo_b, lo_c]), np.concatenate([hi_b, hi_c]))
        sse = yy - 2 * beta @ g + beta @ G @ beta
        return float(sse), beta

    best = None
    for th in cand.grid:
        sse, beta = solve(th)
        if best is None or sse < best[0]:
            best = (sse, th, beta)
    if best[1]:
        th = list(best[1])
        for d in range(len(th)):
            vals = np.unique([g[d] for g in cand.grid])
            i = int(np.searchsorted(vals, th[d]))
            lo, hi = vals[max(i - 1, 0)], vals[min(i + 1, len(vals) - 1)]
            if hi <= lo:
                continue
            fine = np.geomspace(lo, hi, 9) if lo > 0 else np.linspace(lo, hi, 9)
            for v in fine:
                trial = tuple(th[:d] + [float(v)] + th[d + 1:])
                sse, beta = solve(trial)
                if sse < best[0]:
                    best = (sse, trial, beta)
            th = list(best[1])
    return best[1], best[2]


def blocks(F, n_cells: int = 6) -> np.ndarray:
    """Spatial block index of each point (cubic cells, ~n_cells along the longest extent).

    Parameters
    ----------
    F : dict
        Features (``x_mm, y_mm, z_mm``: (n,) mm).
    n_cells : int
        Cells along the longest extent of the points.

    Returns
    -------
    (n,) int ndarray
        Block index 0 … b − 1 (occupied cells only).
    """
    p = np.stack([F["x_mm"], F["y_mm"], F["z_mm"]], 1)
    lo, hi = p.min(0), p.max(0)
    h = max(float((hi - lo).max()) / n_cells, 1e-6)
    c = np.floor((p - lo) / h).astype(np.int64)
    _, inv = np.unique(c, axis=0, return_inverse=True)
    return inv.ravel()


def folds(block: np.ndarray, k: int = K_FOLDS) -> np.ndarray:
    """Fold of each point: blocks dealt to folds in a fixed pseudo-random order.

    Parameters
    ----------
    block : (n,) int ndarray
        Block of each point (``blocks``).
    k : int
        Number of folds.

    Returns
    -------
    (n,) int ndarray
        Fold 0 … k − 1.
    """
    nb = block.max() + 1
    perm = np.random.default_rng(12345).permutation(nb)
    return (perm[block] % k).astype(np.int64)


def noise_sigma(F, y) -> float:
    """Robust σ of the probe noise: MAD of differences of consecutive points along the path.

    Parameters
    ----------
    F, y
        As in the module docstring.

    Returns
    -------
    float
        σ (µm): 1.4826·MAD/√2 of the differences of neighbours less than 1 mm apart.
    """
    same = (F["program_id"][1:] == F["program_id"][:-1])
    step = np.hypot(np.hypot(np.diff(F["x_mm"]), np.diff(F["y_mm"])), np.diff(F["z_mm"]))
    ok = same & (step < 1.0)
    d = np.diff(y)[ok] if ok.sum() >= 10 else np.diff(y)
    if len(d) == 0:
        return float(np.std(y)) or 1.0
    return max(float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2)), 1e-6)


GRID_POINTS = 20000   # grid searches run on at most this many training points (fixed subset)


def grid_subset(train: np.ndarray) -> np.ndarray:
    """The points grid searches run on: ``train`` itself, or a fixed random ``GRID_POINTS`` of it.

    Parameters
    ----------
    train : (n,) bool ndarray

    Returns
    -------
    (n,) bool ndarray
    """
    idx = np.flatnonzero(train)
    if len(idx) <= GRID_POINTS:
        return train
    keep = np.zeros_like(train)
    keep[np.sort(np.random.default_rng(0).choice(idx, GRID_POINTS, replace=False))] = True
    return keep


def fit_joint(F, y, train, chosen: list, cand: Effect):
    """Add ``cand`` to ``chosen`` on ``train``, re-fitting the chosen effects' nonlinear parameters.

    Coordinate descent, one pass: candidate grid with the others fixed, each chosen effect's grid
    with the rest (candidate included) fixed, the candidate again. Returns (chosen with updated
    nonlinear parameters, candidate's value, betas on the whole training set).

    Parameters
    ----------
    F, y, train, chosen
        As in the module docstring.
    cand : Effect
        The effect added.

    Returns
    -------
    chosen : list of (Effect, tuple)
    th : tuple
        The candidate's nonlinear value.
    beta : (p,) ndarray
        Linear parameters of ``chosen`` then ``cand`` (µm per unit of each basis column).
    """
    sub = grid_subset(train)
    th, _ = fit_effects(F, y, sub, chosen, cand)
    chosen = list(chosen)
    if chosen:
        for i, (e, t) in enumerate(chosen):
            if not t:
                continue
            others = chosen[:i] + chosen[i + 1:] + [(cand, th)]
            t2, _ = fit_effects(F, y, sub, others, e)
            chosen[i] = (e, t2)
        th, _ = fit_effects(F, y, sub, chosen, cand)
    X = np.hstack([e.basis(F, t) for e, t in chosen] + [cand.basis(F, th)])
    beta = lstsq_bounded(X[train], y[train], *bounds_of(F, chosen + [(cand, th)]))
    return chosen, th, beta


def cv_predict(F, y, fold, effects: list, cand: Optional[Effect] = None):
    """Held-out prediction of ``effects`` (+ cand): each fold predicted by the fit on the others.

    ``effects`` are (Effect, grid value); with a candidate, all nonlinear parameters are re-fitted
    on each training set (``fit_joint``), else they stay fixed.

    Parameters
    ----------
    F, y, fold, effects
        As in the module docstring.
    cand : Effect, optional

    Returns
    -------
    (n,) ndarray
        Held-out prediction of the residual (µm).
    """
    pred = np.zeros_like(y)
    for f in range(fold.max() + 1):
        test = fold == f
        train = ~test
        if cand is not None:
            ch, th, beta = fit_joint(F, y, train, effects, cand)
            X = np.hstack([e.basis(F, t) for e, t in ch] + [cand.basis(F, th)])
        else:
            X = np.hstack([e.basis(F, t) for e, t in effects])
            beta = lstsq_bounded(X[train], y[train], *bounds_of(F, effects))
        pred[test] = X[test] @ beta
    return pred


def fold_fits(F, y, fold, chosen: list) -> list:
    """The chosen effects fitted without each held-out fold (nonlinear parameters re-fitted on the
    training blocks, the servo lag with its tooth-passage envelope).

    Parameters
    ----------
    F, y, fold, chosen
        As in the module docstring.

    Returns
    -------
    list of ((n,) bool ndarray, list of (Effect, tuple, ndarray))
        Per fold: its test mask and every effect with its nonlinear value and amplitudes.
    """
    out = []
    for f in range(int(fold.max()) + 1):
        test = fold == f
        if not chosen:
            out.append((test, []))
            continue
        ch, th, beta = fit_joint(F, y, ~test, chosen[:-1], chosen[-1][0])
        ch, beta = refine_servo(F, y, ~test, ch + [(chosen[-1][0], th)], beta)
        items, k = [], 0
        for e, t in ch:
            items.append((e, t, beta[k:k + e.n_lin]))
            k += e.n_lin
        out.append((test, items))
    return out


def predict_effects(F, chosen: list, beta: np.ndarray) -> np.ndarray:
    """Σ of the chosen effects' contributions (basis × amplitudes).

    Parameters
    ----------
    F, chosen, beta
        As in the module docstring.

    Returns
    -------
    (n,) ndarray
        µm.
    """
    out, k = np.zeros(len(F["q_deg"])), 0
    for e, th in chosen:
        out += e.basis(F, th) @ beta[k:k + e.n_lin]
        k += e.n_lin
    return out


def params_of(effects: list, beta: np.ndarray) -> dict:
    """Reported parameters of every effect.

    Parameters
    ----------
    effects, beta
        As in the module docstring.

    Returns
    -------
    dict
        {effect name: {parameter: float}}.
    """
    out, k = {}, 0
    for e, th in effects:
        out[e.name] = e.params(beta[k:k + e.n_lin], th)
        k += e.n_lin
    return out


def shrink_where_acting(y, after, pred) -> Optional[float]:
    """1 − RMS(after)/RMS(y) on the points where ``pred`` exceeds a tenth of its peak.

    Parameters
    ----------
    y, after, pred : (n,) ndarray
        Residual before, after, and the effects' held-out prediction (µm).

    Returns
    -------
    float or None
        None when ``pred`` is zero or the residual there is.
    """
    if not np.any(pred):
        return None
    m = np.abs(pred) > 0.1 * np.abs(pred).max()
    b = rms(y[m])
    return float(1 - rms(after[m]) / b) if b > 0 else None


def rms(v) -> float:
    """Root mean square of ``v`` (0 when empty)."""
    return float(np.sqrt(np.mean(np.square(v)))) if len(v) else 0.0
