"""Calibration on a reference part (a test cut with no effect to find): the force-model scale, the
prediction's floor near path corners, and the model floor left; applied to a measurement as its
baseline before the diagnosis.
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from stages.gap.effects import FORCE_SCALE_RANGE, catalogue
from stages.gap.fit import fit_effects, noise_sigma, params_of
from stages.gap.servo import refine_servo, servo_signature
from stages.gap.uncertainty import param_uncertainty, polish_fit


def apply_baseline(F: dict, force_scale: float, corner: Optional[tuple] = None,
                   floor_map: Optional[tuple] = None) -> dict:
    """The prediction with its force model scaled and, given ``corner`` = (a µm, λ mm), the model's
    own floor near path corners added (both calibrations found on a reference part:
    ``corner_floor``); given ``floor_map``, the reference's residual added point by point.

    Parameters
    ----------
    F : dict
        Features of n points (``point_id``, ``predicted_um``, ``pred_deflection_um``,
        ``measured_um``: (n,) µm).
    force_scale : float
        Force-model scale s0 (ratio).
    corner : (float, float), optional
        The corner floor (a µm, λ mm).
    floor_map : (ids, values), optional
        The reference's residual (µm) at its point ids; 0 at a point it does not have.

    Returns
    -------
    dict
        A copy of ``F`` with the prediction, its deflection part and the residual changed
        (``baseline_extra_um``: the corner floor's part, µm).
    """
    F = dict(F)
    F["predicted_um"] = F["predicted_um"] + (force_scale - 1.0) * F["pred_deflection_um"]
    F["pred_deflection_um"] = force_scale * F["pred_deflection_um"]
    if corner is not None:
        extra = servo_signature(F, corner[0], corner[1])
        F["predicted_um"] = F["predicted_um"] + extra
        # kept apart: a re-run of the prediction (``stages.gap.predictor.how_far``) adds it again
        F["baseline_extra_um"] = F.get("baseline_extra_um", 0.0) + extra
    if floor_map is not None:
        order = np.argsort(floor_map[0])
        ids, vals = np.asarray(floor_map[0])[order], np.asarray(floor_map[1], float)[order]
        pos = np.searchsorted(ids, F["point_id"]).clip(0, len(ids) - 1)
        extra = np.where(ids[pos] == F["point_id"], vals[pos], 0.0)
        F["predicted_um"] = F["predicted_um"] + extra
        F["baseline_extra_um"] = F.get("baseline_extra_um", 0.0) + extra
    F["residual_um"] = F["measured_um"] - F["predicted_um"]
    return F


def baseline(F: dict, calibration: dict) -> tuple[dict, float]:
    """A measurement with a reference part's ``calibration`` (``calibrate``) applied, and the model
    floor left for the diagnosis's size test (0 once the reference's residual is subtracted point
    by point)."""
    fm = calibration.get("_floor_map")
    F = apply_baseline(F, calibration["force_scale_s0"], calibration["corner_floor"], fm)
    return F, (0.0 if fm is not None else calibration["floor_um"])


S0_SE_MAX = 0.1  # the force scale is taken from a reference that pins it to 10 %
FLOOR_Z = 3.0   # the corner floor is taken when its amplitude is at least this many standard errors


def corner_floor(F: dict) -> Optional[tuple]:
    """The prediction's floor near path corners on a reference part (no effect), as the servo lag it
    reads as: (a µm, λ mm), or None without corners.

    Near corners the prediction (one generating point per pass) and a real machine differ by a
    pattern set by the path, not by the machine's state: on the sample raster, where a servo lag
    shows only ~1 µm RMS on ~100 points (the bisector lies nearly in the surface), it reads as a
    lag of about +30 µm with λ 0.05 mm. Left in, it adds to a real lag and pulls the fit along
    the a–λ ridge (a +12.5 µm, λ 0.31 mm lag read as +30 µm, λ 0.17 mm at σ 0.3 µm, 4.7 and 8.9
    stated SE off; all 6 servo misses over 3 fresh blind-check seeds were lags of that sign).
    Taken from the reference it is part of the baseline, like the force scale: on that seed the
    servo misses went from 3 to 2 (the σ 0.3 µm case within 20 %); the ones left, at σ ≥ 0.6 µm,
    are still lags of that sign. None when the reference does not pin it: amplitude below
    ``FLOOR_Z`` standard errors (``param_uncertainty`` at the polished fit).

    Parameters
    ----------
    F : dict
        Features of the reference part's n points.

    Returns
    -------
    (float, float) or None
        (a µm, λ mm).
    """
    cand = [e for e in catalogue(F) if e.name == "servo_corner"]
    if not cand:
        return None
    y = F["residual_um"].astype(float)
    ones = np.ones(len(y), bool)
    th, beta = fit_effects(F, y, ones, [], cand[0])
    chosen, beta = refine_servo(F, y, ones, [(cand[0], th)], beta)
    chosen, beta = polish_fit(F, y, chosen, beta)
    p = params_of(chosen, beta)["servo_corner"]
    a, lam = p["a_um"], p["lambda_mm"]
    if not (np.isfinite(a) and a != 0):
        return None
    # taken only when the reference pins it: read from the few points within ~0.1 mm of the
    # corners, one reference at σ 0.65 µm on the sample plan gives it to ±35–140 µm (+28 µm, λ 0.037
    # mm from one draw, +75 µm, λ 0.057 mm from another, +37 µm, λ 0.048 mm noise-free); subtracted
    # from every case, the second made 2 of 8 no-effect cases of its blind check claim a lag of −17 µm
    se = param_uncertainty(F, y, chosen, beta, noise_sigma(F, y))["se"].get("servo_corner", {}).get("a_um")
    if se is None or not abs(a) >= FLOOR_Z * se:
        return None
    return (a, lam)


def calibrate(F0: dict, predictor=None) -> dict:
    """Calibration on a reference part measured without any effect to find (a test cut on a warm,
    checked machine with a measured tool): the force-model scale s0, the prediction's floor near
    path corners as the servo lag it reads as (``corner_floor``: None unless the reference pins it
    to 3 standard errors), and the model floor left (residual RMS beyond the probe noise).

    s0 is the least-squares scale of the predicted deflection on the residual, taken only when the
    reference pins it (standard error ≤ ``S0_SE_MAX``) within ``FORCE_SCALE_RANGE``, else 1: on a
    floor plan the predicted deflection along the normals is nearly 0 and s0 came out −0.42 and
    1.88 from two references. When the model floor exceeds the probe noise (the prediction's own
    error on this program and plan: 4.5 µm RMS on the walls of the sample mould's Z-level program
    against 0.74 µm of noise, no effect to find), the reference's residual is kept to be subtracted
    point by point (``_floor_map``; its noise then adds to every measurement's, which the
    diagnosis's noise estimate sees), since a size test against such a floor hides every effect
    smaller than it and lets corner patterns pass for effects. With a ``predictor`` s0 becomes its
    baseline; ``baseline`` applies the calibration to a measurement.

    Parameters
    ----------
    F0 : dict
        Features of the reference part's n points.
    predictor : stages.gap.predictor.Predictor, optional
        Its ``scale`` is set to s0.

    Returns
    -------
    dict
        ``force_scale_s0``, ``force_scale_se``, ``corner_floor`` ((a µm, λ mm) or None), ``floor_um``,
        ``floor_subtracted`` (bool), ``n_points``, ``reference_rms_um``, ``noise_est_um`` (µm);
        ``_floor_map`` (ids, residual µm) when the floor is subtracted point by point (not for JSON).
    """
    d = F0["pred_deflection_um"]
    dd = float(np.dot(d, d))
    s0, se = 1.0, math.inf
    if dd > 0:
        fit = float(1.0 + np.dot(d, F0["residual_um"]) / dd)
        se = noise_sigma(F0, F0["residual_um"]) / math.sqrt(dd)
        if se <= S0_SE_MAX and FORCE_SCALE_RANGE[0] <= fit <= FORCE_SCALE_RANGE[1]:
            s0 = fit
    F0 = apply_baseline(F0, s0)
    if predictor is not None:
        predictor.scale = s0
    corner = corner_floor(F0)
    F0 = apply_baseline(F0, 1.0, corner)
    sig0 = noise_sigma(F0, F0["residual_um"])
    floor = float(math.sqrt(max(np.mean(F0["residual_um"] ** 2) - sig0 ** 2, 0.0)))
    out = {"force_scale_s0": s0, "force_scale_se": se if math.isfinite(se) else None, "corner_floor": corner,
           "floor_um": floor, "floor_subtracted": bool(floor > sig0), "n_points": int(len(F0["residual_um"])),
           "reference_rms_um": float(np.sqrt(np.mean(F0["residual_um"] ** 2))), "noise_est_um": sig0}
    if out["floor_subtracted"]:
        out["_floor_map"] = (np.asarray(F0["point_id"]).copy(), F0["residual_um"].astype(float).copy())
    return out
