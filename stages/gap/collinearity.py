"""How much an effect explains next to others: its fit on all points, its own contribution where it
acts, and the canonical correlation of its signature with theirs (the size test of
``stages.gap.diagnose`` and the ambiguity of ``stages.gap.uncertainty``). Shared parameters as in
``stages.gap.fit``.
"""
from __future__ import annotations

import numpy as np

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
