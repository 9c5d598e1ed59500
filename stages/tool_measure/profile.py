"""The tool over several images: low-pass profile (CV1 → CV2), runout and cutting envelope.

Issue 6, seeds 002 (the first error CV1 filtered to CV2) and 003 (eccentricity from the axis seen at
several spindle angles). Each image's contour error comes from ``silhouette.measure_image``.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from scipy.ndimage import gaussian_filter1d

from stages import InputError
from stages.tool_measure.grid import CONTACT_DEG, STEP_DEG

# ISO 16610-21 Gaussian profile filter: sigma = sqrt(ln 2 / (2 pi^2)) * cutoff wavelength.
_ISO_SIGMA_PER_CUTOFF = float(np.sqrt(np.log(2.0) / (2.0 * np.pi ** 2)))


def lowpass(error_um, cutoff_deg=5.0, step_deg=STEP_DEG):
    """Seed 002 CV1 → CV2: zero-phase Gaussian profile filter (ISO 16610-21) along the contact angle.

    Parameters
    ----------
    error_um : (..., m) array on an even grid
    cutoff_deg : float
        Cutoff wavelength λc (50 % transmission), degrees of contact angle; 0 disables.

    Notes
    -----
    The ends are mirrored: the profile is even about the tip (both sides average to a
    symmetric curve) and continues smoothly into the shank at 90°.
    """
    e = np.asarray(error_um, dtype=float)
    if not cutoff_deg:
        return e.copy()
    sigma = _ISO_SIGMA_PER_CUTOFF * cutoff_deg / step_deg
    return gaussian_filter1d(e, sigma, axis=-1, mode="reflect")


def eccentricity(axis_um, angles_deg) -> dict:
    """Runout from the axis position seen at several spindle angles.

    The image shows the horizontal component of the eccentric offset: x(θ) = a + e·cos(θ − θ0).
    Fitted by linear least squares in (a, e cosθ0, e sinθ0).

    Returns
    -------
    dict
        eccentricity_um (None for one image), phase_deg (θ0: the spindle angle at which the tool
        axis is seen furthest to the image's right), spindle_axis_um (a), residual_um (RMS),
        lower_bound (True when fewer than 3 distinct angles fix the sinusoid).
    """
    x = np.asarray(axis_um, dtype=float)
    th = np.radians(np.asarray(angles_deg, dtype=float))
    distinct = np.unique(np.round(np.asarray(angles_deg, dtype=float) % 360.0, 6)).size
    if x.size < 2:
        return {"eccentricity_um": None, "phase_deg": None, "spindle_axis_um": float(x.mean()),
                "residual_um": None, "lower_bound": True}
    if distinct < 3:
        return {"eccentricity_um": float(np.ptp(x) / 2), "phase_deg": None, "spindle_axis_um": float(x.mean()),
                "residual_um": None, "lower_bound": True}
    A = np.column_stack([np.ones_like(th), np.cos(th), np.sin(th)])
    (a, b, c), *_ = np.linalg.lstsq(A, x, rcond=None)
    res = x - A @ np.array([a, b, c])
    return {"eccentricity_um": float(np.hypot(b, c)), "phase_deg": float(np.degrees(np.arctan2(c, b)) % 360.0),
            "spindle_axis_um": float(a), "residual_um": float(np.sqrt(np.mean(res ** 2))),
            "lower_bound": False}


def measure_tool(measurements, angles_deg, um_per_px, cutoff_deg=5.0):
    """Combine per-image measurements into the tool profile, runout and envelope.

    Parameters
    ----------
    measurements : list of dict
        Outputs of :func:`measure_image` (same tool, different spindle angles).
    angles_deg : (n,) float
        Spindle angle of each image.
    um_per_px : float
    cutoff_deg : float
        Low-pass cutoff for CV2 (see :func:`lowpass`).

    Returns
    -------
    profile : DataFrame
        contact_deg, error_um (CV2, filtered), error_raw_um (CV1: mean over images and sides,
        each about its own axis, so runout is excluded).
    summary : dict
        eccentricity (see :func:`eccentricity`), envelope {contact_deg, error_um}: the cutting
        envelope = outermost filtered image profile minus e·sin q (the runout of the rotating
        tool sweeps every angle, not only the imaged ones), flute_spread_um (largest spread
        between image profiles: non-axisymmetric edges), per-image axis offsets.
    """
    if not measurements:
        raise InputError("no images to measure")
    err = np.stack([m["error_um"] for m in measurements])          # (n, 2, m)
    cv1 = err.mean(axis=(0, 1))
    cv2_ = lowpass(cv1, cutoff_deg)
    axis_um = np.array([m["centre_px"][0] for m in measurements]) * um_per_px
    zc_um = np.array([m["centre_px"][1] for m in measurements]) * um_per_px
    ecc = eccentricity(axis_um, angles_deg)
    e = ecc["eccentricity_um"] or 0.0
    filtered = lowpass(err.reshape(-1, err.shape[-1]), cutoff_deg)
    envelope = filtered.min(axis=0) - e * np.sin(np.radians(CONTACT_DEG))
    spread = filtered.max(axis=0) - filtered.min(axis=0)
    images = [{
        "file": Path(m.get("file", f"image{i}")).name,
        "spindle_deg": float(a),
        "axis_offset_um": float(x - ecc["spindle_axis_um"]),
        "centre_z_offset_um": float(z - zc_um.mean()),
        "diameter_um": m["diameter_um"],
        "radius_fit_um": m["radius_fit_um"],
    } for i, (m, a, x, z) in enumerate(zip(measurements, angles_deg, axis_um, zc_um))]
    profile = pd.DataFrame({"contact_deg": CONTACT_DEG.copy(), "error_um": cv2_, "error_raw_um": cv1})
    summary = {
        "n_images": len(measurements),
        "eccentricity_um": ecc["eccentricity_um"],
        "eccentricity": ecc,
        "envelope": {"contact_deg": CONTACT_DEG.tolist(), "error_um": np.round(envelope, 4).tolist()},
        "flute_spread_max_um": float(spread.max()),
        "centre_z_px": float(np.mean([m["centre_px"][1] for m in measurements])),
        "images": images,
        "lowpass": {"filter": "Gaussian, ISO 16610-21", "cutoff_deg": cutoff_deg},
    }
    return profile, summary
