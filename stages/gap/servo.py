"""The servo lag near path corners as the surface shows it: the envelope of discrete tooth passages.

A machine whose axes lag behind the commanded path near a direction change leaves a surface set
by the deepest of the tooth passages around each point, each with its own lag. The smooth form
(``servo_smooth``) is the lag at the point's own path position; ``servo_signature`` is the
envelope averaged over the unknown spindle phase; ``refine_servo`` re-fits a lag chosen with the
smooth form with the envelope.

``F`` throughout is the features dict of ``stages.gap.associate.associate`` (arrays of shape (n,)
per measured point; ``F["_geometry"]`` the paths, ball radius and flutes when it was built there);
shared parameters as in ``stages.gap.fit``.
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from stages.geometry.paths import corner_features, path_point

ENV_PHASES = 8      # spindle phases averaged: the diagnosis does not know the phase a point was cut at
ENV_TOL_UM = 1e-3   # the envelope is computed where it may differ from the smooth form by more than this


def servo_smooth(F, lam_mm: float) -> np.ndarray:
    """The smooth servo-lag signature, per µm of lag amplitude a.

    (b·n)·sin(θ/2)/sin 45°·exp(−d/λ): the lag of the tool at the point's own path position
    (b inside bisector, θ corner angle, d path distance to the corner).

    Parameters
    ----------
    F : dict
        Features of n points (``bx, by, bz, nx, ny, nz, corner_deg, corner_dist_mm``: (n,)).
    lam_mm : float
        Decay length λ (mm).

    Returns
    -------
    (n,) ndarray
        µm along the normal per µm of a (0 where no corner is known).
    """
    return ((F["bx"] * F["nx"] + F["by"] * F["ny"] + F["bz"] * F["nz"])
            * np.sin(np.radians(F["corner_deg"]) / 2) / math.sin(math.pi / 4)
            * np.exp(-np.where(np.isfinite(F["corner_dist_mm"]), F["corner_dist_mm"], 1e9) / lam_mm))


def envelope_geometry(F, a_max_um: float, lam_max_mm: float) -> dict:
    """The tooth passages around every point near a corner, for lags up to ``a_max_um`` and decay
    lengths up to ``lam_max_mm`` (cached on ``F``).

    The surface at a point is left by discrete tooth passages, one per feed per tooth fz = feed /
    (rpm·flutes) along the path, each a ball (radius R) centred on the path at its own position plus
    the servo lag there. Which passage cuts deepest at a point depends on the spindle phase, which
    the diagnosis does not know: ``ENV_PHASES`` phases, evenly spread over one fz, are averaged. A
    passage farther than W along the path cannot cut deeper than the nearest one (its ball lies
    δ²/2R higher at the point, more than any lag difference 2·a_max plus the nearest passage's own
    feed mark; its lag along the path moves it by at most a_max). Beyond ``d_near`` from a corner
    the lag changes so slowly along the path that the deepest passage gains less than
    ``ENV_TOL_UM`` over the smooth form (≈ R·(ℓ/λ)²/2 for a lag ℓ): the smooth form is used there.

    Per near point, phase and passage (offset δ): the ray entry into the nominal ball, A0 − √(R² − P0)
    (A0 = (c − p)·n, P0 = |(c − p)⊥n|²), and the lag's unit vector bm = b·sin(θ/2)/sin 45° as
    B = bm·n, Q = (c − p)⊥·bm⊥, S = |bm⊥|², with the passage's corner distance: a lag g = a·e^(−d/λ)
    moves the entry to A0 + g·B − √(R² − P0 − 2gQ − g²S).

    Parameters
    ----------
    F : dict
        Features of n points with ``F["_geometry"]`` (paths, ball radius R mm, flutes, cache).
    a_max_um : float
        Largest |lag| (µm) the geometry must cover.
    lam_max_mm : float
        Largest decay length λ (mm) it must cover.

    Returns
    -------
    dict
        ``idx`` (m,) indices of the near points; per near point, phase and passage (m, phases, k):
        ``A0, P0, B, Q, S`` (mm, mm², 1, mm, 1), ``dist`` (mm to the passage's corner), ``valid``;
        ``e0`` (m, phases) the nominal entry (mm); ``R`` (mm); ``a_max``, ``lam_max``.
    """
    geo = F["_geometry"]
    for g in geo["cache"]:
        if g["a_max"] >= a_max_um and g["lam_max"] >= lam_max_mm:
            return g
    R, Z = float(geo["R"]), int(geo["flutes"])
    amax = abs(a_max_um) * 1e-3 * math.sqrt(2)                   # mm; sin(θ/2)/sin 45° ≤ √2
    fz = F["feed_mm_min"] / np.maximum(F["rpm"] * Z, 1e-9)
    W = np.sqrt(2 * R * 2 * amax + (fz / 2) ** 2) + amax
    lag_tol = lam_max_mm * math.sqrt(2 * ENV_TOL_UM * 1e-3 / R)
    d_near = W + lam_max_mm * math.log(max(amax / lag_tol, 1.0))
    cd = F["corner_dist_mm"]
    idx = np.flatnonzero(np.isfinite(cd) & (cd < d_near) & (fz > 0))
    out = {"a_max": float(abs(a_max_um)), "lam_max": float(lam_max_mm), "idx": idx}
    geo["cache"].append(out)
    if not idx.size:
        return out
    K = int(min(np.ceil((W[idx] / fz[idx]).max()), 400))
    off = ((np.arange(ENV_PHASES) + 0.5) / ENV_PHASES - 0.5)[:, None] + np.arange(-K, K + 1)[None, :]
    delta = off[None] * fz[idx, None, None]                      # (m, phases, passages) mm
    shape = delta.shape
    arr = {k: np.full(shape, np.inf if k == "dist" else 0.0) for k in ("A0", "P0", "B", "Q", "S", "dist")}
    valid = np.abs(delta) <= (W[idx] + fz[idx])[:, None, None]
    pts = np.stack([F["x_mm"], F["y_mm"], F["z_mm"]], 1)[idx]
    nrm = np.stack([F["nx"], F["ny"], F["nz"]], 1)[idx]
    prog = F["program_id"][idx]
    for pid, path in geo["paths"].items():
        m = np.flatnonzero(prog == pid)
        if not m.size or len(path.pass_id) == 0:
            continue
        s = (F["s_mm"][idx[m]][:, None, None] + delta[m]).ravel()
        c, row = path_point(path, s)
        dist, ang, b = corner_features(path, row, (s - path.s0[row]) / path.length[row])
        sh = (len(m),) + shape[1:]
        cp = c.reshape(sh + (3,)) - pts[m][:, None, None, :]
        n = nrm[m][:, None, None, :]
        bm = (b * (np.sin(np.radians(ang) / 2) / math.sin(math.pi / 4))[:, None]).reshape(sh + (3,))
        A0 = np.sum(cp * n, -1)
        B = np.sum(bm * n, -1)
        arr["A0"][m], arr["B"][m] = A0, B
        arr["P0"][m] = np.sum(cp * cp, -1) - A0 * A0
        arr["Q"][m] = np.sum(cp * bm, -1) - A0 * B
        arr["S"][m] = np.sum(bm * bm, -1) - B * B
        arr["dist"][m] = dist.reshape(sh)
    inner = R * R - arr["P0"]
    e0 = np.where(valid & (inner >= 0), arr["A0"] - np.sqrt(np.maximum(inner, 0.0)), np.inf)
    out.update(arr, valid=valid, e0=e0.min(axis=2), R=R)
    return out


def servo_signature(F, a_um: float, lam_mm: float, geometry: Optional[dict] = None) -> np.ndarray:
    """The surface a servo lag (a µm, decay λ mm) leaves (µm along n): the envelope of the tooth
    passages around each point near a corner, averaged over the spindle phase (``envelope_geometry``),
    and a·``servo_smooth`` where the two agree within ``ENV_TOL_UM``. Without the path geometry
    (features built elsewhere) the smooth form. ``geometry``: an ``envelope_geometry`` result that
    covers (a, λ), used instead of the first adequate one of the cache (finite differences must
    read every (a, λ) with the same passages).

    Parameters
    ----------
    F : dict
        Features of n points.
    a_um : float
        Lag amplitude a (µm; + towards the inside of the turn).
    lam_mm : float
        Decay length λ (mm).
    geometry : dict, optional
        An ``envelope_geometry`` result covering (a, λ).

    Returns
    -------
    (n,) ndarray
        Surface change along the normal (µm, + = material left).
    """
    sig = a_um * servo_smooth(F, lam_mm)
    if "_geometry" not in F or a_um == 0:
        return sig
    g = geometry if geometry is not None else envelope_geometry(F, abs(a_um), lam_mm)
    if not g["idx"].size:
        return sig
    R = g["R"]
    gl = a_um * 1e-3 * np.exp(-g["dist"] / lam_mm)
    inner = R * R - (g["P0"] + 2 * gl * g["Q"] + gl * gl * g["S"])
    e = np.where(g["valid"] & (inner >= 0), g["A0"] + gl * g["B"] - np.sqrt(np.maximum(inner, 0.0)), np.inf)
    d = e.min(axis=2) - g["e0"]
    ok = np.isfinite(d)
    env = np.where(ok, d, 0.0).sum(axis=1) / np.maximum(ok.sum(axis=1), 1) * 1e3
    sig[g["idx"]] = np.where(ok.any(axis=1), env, sig[g["idx"]])
    return sig


def refine_servo(F, y, mask, chosen: list, beta: np.ndarray):
    """The servo lag of ``chosen`` re-fitted with the tooth-passage envelope (``servo_signature``).

    The effects are chosen with the smooth form; its fit (a_s, λ_s) starts a Nelder–Mead search of
    (a, λ) within [a_s/2, 2·a_s] × [λ_s/2, 2·λ_s], the other effects' linear parameters solved at
    each step.

    Parameters
    ----------
    F, y, mask, chosen, beta
        As in ``stages.gap.fit``.

    Returns
    -------
    chosen : list of (Effect, tuple)
        The same, the servo entry's value now (λ mm, a µm).
    beta : (p,) ndarray
        Linear parameters in the same layout (the servo entry's is a).
    """
    names = [e.name for e, _ in chosen]
    if "servo_corner" not in names or "_geometry" not in F:
        return chosen, beta
    from scipy.optimize import minimize
    i = names.index("servo_corner")
    k0 = sum(e.n_lin for e, _ in chosen[:i])
    e_s, th = chosen[i]
    lam_s = float(th[0])
    a_s = float(beta[k0])                       # µm of lag in both forms of the basis
    if not np.isfinite(a_s) or abs(a_s) < 1e-6:
        return chosen, beta
    envelope_geometry(F, 2 * abs(a_s), 2 * lam_s)
    others = [(e, t) for j, (e, t) in enumerate(chosen) if j != i]
    Xo = np.hstack([e.basis(F, t) for e, t in others])[mask] if others else None
    ym = y[mask]

    def solve(x):
        a, lam = a_s * x[0], lam_s * math.exp(x[1])
        r = ym - servo_signature(F, a, lam)[mask]
        bo = np.linalg.lstsq(Xo, r, rcond=None)[0] if Xo is not None else np.zeros(0)
        if Xo is not None:
            r = r - Xo @ bo
        return float(r @ r), bo

    def cost(x):
        if not (0.5 <= x[0] <= 2.0 and abs(x[1]) <= math.log(2.0)):
            return np.inf
        return solve(x)[0]

    sol = minimize(cost, np.array([1.0, 0.0]), method="Nelder-Mead",
                   options={"initial_simplex": [[1.0, 0.0], [1.1, 0.0], [1.0, 0.1]], "xatol": 1e-4, "fatol": 1e-9,
                            "maxiter": 400})
    x = sol.x if np.isfinite(sol.fun) else np.array([1.0, 0.0])
    a, lam = a_s * float(x[0]), lam_s * math.exp(float(x[1]))
    _, bo = solve(x)
    out = list(chosen)
    out[i] = (e_s, (lam, a))
    b = np.empty(len(beta))
    j, k = 0, 0
    for jj, (e, _) in enumerate(chosen):
        if jj == i:
            b[k] = a
        else:
            b[k:k + e.n_lin] = bo[j:j + e.n_lin]
            j += e.n_lin
        k += e.n_lin
    return out, b


