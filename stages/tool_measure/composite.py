"""Composite compensation profile of seed 002 (claims 1–2): the first error plus the second error
measured on a part, between the transition points X1 and X2 where the second error is significant.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from stages import InputError
from stages.tool_measure.grid import CONTACT_DEG, STEP_DEG, on_grid


def contact_angle_deg(normals) -> np.ndarray:
    """Contact angle of the tool point that generates a surface point with outward normal n.

    The (corner) centre lies at contact + r·n, so the centre → contact direction is −n and its
    angle from the downward axis (0, 0, −1) is arccos(n_z) (DESIGN §5; ball and bull alike).
    """
    n = np.asarray(normals, dtype=float)
    nz = n[:, 2] / np.linalg.norm(n, axis=1)
    return np.degrees(np.arccos(np.clip(nz, -1.0, 1.0)))


def _kernel(sigma_bins):
    half = int(np.ceil(4 * sigma_bins))
    x = np.arange(-half, half + 1)
    return np.exp(-0.5 * (x / sigma_bins) ** 2)


def find_transitions(contact_deg, second_um, threshold_um, floor_um):
    """Transition points X1, X2 of seed 002: where the second error departs from zero and returns.

    A region is a run of angles where |second| ≥ threshold (significant); it is widened on both
    sides while the second error keeps its sign and stays above the floor, so the composite has
    no step larger than the floor at X1 and X2. NaN (no data) ends a region.

    Parameters
    ----------
    contact_deg : (m,) float
    second_um : (m,) float, NaN where no measured point informs the angle
    threshold_um, floor_um : float or (m,) float

    Returns
    -------
    list of dict
        x1_deg, x2_deg, peak_deg, peak_um, and slice indices i1, i2 (inclusive).
    """
    q = np.asarray(contact_deg, dtype=float)
    s = np.asarray(second_um, dtype=float)
    thr = np.broadcast_to(threshold_um, s.shape)
    floor = np.broadcast_to(floor_um, s.shape)
    fin = np.isfinite(s)
    core = fin & (np.abs(np.where(fin, s, 0)) >= thr)
    regions = []
    i, m = 0, s.size
    while i < m:
        if not core[i]:
            i += 1
            continue
        j = i
        while j + 1 < m and core[j + 1] and np.sign(s[j + 1]) == np.sign(s[i]):
            j += 1
        sign = np.sign(s[i])
        a, b = i, j
        while a - 1 >= 0 and fin[a - 1] and np.sign(s[a - 1]) == sign and abs(s[a - 1]) > floor[a - 1]:
            a -= 1
        while b + 1 < m and fin[b + 1] and np.sign(s[b + 1]) == sign and abs(s[b + 1]) > floor[b + 1]:
            b += 1
        k = a + int(np.argmax(np.abs(s[a:b + 1])))
        peak = s[k]
        if regions and a <= regions[-1]["i2"]:
            prev = regions[-1]
            prev["i2"], prev["x2_deg"] = b, float(q[b])
            if abs(peak) > abs(prev["peak_um"]):
                prev["peak_um"], prev["peak_deg"] = float(peak), float(q[k])
        else:
            regions.append({"x1_deg": float(q[a]), "x2_deg": float(q[b]), "peak_deg": float(q[k]),
                            "peak_um": float(peak), "i1": a, "i2": b})
        i = b + 1
    return regions


def composite_profile(tool_profile_df, points_xyz, deviation_um, normals, *, bandwidth_deg=0.5,
                      threshold_um=0.5, min_points=10.0, first_applied=True) -> pd.DataFrame:
    """Composite tool error shape CV2 + 3a1 of seed 002.

    The measured workpiece error at each point is the equivalent contour error of the tool
    point that generated it (material left ≡ the tool is smaller there: same sign), at the
    contact angle q = arccos(n_z). These are smoothed over q (Gaussian kernel regression), the
    transition points X1, X2 where this second error becomes significant are found, and between
    them it is added to the measured tool contour error.

    Parameters
    ----------
    tool_profile_df : DataFrame or path of a profile CSV
        contact_deg, error_um: the first error (CV2), e.g. from :func:`measure_tool`.
    points_xyz : (n, 3) float
        Measured points (mm); only checked (the contact angle depends on the normal alone).
    deviation_um : (n,) float
        Measured deviation along n, positive = material left (DESIGN §5).
    normals : (n, 3) float
        Outward surface normals (into air); points facing down (n_z < 0) cannot be cut by a
        3-axis tool and are dropped.
    bandwidth_deg : float
        Finest kernel standard deviation over the contact angle: the resolution of the second
        error where points are dense. Where fewer than ``min_points`` effective points fall
        within it, it is doubled (up to 16×) at that angle. Wider kernels round steep changes
        and then over-correct at the feet of a region (bias ≈ bandwidth² × curvature / 2).
    threshold_um : float
        Smallest second error treated as real; the effective threshold is also at least four
        standard errors of the local mean (many angles are tested at once).
    min_points : float
        Effective points wanted under the kernel; with 16× the bandwidth still fewer, the
        angle has no second error (NaN: no data, nothing added).
    first_applied : bool
        True (the seed's procedure) when the measured part was machined with the first error
        already compensated, so the deviation is all second error. False when it was machined
        uncompensated: the part then also shows the tool's own contour error, and the second
        error is the deviation minus the first error.

    Returns
    -------
    DataFrame
        contact_deg, error_um (composite), first_um, second_um (NaN: no data), second_se_um,
        n_eff, bandwidth_deg (used at that angle), in_transition. ``attrs``: transitions (list of X1/X2 regions, see
        :func:`find_transitions`), n_points, n_dropped.
    """
    if isinstance(tool_profile_df, (str, Path)):
        tool_profile_df = pd.read_csv(tool_profile_df)
    first = on_grid(tool_profile_df, "error_um", "tool_profile")
    p = np.asarray(points_xyz, dtype=float)
    d = np.asarray(deviation_um, dtype=float)
    n = np.asarray(normals, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or n.shape != p.shape or d.shape != (p.shape[0],):
        raise InputError(f"points_xyz {p.shape}, normals {n.shape}, deviation_um {d.shape}: "
                         "need (n, 3), (n, 3) and (n,)")
    bad = ~(np.isfinite(p).all(1) & np.isfinite(n).all(1) & np.isfinite(d)) | (np.linalg.norm(n, axis=1) == 0)
    if bad.any():
        raise InputError(f"measured point {int(np.flatnonzero(bad)[0])}: non-finite value or zero normal")
    q = contact_angle_deg(n)
    keep = q <= 90.0 + 1e-9
    q, d = np.minimum(q[keep], 90.0), d[keep]
    if not first_applied:
        d = d - np.interp(q, CONTACT_DEG, first)
    # bin on the 0.1° grid, then Gaussian kernel sums by convolution (O(n + grid))
    idx = np.clip(np.rint(q / STEP_DEG).astype(int), 0, CONTACT_DEG.size - 1)
    cnt = np.bincount(idx, minlength=CONTACT_DEG.size).astype(float)
    s1 = np.bincount(idx, weights=d, minlength=CONTACT_DEG.size)
    s2 = np.bincount(idx, weights=d * d, minlength=CONTACT_DEG.size)
    # measurement noise from neighbours in q (robust to a smooth trend): MAD of differences
    dd = np.diff(d[np.argsort(q, kind="stable")])
    noise = 1.4826 * np.median(np.abs(dd - np.median(dd))) / np.sqrt(2) if dd.size >= 2 else 0.0
    # adaptive bandwidth: at each angle the narrowest of bandwidth × 1, 2, 4, 8, 16 that holds
    # min_points effective points (dense data keep the resolution, sparse data are averaged)
    second = np.full(CONTACT_DEG.size, np.nan)
    se = np.full(CONTACT_DEG.size, np.nan)
    n_eff_used = np.zeros(CONTACT_DEG.size)
    bw_used = np.full(CONTACT_DEG.size, np.nan)
    todo = np.ones(CONTACT_DEG.size, dtype=bool)
    for factor in (1, 2, 4, 8, 16):
        ker = _kernel(min(bandwidth_deg * factor / STEP_DEG, (CONTACT_DEG.size - 1) / 8))
        W = np.convolve(cnt, ker, mode="same")
        W2 = np.convolve(cnt, ker ** 2, mode="same")
        S1 = np.convolve(s1, ker, mode="same")
        S2 = np.convolve(s2, ker, mode="same")
        with np.errstate(invalid="ignore", divide="ignore"):
            n_eff = np.where(W2 > 0, W ** 2 / W2, 0.0)
            mean = S1 / W
            var = np.maximum(S2 / W - mean ** 2, 0.0)
            # a local standard error from few points is itself noisy: use the larger of the
            # local and the global scatter so a chance tight cluster is not "significant"
            se_k = np.sqrt(np.maximum(var, noise ** 2) / np.maximum(n_eff - 1, 1))
        take = todo & (n_eff >= min_points)
        second[take], se[take] = mean[take], se_k[take]
        n_eff_used[take], bw_used[take] = n_eff[take], bandwidth_deg * factor
        todo &= ~take
    thr = np.maximum(threshold_um, 4 * np.nan_to_num(se))
    floor = np.maximum(0.1 * threshold_um, 2 * np.nan_to_num(se))
    regions = find_transitions(CONTACT_DEG, second, thr, floor)
    inside = np.zeros(CONTACT_DEG.size, dtype=bool)
    for r in regions:
        inside[r["i1"]:r["i2"] + 1] = True
    composite = first + np.where(inside, np.nan_to_num(second), 0.0)
    out = pd.DataFrame({"contact_deg": CONTACT_DEG.copy(), "error_um": composite, "first_um": first,
                        "second_um": second, "second_se_um": se, "n_eff": n_eff_used,
                        "bandwidth_deg": bw_used, "in_transition": inside})
    out.attrs["transitions"] = [{k: v for k, v in r.items() if k not in ("i1", "i2")} for r in regions]
    out.attrs["n_points"] = int(keep.sum())
    out.attrs["n_dropped"] = int((~keep).sum())
    return out
