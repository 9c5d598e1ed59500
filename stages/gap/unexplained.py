"""Structure the catalogue does not explain (issue 59): what is left in the residual after the
chosen effects, when it is well above the noise.

Two scans of the residual r (µm) of the chosen effects fitted on all points, each with a false-claim
rate ``ALPHA`` shared over everything it tries (Bonferroni), and the practical size the selection
asks of an effect (half of hypot(σ, model floor)):

- periodic along a machine axis c ∈ {x, y, z}: per trial period P, a tool offset
  a·sin(2πc/P) + b·cos(2πc/P) along each direction the normals see (RMS of n_j ≥ ``MIN_NORMAL``),
  fitted by least squares with a constant; its gain in σ² is χ² with 2k degrees of freedom without
  such an error (a Lomb–Scargle periodogram generalised to the offset's direction). Periods from two
  cycles over the points' span down to three point spacings, where the points' phases spread round
  the cycle (on two levels of an axis any period fits); the best is refined on a finer grid.
- localised: the mean of r within a ball of radius ρ around each point, ρ a sixteenth, eighth and
  quarter of the part's largest extent; z = Σr/(σ√k) is standard normal without such an error
  (Bonferroni over every window tried).

A catalogue effect that only soaks up part of such an error explains little of it on held-out
blocks: when the scan finds structure and the chosen effects' held-out shrink is below
``SHRINK_CLAIM``, the answer is "unexplained" and those effects are possible, not claimed.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import chi2, norm

from stages.gap.fit import ALPHA

MIN_NORMAL = 0.2          # RMS of a normal component below which the offset along it is not fitted
SHRINK_CLAIM = 0.5        # held-out shrink the chosen effects need to be claimed next to found structure
MAX_SCAN_POINTS = 4000    # the scans use at most this many points (drawn with a fixed seed)
MAX_PERIODS = 200         # independent periods tried per axis at most
MIN_PHASE_COVER = 0.1     # a fifth of evenly spread phases' (``_phase_cover``)
_AXES = ("x", "y", "z")


def periodic_scan(F: dict, r: np.ndarray, sigma: float, alpha: float = ALPHA) -> dict | None:
    """The most significant periodic offset along a machine axis, if any.

    Parameters
    ----------
    F : dict
        Features of n points (``x_mm, y_mm, z_mm, nx, ny, nz``).
    r : (n,) ndarray
        Residual (µm).
    sigma : float
        Probe noise σ (µm).
    alpha : float
        False-claim rate over all axes and periods tried.

    Returns
    -------
    dict or None
        ``axis``, ``period_mm``, ``amplitude_um`` (peak of the fitted deviation along the normals,
        √2 × its RMS), ``offset_um`` {direction: peak offset}, ``gain_sigma2``, ``threshold_sigma2``,
        ``rms_um``; None when no period is significant.
    """
    pts = np.stack([F["x_mm"], F["y_mm"], F["z_mm"]], 1)
    nrm = np.stack([F["nx"], F["ny"], F["nz"]], 1)
    dirs = [j for j in range(3) if math.sqrt(float(np.mean(nrm[:, j] ** 2))) >= MIN_NORMAL]
    spacing = _spacing(pts)
    trials, best = [], None
    for ax in range(3):
        c = pts[:, ax]
        span = float(np.ptp(c))
        fmin, fmax = 2.0 / max(span, 1e-9), 1.0 / (3.0 * spacing)
        if fmax <= fmin:
            continue
        fmax = min(fmax, fmin + MAX_PERIODS / span)             # scan time bounded on dense plans
        f = np.arange(fmin, fmax, 1.0 / (5.0 * span))          # 5× oversampled
        trials.append((fmax - fmin) * span)                   # independent periods on this axis
        g = _gains(c, nrm[:, dirs], r, f)
        i = int(np.argmax(g))
        if best is None or g[i] > best[1]:
            best = (ax, g[i], f[i], span)
    if best is None:
        return None
    ax, _, f0, span = best
    fine = np.linspace(f0 - 0.2 / span, f0 + 0.2 / span, 81)  # the peak to a fiftieth of its width
    g = _gains(pts[:, ax], nrm[:, dirs], r, fine)
    f0 = float(fine[int(np.argmax(g))])
    gain = float(g.max()) / sigma ** 2
    thr = float(chi2.isf(alpha / max(sum(trials), 1.0), 2 * len(dirs)))
    if gain <= thr:
        return None
    X = _basis(pts[:, ax], nrm[:, dirs], f0)
    beta = np.linalg.lstsq(X, r, rcond=None)[0]
    fitted = X[:, 1:] @ beta[1:]
    fitted -= fitted.mean()                                   # the constant is not structure
    return {"axis": _AXES[ax], "period_mm": 1.0 / f0, "amplitude_um": math.sqrt(2.0) * float(np.std(fitted)),
            "offset_um": {_AXES[d]: float(math.hypot(beta[1 + 2 * k], beta[2 + 2 * k])) for k, d in enumerate(dirs)},
            "gain_sigma2": gain, "threshold_sigma2": thr, "rms_um": float(np.std(fitted)), "_fit": fitted}


def bump_scan(F: dict, r: np.ndarray, sigma: float, alpha: float = ALPHA) -> dict | None:
    """The most significant local mean of the residual, if any.

    Parameters
    ----------
    F, r, sigma, alpha
        As ``periodic_scan``.

    Returns
    -------
    dict or None
        ``centre_mm`` [x, y, z], ``radius_mm``, ``mean_um``, ``n_points``, ``z``, ``z_threshold``,
        ``bbox_mm`` of the points of the window; None when no window is significant.
    """
    pts = np.stack([F["x_mm"], F["y_mm"], F["z_mm"]], 1)
    tree = cKDTree(pts)
    size = float(np.ptp(pts, axis=0).max())
    centres = _subsample(len(pts))
    n_windows, best = 0.0, None
    for rho in (size / 16, size / 8, size / 4):
        nb = tree.query_ball_point(pts[centres], rho)
        k = np.array([len(v) for v in nb])
        s = np.array([r[v].sum() for v in nb])
        # every window tried counts: counting only the windows that do not overlap (the points over a
        # typical window's count) claimed structure in 1.3 % of pure-noise draws at α 0.1 % (sample plan)
        n_windows += float(np.sum(k >= 5))
        z = np.where(k >= 5, s / (sigma * np.sqrt(np.maximum(k, 1))), 0.0)
        i = int(np.argmax(np.abs(z)))
        if best is None or abs(z[i]) > abs(best["z"]):
            idx = nb[i]
            best = {"centre_mm": pts[centres[i]].tolist(), "radius_mm": rho, "mean_um": float(s[i] / k[i]),
                    "n_points": int(k[i]), "z": float(z[i]), "_idx": np.asarray(idx),
                    "bbox_mm": pts[idx].min(0).tolist() + pts[idx].max(0).tolist()}
    zthr = float(norm.isf(alpha / (2.0 * max(n_windows, 1.0))))
    if best is None or abs(best["z"]) <= zthr:
        return None
    best["z_threshold"] = zthr
    return best


def unexplained(F: dict, r: np.ndarray, sigma: float, floor_um: float = 0.0) -> dict | None:
    """Structure left in ``r`` beyond the noise: the periodic and the local scan, each kept when it
    is significant and its size (RMS of the periodic fit; |mean| of the window) reaches half of
    hypot(σ, floor), the size test of the selection.

    Parameters
    ----------
    F, r, sigma
        As ``periodic_scan``.
    floor_um : float
        The model's own floor (µm).

    Returns
    -------
    dict or None
        ``periodic`` and ``local`` (dicts or None) and ``description``; None when neither is found.
    """
    need = 0.5 * math.hypot(sigma, floor_um)
    idx = _subsample(len(r))
    F = {k: np.asarray(F[k])[idx] for k in ("x_mm", "y_mm", "z_mm", "nx", "ny", "nz")}
    r = np.asarray(r, float)[idx]
    per, loc = periodic_scan(F, r, sigma), bump_scan(F, r, sigma)
    # the weaker finding is looked for again once the stronger is taken out: a bump leaves a small
    # periodic trace and a periodic error a local mean at its crest
    if per is not None and (loc is None or per["gain_sigma2"] / per["threshold_sigma2"]
                            >= (loc["z"] / loc["z_threshold"]) ** 2):
        loc = bump_scan(F, r - per["_fit"], sigma)
    elif loc is not None:
        rr = r.copy()
        rr[loc["_idx"]] -= loc["mean_um"]
        per = periodic_scan(F, rr, sigma)
    if per is not None and per["rms_um"] < need:
        per = None
    if loc is not None and abs(loc["mean_um"]) < need:
        loc = None
    for d in (per, loc):
        for k in ("_fit", "_idx"):
            (d or {}).pop(k, None)
    if per is None and loc is None:
        return None
    parts = []
    if per is not None:
        parts.append(f"periodic along {per['axis']}: period {per['period_mm']:.3g} mm, amplitude {per['amplitude_um']:.2g} µm")
    if loc is not None:
        c = ", ".join(f"{v:.3g}" for v in loc["centre_mm"])
        parts.append(f"local: mean {loc['mean_um']:.2g} µm within {loc['radius_mm']:.2g} mm of ({c}) mm, "
                     f"{loc['n_points']} points")
    return {"periodic": per, "local": loc, "description": "; ".join(parts)}


def _basis(c: np.ndarray, nd: np.ndarray, f: float) -> np.ndarray:
    w = 2 * np.pi * f * c
    cols = [np.ones_like(c)]
    for j in range(nd.shape[1]):
        cols += [nd[:, j] * np.sin(w), nd[:, j] * np.cos(w)]
    return np.stack(cols, 1)


def _phase_cover(c: np.ndarray, f: float) -> float:
    """Smallest eigenvalue of the mean Gram matrix of (1, cos φ, sin φ), φ = 2πfc: 0.5 for phases
    spread round the cycle, 0 when they fall on two values (points on two levels of the axis: any
    period fits them)."""
    w = 2 * np.pi * f * c
    C1, S1, C2, S2 = np.mean(np.cos(w)), np.mean(np.sin(w)), np.mean(np.cos(2 * w)), np.mean(np.sin(2 * w))
    G = np.array([[1.0, C1, S1], [C1, (1 + C2) / 2, S2 / 2], [S1, S2 / 2, (1 - C2) / 2]])
    return float(np.linalg.eigvalsh(G)[0])


def _gains(c: np.ndarray, nd: np.ndarray, r: np.ndarray, freqs: np.ndarray) -> np.ndarray:
    """SSE reduction (µm²) of the periodic offset over a constant, per frequency; 0 where the points'
    phases do not determine a sinusoid (``_phase_cover`` below ``MIN_PHASE_COVER``)."""
    sse0 = float(np.sum((r - r.mean()) ** 2))
    out = np.zeros(len(freqs))
    for i, f in enumerate(freqs):
        if _phase_cover(c, f) < MIN_PHASE_COVER:
            continue
        X = _basis(c, nd, f)
        beta = np.linalg.lstsq(X, r, rcond=None)[0]
        out[i] = sse0 - float(np.sum((r - X @ beta) ** 2))
    return out


def _spacing(pts: np.ndarray) -> float:
    """Median distance of a point to its nearest neighbour (mm)."""
    sub = pts[_subsample(len(pts))]
    d, _ = cKDTree(pts).query(sub, k=2)
    return max(float(np.median(d[:, 1])), 1e-6)


def _subsample(n: int) -> np.ndarray:
    if n <= MAX_SCAN_POINTS:
        return np.arange(n)
    return np.sort(np.random.default_rng(0).choice(n, MAX_SCAN_POINTS, replace=False))
