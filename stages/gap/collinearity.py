"""How much an effect explains next to others: its fit on all points, its own contribution where it
acts, and the canonical correlation of its signature with theirs (the size test of
``stages.gap.diagnose`` and the ambiguity of ``stages.gap.uncertainty``). Shared parameters as in
``stages.gap.fit``.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from scipy.stats import chi2

from stages.gap.effects import Effect
from stages.gap.fit import fit_joint, grid_subset, predict_effects

AMBIGUOUS_RHO = 0.95  # reported as ambiguous: the chosen effect's signatures explain ≥ 90 % of the other's


def insample_fit(F, y, chosen: list, cand: Effect) -> tuple[float, float, float]:
    """``chosen`` + ``cand`` fitted on all points (``fit_joint``): (SSE, RMS of the candidate's own
    contribution where it acts, its signature's canonical correlation with the chosen effects'
    at the fitted values). The SSE is the in-sample side of a comparison between candidates whose
    signatures are nearly collinear (``stages.gap.diagnose``); the contribution is the size of
    such a candidate.

    Parameters
    ----------
    F, y, chosen
        As in ``stages.gap.fit``.
    cand : Effect

    Returns
    -------
    sse : float
        µm².
    own_rms : float
        µm (``acting_rms`` of the candidate's contribution).
    rho : float
        Canonical correlation (``collinearity``).
    """
    ch, th, beta = fit_joint(F, y, np.ones(len(y), bool), chosen, cand)
    r = y - predict_effects(F, ch + [(cand, th)], beta)
    k = sum(e.n_lin for e, _ in ch)
    return float(r @ r), acting_rms(cand.basis(F, th) @ beta[k:]), collinearity(F, ch, cand.basis(F, th))


def collinearity(F, chosen: list, X: np.ndarray) -> float:
    """Largest canonical correlation between the columns of ``X`` and the chosen effects'
    signatures (on the grid-search subset of the points); 0 when none is chosen.

    Parameters
    ----------
    F, chosen
        As in ``stages.gap.fit``.
    X : (n, k) ndarray
        Signature columns.

    Returns
    -------
    float
        In [0, 1].
    """
    if not chosen or X.shape[1] == 0:
        return 0.0
    sub = grid_subset(np.ones(len(X), bool))
    Qc = orthonormal_basis(np.hstack([e.basis(F, t) for e, t in chosen])[sub])
    Qg = orthonormal_basis(X[sub])
    if Qc.shape[1] == 0 or Qg.shape[1] == 0:
        return 0.0
    return float(min(np.linalg.svd(Qg.T @ Qc, compute_uv=False)[0], 1.0))


def insample_sse(F, y, chosen: list, cand: Effect) -> float:
    """SSE (µm²) of ``chosen`` + ``cand`` fitted on all points (``insample_fit``)."""
    return insample_fit(F, y, chosen, cand)[0]


def collinear_size(explained: float, own: float, rho: float) -> float:
    """The size an effect is judged by (``stages.gap.diagnose``): the RMS it explains
    beyond the other effects, or its own fitted contribution when its signature is nearly collinear
    with theirs (canonical correlation ≥ ``AMBIGUOUS_RHO``).

    Parameters
    ----------
    explained : float
        RMS explained beyond the others (µm).
    own : float
        RMS of its own contribution where it acts (µm).
    rho : float
        Canonical correlation with the others' signatures.

    Returns
    -------
    float
        µm.
    """
    return max(explained, own) if rho >= AMBIGUOUS_RHO else explained


def acting_rms(c: np.ndarray) -> float:
    """RMS of a contribution where it acts: the points beyond a tenth of its peak.

    Parameters
    ----------
    c : (n,) ndarray
        Contribution (µm).

    Returns
    -------
    float
        µm (0 for an empty or zero contribution).
    """
    a = np.abs(c)
    if not a.size or not a.max() > 0:
        return 0.0
    return float(np.sqrt(np.mean(c[a > 0.1 * a.max()] ** 2)))


def orthonormal_basis(X: np.ndarray) -> np.ndarray:
    """Orthonormal basis of the columns of X (rank-revealing).

    Parameters
    ----------
    X : (n, k) ndarray

    Returns
    -------
    (n, r) ndarray
        r ≤ k orthonormal columns spanning X's (singular values below 1e-9 of the largest dropped).
    """
    if X.shape[1] == 0:
        return X
    U, sv, _ = np.linalg.svd(X, full_matrices=False)
    return U[:, sv > max(sv[0], 1e-300) * 1e-9] if sv.size and sv[0] > 0 else U[:, :0]


def _refit(F, y, effects: list) -> tuple[float, list]:
    """``effects`` [(Effect, th)] fitted jointly on all points within their bounds, the nonlinear
    values of all re-fitted together (``fit_joint``): (SSE µm², each effect's contribution (n,) µm)."""
    if not effects:
        return float(y @ y), []
    ch, th, beta = fit_joint(F, y, np.ones(len(y), bool), effects[:-1], effects[-1][0])
    X = [e.basis(F, t) for e, t in ch + [(effects[-1][0], th)]]
    ks = np.cumsum([0] + [x.shape[1] for x in X])
    parts = [x @ beta[ks[i]:ks[i + 1]] for i, x in enumerate(X)]
    r = y - sum(parts)
    return float(r @ r), parts


def _freed(e: Effect) -> Effect:
    return e if e.keep is None else replace(e, keep=None, n_lin=e.n_full, n_full=None)


def held_mimics(F, y, chosen: list, sigma: float, floor_um: float, alpha: float) -> tuple[list, dict]:
    """The chosen effects that cannot be told from the amplitudes the others hold at nominal.

    An amplitude the points do not observe (``stages.gap.observability``) is held at 0, so what it
    does on the few points that see it weakly stays in the residual, where another effect may take
    it up: on a floor plan the x part of a thermal drift, read through the 3–4° feet of the ramps,
    came back as a 1–2 µm tool-contour dent centred on their contact angle, and the drift's τ
    bent to a wear's ramp. With every held amplitude freed (within its bounds) and the nonlinear
    values re-fitted, each chosen effect must still pay for itself next to the others as the
    backward check asks (``stages.gap.diagnose``): its χ² gain at ``alpha`` and, where
    it acts, an RMS of half hypot(σ, floor). One that does not is possible, not claimed; the smallest
    goes first, then the check is repeated.

    Parameters
    ----------
    F, y
        As in ``stages.gap.fit``.
    chosen : list of (Effect, tuple)
    sigma, floor_um : float
        Probe noise σ and the model's floor (µm).
    alpha : float
        False-claim rate.

    Returns
    -------
    chosen : list of (Effect, tuple)
        Without the effects moved to possible.
    possible : dict
        {effect: reason}.
    """
    possible = {}
    while len(chosen) >= 2 and any(e.keep is not None for e, _ in chosen):
        freed = [(_freed(e), t) for e, t in chosen]
        sse_all, parts = _refit(F, y, freed)
        for i in np.argsort([acting_rms(c) for c in parts]):
            rest = freed[:i] + freed[i + 1:]
            held = [e.name for e, _ in chosen[:i] + chosen[i + 1:] if e.keep is not None]
            if not held:
                continue
            d_sse = _refit(F, y, rest)[0] - sse_all
            support = max(int(np.sum(np.abs(parts[i]) > 0.1 * np.abs(parts[i]).max())), 1) if np.any(parts[i]) else len(y)
            if (d_sse / sigma ** 2 > float(chi2.ppf(1 - alpha, chosen[i][0].n_params))
                    and math.sqrt(max(d_sse, 0.0) / support) >= 0.5 * math.hypot(sigma, floor_um)):
                continue
            possible[chosen[i][0].name] = (f"cannot be told from what {', '.join(held)} would do with the "
                                           "amplitudes these points do not observe (held at nominal)")
            chosen = chosen[:i] + chosen[i + 1:]
            break
        else:
            break
    return chosen, possible
