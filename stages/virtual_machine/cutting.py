"""Cutting forces of discrete flutes on the engaged micro-edges (Lee–Altintas ball-end model).

Chip of flute j at a micro-edge: ``h_j = max(0, min_m(m·fz·(v·u) + (ρ_j − ρ_{j+m})·sin κ))`` with v the
3-D feed direction, u the edge's outward normal (v·u = sin κ cos φ on a level pass) and the flutes'
radial offsets ρ_j (runout): the flute cuts what the last of the m flutes before it left. The
tangential, radial and axial forces are linear in the chip with edge terms.
"""
from __future__ import annotations

import math

import numpy as np

from stages.geometry.paths import Path3
from stages.virtual_machine.engagement import N_PHI

N_ROT = 192       # spindle angle samples per revolution
COEFFS = ("ktc", "krc", "kac", "kte", "kre", "kae")


def flute_offsets(flutes: int, e_um: float, phase_deg: float) -> np.ndarray:
    """Radial offset of each flute (mm) for a runout ``e_um`` at ``phase_deg``: e·cos(2πj/N + phase)."""
    j = np.arange(flutes)
    return e_um * 1e-3 * np.cos(2 * np.pi * j / flutes + math.radians(phase_deg))


def station_forces(path: Path3, pass_row: np.ndarray, engaged: np.ndarray, edges, radius_mm: float,
                   flutes: int, helix_rad: float, coeffs: dict, rho: np.ndarray, chunk: int = 32):
    """Machine-frame force on the tool over one revolution per station.

    Parameters
    ----------
    path : Path3
    pass_row : (S,) int
        The pass of each station.
    engaged : (S, levels, N_PHI // 8) uint8
        Packed engaged micro-edges (``engagement.engagement``).
    edges : (zc, kappa, ds)
        The micro-edge levels (``engagement.edge_grid``).
    radius_mm : float
    flutes : int
    helix_rad : float
        Helix angle: the edge at height z lags its tip end by z·tan β / R.
    coeffs : dict
        ktc, krc, kac (N/mm²) and kte, kre, kae (N/mm).
    rho : (flutes,) float
        Radial offset of each flute, mm (:func:`flute_offsets`).
    chunk : int
        Stations computed at a time (bounds the memory).

    Returns
    -------
    fx, fy : (S, N_ROT) float
        Newton, at spindle angles θ_i = i·360/N_ROT (clockwise spindle).
    """
    zc, kappa, ds = edges
    Z = flutes
    theta = np.arange(N_ROT) * 2 * np.pi / N_ROT
    lag = zc * math.tan(helix_rad) / radius_mm
    # position angle from the feed direction of flute j, level l at spindle angle θ (clockwise spindle)
    phi = (-theta[:, None, None] - 2 * np.pi * np.arange(Z)[None, :, None] / Z + lag[None, None, :]) % (2 * np.pi)
    cphi, sphi = np.cos(phi), np.sin(phi)
    ibin = np.minimum((phi / (2 * np.pi) * N_PHI).astype(np.int64), N_PHI - 1)
    S = len(pass_row)
    fx, fy = np.zeros((S, N_ROT)), np.zeros((S, N_ROT))
    for s0 in range(0, S, chunk):
        sl = slice(s0, min(s0 + chunk, S))
        fx[sl], fy[sl] = _forces(path, pass_row[sl], engaged[sl], Z, coeffs, cphi, sphi, ibin, rho, kappa, ds)
    return fx, fy


def _forces(p, rows, engaged, Z, c, cphi, sphi, ibin, rho, kappa, ds):
    """Machine-frame (fx, fy) on the tool over one revolution for the stations of passes ``rows``.

    Chip of a micro-edge: the feed per tooth along the 3-D feed direction v, projected on the
    edge's outward normal u (ball: (sin κ cos φ, sin κ sin φ, −cos κ) in the feed frame; side:
    κ = 90°), plus the flutes' radial offsets (runout) projected on u.
    """
    fz = p.feed[rows] / (p.rpm[rows] * Z)                                # (P,)
    d = p.c1[rows] - p.c0[rows]
    alpha = np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1]))
    E = np.unpackbits(engaged, axis=2, count=N_PHI).astype(bool)         # (P, levels, N_PHI)
    act = np.flatnonzero(E.any(axis=(0, 2)))                             # levels cut by some pass
    fxf = np.zeros((len(fz), N_ROT))
    fyf = np.zeros((len(fz), N_ROT))
    if act.size:
        cp, sp, ib = cphi[:, :, act], sphi[:, :, act], ibin[:, :, act]
        sk, ck, dsa = np.sin(kappa[act]), np.cos(kappa[act]), ds[act]
        vu = (np.cos(alpha)[:, None, None, None] * sk * cp[None]
              - np.sin(alpha)[:, None, None, None] * ck)                  # (P, rot, Z, levels)
        best = None
        for m in range(1, Z + 1):
            delta = rho - rho[(np.arange(Z) + m) % Z]
            cand = m * fz[:, None, None, None] * vu + delta[None, None, :, None] * sk
            best = cand if best is None else np.minimum(best, cand)
        h = np.maximum(best, 0.0)
        eng = E[:, act[None, None, :], ib]                                # (P, rot, Z, levels)
        cut = eng & (h > 1e-12)
        ft = (c["ktc"] * h * dsa + c["kte"] * dsa) * cut
        fr = (c["krc"] * h * dsa + c["kre"] * dsa) * cut
        fa = (c["kac"] * h * dsa + c["kae"] * dsa) * cut
        fxf = np.sum(-fr * sk * cp - ft * sp - fa * ck * cp, axis=(2, 3))
        fyf = np.sum(-fr * sk * sp + ft * cp - fa * ck * sp, axis=(2, 3))
    f = np.arctan2(d[:, 1], d[:, 0])[:, None]
    return np.cos(f) * fxf - np.sin(f) * fyf, np.sin(f) * fxf + np.cos(f) * fyf
