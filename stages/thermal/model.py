"""Thermal drift of the machine's axes (seed 003): first-order responses to its heat input.

Each heat source k is a first-order lag of the machine's heat input u(t) with time constant τ_k:

    τ_k · r_k'(t) = u(t) − r_k(t),   r_k(0) = 0 (cold at t = 0),

u held constant between samples (the value of the latest sample at or before t; 1 throughout
when the measurements carry no heat-input column: the machine runs from t = 0). The drift of
axis i at time t and position p is linear in the responses:

    d_i(t, p) = c_i + Σ_k r_k(t) · (A_ik + Σ_j B_ikj (p_j − p̄_j)) + Σ_m g_im (T_m(t) − T_m0),

``A`` the gains (µm per source at steady state), ``B`` the position-dependent cross terms the seed
found linear within the measured range (µm per mm), ``T`` optional temperature readings (°C).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

AXES = ("x", "y", "z")
POSITION_COLUMNS = ("x_mm", "y_mm", "z_mm")


def responses(t: np.ndarray, u: np.ndarray | None, taus: np.ndarray) -> np.ndarray:
    """First-order responses (n, K) at the sorted times ``t`` (s) to the heat input ``u`` (n,)
    held from each sample to the next, zero at t = 0; ``u`` None means 1 throughout."""
    t = np.asarray(t, float)
    taus = np.asarray(taus, float)
    if u is None:
        return -np.expm1(-np.maximum(t, 0.0)[:, None] / taus[None, :])
    u = np.asarray(u, float)
    out = np.empty((len(t), len(taus)))
    # piecewise-constant input: closed form within each run of equal values, state carried across
    starts = np.flatnonzero(np.r_[True, u[1:] != u[:-1]])
    ends = np.r_[starts[1:], len(t)]
    state, t_state = np.zeros(len(taus)), 0.0
    for s, e in zip(starts, ends):
        level = u[s]
        seg = np.maximum(t[s:e] - t_state, 0.0)[:, None] / taus[None, :]
        out[s:e] = level + (state - level) * np.exp(-seg)
        # the input holds this level until the next sample's time
        t_next = t[e] if e < len(t) else t[e - 1]
        state = level + (state - level) * np.exp(-max(t_next - t_state, 0.0) / taus)
        t_state = t_next
    return out


@dataclass
class DriftModel:
    """A fitted drift model (see the module's docstring); ``to_dict``/``from_dict`` are the YAML form.

    Attributes
    ----------
    taus_s : (K,) time constants, s.
    coef : {axis: (m,) coefficients} in the order of :meth:`columns`.
    heat_column, heat_reference : the heat-input column and the value that counts as 1 (None: the
        machine runs from t = 0).
    positions, position_origin : position columns used for the cross terms and their mean.
    temperatures, temperature_origin : temperature columns and their first reading.
    """

    taus_s: np.ndarray
    coef: dict = field(default_factory=dict)
    heat_column: str | None = None
    heat_reference: float = 1.0
    positions: tuple = ()
    position_origin: np.ndarray = field(default_factory=lambda: np.zeros(0))
    temperatures: tuple = ()
    temperature_origin: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def columns(self) -> list[str]:
        """Names of the linear coefficients of every axis, in order."""
        K = len(self.taus_s)
        names = ["offset_um"] + [f"gain{k + 1}_um" for k in range(K)]
        names += [f"gain{k + 1}_um_per_{p}" for k in range(K) for p in self.positions]
        names += [f"um_per_{c}" for c in self.temperatures]
        return names

    def design(self, data: dict, taus: np.ndarray | None = None) -> np.ndarray:
        """Design matrix (n, m) of the measurements or times ``data`` (columns by name)."""
        taus = self.taus_s if taus is None else taus
        t = np.asarray(data["time_s"], float)
        u = None if self.heat_column is None else np.asarray(data[self.heat_column], float) / self.heat_reference
        r = responses(t, u, taus)
        cols = [np.ones((len(t), 1)), r]
        for k in range(len(taus)):
            for j, p in enumerate(self.positions):
                cols.append((r[:, k] * (np.asarray(data[p], float) - self.position_origin[j]))[:, None])
        for m, c in enumerate(self.temperatures):
            cols.append((np.asarray(data[c], float) - self.temperature_origin[m])[:, None])
        return np.hstack(cols)

    def predict(self, data: dict) -> dict:
        """Drift (µm) per axis at the rows of ``data``: {"dx_um": (n,), "dy_um": ..., "dz_um": ...}."""
        X = self.design(data)
        return {f"d{a}_um": X @ np.asarray(self.coef[a], float) for a in AXES}

    def needs(self) -> list[str]:
        """Columns a prediction needs besides ``time_s``."""
        return ([self.heat_column] if self.heat_column else []) + list(self.positions) + list(self.temperatures)

    def to_dict(self) -> dict:
        names = self.columns()
        return {
            "kind": "thermal_drift",
            "time_constants_s": [round(float(x), 3) for x in self.taus_s],
            "heat_input": None if self.heat_column is None else
            {"column": self.heat_column, "reference": float(self.heat_reference)},
            "positions": {"columns": list(self.positions), "origin_mm": [float(x) for x in self.position_origin]},
            "temperatures": {"columns": list(self.temperatures),
                             "origin_c": [float(x) for x in self.temperature_origin]},
            "axes": {a: {n: float(v) for n, v in zip(names, self.coef[a])} for a in AXES},
        }

    @classmethod
    def from_dict(cls, d: dict) -> "DriftModel":
        heat = d.get("heat_input") or {}
        pos = d.get("positions") or {}
        temp = d.get("temperatures") or {}
        m = cls(np.asarray(d["time_constants_s"], float), {}, heat.get("column"), float(heat.get("reference", 1.0)),
                tuple(pos.get("columns", ())), np.asarray(pos.get("origin_mm", []), float),
                tuple(temp.get("columns", ())), np.asarray(temp.get("origin_c", []), float))
        names = m.columns()
        m.coef = {a: np.array([float(d["axes"][a][n]) for n in names]) for a in AXES}
        return m
