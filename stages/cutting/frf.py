"""Tool-tip compliance and deflection over one revolution (DESIGN §7; seed 000 paras 0048, 0062–0063).

Compliance G(f) (µm/N) per machine axis x and y (direct terms only; cross terms xy are taken as 0):

- modal: a sum of single-degree-of-freedom modes, each (fn_hz, zeta, k_n_per_um)::

      G(f) = Σ 1 / (k·(1 − r² + 2iζr)),   r = f / fn

  i.e. m·ẍ + c·ẋ + k·x = F per mode with m = k/ωn², c = 2ζ√(k·m);
- measured: a CSV table from an impact test, header line then rows::

      freq_hz,xx_re,xx_im,yy_re,yy_im
      0,0.5,0,0.5,0
      10,0.5012,-0.0011,0.5009,-0.0010
      ...

  ``xx`` = x displacement / x force, ``yy`` = y / y, real and imaginary parts in **µm/N**, frequency
  ascending. Values between rows are interpolated linearly (real and imaginary parts separately);
  below the first row the first row is held (only its real part at 0 Hz: the static compliance is
  real), above the last row the compliance is taken as 0 (harmonics beyond the measured band are
  not amplified — measure up to at least flutes × the highest spindle frequency × a few).

Deflection: the cutting force of a predicted pass is the same every revolution (a finishing cut
changes little over a pass, para 0062), so only the forced, periodic response matters. With the
force sampled at n uniform spindle angles over one revolution (period T = 60/rpm), harmonic m has
frequency m·rpm/60 and D_m = G(m·rpm/60)·F_m; the inverse FFT gives d(θ) at the same angles. The
time-domain check integrates the modes with classical RK4 from rest over enough revolutions for
the free vibration to decay (e^{−ζωn t} < 1e−7) and returns the last revolution; the force
between samples is the trigonometric interpolant of the samples (what the FFT assumes).
"""
from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from stages import InputError
from stages.tables import read_numeric_csv

FRF_COLUMNS = ("freq_hz", "xx_re", "xx_im", "yy_re", "yy_im")


def modal_compliance(freq_hz, modes) -> np.ndarray:
    """Σ over ``modes`` (dicts fn_hz, zeta, k_n_per_um) of the SDOF compliance, µm/N (complex)."""
    f = np.asarray(freq_hz, dtype=float)
    g = np.zeros(f.shape, dtype=complex)
    for mode in modes:
        r = f / float(mode["fn_hz"])
        g += 1.0 / (float(mode["k_n_per_um"]) * (1.0 - r * r + 2j * float(mode["zeta"]) * r))
    return g


@functools.lru_cache(maxsize=16)
def _read_frf_table_cached(path: str, mtime: float):
    a = read_numeric_csv(path, FRF_COLUMNS, "machine.frf.table")
    if len(a) < 2:
        raise InputError(f"{path}: FRF table needs at least 2 rows")
    if np.any(np.diff(a[:, 0]) <= 0) or a[0, 0] < 0:
        raise InputError(f"{path}: freq_hz must be ≥ 0 and strictly ascending")
    return a


def read_frf_table(path) -> np.ndarray:
    """Read a measured FRF CSV (see module docstring); returns (n, 5) float array."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"machine.frf.table: no such file {path}")
    return _read_frf_table_cached(str(p.resolve()), p.stat().st_mtime)


def table_compliance(freq_hz, table: np.ndarray, axis: str) -> np.ndarray:
    """Interpolated compliance (µm/N) of axis 'x' or 'y' from a table read by ``read_frf_table``."""
    f = np.asarray(freq_hz, dtype=float)
    c = {"x": 1, "y": 3}[axis]
    fq, re, im = table[:, 0], table[:, c], table[:, c + 1]
    g = np.interp(f, fq, re) + 1j * np.interp(f, fq, im)
    g = np.where(f > fq[-1], 0.0, g)
    return np.where(f == 0, np.real(g), g)


def compliance(freq_hz, frf: dict | None):
    """(Gx, Gy) in µm/N at ``freq_hz`` from ``machine.frf`` (modes, or a measured table)."""
    if not frf:
        raise InputError("machine.frf: no compliance given (modes for x and y, or a measured table)")
    if frf.get("table"):
        table = read_frf_table(frf["table"])
        return table_compliance(freq_hz, table, "x"), table_compliance(freq_hz, table, "y")
    if not frf.get("x") or not frf.get("y"):
        raise InputError("machine.frf: give modes for both x and y, or a measured table")
    return modal_compliance(freq_hz, frf["x"]), modal_compliance(freq_hz, frf["y"])


def harmonic_freqs_hz(n_rot: int, spindle_rpm) -> np.ndarray:
    """Frequencies of the rfft bins of one revolution sampled n_rot times: (P, n_rot//2+1)."""
    m = np.arange(n_rot // 2 + 1)
    return np.asarray(spindle_rpm, dtype=float)[:, None] / 60.0 * m[None, :]


def deflection_fft(force_n: np.ndarray, spindle_rpm, compliance_fn) -> np.ndarray:
    """Periodic forced response d = irfft(G·rfft(F)) over one revolution.

    Parameters
    ----------
    force_n : ndarray (P, n_rot)
        Force on the tool along one axis, sampled at θ_i = i·360/n_rot.
    spindle_rpm : ndarray (P,)
    compliance_fn : callable(freq_hz ndarray) -> complex ndarray (µm/N)

    Returns
    -------
    ndarray (P, n_rot), µm
    """
    force_n = np.asarray(force_n, dtype=float)
    n_rot = force_n.shape[-1]
    spec = np.fft.rfft(force_n, axis=-1)
    g = compliance_fn(harmonic_freqs_hz(n_rot, spindle_rpm))
    return np.fft.irfft(spec * g, n=n_rot, axis=-1)


def deflection_rk4(force_n: np.ndarray, spindle_rpm, modes, decay: float = 1e-7,
                   points_per_period: int = 40, chunk: int = 256) -> np.ndarray:
    """Time-domain check: RK4 integration of the modes from rest, last revolution returned.

    Parameters
    ----------
    force_n : ndarray (P, n_rot)
        Force over one revolution at θ_i = i·360/n_rot; it repeats every revolution.
    spindle_rpm : ndarray (P,)
    modes : list of dict (fn_hz, zeta, k_n_per_um)
    decay : float
        Integrate until the slowest mode's free vibration has decayed below this factor.
    points_per_period : int
        RK4 steps per period of the highest mode (at least).

    Returns
    -------
    ndarray (P, n_rot), µm, at the same angles as ``force_n``.
    """
    force_n = np.atleast_2d(np.asarray(force_n, dtype=float))
    rpm = np.broadcast_to(np.asarray(spindle_rpm, dtype=float), (force_n.shape[0],))
    out = np.empty_like(force_n)
    fn = np.array([float(m["fn_hz"]) for m in modes])
    zeta = np.array([float(m["zeta"]) for m in modes])
    k = np.array([float(m["k_n_per_um"]) for m in modes])
    wn = 2 * np.pi * fn
    for value in np.unique(rpm):
        for start in range(0, int(np.sum(rpm == value)), chunk):
            sel = np.flatnonzero(rpm == value)[start:start + chunk]
            out[sel] = _rk4_one_speed(force_n[sel], float(value), fn, zeta, k, wn, decay, points_per_period)
    return out


def _rk4_one_speed(force_n, rpm, fn, zeta, k, wn, decay, points_per_period):
    """RK4 from rest for passes sharing one spindle speed; returns the last revolution (P, n_rot)."""
    n_pass, n_rot = force_n.shape
    period = 60.0 / rpm
    # substeps per force sample so that dt resolves the fastest mode
    sub = max(1, int(np.ceil(points_per_period * fn.max() * period / n_rot)))
    n_steps = n_rot * sub
    dt = period / n_steps
    n_rev = int(np.ceil(-np.log(decay) / (zeta * wn).min() / period)) + 1
    # force at half steps over one period: the trigonometric interpolant of the samples
    spec = np.fft.rfft(force_n, axis=-1)
    fine = np.fft.irfft(spec, n=2 * n_steps, axis=-1) * (2 * n_steps / n_rot)
    fine = np.concatenate([fine, fine[:, :1]], axis=1)                       # wrap for index 2n
    x = np.zeros((n_pass, len(fn)))
    v = np.zeros_like(x)
    acc_f = (wn ** 2 / k)[None, :]                                           # ωn²/k per mode

    def accel(xx, vv, f):
        return acc_f * f[:, None] - 2 * zeta * wn * vv - wn ** 2 * xx

    last = np.empty((n_pass, n_rot))
    for rev in range(n_rev):
        for step in range(n_steps):
            if rev == n_rev - 1 and step % sub == 0:
                last[:, step // sub] = x.sum(axis=1)
            f0, fh, f1 = fine[:, 2 * step], fine[:, 2 * step + 1], fine[:, 2 * step + 2]
            k1x, k1v = v, accel(x, v, f0)
            k2x, k2v = v + 0.5 * dt * k1v, accel(x + 0.5 * dt * k1x, v + 0.5 * dt * k1v, fh)
            k3x, k3v = v + 0.5 * dt * k2v, accel(x + 0.5 * dt * k2x, v + 0.5 * dt * k2v, fh)
            k4x, k4v = v + dt * k3v, accel(x + dt * k3x, v + dt * k3v, f1)
            x = x + dt / 6 * (k1x + 2 * k2x + 2 * k3x + k4x)
            v = v + dt / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)
    return last


def _compliance_per_pass(n_rot: int, spindle_rpm, frf: dict):
    """(Gx, Gy) at the harmonics of each pass, (P, n_rot//2+1); evaluated once per distinct speed."""
    rpm = np.asarray(spindle_rpm, dtype=float)
    uniq, inv = np.unique(rpm, return_inverse=True)
    gx, gy = compliance(harmonic_freqs_hz(n_rot, uniq), frf)
    return gx[inv.ravel()], gy[inv.ravel()]


def tool_deflection(forces_xy: np.ndarray, spindle_rpm, frf: dict, method: str = "fft") -> np.ndarray:
    """Deflection (µm) along machine x and y of forces (P, n_rot, 2+) on the tool.

    The tool moves along the force acting on it (compliance positive at 0 Hz). ``method``: 'fft'
    (default) or 'rk4' (modal FRF only). Returns (P, n_rot, 2).
    """
    fx, fy = deflection_xy(np.ascontiguousarray(forces_xy[..., 0]), np.ascontiguousarray(forces_xy[..., 1]),
                           spindle_rpm, frf, method)
    return np.stack([fx, fy], axis=-1)


def deflection_xy(fx_n: np.ndarray, fy_n: np.ndarray, spindle_rpm, frf: dict, method: str = "fft"):
    """``tool_deflection`` on separate (P, n_rot) force arrays; returns (dx_um, dy_um)."""
    n_rot = fx_n.shape[1]
    if method == "fft":
        gx, gy = _compliance_per_pass(n_rot, spindle_rpm, frf)
        dx = np.fft.irfft(np.fft.rfft(fx_n, axis=1) * gx, n=n_rot, axis=1)
        dy = np.fft.irfft(np.fft.rfft(fy_n, axis=1) * gy, n=n_rot, axis=1)
        return dx, dy
    if method == "rk4":
        if not frf or frf.get("table") or not frf.get("x") or not frf.get("y"):
            raise InputError("machine.frf: the RK4 check needs modal parameters for x and y")
        return (deflection_rk4(fx_n, spindle_rpm, frf["x"]), deflection_rk4(fy_n, spindle_rpm, frf["y"]))
    raise ValueError(f"deflection method {method!r}: 'fft' or 'rk4'")
