"""Render sample backlit silhouette images of tool T1 and measure them (issue 6).

Usage::

    python scripts/make_tool_images.py [--out data_samples]

Writes

``tool_images/t1/t1_<angle>deg.png``
    Six 8-bit grey images of the tip hemisphere of T1 (Ø10 mm ball, as in
    ``scripts/make_samples.py``) at spindle angles 0, 60, ..., 300°, 6 µm/px: tool dark on an LED
    back-light, axis vertical, tip down. Realistic defects: vignetting, optical blur (σ 1 px),
    sensor noise (σ 1.8 grey levels), 8-bit quantisation, a few dust specks on the glass.
    The tool (true contour, µm, + = smaller than nominal): the same slight undersize growing toward
    the equator and bump near 55° as ``tools/t1_profile.csv`` (0.6 + 2.4 (q/90)² + 0.9 exp(...)),
    plus a fine 0.3 µm waviness of 1.5° period (seed 002's "finely wavy" CV1), held 4 µm
    eccentric in the chuck (phase 35°).
``tools/t1_profile_measured.csv`` (+ ``.json``, ``.png``)
    The profile measured from these images by ``stages.tool_measure.tool_profile_command``
    (what ``pipeline tool-profile`` runs). The images were taken in the machine with the tool at
    a known height (tool length from the tool setter), so the ball-centre row is given
    (``centre_z_px``) rather than fitted; the result then reproduces ``tools/t1_profile.csv``
    (printed at the end). Without it the least-squares placement shifts the curve by a·cos q.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

DIAMETER_MM = 10.0
UM_PER_PX = 8.0
ANGLES_DEG = np.arange(6) * 60.0
ECC_UM, ECC_PHASE_DEG = 4.0, 35.0
R_PX = 500.0 * DIAMETER_MM / UM_PER_PX
MARGIN_PX = 40
ABOVE_CENTRE_PX = 60
H = int(ABOVE_CENTRE_PX + R_PX + MARGIN_PX)
W = int(2 * R_PX + 2 * MARGIN_PX)
XC, ZC = W / 2.0, float(ABOVE_CENTRE_PX)


def true_error_um(q):
    """True contour error of T1 (µm, + = smaller than nominal) at contact angle q (deg)."""
    q = np.asarray(q, dtype=float)
    s = q / 90.0
    smooth = 0.6 + 2.4 * s ** 2 + 0.9 * np.exp(-0.5 * ((q - 55.0) / 6.0) ** 2)
    return smooth + 0.3 * np.sin(2 * np.pi * q / 1.5)


def _distance(x, y, xc):
    """Signed distance (px, < 0 inside) to the silhouette: shank above the centre row, ball below."""
    dx = np.abs(x - xc)
    dy = y - ZC
    d = dx - R_PX                                         # shank (q = 90° radius, error 3.0 µm)
    d = d + true_error_um(90.0) / UM_PER_PX
    below = dy > 0
    q = np.degrees(np.arctan2(dx[below], dy[below]))
    d[below] = np.hypot(dx[below], dy[below]) - (R_PX - true_error_um(q) / UM_PER_PX)
    return d


def render(angle_deg, rng, ss=8):
    """One 8-bit image at a spindle angle: exact edge-pixel coverage by ss×ss supersampling."""
    xc = XC + ECC_UM / UM_PER_PX * np.cos(np.radians(angle_deg - ECC_PHASE_DEG))
    yy, xx = np.mgrid[0:H, 0:W].astype(float)
    d = _distance(xx, yy, xc)
    cover = (d < 0).astype(float)
    ey, ex = np.nonzero(np.abs(d) < 1.5)
    o = (np.arange(ss) + 0.5) / ss - 0.5
    oy, ox = np.meshgrid(o, o, indexing="ij")
    cover[ey, ex] = (_distance(ex[:, None] + ox.ravel(), ey[:, None] + oy.ravel(), xc) < 0).mean(axis=1)
    for _ in range(3):                                    # dust on the cover glass (not on the edge)
        cx, cy = rng.uniform(0.05, 0.95) * W, rng.uniform(0.75, 0.98) * H
        if abs(np.hypot(cx - xc, cy - ZC) - R_PX) > 40:
            cover = np.maximum(cover, np.clip(2.5 - np.hypot(xx - cx, yy - cy), 0, 1) * 0.7)
    cover = cv2.GaussianBlur(cover, (0, 0), 1.0)
    vignette = 1.0 - 0.25 * (((xx - W / 2) / W) ** 2 + ((yy - H / 2) / H) ** 2)
    img = 22.0 + (215.0 * vignette - 22.0) * (1.0 - cover) + rng.normal(0.0, 1.8, cover.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default="data_samples", help="samples directory")
    args = ap.parse_args(argv)
    out = Path(args.out)
    img_dir = out / "tool_images" / "t1"
    img_dir.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(6)
    for a in ANGLES_DEG:
        path = img_dir / f"t1_{int(a):03d}deg.png"
        cv2.imwrite(str(path), render(a, rng), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    size = sum(p.stat().st_size for p in img_dir.glob("*.png"))
    print(f"{len(ANGLES_DEG)} images {W}×{H} px at {UM_PER_PX} µm/px in {img_dir} ({size / 1e6:.2f} MB)")

    import sys
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from stages.tool_measure import tool_profile_command

    res = tool_profile_command(img_dir, UM_PER_PX, DIAMETER_MM, "ball", out / "tools" / "t1_profile_measured.csv",
                               centre_z_px=ZC)
    print(f"wrote {res['csv']}, {res['json']}, {res['png']}")
    print(f"eccentricity {res['eccentricity_um']:.2f} µm (true {ECC_UM}), "
          f"diameter {res['fit']['diameter_um_mean']:.1f} µm")
    import pandas as pd
    m = pd.read_csv(res["csv"])
    q = m["contact_deg"].to_numpy()
    smooth = true_error_um(q) - 0.3 * np.sin(2 * np.pi * q / 1.5)
    band = (q >= 5) & (q <= 85)
    print(f"measured vs true smooth contour, 5-85°: RMS {np.sqrt(np.mean((m['error_um'] - smooth)[band] ** 2)):.3f} µm")
    ref = out / "tools" / "t1_profile.csv"
    if ref.exists():
        r = pd.read_csv(ref)
        diff = m["error_um"].to_numpy() - np.interp(q, r["contact_deg"], r["error_um"])
        print(f"vs {ref}: RMS difference 5-85° {np.sqrt(np.mean(diff[band] ** 2)):.3f} µm")


if __name__ == "__main__":
    main()
