"""The diagnosis as workflow changes (``<out>/gap/model_update.yaml``, issue 60): an overlay that
``pipeline run WORKFLOW --overlay gap/model_update.yaml`` merges over the workflow, so the next
prediction and correction include the diagnosed effects.

Each kept effect becomes the workflow keys that model it (the same changes the diagnosis'
re-prediction made, ``stages.gap.predictor.Predictor.tool_for``):

- ``runout``: ``tool.runout_um`` = the workflow's runout + e;
- ``tool_contour``, ``tool_wear``: ``tool.profile`` = a table beside the overlay, the workflow's
  profile plus the fitted dent a·exp(−½((q − q0)/w)²) plus, for the wear, its radius loss rate·L̄
  at the mean cut length L̄ of the measured points (a profile is static: the wear's growth along
  the program is not modelled, only its mean);
- ``force_scale``: ``material`` ktc…kae × the scale (× a reference calibration's s0);
- ``thermal_drift``: ``drift`` = a one-source drift model (``stages.thermal.model.DriftModel``,
  τ and per-axis gains A, no offset) written beside the overlay, its clock starting with the
  program (``start_s: 0``), the clock the diagnosis fitted it on;
- ``servo_corner``, ``machine_geometry``: the workflow has no key for them; they are listed as
  not applied with the reason (file comments and ``summary.json``), never dropped.

A parameter the diagnosis reports not observable stays at nominal: its effect is not applied.
The overlay's paths are relative to its own folder.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np
import yaml

from stages.cutting.surface_error import read_profile
from stages.thermal.model import AXES, DriftModel

COEFFS = ("ktc", "krc", "kac", "kte", "kre", "kae")
NO_KEY = {
    "servo_corner": "the workflow has no key for a servo lag at path corners (the prediction models no "
                    "servo dynamics)",
    "machine_geometry": "the workflow has no key for axis scale and squareness errors (the prediction "
                        "models no machine geometry)",
}
PROFILE_FILE = "tool_profile_model_update.csv"
DRIFT_FILE = "drift_model_update.yaml"


def _hidden(observability: dict, effect: str, keys) -> list:
    """The parameters of ``effect`` among ``keys`` the diagnosis could not observe."""
    return [k for k in keys if (observability.get(effect) or {}).get(k)]


def profile_values(q: np.ndarray, base_profile: Optional[str], contour: Optional[dict], wear_um: float) -> np.ndarray:
    """Contour error (µm, + = tool smaller) at contact angles ``q`` (deg): the workflow's profile
    table, the fitted dent and a uniform radius loss ``wear_um``."""
    e = np.full(len(q), float(wear_um))
    if contour is not None:
        e += contour["a_um"] * np.exp(-0.5 * ((q - contour["q0_deg"]) / contour["width_deg"]) ** 2)
    if base_profile:
        pq_, pe_ = read_profile(base_profile)
        e += np.interp(q, pq_, pe_)
    return e


def workflow_update(params: dict, observability: dict, tool: dict, material: dict, *, tool_t: Optional[int],
                    material_t: Optional[int], base: Path, outdir: Path, has_drift: bool = False,
                    force_scale0: float = 1.0, cut_len_mean_m: float = 0.0) -> dict:
    """The overlay of the kept effects ``params`` and the files it names (written into ``outdir``).

    Parameters
    ----------
    params : dict
        {effect: fitted parameters} of the kept effects (``summary.json``'s ``params``).
    observability : dict
        {effect: {parameter: reason or None}}; a reason means not observable (held at nominal).
    tool, material : dict
        The workflow's entries the diagnosed program used (file paths as written in the workflow).
    tool_t, material_t : int or None
        Their T numbers when the workflow lists several (the overlay then names the entry by ``t``).
    base : Path
        The workflow's base directory (its relative paths).
    outdir : Path
        Where the overlay and its files go.
    has_drift : bool
        The workflow already has a ``drift`` model (a second fitted drift is then not merged in).
    force_scale0 : float
        A reference calibration's force-model scale (1 without one).
    cut_len_mean_m : float
        Mean cut length at the measured points, m (the tool wear's mean radius loss).

    Returns
    -------
    dict
        ``overlay`` (workflow keys), ``applied`` ({effect: {workflow key: value}}), ``unapplied``
        ({effect: reason}).
    """
    overlay, applied, unapplied = {}, {}, {}
    t_entry = {} if tool_t is None else {"t": tool_t}
    tool_up = {}
    if "runout" in params:
        if _hidden(observability, "runout", ["e_um"]):
            unapplied["runout"] = "e not observable on these points: held at nominal"
        else:
            tool_up["runout_um"] = float(tool.get("runout_um") or 0.0) + max(float(params["runout"]["e_um"]), 0.0)
            applied["runout"] = {"tool.runout_um": tool_up["runout_um"]}
    contour = params.get("tool_contour")
    if contour is not None and _hidden(observability, "tool_contour", ["a_um"]):
        unapplied["tool_contour"], contour = "a not observable on these points: held at nominal", None
    wear_um = 0.0
    if "tool_wear" in params:
        if _hidden(observability, "tool_wear", ["rate_um_per_m"]):
            unapplied["tool_wear"] = "rate not observable on these points: held at nominal"
        else:
            wear_um = float(params["tool_wear"]["rate_um_per_m"]) * float(cut_len_mean_m)
    if contour is not None or wear_um:
        q = np.round(np.arange(0.0, 90.0 + 1e-9, 0.25), 6)
        prof = tool.get("profile")
        e = profile_values(q, str(base / prof) if prof and not Path(prof).is_absolute() else prof, contour, wear_um)
        outdir.mkdir(parents=True, exist_ok=True)
        (outdir / PROFILE_FILE).write_text("contact_deg,error_um\n" + "".join(f"{a:.4f},{b:.6f}\n" for a, b in zip(q, e)))
        tool_up["profile"] = PROFILE_FILE
        if contour is not None:
            applied["tool_contour"] = {"tool.profile": PROFILE_FILE}
        if wear_um:
            applied["tool_wear"] = {"tool.profile": PROFILE_FILE, "radius_loss_um": wear_um}
    if tool_up:
        overlay["tool"] = dict(t_entry, **tool_up)
    scale = float(force_scale0)
    if "force_scale" in params:
        if _hidden(observability, "force_scale", ["scale"]):
            unapplied["force_scale"] = "scale not observable on these points: held at nominal"
        else:
            scale *= float(params["force_scale"]["scale"])
    if scale != 1.0:
        mat = {k: float(material[k]) * scale for k in COEFFS if material.get(k) is not None}
        overlay["material"] = dict({} if material_t is None else {"t": material_t}, **mat)
        # the reference part's calibration s0 alone (no force_scale kept) is a model change too
        label = "force_scale" if "force_scale" in params and "force_scale" not in unapplied else "calibration"
        applied[label] = {f"material.{k}": v for k, v in mat.items()} | {"scale": scale}
    if "thermal_drift" in params:
        p = params["thermal_drift"]
        if has_drift:
            unapplied["thermal_drift"] = ("the workflow already has a drift model; the residual drift is not "
                                          "merged into it (refit it with `pipeline thermal-fit`)")
        else:
            # an axis not observable keeps its nominal 0 (the fit already holds it there)
            gains = {a: (0.0 if _hidden(observability, "thermal_drift", [f"a{a}_um"]) else float(p[f"a{a}_um"]))
                     for a in AXES}
            model = DriftModel(np.array([float(p["tau_s"])]), {a: np.array([0.0, gains[a]]) for a in AXES})
            outdir.mkdir(parents=True, exist_ok=True)
            (outdir / DRIFT_FILE).write_text(yaml.safe_dump(model.to_dict(), sort_keys=False))
            overlay["drift"] = {"model": DRIFT_FILE, "start_s": 0.0}
            applied["thermal_drift"] = {"drift.model": DRIFT_FILE, "tau_s": float(p["tau_s"])} | {
                f"{a}.gain1_um": gains[a] for a in AXES}
    for name in params:
        if name in NO_KEY:
            unapplied[name] = NO_KEY[name]
    return {"overlay": overlay, "applied": applied, "unapplied": unapplied}


def write_update(path: Path, upd: dict, params: dict) -> Path:
    """Write the overlay ``upd["overlay"]`` as YAML with comments naming what is not applied and why."""
    lines = ["# Model update of `pipeline diagnose`: workflow keys for", "#   pipeline run WORKFLOW --overlay " + path.name,
             "# (paths relative to this file's folder)."]
    for name, why in upd["unapplied"].items():
        lines.append(f"# not applied: {name} {params.get(name)}: {why}")
    if not upd["overlay"]:
        lines.append("# no kept effect has a workflow key: this overlay changes nothing")
    body = yaml.safe_dump(upd["overlay"], sort_keys=False) if upd["overlay"] else "{}\n"
    path.write_text("\n".join(lines) + "\n" + body)
    return path
