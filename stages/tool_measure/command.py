"""``pipeline tool-profile``: tool contour, runout and envelope from a directory of silhouette images.

One function, :func:`tool_profile_command`, does the whole job (``images`` → ``silhouette`` →
``profile``); the click command in ``pipeline/cli.py`` only parses options and prints its summary.
Outputs beside ``out_csv``:

- ``<name>.csv``: contact_deg, error_um (low-pass filtered, seed 002 CV2), error_raw_um (CV1);
  the tool-profile table of ``tool.profile`` (DESIGN §4);
- ``<name>.json``: eccentricity, envelope, fit, per-image axis offsets;
- ``<name>.png``: fitted vs measured profile overlay and the error curves.

Every image is read and checked before anything is written, and the three files are written
under temporary names and renamed at the end, so an error leaves no partial output.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from stages import InputError
from stages.tool_measure.images import list_images, load_image, spindle_angles
from stages.tool_measure.profile import measure_tool
from stages.tool_measure.silhouette import measure_image_file, tool_radii_mm


def tool_profile_command(images_dir, um_per_px, diameter_mm, tool_type="ball", out_csv="profile.csv", *,
                         corner_radius_mm=None, cutoff_deg=5.0, reference="lsq", scale_tol=0.05,
                         centre_z_px=None) -> dict:
    """Measure a tool from its silhouette images and write profile CSV, JSON and PNG.

    Parameters
    ----------
    images_dir : path
        Directory of images of one tool at different spindle angles (angle in the file name as
        ``..._060deg.png``, else assumed evenly spaced over a turn in name order).
    um_per_px : float
        Image scale.
    diameter_mm : float
        Nominal tool diameter.
    tool_type : "ball" or "bull"
    out_csv : path
        Profile CSV to write; the JSON and PNG take the same name with their suffix.
    corner_radius_mm : float, optional
        Nominal corner radius (bull-nose tools).
    cutoff_deg : float
        Low-pass cutoff (ISO 16610-21 Gaussian) for CV1 → CV2, degrees of contact angle.
    reference : "lsq" or "tip"
        Axial placement of the ideal profile (see :func:`stages.tool_measure.silhouette.measure_image`).
    scale_tol : float
        Relative diameter mismatch above which an image is refused as being at the wrong scale.
    centre_z_px : float, optional
        Reuse the centre row of an earlier measurement of the same tool in the same machine frame
        (its JSON ``centre_z_px``), so that the difference of the two profiles is the wear.

    Returns
    -------
    dict
        The JSON summary without the envelope arrays, plus the paths written (csv, json, png).

    Raises
    ------
    stages.InputError
        Any unusable image (the message names the file) or bad argument; nothing is written.
    """
    if tool_type not in ("ball", "bull"):
        raise InputError(f"--type: {tool_type!r}: use ball or bull")
    if not (um_per_px and um_per_px > 0):
        raise InputError(f"--um-per-px: must be > 0, got {um_per_px}")
    if not (diameter_mm and diameter_mm > 0):
        raise InputError(f"--diameter-mm: must be > 0, got {diameter_mm}")
    paths = list_images(images_dir)
    angles, angle_source = spindle_angles(paths)
    measurements = [measure_image_file(p, um_per_px, diameter_mm, tool_type, corner_radius_mm=corner_radius_mm,
                                       reference=reference, scale_tol=scale_tol,
                                       centre_z_px=centre_z_px) for p in paths]
    profile, summary = measure_tool(measurements, angles, um_per_px, cutoff_deg)

    out_csv = Path(out_csv)
    out_json, out_png = out_csv.with_suffix(".json"), out_csv.with_suffix(".png")
    summary = {
        "tool_type": tool_type,
        "diameter_mm": float(diameter_mm),
        "corner_radius_mm": None if tool_type == "ball" else corner_radius_mm,
        "um_per_px": float(um_per_px),
        "images_dir": str(images_dir),
        "spindle_angles_from": angle_source,
        **summary,
        "fit": {
            "ideal": "circle of nominal radius" if tool_type == "ball" else "corner arcs of nominal radius",
            "reference": reference if centre_z_px is None else f"fixed centre row {centre_z_px:g} px",
            "method": "normal rays every 0.1°, 50 % crossing refined by edge area with local levels, "
                      "robust (Huber) least-squares centre",
            "diameter_um_mean": float(np.mean([m["diameter_um"] for m in measurements])),
            "radius_fit_um_mean": float(np.mean([m["radius_fit_um"] for m in measurements])),
        },
        "sign": "error_um > 0: tool smaller than nominal (material left on the part)",
        "profile_csv": out_csv.name,
    }
    out_csv.parent.mkdir(parents=True, exist_ok=True)
    # renamed in this order: the CSV (what workflows read) appears last, when the rest is there
    tmp = {p: p.with_name(f".{p.name}.tmp{os.getpid()}") for p in (out_png, out_json, out_csv)}
    try:
        table = profile.copy()
        table["contact_deg"] = table["contact_deg"].map("{:.1f}".format)
        table.to_csv(tmp[out_csv], index=False, float_format="%.4f")
        tmp[out_json].write_text(_json_text(summary))
        _overlay_png(tmp[out_png], load_image(paths[0])[0], measurements[0], profile, summary)
        for final, t in tmp.items():
            os.replace(t, final)
    finally:
        for t in tmp.values():
            if t.exists():
                t.unlink()
    result = {k: v for k, v in summary.items() if k != "envelope"}
    result.update(csv=str(out_csv), json=str(out_json), png=str(out_png))
    return result


def _json_text(summary):
    """Indented JSON, with the 901-long envelope arrays kept on one line each."""
    env = summary["envelope"]
    text = json.dumps({**summary, "envelope": "@ENVELOPE@"}, indent=1, ensure_ascii=False)
    inline = ('{"contact_deg": ' + json.dumps(env["contact_deg"]) + ',\n  "error_um": '
              + json.dumps(env["error_um"]) + "}")
    return text.replace('"@ENVELOPE@"', inline) + "\n"


def _overlay_png(path, grey, m0, profile, summary):
    """Three panels: first image with measured edge and fitted ideal profile; the profile with
    its error magnified; error per contact angle (CV1, CV2, envelope)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(15, 5), dpi=100)
    FigureCanvasAgg(fig)
    ax0, ax1, ax2 = fig.subplots(1, 3)
    um = summary["um_per_px"]
    q = np.radians(profile["contact_deg"].to_numpy())
    xc, zc = m0["centre_px"]
    r0_mm, rc_mm = tool_radii_mm(summary["diameter_mm"], summary["tool_type"], summary["corner_radius_mm"])
    r0_px, rc_px = 1000 * r0_mm / um, 1000 * rc_mm / um

    step = max(1, int(np.ceil(max(grey.shape) / 1200)))
    ax0.imshow(grey[::step, ::step], cmap="gray", extent=(-0.5, grey.shape[1] - 0.5, grey.shape[0] - 0.5, -0.5))
    ex, ey = m0["edge_xy_px"]
    for s, sgn in enumerate((1, -1)):
        ax0.plot(xc + sgn * (r0_px + rc_px * np.sin(q)), zc + rc_px * np.cos(q), "r--", lw=1,
                 label="fitted ideal" if s == 0 else None)
        ax0.plot(ex[s, ::20], ey[s, ::20], "g.", ms=2, label="measured edge" if s == 0 else None)
    ax0.axvline(xc, color="c", lw=0.5)
    ax0.set_title(f"{Path(m0['file']).name}: edge and fitted profile")
    ax0.set_aspect("equal")
    ax0.legend(loc="lower right", fontsize=8)

    err = profile["error_um"].to_numpy()
    mag = 0.1 * rc_px * um / max(np.abs(err).max(), 1.0)   # largest error shown as 10 % of the radius
    for sgn in (1, -1):
        ax1.plot(sgn * (r0_px * um + rc_px * um * np.sin(q)), -rc_px * um * np.cos(q), "r--", lw=1)
        rr = rc_px * um - mag * err
        ax1.plot(sgn * (r0_px * um + rr * np.sin(q)), -rr * np.cos(q), "b-", lw=1)
    ax1.set_title(f"ideal (red) vs measured (blue), error ×{mag:.0f}")
    ax1.set_xlabel("µm")
    ax1.set_aspect("equal")

    deg = profile["contact_deg"]
    ax2.plot(deg, profile["error_raw_um"], color="0.6", lw=0.6, label="raw (CV1)")
    ax2.plot(deg, err, "b-", lw=1.5, label=f"filtered (CV2, λc {summary['lowpass']['cutoff_deg']:g}°)")
    env = summary["envelope"]
    ecc = summary["eccentricity_um"]
    ax2.plot(env["contact_deg"], env["error_um"], color="orange", ls="--", lw=1,
             label=f"cutting envelope (runout {ecc:.1f} µm)" if ecc is not None else "cutting envelope")
    ax2.axhline(0, color="k", lw=0.5)
    ax2.set_xlabel("contact angle (°)")
    ax2.set_ylabel("error (µm), + = tool smaller")
    ax2.set_xlim(0, 90)
    ax2.legend(fontsize=8)
    ax2.set_title(f"contour error, {summary['n_images']} images")
    fig.tight_layout()
    fig.savefig(path, format="png")
