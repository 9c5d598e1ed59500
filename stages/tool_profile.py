"""Tool contour, runout and wear from backlit silhouette images; composite compensation profile.

Issue 6, seeds 002 (JP7659657B2: first error CV1 → CV2, second error, transitions X1/X2) and 003
(in-machine microscope: eccentricity and wear to ~0.7 µm).

Image conventions: 8- or 16-bit grey (colour is converted), tool dark on a bright back-light, tool
axis vertical (image columns), tip down, scale ``um_per_px`` given. Image coordinates: x to the
right, y down; pixel centres at integer coordinates.

Profile conventions (DESIGN §5): contact angle q at the ball (or corner) centre between the
downward tool axis and the contour point, 0° tip, 90° equator, grid 0–90° in 0.1° steps.
``error_um`` positive = tool smaller than nominal there (it leaves material on the part).

How the edge is found. Row scans lose accuracy where the edge is nearly horizontal (the tip), so
the edge is sampled along the normal of the ideal profile instead: one ray per contact angle and
side from the (corner) centre, intensity interpolated bicubically (``cv2.remap``) every 0.25 px.
The edge is first the crossing, walking outward from inside the tool (dust in the background
does not matter), of the 50 % level between the dark and bright ends of the ray; it is then
refined by area: the integral of the normalised darkness over ±3 px, with the dark and bright
levels read 3–8 px either side, equals the distance to the edge for any symmetric blur and for
pixel integration, so it carries neither the sub-pixel-phase bias of an interpolated crossing
(up to ~0.1 px, not averaged where the phase is stationary: tip and equator) nor the bias of a
back-light that falls off along the ray (vignetting). The centre is fitted by robust least
squares (Huber IRLS) on these points with the nominal radius and the rays resampled from the
new centre until it moves less than 0.005 px.
"""
from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
from scipy.ndimage import gaussian_filter1d

from stages import InputError

STEP_DEG = 0.1
CONTACT_DEG = np.round(np.arange(0, 901) * STEP_DEG, 1)
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".bmp", ".jpg", ".jpeg")
# ISO 16610-21 Gaussian profile filter: sigma = sqrt(ln 2 / (2 pi^2)) * cutoff wavelength.
_ISO_SIGMA_PER_CUTOFF = float(np.sqrt(np.log(2.0) / (2.0 * np.pi ** 2)))
_ANGLE_RE = re.compile(r"(\d+(?:\.\d+)?)\s*deg", re.IGNORECASE)
_RAY_STEP_PX = 0.25


# --------------------------------------------------------------------------------------------
# files and image checks
# --------------------------------------------------------------------------------------------

def list_images(images_dir) -> list[Path]:
    """Image files of a directory (png, tif, bmp, jpg), sorted by name.

    Raises
    ------
    InputError
        The directory does not exist or holds no image file.
    """
    d = Path(images_dir)
    if not d.is_dir():
        raise InputError(f"{d}: not a directory of tool images")
    paths = sorted(p for p in d.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not paths:
        raise InputError(f"{d}: no images ({', '.join(IMAGE_SUFFIXES)}) in this directory")
    return paths


def spindle_angles(paths) -> tuple[np.ndarray, str]:
    """Spindle angle of each image, from its file name (``t1_060deg.png`` → 60°).

    If no name carries an angle, the images are taken as evenly spaced over one turn in name
    order. A mix of named and unnamed files is an error (naming the first file without one).

    Returns
    -------
    angles_deg : (n,) float
    source : "file names" or "assumed evenly spaced"
    """
    found = [_ANGLE_RE.findall(Path(p).stem) for p in paths]
    if not any(found):
        n = len(paths)
        return np.arange(n) * 360.0 / n, "assumed evenly spaced"
    for p, f in zip(paths, found):
        if not f:
            raise InputError(f"{p}: no spindle angle in the file name (e.g. t1_060deg.png) while "
                             "other images of the directory have one")
    return np.array([float(f[-1]) for f in found]) % 360.0, "file names"


def load_image(path) -> tuple[np.ndarray, float]:
    """Read one image as float32 grey levels.

    Returns
    -------
    grey : (h, w) float32
    full_scale : float
        The value a saturated pixel has (255 for 8-bit, 65535 for 16-bit).

    Raises
    ------
    InputError
        Missing, empty or undecodable file, or an image too small to hold a tool; the message
        starts with the path.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such image file")
    if path.stat().st_size == 0:
        raise InputError(f"{path}: empty file (0 bytes)")
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise InputError(f"{path}: unreadable: OpenCV cannot decode it as an image")
    if raw.dtype == np.uint8:
        full = 255.0
    elif raw.dtype == np.uint16:
        full = 65535.0
    else:
        raise InputError(f"{path}: unsupported pixel type {raw.dtype} (use 8- or 16-bit grey)")
    if raw.ndim == 3:
        code = {3: cv2.COLOR_BGR2GRAY, 4: cv2.COLOR_BGRA2GRAY}.get(raw.shape[2])
        if code is None:
            raise InputError(f"{path}: unsupported number of channels {raw.shape[2]}")
        raw = cv2.cvtColor(raw, code)
    if raw.size == 0 or min(raw.shape[:2]) < 16:
        raise InputError(f"{path}: empty image ({raw.shape[1]}×{raw.shape[0]} px)")
    return raw.astype(np.float32), full


def image_levels(grey: np.ndarray, full_scale: float, max_saturated: float = 0.01) -> tuple[float, float]:
    """Check exposure and return the (dark, bright) grey levels of tool and back-light.

    Raises
    ------
    InputError
        Blank image, saturated background, or no dark silhouette (message without the path;
        :func:`measure_image_file` adds it).
    """
    if float(grey.max()) == float(grey.min()):
        raise InputError(f"empty image: every pixel is {grey.flat[0]:g} (no back-light, lens cap or blank frame)")
    saturated = float(np.mean(grey >= full_scale - 0.5))
    if saturated > max_saturated:
        raise InputError(f"saturated: {100 * saturated:.1f} % of pixels at full scale ({full_scale:g}); "
                         "the 50 % edge level is then wrong — lower the exposure or the back-light")
    g8 = np.clip(grey * (255.0 / full_scale), 0, 255).astype(np.uint8)
    t, _ = cv2.threshold(g8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    t = (t + 0.5) * full_scale / 255.0
    low, high = grey[grey < t], grey[grey >= t]
    if low.size == 0 or high.size == 0:
        raise InputError("no tool: the image has a single grey level class")
    dark, bright = float(np.median(low)), float(np.median(high))
    contrast = (bright - dark) / full_scale
    if contrast < 0.2:
        raise InputError(f"no tool: no dark silhouette against a bright back-light (contrast "
                         f"{100 * contrast:.0f} % of full scale, need ≥ 20 %)")
    return dark, bright


# --------------------------------------------------------------------------------------------
# edge sampling and fit
# --------------------------------------------------------------------------------------------

def _tool_radii(diameter_mm, tool_type, corner_radius_mm):
    """(r0, rc) in mm: corner-centre distance from the axis and corner (contour arc) radius."""
    R = 0.5 * float(diameter_mm)
    if tool_type == "ball":
        return 0.0, R
    if tool_type == "bull":
        if corner_radius_mm is None or not (0 < corner_radius_mm < R):
            raise InputError("corner_radius_mm: a bull-nose tool needs 0 < corner radius < diameter/2")
        return R - float(corner_radius_mm), float(corner_radius_mm)
    raise InputError(f"tool_type: {tool_type!r}: contour measurement needs 'ball' or 'bull'")


def _locate(grey, dark, bright, r0_px, rc_px, um_per_px, scale_tol):
    """Coarse centre (pixel level) from the largest dark blob; checks the tool is in the field."""
    h, w = grey.shape
    mask = (grey < 0.5 * (dark + bright)).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if n < 2:
        raise InputError("no tool: no dark region")
    lab = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    x0, y0, bw, bh, area = (int(v) for v in stats[lab, :5])
    if area < 0.01 * h * w:
        raise InputError(f"no tool: the largest dark region has only {area} px")
    if y0 != 0:
        raise InputError("no tool: no dark silhouette enters from the top edge "
                         "(expected: tool axis vertical, tip down)")
    if y0 + bh >= h:
        raise InputError("the tool reaches the bottom edge: tip not in the field (or tool upside down)")
    if x0 == 0 or x0 + bw >= w:
        raise InputError("the tool touches the left/right edge: field too narrow, tool off centre or wrong scale")
    y_tip = y0 + bh - 1 + 0.5
    zc = y_tip - rc_px
    if zc < 2:
        raise InputError(f"wrong scale or field too small: the field ends {(-zc + 2) * um_per_px:.0f} µm below "
                         "the (corner) centre; image the tip up to beyond the equator, check --um-per-px and --diameter-mm")
    cols = np.flatnonzero(labels[int(round(zc))] == lab)
    xl, xr = cols.min() - 0.5, cols.max() + 0.5
    width = xr - xl
    nominal = 2 * (r0_px + rc_px)
    # a row at the nominal equator shows ~the true diameter when the scale is wrong: a coarse check
    # here keeps the ray search from chasing an edge outside its window
    if abs(width / nominal - 1) > max(1.5 * scale_tol, 0.05):
        raise InputError(f"wrong scale: the silhouette is {width * um_per_px:.0f} µm wide at the equator row, "
                         f"nominal {nominal * um_per_px:.0f} µm (check --um-per-px {um_per_px:g} and --diameter-mm)")
    return 0.5 * (xl + xr), zc


def sample_edges(grey, xc, zc, r0_px, rc_px, contact_deg=CONTACT_DEG, half_window_px=None, min_contrast=0.0):
    """Sub-pixel edge radius along the normal rays of the ideal profile.

    Parameters
    ----------
    grey : (h, w) float32
    xc, zc : float
        Tool axis column and (corner) centre row, px.
    r0_px, rc_px : float
        Corner-centre distance from the axis and contour arc radius, px (ball: 0, R).
    contact_deg : (m,) float
    half_window_px : float, optional
        The ray spans rc ± this (default max(25 px, 6 % of rc)).
    min_contrast : float
        Grey-level difference between the ray's ends below which it crossed no edge.

    Returns
    -------
    radius : (2, m) float
        Edge distance from the right (row 0) and left (row 1) corner centre, px; NaN where the
        ray leaves the image or shows no dark-to-bright transition.
    """
    if half_window_px is None:
        half_window_px = max(25.0, 0.06 * rc_px)
    h, w = grey.shape
    q = np.radians(np.asarray(contact_deg, dtype=float))
    t = np.arange(-half_window_px, half_window_px + 0.5 * _RAY_STEP_PX, _RAY_STEP_PX)
    r = rc_px + t
    out = np.full((2, q.size), np.nan)
    nend = max(3, r.size * 15 // 100)
    half_area = int(round(3.0 / _RAY_STEP_PX))          # area window ±3 px
    level_len = int(round(5.0 / _RAY_STEP_PX))          # then 5 px for the local levels
    rows = np.arange(q.size)
    for k, sgn in enumerate((1.0, -1.0)):
        mx = (xc + sgn * r0_px) + sgn * np.sin(q)[:, None] * r[None, :]
        my = zc + np.cos(q)[:, None] * r[None, :]
        # rays may run out of the field beyond the edge (tight crop under the tip): the samples
        # inside form a prefix of the ray; its last nend samples give the bright level
        valid = (mx >= 0) & (mx <= w - 1) & (my >= 0) & (my <= h - 1)
        n_in = np.where(valid.all(axis=1), r.size, np.argmin(valid, axis=1))
        v = cv2.remap(grey, mx.astype(np.float32), my.astype(np.float32), cv2.INTER_CUBIC,
                      borderMode=cv2.BORDER_REPLICATE)
        dark = np.median(v[:, :nend], axis=1)
        tail = np.clip(n_in[:, None] - nend + np.arange(nend)[None, :], 0, r.size - 1)
        bright = np.median(v[rows[:, None], tail], axis=1)
        thr = 0.5 * (dark + bright)
        above = v >= thr[:, None]
        j = np.argmax(above, axis=1)
        gap = int(round(3.0 / _RAY_STEP_PX))           # bright level ≥ 3 px beyond the crossing
        ok = (valid[:, 0] & above.any(axis=1) & (j > 0) & (j < n_in - nend - gap)
              & (bright - dark > max(min_contrast, 0.0)))
        jj = np.where(ok, j, 1)
        v0, v1 = v[rows, jj - 1], v[rows, jj]
        frac = np.where(v1 > v0, (thr - v0) / np.where(v1 > v0, v1 - v0, 1.0), 0.5)
        # Refine by area: over a window centred on the crossing, the integral of the normalised
        # darkness equals the distance to the edge for any symmetric blur and for pixel
        # integration; the 50 % crossing of interpolated samples is biased by up to ~0.1 px with
        # the sub-pixel phase, which the filter averages away except where the phase is stationary
        # (the tip and the equator).
        # levels just outside the area window (3-8 px from the crossing): the back-light falls
        # off along the ray (vignetting), and levels read at the ray's far end bias the area
        centre = jj - 1 + frac
        c = np.rint(centre).astype(int)
        near = np.arange(half_area, half_area + level_len)[None, :]
        bright_near = np.median(v[rows[:, None], np.clip(c[:, None] + near, 0, r.size - 1)], axis=1)
        dark_near = np.median(v[rows[:, None], np.clip(c[:, None] - near, 0, r.size - 1)], axis=1)
        a = np.clip(c - half_area, 0, r.size - 1 - 2 * half_area)
        win = a[:, None] + np.arange(2 * half_area + 1)[None, :]
        dark_frac = ((bright_near[:, None] - v[rows[:, None], win])
                     / np.maximum(bright_near - dark_near, 1e-6)[:, None])
        area = _RAY_STEP_PX * (dark_frac.sum(axis=1) - 0.5 * (dark_frac[:, 0] + dark_frac[:, -1]))
        inside_window = (c - half_area - level_len >= 0) & (c + half_area + level_len < n_in)
        out[k] = np.where(ok & inside_window, r[a] + area, np.nan)
    return out


def _huber_fit(design, y, n_iter=20):
    """Robust linear least squares (Huber weights, k = 1.345 MAD-sigma), NaN rows ignored."""
    good = np.isfinite(y)
    A, b = design[good], y[good]
    wts = np.ones(b.size)
    coef = np.zeros(A.shape[1])
    for _ in range(n_iter):
        sw = np.sqrt(wts)
        coef, *_ = np.linalg.lstsq(A * sw[:, None], b * sw, rcond=None)
        res = b - A @ coef
        s = 1.4826 * np.median(np.abs(res - np.median(res))) + 1e-9
        k = 1.345 * s
        wts = np.minimum(1.0, k / np.maximum(np.abs(res), 1e-12))
    return coef


def _design(contact_deg):
    q = np.radians(np.asarray(contact_deg, dtype=float))
    ux = np.concatenate([np.sin(q), -np.sin(q)])
    uy = np.concatenate([np.cos(q), np.cos(q)])
    return ux, uy


def measure_image(grey, full_scale, um_per_px, diameter_mm, tool_type="ball", corner_radius_mm=None,
                  reference="lsq", scale_tol=0.05, max_missing=0.05, centre_z_px=None):
    """Contour error of one silhouette, per contact angle and side, about its own axis.

    Parameters
    ----------
    grey : (h, w) float array
    full_scale : float
        Saturation value (255 or 65535).
    um_per_px : float
    diameter_mm : float
    tool_type : "ball" or "bull"
    corner_radius_mm : float, optional
        Required for "bull".
    reference : "lsq" or "tip"
        How the ideal profile is placed along the axis: robust least squares with the nominal
        radius ("lsq"), or through the measured tip (error 0 at q = 0, as a tool length set on
        the tip would place it). The axis column is always fitted.
    scale_tol : float
        Relative deviation of measured from nominal diameter (and, for a ball, of the freely
        fitted radius) above which the image is refused as being at the wrong scale.
    max_missing : float
        Largest fraction of contact angles whose ray may miss the edge (dust, chips); those are
        interpolated.
    centre_z_px : float, optional
        Fix the (corner) centre row instead of fitting it: the machine frame of an earlier
        measurement of the same tool (its ``fit.centre_z_px``). Needed for wear: a fitted centre
        absorbs part of a broad wear land, a fixed frame does not. The axis column is still
        fitted (the silhouette is symmetric about it).

    Returns
    -------
    dict
        contact_deg (m,), error_um (2, m) right/left, centre_px (xc, zc), diameter_um,
        radius_fit_um (free fit), edge_xy_px (2, 2, m) edge points for overlays, shape.

    Raises
    ------
    InputError
        Bad exposure, no tool, tool not in the field, wrong scale, edge not found.
    """
    if not um_per_px > 0:
        raise InputError(f"um_per_px: must be > 0, got {um_per_px}")
    if reference not in ("lsq", "tip"):
        raise InputError(f"reference: {reference!r}: use 'lsq' or 'tip'")
    r0_mm, rc_mm = _tool_radii(diameter_mm, tool_type, corner_radius_mm)
    grey = np.asarray(grey, dtype=np.float32)
    dark, bright = image_levels(grey, full_scale)
    r0_px, rc_px = 1000.0 * r0_mm / um_per_px, 1000.0 * rc_mm / um_per_px
    xc, zc = _locate(grey, dark, bright, r0_px, rc_px, um_per_px, scale_tol)
    min_contrast = 0.5 * (bright - dark)  # a ray with less than half the image contrast crossed no edge
    ux, uy = _design(CONTACT_DEG)
    ones = np.ones_like(ux)
    for _ in range(8):
        radius = sample_edges(grey, xc, zc, r0_px, rc_px, min_contrast=min_contrast)
        y = radius.ravel() - rc_px
        if np.mean(~np.isfinite(y)) > 0.5:
            raise InputError("edge not found along most normals of the nominal profile "
                             "(wrong scale, wrong tool type or diameter, or no tool)")
        if centre_z_px is not None:
            dx, = _huber_fit(ux[:, None], y)
            dz = float(centre_z_px) - zc
        elif reference == "lsq":
            dx, dz = _huber_fit(np.column_stack([ux, uy]), y)
        else:
            dx, = _huber_fit(ux[:, None], y)
            tip = CONTACT_DEG <= 1.0
            dz = float(np.nanmedian(np.concatenate([y[:CONTACT_DEG.size][tip], y[CONTACT_DEG.size:][tip]])))
        xc, zc = xc + dx, zc + dz
        if np.hypot(dx, dz) < 0.005:
            break
    radius = sample_edges(grey, xc, zc, r0_px, rc_px, min_contrast=min_contrast)
    missing = np.mean(~np.isfinite(radius), axis=1)
    if missing.max() > max_missing:
        raise InputError(f"edge not found at {100 * missing.max():.0f} % of the contact angles (dirt or chips "
                         "on the edge, tool partly outside the field, or wrong scale/diameter)")
    for k in range(2):
        bad = ~np.isfinite(radius[k])
        if bad.any():
            radius[k, bad] = np.interp(CONTACT_DEG[bad], CONTACT_DEG[~bad], radius[k, ~bad])
    dR, _, _ = _huber_fit(np.column_stack([ones, ux, uy]), radius.ravel() - rc_px)
    radius_fit_um = (rc_px + dR) * um_per_px
    diameter_um = (radius[0, -1] + radius[1, -1] + 2 * r0_px) * um_per_px
    nominal_um = 1000.0 * diameter_mm
    if abs(diameter_um / nominal_um - 1) > scale_tol or (
            tool_type == "ball" and abs(radius_fit_um / (500.0 * diameter_mm) - 1) > scale_tol):
        raise InputError(f"wrong scale: measured diameter {diameter_um:.0f} µm (fitted radius "
                         f"{radius_fit_um:.0f} µm), nominal {nominal_um:.0f} µm, beyond ±{100 * scale_tol:g} % "
                         f"(check --um-per-px {um_per_px:g} and --diameter-mm {diameter_mm:g})")
    q = np.radians(CONTACT_DEG)
    sgn = np.array([1.0, -1.0])[:, None]
    edge_x = xc + sgn * (r0_px + radius * np.sin(q))
    edge_y = zc + radius * np.cos(q)
    return {
        "contact_deg": CONTACT_DEG.copy(),
        "error_um": (rc_px - radius) * um_per_px,
        "centre_px": (float(xc), float(zc)),
        "reference": reference if centre_z_px is None else "fixed centre row",
        "diameter_um": float(diameter_um),
        "radius_fit_um": float(radius_fit_um),
        "edge_xy_px": np.stack([edge_x, edge_y]),
        "shape": grey.shape,
        "levels": (dark, bright),
    }


def measure_image_file(path, um_per_px, diameter_mm, tool_type="ball", **kw):
    """:func:`load_image` + :func:`measure_image`; every error message starts with the path."""
    grey, full = load_image(path)
    try:
        m = measure_image(grey, full, um_per_px, diameter_mm, tool_type, **kw)
    except InputError as e:
        raise InputError(f"{path}: {e}") from None
    m["file"] = str(path)
    return m


# --------------------------------------------------------------------------------------------
# profiles over several images: filter, eccentricity, envelope
# --------------------------------------------------------------------------------------------

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


# --------------------------------------------------------------------------------------------
# wear
# --------------------------------------------------------------------------------------------

def _on_grid(df, column, name):
    if "contact_deg" not in df or column not in df:
        raise InputError(f"{name}: needs columns contact_deg and {column}")
    q = np.asarray(df["contact_deg"], dtype=float)
    v = np.asarray(df[column], dtype=float)
    if q.size < 2 or np.any(np.diff(q) <= 0) or not np.all(np.isfinite(v)):
        raise InputError(f"{name}: contact_deg must increase and {column} be finite")
    return np.interp(CONTACT_DEG, q, v)


def wear_profile(before, after, cut_length_m=None) -> pd.DataFrame:
    """Wear per contact angle between two profiles of the same tool.

    Parameters
    ----------
    before, after : DataFrame
        Profiles (contact_deg, error_um) measured before and after a job.
    cut_length_m : float, optional
        Cutting length of the job (see :func:`cut_length_m`); gives the wear rate.

    Returns
    -------
    DataFrame
        contact_deg, wear_um (after − before; positive = the tool lost material there),
        wear_rate_um_per_m (NaN without a cut length), cut_length_m.
    """
    wear = _on_grid(after, "error_um", "after") - _on_grid(before, "error_um", "before")
    L = float(cut_length_m) if cut_length_m else np.nan
    return pd.DataFrame({"contact_deg": CONTACT_DEG.copy(), "wear_um": wear,
                         "wear_rate_um_per_m": wear / L if L > 0 else np.full_like(wear, np.nan),
                         "cut_length_m": np.full_like(wear, L)})


def cut_length_m(passes, cut_filter=None) -> float:
    """Length of the feed moves of a program, metres (DESIGN §6 passes table).

    Parameters
    ----------
    passes : pyarrow Table or DataFrame
        The passes table (motion, x0_mm..z1_mm).
    cut_filter : pyarrow Table or DataFrame, optional
        The cut_filter table; when given only passes with ``is_cutting`` count.
    """
    df = passes.to_pandas() if hasattr(passes, "to_pandas") else pd.DataFrame(passes)
    feed = df["motion"].to_numpy() != 0
    if cut_filter is not None:
        cf = cut_filter.to_pandas() if hasattr(cut_filter, "to_pandas") else pd.DataFrame(cut_filter)
        cutting = dict(zip(cf["pass_id"], cf["is_cutting"]))
        feed &= df["pass_id"].map(cutting).fillna(False).to_numpy(dtype=bool)
    d = np.column_stack([df[f"{a}1_mm"] - df[f"{a}0_mm"] for a in "xyz"])
    return float(np.linalg.norm(d[feed], axis=1).sum() / 1000.0)


# --------------------------------------------------------------------------------------------
# composite compensation (seed 002, claims 1-2)
# --------------------------------------------------------------------------------------------

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
    first = _on_grid(tool_profile_df, "error_um", "tool_profile")
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
