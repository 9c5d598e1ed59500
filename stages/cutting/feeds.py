"""Feed scheduling: the feed per pass that keeps the predicted tool deflection and the chip within
limits, where a path offset cannot help (a deflection that changes with the offset), as force-based
feed optimisers do.

The micro-edge force model is affine in the feed per tooth fz (the chip thickness is fz times the
engagement's geometry, the edge force does not depend on it) and the compliance is linear, so the
deflection over a revolution is d(θ; fz) = fz·Dc(θ) + De(θ), known from two force evaluations
(:func:`affine_deflection`). The peak max_θ |d(θ; fz)| is convex in fz: the largest fz within the
limit is found by bisection (:func:`largest_feed_per_tooth`). :func:`smooth_down` lowers feeds so
that neighbours differ by at most a ratio (it never raises one).
"""
from __future__ import annotations

import numpy as np


def affine_deflection(d1: tuple, d2: tuple, fz1: np.ndarray, fz2: np.ndarray):
    """(Dc, De): per pass and spindle angle, the deflection per unit fz and at fz = 0.

    Parameters
    ----------
    d1, d2 : (dx, dy) arrays (P, n_rot), µm, predicted at feeds per tooth ``fz1`` and ``fz2`` (P,)
    """
    dx1, dy1 = d1
    dx2, dy2 = d2
    df = (fz2 - fz1)[:, None]
    cx, cy = (dx2 - dx1) / df, (dy2 - dy1) / df
    return np.stack([cx, cy], -1), np.stack([dx1 - cx * fz1[:, None], dy1 - cy * fz1[:, None]], -1)


def peak_deflection(dc: np.ndarray, de: np.ndarray, fz: np.ndarray) -> np.ndarray:
    """max over the revolution of |fz·Dc + De| per pass, µm."""
    return np.linalg.norm(fz[:, None, None] * dc + de, axis=-1).max(1)


def largest_feed_per_tooth(dc: np.ndarray, de: np.ndarray, limit_um: float, fz_max: np.ndarray,
                           iterations: int = 50) -> np.ndarray:
    """The largest fz in [0, ``fz_max``] whose peak deflection is within ``limit_um`` (per pass);
    NaN where even fz = 0 (the edge forces alone) exceeds it."""
    lo = np.zeros(len(dc))
    hi = np.asarray(fz_max, float).copy()
    ok_hi = peak_deflection(dc, de, hi) <= limit_um
    out = np.where(ok_hi, hi, np.nan)
    todo = ~ok_hi & (peak_deflection(dc, de, lo) <= limit_um)
    a, b = lo[todo], hi[todo]
    dct, det = dc[todo], de[todo]
    for _ in range(iterations):                      # g(fz) is convex and g(0) ≤ limit < g(hi)
        mid = 0.5 * (a + b)
        within = peak_deflection(dct, det, mid) <= limit_um
        a, b = np.where(within, mid, a), np.where(within, b, mid)
    out[todo] = a
    return out


def smooth_down(feed: np.ndarray, max_change: float) -> np.ndarray:
    """The largest feeds ≤ ``feed`` whose neighbours differ by at most the ratio 1 + ``max_change``.

    In logs the condition is a slope limit: g[i] = min_j (log f[j] + |i − j|·log(1 + c)), two
    running minima.
    """
    if len(feed) < 2:
        return feed.copy()
    a = np.log1p(max_change)
    g = np.log(feed)
    i = np.arange(len(g))
    fwd = np.minimum.accumulate(g - i * a) + i * a
    bwd = (np.minimum.accumulate((g + i * a)[::-1]))[::-1] - i * a
    return np.exp(np.minimum(fwd, bwd))
