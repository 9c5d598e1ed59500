"""The diagnosis as the user reads it: ``summary.json``'s content and the HTML report."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from stages.gap.effects import LIMITS


def public_summary(res: dict) -> dict:
    """The JSON-able part of a diagnosis ``res`` (``stages.gap.predictor.diagnose_points``) for
    ``summary.json``: its public keys, with ``held_out``, ``model_update`` and ``how_added``."""
    keys = ("effect", "effects", "params", "params_se", "params_se_info", "params_cov", "where", "where_after",
            "sigma_um", "n_points", "n_blocks",
            "rms_before_um", "rms_after_um", "p95_before_um", "p95_after_um", "max_before_um", "max_after_um",
            "shrink", "shrink_where_acting", "ranking", "ambiguous_with",
            "detection_limits", "beyond_limits", "calibration")  # after: held-out, effects added to the simulation
    out = {k: res[k] for k in keys if k in res}
    out["held_out"] = "K-fold over spatial blocks: every point predicted by the fit without its block"
    out["model_update"] = model_update(res["params"])
    out["how_added"] = res.get("how_added", {})
    if "rms_after_terms_um" in res:
        out["rms_after_terms_um"] = res["rms_after_terms_um"]
    return out


def model_update(params: dict) -> dict:
    """How each chosen effect of ``params`` ({effect: reported parameters}) enters the simulation
    model (tool, machine, force model): {model key: value or description}."""
    up = {}
    for name, p in params.items():
        if name == "runout":
            up["tool.runout_um"] = p["e_um"]
        elif name == "force_scale":
            up["material.*"] = f"multiply ktc, krc, kac, kte, kre, kae by {p['scale']:.4g}"
        elif name == "tool_contour":
            up["tool.profile"] = p.get("profile_csv") or (
                f"add {p['a_um']:.3g}·exp(-((q-{p['q0_deg']:.3g})/{p['width_deg']:.3g})²/2) µm "
                f"to error_um (seed 002 second error)")
        elif name == "tool_wear":
            up["tool.wear_um_per_m"] = p["rate_um_per_m"]
        else:
            up[f"machine.{name}"] = p
    return up


def report(gdir: Path, F: dict, res: dict, summary: dict) -> None:
    """Write the gap report: ``index.html`` and ``residual_map.png`` in ``gdir``.

    Parameters
    ----------
    gdir : Path
        Output directory.
    F : dict
        Features of n points (``x_mm``, ``y_mm``, ``t_s``, ``residual_um``).
    res : dict
        The diagnosis (``_after``: (n,) held-out residual after, µm).
    summary : dict
        ``public_summary`` with ``n_rejected``.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    before, after = F["residual_um"], res["_after"]
    lim = float(np.percentile(np.abs(before), 99)) or 1.0
    fig, ax = plt.subplots(1, 3, figsize=(15, 4.5))
    for a, v, title in ((ax[0], before, "residual before (µm)"), (ax[1], after, "residual after, held-out (µm)")):
        sc = a.scatter(F["x_mm"], F["y_mm"], c=v, s=6, cmap="coolwarm", vmin=-lim, vmax=lim)
        a.set_aspect("equal"); a.set_title(title); a.set_xlabel("x mm"); a.set_ylabel("y mm")
        fig.colorbar(sc, ax=a)
    ax[2].scatter(F["t_s"], before, s=3, label="before", alpha=0.6)
    ax[2].scatter(F["t_s"], after, s=3, label="after", alpha=0.6)
    ax[2].set_xlabel("machining time s"); ax[2].set_ylabel("residual µm"); ax[2].legend()
    fig.tight_layout()
    fig.savefig(gdir / "residual_map.png", dpi=90)
    plt.close(fig)
    rows = "".join(f"<tr><td>{r['rank']}</td><td>{r['effect']}</td><td>{r['rms_after_um']:.3f}</td>"
                   f"<td>{r['gain_sigma2']:.1f}</td><td>{r['threshold_sigma2']:.1f}</td>"
                   f"<td>{'yes' if r['significant'] else 'no'}</td></tr>" for r in summary["ranking"])
    wh = "".join(f"<tr><td>{w['bbox_mm']}</td><td>{w['pass_range']}</td><td>{w['contact_deg']}</td>"
                 f"<td>{w['time_s']}</td><td>{w['mean_residual_um']:.2f}</td><td>{w['ci95_um']}</td></tr>"
                 for w in summary["where"])
    lim = "".join(f"<tr><td>{k}</td><td>{v['hidden_up_to_um']:.2f}</td><td>{v['correlation']:.3f}</td>"
                  f"<td>{v['masked_by'] or '(noise)'}</td></tr>"
                  for k, v in sorted(summary.get("detection_limits", {}).items(), key=lambda kv: -kv[1]["hidden_up_to_um"]))
    prm = "".join(
        f"<tr><td>{e}</td><td>{k}</td><td>{v:.4g}</td>"
        + (f"<td>{summary['params_se'][e][k]:.2g}</td><td>[{v - 2 * summary['params_se'][e][k]:.4g}, "
           f"{v + 2 * summary['params_se'][e][k]:.4g}]</td>"
           if summary.get("params_se", {}).get(e, {}).get(k) is not None else
           f"<td colspan=2>{summary.get('params_se_info', {}).get('not_identifiable', {}).get(e + '.' + k, 'no standard error')}</td>")
        + "</tr>"
        for e, p in summary["params"].items() for k, v in p.items() if isinstance(v, (int, float)))
    se_info = summary.get("params_se_info", {})
    amb = "; ".join(f"{e}: cannot be told from " + ", ".join(f"{a['effect']} (correlation {a['correlation']:.3f})" for a in v)
                    for e, v in summary.get("ambiguous_with", {}).items())
    beyond = "".join(f"<li>step {r['step']}: adding {r['effect']} took {', '.join(r['beyond_limits'])} beyond "
                     f"{', '.join(str(LIMITS[k]) for k in r['beyond_limits'])}: <code>{json.dumps(r['params'])}</code></li>"
                     for r in summary.get("beyond_limits", []))
    html = f"""<html><head><meta charset="utf-8"><title>Gap diagnosis</title></head><body>
<h1>Sim-to-real gap</h1>
<p>Effect: <b>{summary['effect']}</b>; all added: {summary['effects']}; parameters: <code>{json.dumps(summary['params'])}</code></p>
<p>Held-out residual: RMS {summary['rms_before_um']:.3f} → {summary['rms_after_um']:.3f} µm (shrink {summary['shrink']:.1%}),
P95 {summary['p95_before_um']:.3f} → {summary['p95_after_um']:.3f} µm, max {summary['max_before_um']:.3f} → {summary['max_after_um']:.3f} µm;
noise σ {summary['sigma_um']:.3f} µm; {summary['n_points']} points, {summary['n_rejected']} rejected (rejected.csv).</p>
<img src="residual_map.png">
<h2>Fitted parameters and their standard errors</h2>
<p>All chosen effects fitted jointly on all points; standard error from the model linearised at the fit,
s²·(JᵀJ)⁻¹ with s = {se_info.get('sigma_um', float('nan')):.3f} µm (the larger of the noise estimate and the residual RMS),
assuming independent residuals. ±2 SE is about a 95 % interval.</p>
<table border=1><tr><th>effect</th><th>parameter</th><th>value</th><th>SE</th><th>±2 SE</th></tr>{prm}</table>
<h2>Effect ranking (first round, held-out blocks)</h2>
<table border=1><tr><th>rank</th><th>effect</th><th>RMS after µm</th><th>gain / σ²</th><th>threshold</th><th>significant</th></tr>{rows}</table>
<h2>Not seen: detection limits next to the effects found</h2>
<p>{amb or "No effect found is ambiguous with another on these points."}</p>
<table border=1><tr><th>effect</th><th>would not be claimed up to (RMS µm)</th><th>signature correlation</th><th>with</th></tr>{lim}</table>
<h2>Not chosen: fits beyond a real machine's limits</h2>
<p>Limits (4 × the largest the seeds measured): thermal drift reached by the run's end {LIMITS['thermal_drift']:g} µm,
machine geometry {LIMITS['machine_geometry']:g} µm/mm per coefficient, runout {LIMITS['runout']:g} µm,
tool contour {LIMITS['tool_contour']:g} µm. Beyond them two effects cancel each other; that combination is not chosen.</p>
<ul>{beyond or "<li>none</li>"}</ul>
<h2>Where (blocks with mean residual beyond the noise)</h2>
<table border=1><tr><th>bbox mm</th><th>passes</th><th>q deg</th><th>time s</th><th>mean µm</th><th>95 %</th></tr>{wh}</table>
</body></html>"""
    (gdir / "index.html").write_text(html)
