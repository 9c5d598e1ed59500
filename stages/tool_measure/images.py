"""Tool images on disk: the files of a directory, their spindle angles, grey levels and exposure.

Image conventions: 8- or 16-bit grey (colour is converted), tool dark on a bright back-light, tool
axis vertical (image columns), tip down. Every error names the file (or is raised for the caller to
prefix with it).
"""
from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from stages import InputError

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".bmp", ".jpg", ".jpeg")
_ANGLE_RE = re.compile(r"(\d+(?:\.\d+)?)\s*deg", re.IGNORECASE)


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

