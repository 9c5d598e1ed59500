"""Scoring of the blind check (DESIGN §8 step 5): fitted parameters against the truth, relative and
in units of their stated standard errors.
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from stages.gap.cases import geometry_offsets


# amplitudes of the effects scored as a vector or field (``param_error``)
_VECTOR_AMPLITUDES = ("ax_um", "ay_um", "az_um", "sx", "sy", "sz", "exy", "exz", "eyz")


def param_error(kind: str, true: dict, fit: dict, geom=None, *, flutes: int, not_observable=()) -> float:
    """Relative error of the fitted parameters (vector norm for multi-parameter effects).

    Parameters
    ----------
    kind : str
        The effect.
    true, fit : dict
        Its true (as the virtual machine took them) and fitted parameters.
    geom : ((n, 3) ndarray, (n, 3) ndarray), optional
        Tool tips (mm) and normals at the points: the machine geometry is scored by its field.
    flutes : int
        The tool's flutes (the runout the surface shows is the largest flute offset).
    not_observable : sequence of str
        Amplitudes the diagnosis held at nominal as the plan does not observe them: scored at 0 on
        both sides (a drift vector or geometry field judged on the part the points determine).

    Returns
    -------
    float
        Relative error (0.2 = 20 %).
    """
    held = [k for k in not_observable if k in _VECTOR_AMPLITUDES]   # a nonlinear value is scored as it is
    if held:
        true = {k: (0.0 if k in held else v) for k, v in true.items()}
        fit = {k: (0.0 if k in held else v) for k, v in fit.items()}
    if kind == "runout":
        return abs(fit["e_um"] - runout_effective(true, flutes)) / runout_effective(true, flutes)
    if kind == "force_scale":
        return abs(fit["scale"] - true["scale"]) / abs(true["scale"] - 1.0)
    if kind == "tool_contour":
        return max(abs(fit["a_um"] - true["a_um"]) / abs(true["a_um"]),
                   abs(fit["q0_deg"] - true["q0_deg"]) / true["width_deg"],
                   abs(fit["width_deg"] - true["width_deg"]) / true["width_deg"])
    if kind == "thermal_drift":
        a = np.array([true[k] for k in ("ax_um", "ay_um", "az_um")])
        b = np.array([fit[k] for k in ("ax_um", "ay_um", "az_um")])
        return max(float(np.linalg.norm(a - b) / np.linalg.norm(a)), abs(fit["tau_s"] - true["tau_s"]) / true["tau_s"])
    if kind == "servo_corner":
        return max(abs(fit["a_um"] - true["a_um"]) / abs(true["a_um"]),
                   abs(fit["lambda_mm"] - true["lambda_mm"]) / true["lambda_mm"])
    if kind == "machine_geometry" and geom is not None:
        # the six coefficients are not all identifiable on a part a few mm tall (z terms ~ an offset);
        # the error of the tool-offset field they make, over the measured points, is
        tip, n = geom
        field = lambda g: np.sum(n * geometry_offsets(g, tip), 1)  # noqa: E731
        ft = field(true)
        return float(np.sqrt(np.mean((field(fit) - ft) ** 2)) / np.sqrt(np.mean(ft ** 2)))
    keys = list(true)
    a = np.array([true[k] for k in keys])
    b = np.array([fit[k] for k in keys])
    return float(np.linalg.norm(a - b) / np.linalg.norm(a))


def param_terms(kind: str, true: dict, fit: dict, se: dict, cov: Optional[dict] = None, geom=None, *,
                flutes: int) -> dict:
    """The fitted parameters of one true effect against the truth, in units of their stated standard
    errors, and the terms of ``param_error`` with the error each could have at 2 SE.

    ``z``: per parameter with a truth, |fit − truth| / se (None when the diagnosis stated no se; the
    runout's e against the largest flute offset, its force part e_force_um has no truth here).
    ``terms``: per term of ``param_error`` (same normalisation), its relative error and ``rel_2se`` =
    2·se / normaliser — above 0.2 the points cannot pin that term to 20 % (for the drift's amplitude
    vector and the machine-geometry field, the RMS of the error the covariance implies:
    √trace(Σ)/‖A‖ and √(mean over the points of (n·offset(δg))²)/RMS of the field).

    Parameters
    ----------
    kind, true, fit, geom, flutes
        As ``param_error``.
    se : dict
        Stated standard error per parameter (None: not stated).
    cov : dict, optional
        Stated covariance ({"names", "matrix"}).

    Returns
    -------
    dict
        {"z": {parameter: float or None}, "terms": [{"param", "rel_error", "rel_2se",
        "pinnable_to_20pct"}]}.
    """
    def z(key, t):
        s = se.get(key)
        return abs(fit[key] - t) / s if s is not None and s > 0 else None

    def rel(key, norm):
        s = se.get(key)
        return 2 * s / norm if s is not None else None

    zz, terms = {}, []
    if kind == "runout":
        eff = runout_effective(true, flutes)
        zz["e_um"] = z("e_um", eff)
        terms.append({"param": "e_um", "rel_error": abs(fit["e_um"] - eff) / eff, "rel_2se": rel("e_um", eff)})
    elif kind == "force_scale":
        d = abs(true["scale"] - 1.0)
        zz["scale"] = z("scale", true["scale"])
        terms.append({"param": "scale", "rel_error": abs(fit["scale"] - true["scale"]) / d, "rel_2se": rel("scale", d)})
    elif kind == "tool_contour":
        w = true["width_deg"]
        for k, norm in (("a_um", abs(true["a_um"])), ("q0_deg", w), ("width_deg", w)):
            zz[k] = z(k, true[k])
            terms.append({"param": k, "rel_error": abs(fit[k] - true[k]) / norm, "rel_2se": rel(k, norm)})
    elif kind == "thermal_drift":
        keys = ("ax_um", "ay_um", "az_um")
        a = np.array([true[k] for k in keys])
        b = np.array([fit[k] for k in keys])
        for k in keys + ("tau_s",):
            zz[k] = z(k, true[k])
        ses = [se.get(k) for k in keys]
        terms.append({"param": "a_vector", "rel_error": float(np.linalg.norm(a - b) / np.linalg.norm(a)),
                      "rel_2se": (2 * math.sqrt(sum(x * x for x in ses)) / float(np.linalg.norm(a))
                                  if all(x is not None for x in ses) else None)})
        terms.append({"param": "tau_s", "rel_error": abs(fit["tau_s"] - true["tau_s"]) / true["tau_s"],
                      "rel_2se": rel("tau_s", true["tau_s"])})
    elif kind == "servo_corner":
        for k, norm in (("a_um", abs(true["a_um"])), ("lambda_mm", true["lambda_mm"])):
            zz[k] = z(k, true[k])
            terms.append({"param": k, "rel_error": abs(fit[k] - true[k]) / norm, "rel_2se": rel(k, norm)})
    elif kind == "tool_wear":
        k = "rate_um_per_m"
        zz[k] = z(k, true[k])
        terms.append({"param": k, "rel_error": abs(fit[k] - true[k]) / abs(true[k]), "rel_2se": rel(k, abs(true[k]))})
    elif kind == "machine_geometry":
        keys = ("sx", "sy", "sz", "exy", "exz", "eyz")
        for k in keys:
            zz[k] = z(k, true[k])
        if geom is not None:
            tip, n = geom
            field = lambda g: np.sum(n * geometry_offsets(g, tip), 1)  # noqa: E731
            ft = field(true)
            norm = float(np.sqrt(np.mean(ft ** 2)))
            r2 = None
            if cov is not None:
                idx = [cov["names"].index(f"machine_geometry.{k}") if f"machine_geometry.{k}" in cov["names"] else None
                       for k in keys]
                if all(i is not None for i in idx):
                    S = np.array([[cov["matrix"][i][j] if cov["matrix"][i][j] is not None else np.nan for j in idx]
                                  for i in idx])
                    # each coefficient's field per unit, at the points: mean of (N Σ Nᵀ) diagonal
                    N = np.stack([field({kk: float(kk == k) for kk in keys}) for k in keys], 1)
                    v = float(np.mean(np.einsum("pi,ij,pj->p", N, S, N)))
                    r2 = 2 * math.sqrt(v) / norm if np.isfinite(v) and v >= 0 else None
            terms.append({"param": "field", "rel_error": float(np.sqrt(np.mean((field(fit) - ft) ** 2)) / norm),
                          "rel_2se": r2})
    for t in terms:
        t["pinnable_to_20pct"] = None if t["rel_2se"] is None else bool(t["rel_2se"] <= 0.2)
    return {"z": zz, "terms": terms}


def coefficient_error(true: dict, fit: dict) -> float:
    """Relative error of a parameter vector (norm), for the record.

    Parameters
    ----------
    true, fit : dict
        {parameter: float}; the keys of ``true`` found in ``fit`` count.

    Returns
    -------
    float
    """
    keys = [k for k in true if k in fit]
    a = np.array([true[k] for k in keys], float)
    b = np.array([fit[k] for k in keys], float)
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(a), 1e-12))


def runout_effective(true: dict, flutes: int) -> float:
    """The largest flute offset e·max_j cos(2πj/N + phase): what the surface shows.

    Parameters
    ----------
    true : dict
        ``e_um`` (µm) and ``phase_deg`` of the runout.
    flutes : int
        N.

    Returns
    -------
    float
        µm.
    """
    return true["e_um"] * max(math.cos(2 * math.pi * j / flutes + math.radians(true["phase_deg"])) for j in range(flutes))
