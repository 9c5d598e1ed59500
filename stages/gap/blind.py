"""The blind check (DESIGN §8 step 5): random effects on the virtual machine, diagnosed without
being told, scored against the truth (identification, parameter recovery, stated standard errors,
misses within the stated detection limits).
"""
from __future__ import annotations

import math
import time
from typing import Optional

import numpy as np
import pyarrow as pa

from stages import InputError
from stages.gap.associate import associate
from stages.gap.calibration import apply_baseline, calibrate
from stages.gap.cases import draw_pair, geometry_offsets, random_case, true_order, true_sizes
from stages.gap.measurements import measurement_table
from stages.gap.predictor import Predictor, diagnose_points
from stages.geometry.cutter import Cutter
from stages.virtual_machine import EFFECTS


def param_error(kind: str, true: dict, fit: dict, geom=None, *, flutes: int) -> float:
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

    Returns
    -------
    float
        Relative error (0.2 = 20 %).
    """
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


def check_kinds(kinds):
    """The effect kinds (list of str) the blind check cycles through, checked; None: all."""
    if not kinds:
        return None
    bad = [k for k in kinds if k != "none" and k not in EFFECTS]
    if bad:
        raise InputError(f"--kinds: unknown {bad} (known: none, {', '.join(EFFECTS)})")
    return list(kinds)


def blind_cases(vm, passes: pa.Table, errors: Optional[pa.Table], tool, pts: np.ndarray, nrm: np.ndarray,
                cases: int, seed: int, noise=(0.3, 1.0), pairs: int = 0, off_part_mm: float = 0.05,
                kinds: Optional[list] = None, progress=None, deflection: Optional[pa.Table] = None,
                predictor: Optional[Predictor] = None) -> dict:
    """The blind check on one program: ``cases`` single-effect (or none) cases + ``pairs`` two-effect cases.

    With a ``predictor`` (the run's render tables), the reference part's force scale s0 becomes the
    predictor's baseline, the runout signature is the prediction's own response, and "after" is
    the re-run prediction with the fitted effects (``how_far``).

    Parameters
    ----------
    vm : VirtualMachine
        The program machined (``stages.virtual_machine``).
    passes, errors, deflection : pa.Table
        The run's tables of that program.
    tool : dict or Cutter
    pts, nrm : (n, 3) ndarray
        Plan points (mm) and unit normals.
    cases : int
        Single-effect (or none) cases.
    seed : int
        Seed of the cases' draws.
    noise : (float, float)
        Range of the probe noise σ drawn per case (µm).
    pairs : int
        Two-effect cases.
    off_part_mm : float
    kinds : list of str, optional
        Kinds the single cases cycle through (default: none and every effect).
    progress : callable, optional
        ``progress(i, case)`` after each case.
    predictor : Predictor, optional

    Returns
    -------
    dict
        Accuracy, shrink, parameter errors and coverage figures, and ``cases_detail``.
    """
    flutes = Cutter.from_params(tool).flutes
    ids = np.arange(len(pts))
    p = vm.path
    q = np.degrees(np.arccos(np.clip(nrm[:, 2], -1, 1)))
    ctx = {"duration_s": float(p.t1.max()), "q_max_deg": float(np.percentile(q, 98)),
           "cut_len_mm": float(p.L0[-1] + p.length[-1]),
           "size_mm": float(np.ptp(pts, axis=0).max()), "tips": pts + vm.R * nrm - [0.0, 0.0, vm.R],
           "flutes": flutes}
    kinds = kinds or ["none"] + list(EFFECTS)
    rng = np.random.default_rng(seed)
    plan_cases = [[kinds[i % len(kinds)]] for i in range(cases)]
    rng.shuffle(plan_cases)
    pool = [k for k in kinds if k != "none"] or list(EFFECTS)
    for _ in range(pairs):
        # the larger effect of a pair acts over the whole part (a corner effect is small in RMS)
        a = rng.choice([k for k in pool if k != "servo_corner"])
        b = rng.choice([k for k in pool if k != a])
        plan_cases.append([str(a), str(b)])
    results = []
    t_start = time.perf_counter()
    geom = (pts + vm.R * nrm - [0.0, 0.0, vm.R], nrm)      # tool tip and normal at each point
    # reference part (no effect), as a shop calibrates on a test cut (``calibrate``)
    ref_sigma = float(np.mean(noise))
    err = vm.probe(pts, nrm, {}, ref_sigma, np.random.default_rng(seed + 7919))
    F0, _ = associate(measurement_table(ids, pts, nrm, err), passes, errors, tool, off_part_mm, deflection)
    calibration = dict(calibrate(F0, predictor), reference_noise_um=ref_sigma)
    s0, corner, floor = calibration["force_scale_s0"], calibration["corner_floor"], calibration["floor_um"]
    for ci, kinds_i in enumerate(plan_cases):
        if len(kinds_i) == 2:
            truth = draw_pair(rng, kinds_i, pool, vm, pts, nrm, ctx)
        else:
            truth = {k: random_case(rng, k, ctx) for k in kinds_i if k != "none"}
        sigma = float(rng.uniform(*noise))
        err = vm.probe(pts, nrm, truth, sigma, rng)
        F, rej = associate(measurement_table(ids, pts, nrm, err), passes, errors, tool, off_part_mm, deflection)
        res = diagnose_points(apply_baseline(F, s0, corner), None, floor, predictor)
        by_size = true_order(truth, vm, pts, nrm)
        case = {"case": ci, "truth": truth, "true_order": by_size, "noise_um": sigma,
                "true_rms_um": true_sizes(truth, vm, pts, nrm) if len(truth) >= 2 else None,
                "found": res["effects"], "params": res["params"], "sigma_est_um": res["sigma_um"],
                "rms_before_um": res["rms_before_um"], "rms_after_um": res["rms_after_um"], "shrink": res["shrink"],
                "rms_after_terms_um": res.get("rms_after_terms_um"), "how_added": res.get("how_added"),
                "shrink_where_acting": res["shrink_where_acting"],
                "n_rejected": len(rej)}
        case["not_observable"] = {e: [k for k, w in d.items() if w] for e, d in res.get("observability", {}).items()}
        top = res["effect"]
        case["top1_ok"] = (top == (by_size[0] if by_size else "none"))
        case["ambiguous_with"] = res.get("ambiguous_with", {})
        if len(truth) == 1 and top in truth:
            case["param_error"] = param_error(top, truth[top], res["params"][top], geom, flutes=flutes)
            case["coefficient_error"] = coefficient_error(truth[top], res["params"][top])
        # the fitted parameters against the truth in units of their stated standard errors
        case["params_se"] = res.get("params_se", {})
        pt = {k: param_terms(k, truth[k], res["params"][k], res["params_se"].get(k, {}), res.get("params_cov"), geom,
                             flutes=flutes)
              for k in truth if k in res["params"]}
        case["param_z"] = {k: v["z"] for k, v in pt.items()}
        if case.get("param_error", 0.0) > 0.2:
            # the terms beyond 20 %, with |fit − truth|/se of the parameters behind each
            case["param_miss"] = [dict(t, z={k: pt[top]["z"].get(k) for k in _TERM_KEYS.get(t["param"], (t["param"],))})
                                  for t in pt[top]["terms"] if t["rel_error"] > 0.2]
        if len(truth) >= 2:
            case["pair_order_ok"] = res["effects"][:len(by_size)] == by_size
        # a true effect not named: was it within what the diagnosis said it could miss (its
        # detection limit next to the effects it named)? Reported beside the strict figures
        missed = [k for k in truth if k not in res["effects"]]
        if missed:
            size = case["true_rms_um"] or true_sizes(truth, vm, pts, nrm)
            lim = res.get("detection_limits", {})
            case["missed"] = [{"effect": k, "true_rms_um": size[k],
                               "hidden_up_to_um": lim.get(k, {}).get("hidden_up_to_um"),
                               "correlation": lim.get(k, {}).get("correlation"),
                               "masked_by": lim.get(k, {}).get("masked_by")} for k in missed]
            case["missed_within_stated_limit"] = all(m["hidden_up_to_um"] is not None
                                                     and m["true_rms_um"] <= m["hidden_up_to_um"] for m in case["missed"])
        results.append(case)
        if progress:
            progress(ci, case)
    singles = [c for c in results if len(c["truth"]) <= 1]
    eff = [c for c in singles if c["truth"]]
    zs = lambda cs: [z for c in cs for zk in c.get("param_z", {}).values() for z in zk.values()]  # noqa: E731
    none = [c for c in singles if not c["truth"]]
    perr = [c["param_error"] for c in eff if "param_error" in c]
    summary = {
        "calibration": calibration,
        "seed": seed, "cases": len(singles), "pairs": len(results) - len(singles),
        "noise_um": list(noise), "points_per_case": int(len(pts)),
        "top1_accuracy": float(np.mean([c["top1_ok"] for c in singles])) if singles else None,
        "top1_accuracy_effects": float(np.mean([c["top1_ok"] for c in eff])) if eff else None,
        "none_correct": float(np.mean([c["top1_ok"] for c in none])) if none else None,
        "median_shrink": float(np.median([c["shrink"] for c in eff])) if eff else None,
        "median_shrink_where_acting": float(np.median([c["shrink_where_acting"] or 0.0 for c in eff])) if eff else None,
        "param_error": {"median": float(np.median(perr)) if perr else None,
                        "within_20pct": float(np.mean(np.array(perr) <= 0.2)) if perr else None},
        # the stated standard errors checked: the fraction of fitted parameters (with a truth) whose
        # truth lies within 2 SE (≈ 95 % if they are honest), and for every case missing the 20 %
        # line, each term beyond it with |fit − truth|/se and 2·se/|truth| (> 0.2: the points
        # cannot pin it to 20 %)
        "param_se": _se_summary(singles, results, zs),
        "pair_order_ok": float(np.mean([c["pair_order_ok"] for c in results if "pair_order_ok" in c]))
        if len(results) > len(singles) else None,
        # the strict figures above count every miss; of the misses, those where a true effect was not
        # named although the diagnosis's stated detection limit for it (next to what it named) was
        # at least its true RMS: the data could not show it (signatures nearly collinear on the part)
        "misses_within_stated_limit": {
            "single": [c["case"] for c in singles if c["truth"] and not c["top1_ok"] and c.get("missed_within_stated_limit")],
            "pair": [c["case"] for c in results if len(c["truth"]) >= 2 and not c["pair_order_ok"]
                     and c.get("missed_within_stated_limit")]},
        "per_effect": {k: {"n": sum(1 for c in singles if (list(c["truth"]) or ["none"])[0] == k),
                           "top1": float(np.mean([c["top1_ok"] for c in singles if (list(c["truth"]) or ["none"])[0] == k]))
                           if any((list(c["truth"]) or ["none"])[0] == k for c in singles) else None}
                       for k in kinds},
        "wall_s": time.perf_counter() - t_start,
        "cases_detail": results,
    }
    return summary


# the parameters behind a vector term of ``param_terms``
_TERM_KEYS = {"a_vector": ("ax_um", "ay_um", "az_um"), "field": ("sx", "sy", "sz", "exy", "exz", "eyz")}


def _se_summary(singles: list, results: list, zs) -> dict:
    def cover(z, k):
        have = [x for x in z if x is not None]
        return float(np.mean(np.array(have) <= k)) if have else None
    zsg, zpr = zs(singles), zs([c for c in results if len(c["truth"]) >= 2])
    per = {}
    for c in singles:
        for k, zk in c.get("param_z", {}).items():
            for p, x in zk.items():
                d = per.setdefault(f"{k}.{p}", [])
                d.append(x)
    return {
        "coverage_2se": cover(zsg, 2.0), "coverage_1se": cover(zsg, 1.0),
        "n_params": sum(x is not None for x in zsg), "n_without_se": sum(x is None for x in zsg),
        "coverage_2se_pairs": cover(zpr, 2.0), "n_params_pairs": sum(x is not None for x in zpr),
        "median_z": float(np.median([x for x in zsg if x is not None])) if any(x is not None for x in zsg) else None,
        "per_parameter": {k: {"n": len(v), "within_2se": cover(v, 2.0),
                              "max_z": max((x for x in v if x is not None), default=None)} for k, v in sorted(per.items())},
        "misses_20pct": [{"case": c["case"], "effect": list(c["truth"])[0], "param_error": c["param_error"],
                          "noise_um": c["noise_um"], "terms": c["param_miss"]}
                         for c in singles if "param_miss" in c],
    }
