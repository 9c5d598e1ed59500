"""Kinematics of polygon cutting (seed 004, ``/work/shared/seeds/004_notes_en.md``).

Time is measured as the cutter's rotation angle τ (radians, τ = |ω2| t), so only the speed ratio
matters. In the workpiece-fixed frame the tip of an edge with lag φ is

    x + iy = ε e^{-i w τ} + R e^{i (s (τ - φ) - w τ)},   z = f τ / 2π

with w = ω1/|ω2| (workpiece turns per cutter turn, signed), s = sign(ω2) and f the feed per cutter
revolution; the notes' equations for ω2 > 0. Its distance from the axis depends on the cutter angle
a = s (τ - φ) alone, r² = ε² + R² + 2εR cos a: the edge cuts around a = π, once per cutter turn.
Every passage of every edge is the first one shifted: by -w T in θ and f T / 2π in z, T = φ + 2πk.
"""
from __future__ import annotations

from dataclasses import dataclass
from fractions import Fraction

import numpy as np

# samples of one passage at most; where the polar angle then jumps bins (R within ~0.1 mm of ε at
# the finest grids) the bins between are filled by linear interpolation
MAX_SAMPLES = 1_000_000


@dataclass(frozen=True)
class Setup:
    """A polygon-cutting set-up. Lengths in mm, speeds in rpm (signed: + counter-clockwise seen from +z).

    ``feed_mm`` is the axial feed per revolution of the cutter (``feed_per="tool"``) or of the
    workpiece (``"workpiece"``); ``lags_deg`` one lag angle per edge behind the first, in degrees
    of cutter rotation; ``edge_width_mm`` the edge's extent along the axis.
    """

    workpiece_radius_mm: float
    length_mm: float
    workpiece_rpm: float
    cutter_rpm: float
    radius_mm: float
    eccentricity_mm: float
    feed_mm: float
    feed_per: str = "tool"
    lags_deg: tuple = (0.0,)
    edge_width_mm: float = 1.0

    @property
    def ratio(self) -> float:
        """ω2/ω1, signed (negative: opposite directions)."""
        return self.cutter_rpm / self.workpiece_rpm

    @property
    def w(self) -> float:
        """Workpiece rotation per radian of cutter rotation (signed)."""
        return self.workpiece_rpm / abs(self.cutter_rpm)

    @property
    def s(self) -> float:
        return 1.0 if self.cutter_rpm > 0 else -1.0

    @property
    def feed_per_tool_mm(self) -> float:
        """Axial advance per cutter revolution, mm."""
        return self.feed_mm if self.feed_per == "tool" else self.feed_mm * abs(self.w)

    @property
    def feed_per_workpiece_mm(self) -> float:
        """Axial advance per workpiece revolution, mm."""
        return self.feed_per_tool_mm / abs(self.w)

    @property
    def lags_rad(self) -> np.ndarray:
        return np.radians(np.asarray(self.lags_deg, dtype=float))


def ratio_fraction(ratio: float, max_denominator: int = 1000) -> Fraction:
    """|ω2/ω1| as p/q in lowest terms (the seed's rule: the section is a p-gon when the feed is small
    against the edge width; 999/499 → a twisted blade instead, its p-gon closes after 999 cuts)."""
    return Fraction(abs(ratio)).limit_denominator(max_denominator)


def tip_xy(tau, setup: Setup, lag_deg: float = 0.0):
    """Edge tip in the workpiece-fixed frame.

    Parameters
    ----------
    tau : array_like
        Cutter rotation angle since the start, rad (the time).
    setup : Setup
    lag_deg : float
        The edge's lag angle, degrees.

    Returns
    -------
    x, y, z : ndarray
        mm; z the edge's axial position.
    """
    tau = np.asarray(tau, dtype=float)
    w, s, phi = setup.w, setup.s, np.radians(lag_deg)
    p = setup.eccentricity_mm * np.exp(-1j * w * tau) + setup.radius_mm * np.exp(1j * (s * (tau - phi) - w * tau))
    return p.real, p.imag, setup.feed_per_tool_mm * tau / (2 * np.pi)


def engagement_half_angle(setup: Setup) -> float:
    """Half the cutter angle, around a = π, over which the tip is inside the workpiece (rad; 0: never)."""
    e, R, rw = setup.eccentricity_mm, setup.radius_mm, setup.workpiece_radius_mm
    if e == 0:
        return np.pi if R < rw else 0.0
    c0 = (rw * rw - e * e - R * R) / (2 * e * R)   # cut where cos a < c0
    return float(np.arccos(np.clip(-c0, -1.0, 1.0)))


@dataclass(frozen=True)
class Profile:
    """The cut of one passage of the first edge (T = 0) over the unwrapped polar angle.

    Bin m covers θ in [theta0 + m h, theta0 + (m+1) h); ``r`` is the least tip radius in it (inf:
    not cut) and ``dz`` the tip's axial position there, relative to the passage's start.
    """

    theta0: float
    h: float
    r: np.ndarray
    dz: np.ndarray

    @property
    def span(self) -> float:
        return self.h * len(self.r)


def event_profile(setup: Setup, h: float) -> Profile:
    """The cut one edge passage leaves, binned at ``h`` radians of polar angle.

    The passage is sampled uniformly in cutter angle, finely enough that the polar angle moves at
    most h/2 between samples (its rate is at most |w| + R/|R - ε|, at a = π) up to ``MAX_SAMPLES``;
    consecutive samples further apart are joined by linear interpolation in θ, so every bin between
    the passage's ends holds a value.
    """
    a0 = engagement_half_angle(setup)
    if a0 <= 0:
        return Profile(0.0, h, np.full(0, np.inf), np.zeros(0))
    e, R = setup.eccentricity_mm, setup.radius_mm
    rate = abs(setup.w) + (R / abs(R - e) if abs(R - e) > 1e-12 else 1.0)
    n = int(min(MAX_SAMPLES, np.ceil(2 * a0 * rate / (0.5 * h)) + 2))
    tau = np.pi + np.linspace(-a0, a0, n)
    x, y, z = tip_xy(tau, setup)
    r = np.hypot(x, y)
    theta = np.unwrap(np.arctan2(y, x))
    inside = r <= setup.workpiece_radius_mm
    theta, r, z = _fill(theta[inside], r[inside], z[inside], h)
    if theta.size == 0:
        return Profile(0.0, h, np.full(0, np.inf), np.zeros(0))
    t0 = float(theta.min())
    m = ((theta - t0) / h).astype(np.int64)
    rb = np.full(int(m.max()) + 1, np.inf)
    np.minimum.at(rb, m, r)
    # the axial position where each bin's least radius is reached
    order = np.lexsort((r, m))
    first = np.unique(m[order], return_index=True)
    dz = np.zeros_like(rb)
    dz[first[0]] = z[order[first[1]]]
    return Profile(t0, h, rb, dz)


def _fill(theta, r, z, h):
    """The samples with points interpolated linearly between consecutive samples more than h/2
    apart in θ (k - 1 points where k half-bins are crossed)."""
    if theta.size < 2:
        return theta, r, z
    k = np.maximum(1, np.ceil(np.abs(np.diff(theta)) / (0.5 * h)).astype(np.int64))
    seg = np.repeat(np.arange(k.size), k)
    frac = (np.arange(k.sum()) - np.repeat(np.cumsum(k) - k, k)) / np.repeat(k, k)
    out = [np.append(v[:-1][seg] + frac * np.diff(v)[seg], v[-1]) for v in (theta, r, z)]
    return out[0], out[1], out[2]


def passages(setup: Setup, profile: Profile, z_lo: float, z_hi: float) -> np.ndarray:
    """Start times T (cutter angle, rad) of the passages of every edge whose cut reaches z in [z_lo, z_hi].

    A passage starting at T = φ + 2πk cuts at z = f T / 2π + profile.dz (f per cutter revolution).
    """
    if profile.r.size == 0:
        return np.zeros(0)
    f = setup.feed_per_tool_mm
    cut = np.isfinite(profile.r)
    dz_min, dz_max = float(profile.dz[cut].min()), float(profile.dz[cut].max())
    out = []
    for phi in setup.lags_rad:
        k0 = int(np.ceil((z_lo - dz_max) / f - phi / (2 * np.pi)))
        k1 = int(np.floor((z_hi - dz_min) / f - phi / (2 * np.pi)))
        if k1 >= k0:
            out.append(phi + 2 * np.pi * np.arange(k0, k1 + 1))
    return np.concatenate(out) if out else np.zeros(0)
