"""The effect catalogue (DESIGN §8 step 3): each unmodelled effect as a parametric signature on the
residual r = measured − predicted (µm along the normal).

- ``runout``: −e·sin q (e ≥ 0, µm); when the caller gives the prediction's own response to runout
  (``F["runout_resp_um"]``: forces → deflection → errors re-run with tool.runout_um + e on a grid
  of e), that response (it also holds the changed chip of each flute), interpolated at e
- ``tool_contour``: a·exp(−½((q − q0)/w)²) (a µm, q0 deg, w deg; + = tool smaller = material left)
- ``tool_wear``: rate·L (µm per m of cut, ≥ 0)
- ``thermal_drift``: n·A·(1 − exp(−t/τ)) (A µm per axis, τ s)
- ``force_scale``: (s − 1)·predicted deflection error (s ratio)
- ``servo_corner``: the tool lags by a·sin(θ/2)/sin 45°·exp(−d/λ) towards the inside of the turn
  (a µm, λ mm); chosen with the smooth form, fitted with the tooth-passage envelope
  (``stages.gap.servo``)
- ``machine_geometry``: n·(sx·x + exy·y + exz·z, sy·y + eyz·z, sz·z) at the tool tip (µm/mm)
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from stages.gap.servo import servo_signature, servo_smooth

EFFECT_NAMES = ("runout", "tool_contour", "tool_wear", "thermal_drift", "force_scale", "servo_corner",
                "machine_geometry")


@dataclass
class Effect:
    """One catalogue effect: a signature linear in ``n_lin`` amplitudes at a nonlinear value ``th``.

    Attributes
    ----------
    name : str
        One of ``EFFECT_NAMES``.
    grid : list of tuple
        Nonlinear parameter values searched (``[()]`` when the effect has none).
    n_lin : int
        Number of linear parameters (amplitudes) fitted.
    keep : tuple of int, optional
        The amplitudes fitted, as indices into the effect's ``n_full`` amplitudes: the others are not
        observable on the points and held at nominal, 0 (``stages.gap.observability.restrict``).
    n_full : int, optional
        The effect's own number of amplitudes (= ``n_lin`` when ``keep`` is None).
    """

    name: str
    grid: list                     # nonlinear parameter values (tuples), [()] when none
    n_lin: int
    keep: Optional[tuple] = None
    n_full: Optional[int] = None

    def basis(self, F, th) -> np.ndarray:
        """Signature columns at the nonlinear value ``th``: (n, n_lin), µm per unit amplitude."""
        X = _BASIS[self.name](F, th)
        return X if self.keep is None else X[:, list(self.keep)]

    def full_beta(self, beta) -> np.ndarray:
        """The effect's ``n_full`` amplitudes from the fitted ``beta`` (n_lin,): 0 where not fitted."""
        if self.keep is None:
            return np.asarray(beta, float)
        out = np.zeros(self.n_full)
        out[list(self.keep)] = beta
        return out

    def params(self, beta, th) -> dict:
        """The reported parameters of amplitudes ``beta`` (n_lin,) at ``th`` ({name: float})."""
        return _PARAMS[self.name](self.full_beta(beta), th)

    def linear_keys(self, th) -> list:
        """Reported names of the fitted amplitudes (the first keys of ``params``), in order."""
        n = self.n_full or self.n_lin
        keys = list(_PARAMS[self.name](np.zeros(n), th))[:n]
        return keys if self.keep is None else [keys[j] for j in self.keep]

    @property
    def n_params(self):
        """Linear + nonlinear parameter count (the χ² degrees of freedom of the effect)."""
        return self.n_lin + (len(self.grid[0]) if self.grid and self.grid[0] else 0)


def _q(F):
    return np.radians(F["q_deg"])


def runout_response(F, e_um: float) -> np.ndarray:
    """The prediction's own change per µm of runout at ``e_um`` (tool.runout_um + e re-predicted
    through forces → deflection → errors), linear between the computed values
    ``F["runout_grid_um"]`` (0 → no change): (n, 2) = the flute's −ρ·sin q and the rest (the
    deflection changed by the flutes' unequal chips). (n, 1) = −sin q when none was computed.

    Parameters
    ----------
    F : dict
        Features of n points (``q_deg``; ``runout_grid_um`` (g,) and ``runout_resp_um`` (n, g, 2)
        µm when the prediction was re-run, ``stages.gap.predictor.add_model_responses``).
    e_um : float
        Runout e (µm) at which the response is read (clipped to the computed grid).

    Returns
    -------
    (n, 2) or (n, 1) ndarray
        µm per µm of e.
    """
    if "runout_resp_um" not in F:
        return -np.sin(_q(F))[:, None]
    grid = np.concatenate([[0.0], F["runout_grid_um"]])
    resp = np.concatenate([np.zeros((len(F["q_deg"]), 1, 2)), F["runout_resp_um"]], axis=1)
    e = float(np.clip(e_um, grid[1], grid[-1]))
    i = int(np.clip(np.searchsorted(grid, e) - 1, 0, len(grid) - 2))
    w = (e - grid[i]) / (grid[i + 1] - grid[i])
    return ((1 - w) * resp[:, i] + w * resp[:, i + 1]) / e


_BASIS = {
    "runout": lambda F, th: runout_response(F, th[0] if th else 1.0),
    "tool_contour": lambda F, th: np.exp(-0.5 * ((F["q_deg"] - th[0]) / th[1]) ** 2)[:, None],
    "tool_wear": lambda F, th: (F["cut_len_mm"] * 1e-3)[:, None],
    "thermal_drift": lambda F, th: (np.stack([F["nx"], F["ny"], F["nz"]], 1)
                                    * (1 - np.exp(-np.maximum(F["t_s"], 0) / th[0]))[:, None]),
    "force_scale": lambda F, th: F["pred_deflection_um"][:, None],
    # th = (λ,): the smooth form (effect selection); th = (λ, a): the tooth-passage envelope of a
    # lag a, per µm of a (the fitted model: ``refine_servo``)
    "servo_corner": lambda F, th: (servo_smooth(F, th[0]) if len(th) == 1
                                   else servo_signature(F, th[1], th[0]) / th[1])[:, None],
    "machine_geometry": lambda F, th: np.stack([F["nx"] * F["tip_x_mm"], F["ny"] * F["tip_y_mm"], F["nz"] * F["tip_z_mm"],
                                                F["nx"] * F["tip_y_mm"], F["nx"] * F["tip_z_mm"], F["ny"] * F["tip_z_mm"]], 1),
}
_PARAMS = {
    # with the prediction's response: e (geometric part) and e·s (the deflection part scales with
    # the force model: its own coefficient, = e when the force model is right)
    "runout": lambda b, th: {"e_um": float(b[0])} if len(b) == 1 else {"e_um": float(b[0]), "e_force_um": float(b[1])},
    "tool_contour": lambda b, th: {"a_um": float(b[0]), "q0_deg": float(th[0]), "width_deg": float(th[1])},
    "tool_wear": lambda b, th: {"rate_um_per_m": float(b[0])},
    "thermal_drift": lambda b, th: {"ax_um": float(b[0]), "ay_um": float(b[1]), "az_um": float(b[2]), "tau_s": float(th[0])},
    "force_scale": lambda b, th: {"scale": float(1 + b[0])},
    "servo_corner": lambda b, th: {"a_um": float(b[0]), "lambda_mm": float(th[0])},
    "machine_geometry": lambda b, th: dict(zip(("sx", "sy", "sz", "exy", "exz", "eyz"), map(float, b))),
}

# Physical limits of a fitted effect (the bounds of its fit, ``effect_bounds``): 4 × the largest the seeds measured on real machines (seed 003:
# thermal drift ≈ 50 µm after 3 h of running; an X → Y error of 0–50 µm over ±20 mm, 2.5 µm/mm; a new
# tool ≈ 10 µm off its nominal profile from holder runout). A fit beyond them is no cause but two
# effects cancelling each other where their signatures are nearly collinear (on two raster rows: a
# 226 µm drift against a −271 µm/mm scale error, next to the real 10 µm runout); such a combination
# is not fitted. Sizes: the drift reached by the end of the run |A|·(1 − exp(−T/τ)) (µm), the
# largest geometry coefficient (µm/mm), the runout e and the contour amplitude |a| (µm).
LIMITS = {"thermal_drift": 200.0, "machine_geometry": 10.0, "runout": 40.0, "tool_contour": 40.0}


CONTOUR_WIDTH_DEG = (3.0, 20.0)      # a local profile error, not a size error
FORCE_SCALE_RANGE = (0.1, 10.0)      # a force model off by more than 10× is no model at all
SERVO_LIMIT_UM = 120.0               # 4 × the largest lag the blind check draws


def effect_bounds(F, e: Effect, th) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of an effect's fitted amplitudes (bounded least squares, ``stages.gap.fit.solve_bounded``):
    the physical limits of ``LIMITS`` as a box — each drift axis so that even three equal axes
    stay within the drift limit by the run's end, each geometry coefficient, the runout e (≥ 0)
    and the contour amplitude; the wear rate ≥ 0; the force scale within ``FORCE_SCALE_RANGE``;
    the servo lag within ±``SERVO_LIMIT_UM``.

    Parameters
    ----------
    F : dict
        Features (``t_s`` (n,) s).
    e : Effect
    th : tuple
        Its nonlinear value.

    Returns
    -------
    lo, hi : (e.n_lin,) ndarray
    """
    n = e.n_full or e.n_lin
    lo, hi = np.full(n, -np.inf), np.full(n, np.inf)
    if e.name == "thermal_drift":
        T = max(float(np.max(F["t_s"])), 0.0) if len(F["t_s"]) else 0.0
        reach = max(1.0 - math.exp(-T / max(float(th[0]), 1e-12)), 1e-12)
        lo[:], hi[:] = -LIMITS[e.name] / math.sqrt(3.0) / reach, LIMITS[e.name] / math.sqrt(3.0) / reach
    elif e.name == "machine_geometry":
        lo[:], hi[:] = -LIMITS[e.name], LIMITS[e.name]
    elif e.name == "runout":
        lo[:], hi[:] = -LIMITS[e.name], LIMITS[e.name]
        lo[0] = 0.0
    elif e.name == "tool_contour":
        lo[:], hi[:] = -LIMITS[e.name], LIMITS[e.name]
    elif e.name == "tool_wear":
        lo[:] = 0.0
    elif e.name == "force_scale":
        lo[:], hi[:] = FORCE_SCALE_RANGE[0] - 1.0, FORCE_SCALE_RANGE[1] - 1.0
    elif e.name == "servo_corner":
        lo[:], hi[:] = -SERVO_LIMIT_UM, SERVO_LIMIT_UM
    if e.keep is not None:
        lo, hi = lo[list(e.keep)], hi[list(e.keep)]
    return lo, hi


def catalogue(F) -> list[Effect]:
    """The effects with nonlinear grids sized to the data (q range, duration, corner spacing).

    Parameters
    ----------
    F : dict
        Features of the measured points (``q_deg``, ``t_s``, ``pred_deflection_um``,
        ``corner_dist_mm``; ``runout_grid_um`` when the prediction's runout response is known).

    Returns
    -------
    list of Effect
        The force scale is left out without a predicted deflection, the servo lag without corners.
    """
    qlo, qhi = np.percentile(F["q_deg"], [1, 99])
    T = max(float(F["t_s"].max()), 1e-6)
    q0s = np.arange(max(0.0, qlo), min(qhi, 90.0) + 1e-9, 2.0)
    widths = [4.0, 5.0, 6.5, 8.0, 10.0, 12.5, 15.0, 17.5, 20.0]
    taus = list(T * np.geomspace(0.02, 10.0, 28))
    lams = list(np.geomspace(0.05, 5.0, 24))
    cat = [
        (Effect("runout", [(float(e),) for e in F["runout_grid_um"]], 2) if "runout_resp_um" in F
         else Effect("runout", [()], 1)),
        Effect("tool_contour", [(a, w) for a in q0s for w in widths], 1),
        Effect("tool_wear", [()], 1),
        Effect("thermal_drift", [(t,) for t in taus], 3),
        Effect("force_scale", [()], 1),
        Effect("servo_corner", [(lm,) for lm in lams], 1),
        Effect("machine_geometry", [()], 6),
    ]
    if not np.any(np.abs(F["pred_deflection_um"]) > 0):
        cat = [e for e in cat if e.name != "force_scale"]
    if not np.any(np.isfinite(F["corner_dist_mm"])):
        cat = [e for e in cat if e.name != "servo_corner"]
    return cat
