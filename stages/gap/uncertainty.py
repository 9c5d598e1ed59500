"""How well the points pin the chosen effects: the final joint fit, standard errors from the model
linearised at it, and what the selection could have missed (detection limits, ambiguity).

Shared parameters (``F``, ``y``, ``chosen``, ``beta``, ``sigma`` …) as in ``stages.gap.fit``.
"""
from __future__ import annotations

import math

import numpy as np

from stages.gap.effects import CONTOUR_WIDTH_DEG, Effect, effect_bounds
from stages.gap.collinearity import AMBIGUOUS_RHO, orthonormal_basis
from stages.gap.fit import ALPHA, bounds_of, grid_subset, lstsq_bounded, predict_effects, rms
from stages.gap.servo import envelope_geometry, refine_servo, servo_signature

SE_STEP = 1e-3        # central-difference step of a nonlinear parameter: SE_STEP × max(|value|, 1)
SE_RANK_TOL = 1e-7    # singular value of the column-scaled Jacobian (relative to the largest) below
                      # which a direction of the parameters is not identifiable on the points


def _free_parameters(F, e: Effect, th, b):
    """One chosen effect in the linearised model: (internal names, values, linear flags,
    contribution(v), reported(v) → dict, basis at the fit or None).

    Linear parameters are the effect's amplitudes (their Jacobian columns are its basis columns);
    nonlinear ones its grid values (τ, q0, width, λ, the runout response's e), differentiated by
    central differences. The servo lag's fitted form (th = (λ, a)) is the tooth-passage envelope,
    not linear in a either: both a and λ by central differences, every value read with one
    passage geometry that covers them."""
    b = np.asarray(b, float)
    if e.name == "servo_corner" and len(th) == 2:
        a, lam = float(b[0]), float(th[0])
        g = None
        if "_geometry" in F and a != 0:
            g = envelope_geometry(F, abs(a) + 2 * SE_STEP * max(abs(a), 1.0), lam + 2 * SE_STEP * max(lam, 1.0))
        return (["servo_corner.a_um", "servo_corner.lambda_mm"], np.array([a, lam]), [False, False],
                lambda v: servo_signature(F, float(v[0]), float(v[1]), g),
                lambda v: {"a_um": float(v[0]), "lambda_mm": float(v[1])}, None)
    nl = e.n_lin
    th = tuple(float(t) for t in th)
    keys = list(e.params(b, th))
    # internal names (for the reasons of a non-identifiable parameter): the fitted amplitudes, then
    # the nonlinear values (the reported keys after all amplitudes); the runout response's e is not reported
    names = [f"{e.name}.{k}" for k in e.linear_keys(th)]
    rest = keys[(e.n_full or nl):]
    names += [f"{e.name}.{'response_at_e_um' if e.name == 'runout' else rest[j] if j < len(rest) else 'th' + str(j)}"
              for j in range(len(th))]
    return (names, np.concatenate([b, np.asarray(th, float)]), [True] * nl + [False] * len(th),
            lambda v: e.basis(F, tuple(float(t) for t in v[nl:])) @ v[:nl],
            lambda v: e.params(v[:nl], tuple(float(t) for t in v[nl:])), e.basis(F, th))


def _linearise(F, chosen: list, beta: np.ndarray):
    """The combined prediction of ``chosen`` at ``beta`` and its derivative with respect to every free
    parameter (``_free_parameters``): (prediction, J (n, p), internal names, free values per effect,
    [(effect, reported keys, G = d reported / d free)])."""
    n = len(F["q_deg"])
    cols, names, blocks, values = [], [], [], []
    pred = np.zeros(n)
    k = 0
    for e, th in chosen:
        b = beta[k:k + e.n_lin]
        k += e.n_lin
        nm, v0, is_lin, f, rep, X = _free_parameters(F, e, th, b)
        pred += f(v0)
        h = SE_STEP * np.maximum(np.abs(v0), 1.0)
        J = np.empty((n, len(v0)))
        keys = list(rep(v0))
        G = np.zeros((len(keys), len(v0)))
        for i in range(len(v0)):
            vp, vm = v0.copy(), v0.copy()
            vp[i] += h[i]
            vm[i] -= h[i]
            J[:, i] = X[:, i] if is_lin[i] else (f(vp) - f(vm)) / (2 * h[i])
            rp, rm = rep(vp), rep(vm)
            G[:, i] = [(rp[kk] - rm[kk]) / (2 * h[i]) for kk in keys]
        cols.append(J)
        names += nm
        values.append(v0)
        blocks.append((e.name, keys, G))
    J = np.hstack(cols) if cols else np.zeros((n, 0))
    return pred, J, names, values, blocks


def _with_free(e: Effect, th, v: np.ndarray):
    """(grid value, amplitudes) of effect ``e`` from its free parameter values (``_free_parameters``)."""
    if e.name == "servo_corner" and len(th) == 2:
        return (float(v[1]), float(v[0])), np.array([v[0]], float)
    return tuple(float(t) for t in v[e.n_lin:]), np.asarray(v[:e.n_lin], float)


def _free_bounds(F, e: Effect, th, v0: np.ndarray):
    """Where ``polish_fit`` may move an effect's parameters: amplitudes within their physical limits
    (``effect_bounds``); nonlinear values within a factor 2 of the selection's (positive values: τ,
    λ, width, the runout response's e, the servo lag a with its sign), the contour's centre q0
    within ± its width and within the measured contact angles (0–90°), its width within
    ``CONTOUR_WIDTH_DEG``."""
    lo, hi = np.full(len(v0), -np.inf), np.full(len(v0), np.inf)
    servo = e.name == "servo_corner" and len(th) == 2
    if not servo:
        lo[:e.n_lin], hi[:e.n_lin] = effect_bounds(F, e, th)
    nonlin = range(len(v0)) if servo else range(e.n_lin, len(v0))
    for i in nonlin:
        if e.name == "tool_contour" and i == e.n_lin:
            w = abs(float(v0[i + 1]))
            q = F["q_deg"]
            lo[i] = max(v0[i] - w, float(np.min(q)), 0.0)
            hi[i] = min(v0[i] + w, float(np.max(q)), 90.0)
        else:
            lo[i], hi[i] = sorted((0.5 * v0[i], 2.0 * v0[i]))
            if e.name == "tool_contour":
                lo[i], hi[i] = max(lo[i], CONTOUR_WIDTH_DEG[0]), min(hi[i], CONTOUR_WIDTH_DEG[1])
    return lo, hi


def polish_fit(F, y: np.ndarray, chosen: list, beta: np.ndarray, max_iter: int = 30):
    """All parameters of the chosen effects refined jointly by least squares (Levenberg–Marquardt on
    the linearised model of ``_linearise``), from the selection's fit.

    The selection's nonlinear values come from grids refined once between neighbours (τ in steps
    of ~6 %, q0 of 0.5°, width of ~0.3–0.6°): at a strong signal that step is as large as the noise's
    own spread of the value, so the reported value would sit on a grid point and its standard error
    (``param_uncertainty``, which assumes the least-squares optimum) would not describe it. The
    nonlinear values stay within ``_free_bounds`` of the selection's; a step is taken only when it
    lowers the sum of squares.

    Parameters
    ----------
    F, y, chosen, beta
        As in ``stages.gap.fit``.
    max_iter : int

    Returns
    -------
    chosen : list of (Effect, tuple)
    beta : (p,) ndarray
        In the same layout.
    """
    if not chosen:
        return chosen, beta
    chosen, beta = list(chosen), np.asarray(beta, float).copy()
    pred, J, _, values, _ = _linearise(F, chosen, beta)
    bounds = [_free_bounds(F, e, th, v) for (e, th), v in zip(chosen, values)]
    lo = np.concatenate([b[0] for b in bounds])
    hi = np.concatenate([b[1] for b in bounds])
    sizes = [len(v) for v in values]
    v = np.concatenate(values)
    r = y - pred
    sse = float(r @ r)
    lam = 1e-4

    def unpack(vv):
        ch, bb, k = [], [], 0
        for (e, th), m in zip(chosen, sizes):
            t2, b2 = _with_free(e, th, vv[k:k + m])
            ch.append((e, t2))
            bb.append(b2)
            k += m
        return ch, np.concatenate(bb)

    for _ in range(max_iter):
        A, g = J.T @ J, J.T @ r
        D = np.where(np.diag(A) > 0, np.diag(A), 1.0)
        step = None
        while lam < 1e10:
            try:
                delta = np.linalg.solve(A + lam * np.diag(D), g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            vn = np.clip(v + delta, lo, hi)              # the step projected into the bounds
            if np.all(np.isfinite(vn)):
                ch, bb = unpack(vn)
                rn = y - predict_effects(F, ch, bb)
                sn = float(rn @ rn)
                if sn < sse:
                    step = (vn, ch, bb, rn, sn)
                    lam = max(lam / 10, 1e-9)
                    break
            lam *= 10
        if step is None:
            break
        vn, chosen, beta, r, sn = step
        done = sse - sn <= 1e-12 * sse
        v, sse = vn, sn
        if done:
            break
        _, J, _, _, _ = _linearise(F, chosen, beta)
    return chosen, beta


def param_uncertainty(F, y: np.ndarray, chosen: list, beta: np.ndarray, sigma: float) -> dict:
    """Standard errors of every reported parameter of the final model (all chosen effects jointly,
    on all points), from the model linearised at the fit.

    J: the derivative of the combined prediction Σ_e contribution_e with respect to every free
    parameter (``_free_parameters``: amplitudes → basis columns; nonlinear parameters → central
    differences of the basis, step ``SE_STEP``). cov = s²·(JᵀJ)⁻¹ with s = max(σ, residual RMS
    √(SSE/(n − p))), propagated to the reported form (force scale = 1 + b, …) by the Jacobian of the
    reported parameters, G·cov·Gᵀ. JᵀJ is inverted through the SVD of J with unit-norm columns:
    directions whose singular value is below ``SE_RANK_TOL`` of the largest are not identifiable, and a
    reported parameter that depends on one gets se None with the reason (the parameters it cannot
    be told from); the others are read from the pseudo-inverse. It assumes independent residuals
    and the linearisation: a residual the model does not explain (the prediction's own floor)
    enters through s only.

    Parameters
    ----------
    F, y, chosen, beta
        As in ``stages.gap.fit``.
    sigma : float
        The probe noise estimate (µm); s is the larger of it and the residual RMS.

    Returns
    -------
    dict
        {"se": {effect: {key: se | None}}, "cov": {"names", "matrix"}, "not_identifiable":
        {effect.key: reason}, "sigma_um": s, "noise_sigma_um", "residual_rms_um", "n_points",
        "n_params"}; standard errors in the units of the parameters.
    """
    n = len(y)
    pred, J, names, _, blocks = _linearise(F, chosen, beta)
    se = {e.name: {} for e, _ in chosen}
    rep_names = []
    p = len(names)
    out = {"se": se, "cov": {"names": [], "matrix": []}, "not_identifiable": {}, "noise_sigma_um": float(sigma),
           "n_points": int(n), "n_params": int(p)}
    if not p:
        out.update(sigma_um=float(sigma), residual_rms_um=rms(y))
        return out
    Gf = np.zeros((sum(len(kk) for _, kk, _ in blocks), p))
    r = c = 0
    for name, keys, G in blocks:
        Gf[r:r + len(keys), c:c + G.shape[1]] = G
        rep_names += [f"{name}.{kk}" for kk in keys]
        r += len(keys)
        c += G.shape[1]
    resid = y - pred
    rms_dof = float(np.sqrt(resid @ resid / max(n - p, 1)))
    s = max(float(sigma), rms_dof)
    out.update(sigma_um=s, residual_rms_um=rms_dof)
    reason = {}
    if n <= p or not np.all(np.isfinite(J)):
        why = (f"{n} points for {p} parameters" if n <= p else "the model's derivative is not finite at the fit")
        for nm in rep_names:
            reason[nm] = why
        cov = np.full((len(rep_names), len(rep_names)), np.nan)
    else:
        cn = np.linalg.norm(J, axis=0)
        cn = np.where(cn > 0, cn, 1.0)
        _, S, Vt = np.linalg.svd(J / cn, full_matrices=False)
        keep = S > S[0] * SE_RANK_TOL if S[0] > 0 else np.zeros(len(S), bool)
        Vk = Vt[keep].T / S[keep]
        cov_v = (Vk @ Vk.T) / np.outer(cn, cn) * s * s
        cov = Gf @ cov_v @ Gf.T
        N = Vt[~keep].T                                   # null directions, in column-scaled units
        if N.size:
            Gw = Gf / cn
            for j, nm in enumerate(rep_names):
                g = Gw[j]
                if np.linalg.norm(g @ N) > 1e-6 * max(np.linalg.norm(g), 1e-300):
                    w = np.abs(N @ (N.T @ g))
                    with_ = [names[i] for i in np.argsort(-w) if w[i] > 0.1 * w.max() and names[i] != nm][:4]
                    reason[nm] = ("not identifiable on these points: a combination of it and "
                                  + (", ".join(with_) if with_ else "nothing else")
                                  + f" leaves the prediction unchanged (singular value {S[~keep].max() / S[0]:.1e} "
                                    "of the column-scaled Jacobian)")
    bad = np.array([nm in reason for nm in rep_names])
    cov[bad, :] = np.nan
    cov[:, bad] = np.nan
    for j, nm in enumerate(rep_names):
        eff, key = nm.split(".", 1)
        v = cov[j, j]
        se[eff][key] = float(math.sqrt(v)) if np.isfinite(v) and v >= 0 else None
    out["not_identifiable"] = reason
    out["cov"] = {"names": rep_names,
                  "matrix": [[float(x) if np.isfinite(x) else None for x in row] for row in cov]}
    return out


def final_fit(F, y: np.ndarray, chosen: list):
    """The reported fit of the chosen effects on all points: amplitudes by least squares at the
    selection's nonlinear values, the servo lag re-fitted with the tooth-passage envelope
    (``refine_servo``), then every parameter jointly to the least-squares optimum (``polish_fit``).

    Parameters
    ----------
    F, y, chosen
        As in ``stages.gap.fit``.

    Returns
    -------
    chosen : list of (Effect, tuple)
    beta : (p,) ndarray
    """
    n = len(y)
    X = np.hstack([e.basis(F, t) for e, t in chosen])
    beta = lstsq_bounded(X, y, *bounds_of(F, chosen))
    chosen, beta = refine_servo(F, y, np.ones(n, bool), chosen, beta)
    return polish_fit(F, y, chosen, beta)


def detection_limits(F, chosen: list, cat: list, sigma: float, floor_um: float = 0.0) -> dict:
    """What the selection could have missed: for every catalogue effect not chosen, the largest RMS
    (µm over the points) of a signature of it that would not be claimed next to the chosen effects.

    A signature v of effect G (any of its nonlinear values, any combination of its linear ones) of
    RMS r has the part (1 − ρ²)·r² not explained by the chosen effects' signatures (ρ: its largest
    canonical correlation with them at their fitted values; 0 when none was chosen). The selection
    claims it only when it passes both tests of ``diagnose``: n·(1 − ρ²)·r²/σ² beyond the χ²
    quantile of G's parameter count, and the size test (``collinear_size``): √(n·(1 − ρ²)·r²/support)
    ≥ ½·hypot(σ, floor), support = the points where v exceeds a tenth of its peak, or when ρ ≥
    ``AMBIGUOUS_RHO`` its own RMS where it acts, r·√(n/support), ≥ ½·hypot(σ, floor).
    ``hidden_up_to_um`` is the larger r at which either fails, maximised over G's signatures;
    ``correlation`` is that signature's ρ and ``masked_by`` the chosen effect whose own signatures
    correlate most with it. A nearly collinear pair on the part (ρ → 1) makes the limit large: the
    data cannot tell the two effects apart.

    Parameters
    ----------
    F, chosen, sigma
        As in ``stages.gap.fit``.
    cat : list of Effect
        The catalogue.
    floor_um : float
        The model's own floor on a reference part (µm).

    Returns
    -------
    dict
        {effect not chosen: {"hidden_up_to_um": µm RMS, "correlation": ρ, "masked_by": name or None}}.
    """
    from scipy.stats import chi2
    n = len(F["q_deg"])
    sub = grid_subset(np.ones(n, bool))
    names = {e.name for e, _ in chosen}
    Qc = orthonormal_basis(np.hstack([e.basis(F, t) for e, t in chosen])[sub]) if chosen else None
    Qe = [(e.name, orthonormal_basis(e.basis(F, t)[sub])) for e, t in chosen]
    size = 0.5 * math.hypot(sigma, floor_um)
    out = {}
    for G in cat:
        if G.name in names:
            continue
        thr = float(chi2.ppf(1 - ALPHA, G.n_params))
        best = None
        for th in G.grid:
            Qg = orthonormal_basis(G.basis(F, th)[sub])
            if Qg.shape[1] == 0:
                continue
            if Qc is not None and Qc.shape[1]:
                u, sv, _ = np.linalg.svd(Qg.T @ Qc, full_matrices=False)
                rho, v = float(min(sv[0], 1.0)), Qg @ u[:, 0]
            else:
                rho, v = 0.0, Qg[:, 0]
            unique = max(1.0 - rho * rho, 1e-12)
            frac = float(np.mean(np.abs(v) > 0.1 * np.abs(v).max()))
            # the size test as ``collinear_size``: its own RMS where it acts when nearly
            # collinear, else the part the chosen effects do not explain
            r = max(sigma * math.sqrt(thr / (n * unique)),
                    size * math.sqrt(frac if rho >= AMBIGUOUS_RHO else frac / unique))
            if best is None or r > best[0]:
                by = max(Qe, key=lambda q: float(np.linalg.norm(q[1].T @ v)))[0] if Qe else None
                best = (r, rho, by)
        if best is not None:
            out[G.name] = {"hidden_up_to_um": best[0], "correlation": best[1], "masked_by": best[2]}
    return out


def ambiguous_with(limits: dict, effects: list) -> dict:
    """Per chosen effect, the effects not chosen whose signatures on these points it explains to a
    canonical correlation of at least ``AMBIGUOUS_RHO``: the data cannot tell them apart, and up to
    ``hidden_up_to_um`` of them may be inside the chosen effect's fit.

    Parameters
    ----------
    limits : dict
        ``detection_limits`` result.
    effects : list of str
        The chosen effects.

    Returns
    -------
    dict
        {chosen effect: [{"effect", "correlation", "hidden_up_to_um"}]} (only those with any).
    """
    out = {e: [] for e in effects}
    for g, lim in sorted(limits.items(), key=lambda kv: -kv[1]["correlation"]):
        if lim["masked_by"] in out and lim["correlation"] >= AMBIGUOUS_RHO:
            out[lim["masked_by"]].append({"effect": g, "correlation": lim["correlation"],
                                          "hidden_up_to_um": lim["hidden_up_to_um"]})
    return {k: v for k, v in out.items() if v}
