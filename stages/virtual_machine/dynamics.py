"""The machine's dynamics: modes of the tool-point compliance and time-domain deflection.

Each mode (x and y) is integrated in the time domain with the exact zero-order-hold state-transition
matrix from rest until the free response has died out; the last revolution is the periodic
deflection of a pass or piece (no FFT, no frequency-domain compliance: the prediction uses those).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from stages import InputError
from stages.tables import read_numeric_csv


def machine_modes(frf: Optional[dict], axis: str) -> list[tuple[float, float, float]]:
    """Modes of one axis of the workflow's ``machine.frf``.

    Parameters
    ----------
    frf : dict
        ``{"x": [{fn_hz, zeta, k_n_per_um}, ...], "y": [...]}`` or ``{"table": path}`` of a measured
        compliance (CSV freq_hz, xx_re, xx_im, yy_re, yy_im), fitted by :func:`fit_modes`.
    axis : "x" or "y"

    Returns
    -------
    list of (fn_hz, zeta, k_n_per_um)

    Raises
    ------
    stages.InputError
        No FRF given, or a table without a resonance peak on that axis.
    """
    if not frf:
        raise InputError("machine.frf: the virtual machine needs the machine's compliance (modes or table)")
    if frf.get(axis):
        return [(float(m["fn_hz"]), float(m["zeta"]), float(m["k_n_per_um"])) for m in frf[axis]]
    tab = read_numeric_csv(frf["table"], ["freq_hz", f"{axis}{axis}_re", f"{axis}{axis}_im"], "FRF table")
    modes = fit_modes(tab[:, 0], tab[:, 1] + 1j * tab[:, 2])
    if not modes:
        raise InputError(f"{frf['table']}: no resonance peak in {axis}{axis} (−Im of the compliance)")
    return modes


def modal_frf(f_hz, modes) -> np.ndarray:
    """Compliance (µm/N) of a sum of modes: G = Σ 1/(k(1 − r² + 2iζr)), r = f/fn.

    Parameters
    ----------
    f_hz : (n,) float
    modes : list of (fn_hz, zeta, k_n_per_um)

    Returns
    -------
    (n,) complex
    """
    f = np.asarray(f_hz, float)
    return sum(1.0 / (k * (1 - (f / fn) ** 2 + 2j * z * f / fn)) for fn, z, k in modes)


def fit_modes(f_hz, G, prominence: float = 0.05) -> list[tuple[float, float, float]]:
    """Modes of a measured compliance FRF (standard modal identification).

    Peaks of −Im G that stand out of the measurement noise (prominence at least ``prominence`` of
    the largest) start the modes: fn at the peak, ζ from the half-power width, k from the peak
    height (−Im G = 1/(2ζk) at fn). All modes are then fitted jointly to the complex FRF by least
    squares. Every local maximum of a noisy peak is not a mode: counting each as one multiplied the
    compliance of the sample table by 5 (static) to 15 (at 2.4 kHz).

    Parameters
    ----------
    f_hz : (n,) float
    G : (n,) complex
        Compliance, µm/N.
    prominence : float
        Smallest peak prominence, as a fraction of the largest −Im G.

    Returns
    -------
    list of (fn_hz, zeta, k_n_per_um); empty when −Im G is nowhere positive.
    """
    from scipy.optimize import least_squares
    from scipy.signal import find_peaks
    f = np.asarray(f_hz, float)
    G = np.asarray(G, complex)
    im = -G.imag
    if not np.any(im > 0):
        return []
    pk, _ = find_peaks(im, prominence=prominence * im.max())
    x0 = []
    for p in pk:
        half = im[p] / 2
        lo, hi = p, p
        while lo > 0 and im[lo] > half:
            lo -= 1
        while hi < len(im) - 1 and im[hi] > half:
            hi += 1
        zeta = float(np.clip((f[hi] - f[lo]) / (2 * f[p]), 1e-3, 0.5))
        x0 += [f[p], np.log(zeta), np.log(1.0 / (2 * zeta * im[p]))]
    if not x0:
        return []

    def modes_of(x):
        return [(x[i], np.exp(x[i + 1]), np.exp(x[i + 2])) for i in range(0, len(x), 3)]

    def resid(x):
        d = modal_frf(f, modes_of(x)) - G
        return np.concatenate([d.real, d.imag])
    sol = least_squares(resid, np.array(x0, float), x_scale="jac")
    return [(float(a), float(b), float(c)) for a, b, c in modes_of(sol.x)]


def simulate_deflection(force: np.ndarray, rpm: np.ndarray, modes) -> np.ndarray:
    """Periodic deflection over the last revolution, by time-domain modal integration from rest.

    Exact zero-order-hold discretisation of u'' + 2ζωn u' + ωn² u = ωn²/k · F for each mode; the
    force repeats every revolution, and the integration runs until exp(−ζωn t) < exp(−12).

    Parameters
    ----------
    force : (P, n_rot) float
        Force on the tool (N) at n_rot equal steps of one revolution, per pass or piece.
    rpm : (P,) float
        Spindle speed of each row.
    modes : list of (fn_hz, zeta, k_n_per_um)

    Returns
    -------
    (P, n_rot) float
        Deflection (µm), the sum over the modes.
    """
    from scipy.linalg import expm
    out = np.zeros_like(force)
    for r in np.unique(rpm):
        sel = np.flatnonzero(rpm == r)
        T = 60.0 / r
        dt = T / force.shape[1]
        for fn, zeta, k in modes:
            wn = 2 * np.pi * fn
            A = np.array([[0.0, 1.0], [-wn * wn, -2 * zeta * wn]])
            M = expm(np.block([[A, np.array([[0.0], [wn * wn / k]])], [np.zeros((1, 3))]]) * dt)
            Phi, Gam = M[:2, :2], M[:2, 2]
            n_rev = int(np.ceil(12.0 / (zeta * wn * T))) + 1
            x = np.zeros((len(sel), 2))
            f = force[sel]
            last = np.zeros((len(sel), force.shape[1]))
            for rev in range(n_rev):
                for i in range(force.shape[1]):
                    if rev == n_rev - 1:
                        last[:, i] = x[:, 0]
                    x = x @ Phi.T + f[:, i:i + 1] * Gam[None, :]
            out[sel] += last
    return out
