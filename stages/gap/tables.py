"""The diagnosis's tables: ``gap_points`` (per measured point) and ``gap_effects`` (per effect)."""
from __future__ import annotations

import json

import numpy as np
import pyarrow as pa

EXTRA_POINT_COLUMNS = ("x_mm", "y_mm", "z_mm", "nx", "ny", "nz", "q_deg", "phi_deg", "t_s", "cut_len_mm",
                       "corner_dist_mm", "corner_deg", "feed_mm_min", "pred_deflection_um", "dist_mm",
                       "residual_after_um")


def gap_points_table(F, after) -> pa.Table:
    """The ``gap_points`` table: one row per measured point with its features and residuals.

    Parameters
    ----------
    F : dict
        Features of n points (``stages.gap.associate.associate``).
    after : (n,) ndarray
        Held-out residual after the effects (µm).

    Returns
    -------
    pa.Table
        n rows (schema ``gap_points``).
    """
    cols = {
        "point_id": pa.array(F["point_id"].astype(np.int64)),
        "program_id": pa.array(F["program_id"].astype(str).tolist(), pa.string()),
        "pass_id": pa.array(F["pass_id"].astype(np.int32)),
        "predicted_um": F["predicted_um"], "measured_um": F["measured_um"], "residual_um": F["residual_um"],
    }
    for k in EXTRA_POINT_COLUMNS:
        if k == "residual_after_um":
            cols[k] = after
        else:
            cols[k] = np.asarray(F[k], dtype=float)
    return pa.table(cols)


def gap_effects_table(res: dict) -> pa.Table:
    """The ``gap_effects`` table: one row per catalogue effect of the first round's ranking (an
    effect none of whose amplitudes the points observe is not ranked; ``observability`` says why).

    Parameters
    ----------
    res : dict
        ``stages.gap.diagnose.diagnose`` result.

    Returns
    -------
    pa.Table
        Schema ``gap_effects``; params, params_se and ambiguous_with as JSON text.
    """
    rows = res["ranking"]
    chosen = res["params"]
    return pa.table({
        "effect": pa.array([r["effect"] for r in rows], pa.string()),
        "params": pa.array([json.dumps(chosen.get(r["effect"], {})) for r in rows], pa.string()),
        "params_se": pa.array([json.dumps(res.get("params_se", {}).get(r["effect"], {})) for r in rows], pa.string()),
        "rms_before_um": [r["rms_before_um"] for r in rows],
        "rms_after_um": [r["rms_after_um"] for r in rows],
        "explained": [1 - r["rms_after_um"] / r["rms_before_um"] if r["rms_before_um"] > 0 else 0.0 for r in rows],
        "rank": pa.array([r["rank"] for r in rows], pa.int32()),
        "gain_sigma2": [r["gain_sigma2"] for r in rows],
        "threshold_sigma2": [r["threshold_sigma2"] for r in rows],
        "chosen": [r["effect"] in res.get("effects", chosen) for r in rows],
        "hidden_up_to_um": [float(res.get("detection_limits", {}).get(r["effect"], {}).get("hidden_up_to_um", np.nan))
                            for r in rows],
        "ambiguous_with": pa.array([json.dumps(res.get("ambiguous_with", {}).get(r["effect"], [])) for r in rows],
                                   pa.string()),
        "not_observable": pa.array([json.dumps({k: w for k, w in res.get("observability", {}).get(r["effect"], {}).items()
                                                if w}) for r in rows], pa.string()),
        "possible": pa.array([res.get("possible_why", {}).get(r["effect"]) if r["effect"] in res.get("possible", []) else None
                              for r in rows], pa.string()),
    })
