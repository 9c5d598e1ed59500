"""One backlit silhouette: the tool's contour error per contact angle and side, about its own axis.

Issue 6, seeds 002 (JP7659657B2: first error CV1) and 003 (in-machine microscope). Image
coordinates: x to the right, y down; pixel centres at integer coordinates; scale ``um_per_px`` given.
Profile conventions: ``grid.py``.

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

import cv2
import numpy as np

from stages import InputError
from stages.geometry.cutter import Cutter
from stages.tool_measure.grid import CONTACT_DEG
from stages.tool_measure.images import image_levels, load_image

_RAY_STEP_PX = 0.25


def tool_radii_mm(diameter_mm, tool_type, corner_radius_mm=None) -> tuple[float, float]:
    """Corner-centre distance from the axis and corner (contour arc) radius of the nominal tool, mm.

    Parameters
    ----------
    diameter_mm : float
    tool_type : "ball" or "bull"
    corner_radius_mm : float, optional
        Required for "bull".

    Returns
    -------
    (r0, rc) : the cutter's core radius R − rc and corner radius rc (ball: 0, R).

    Raises
    ------
    stages.InputError
        Another tool type (a flat end mill has no contour arc to measure) or a bad corner radius.
    """
    if tool_type not in ("ball", "bull"):
        raise InputError(f"tool_type: {tool_type!r}: contour measurement needs 'ball' or 'bull'")
    cutter = Cutter.from_params({"type": tool_type, "diameter_mm": diameter_mm, "corner_radius_mm": corner_radius_mm})
    return cutter.core_mm, cutter.corner_mm


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
    r0_mm, rc_mm = tool_radii_mm(diameter_mm, tool_type, corner_radius_mm)
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
