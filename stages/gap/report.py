"""The diagnosis as the user reads it: ``summary.json``'s content and the HTML report."""
from __future__ import annotations

import html as _html
import math
from pathlib import Path

import numpy as np

from stages.gap.effects import LIMITS
from stages.gap.observability import UNITS


def public_summary(res: dict) -> dict:
    """The JSON-able part of a diagnosis ``res`` (``stages.gap.predictor.diagnose_points``) for
    ``summary.json``: its public keys, with ``held_out``, ``model_update`` and ``how_added``."""
    keys = ("effect", "effects", "possible", "possible_why", "unexplained", "params", "params_se", "params_se_info", "params_cov",
            "where", "where_after", "sigma_um", "n_points", "n_blocks",
            "rms_before_um", "rms_after_um", "p95_before_um", "p95_after_um", "max_before_um", "max_after_um",
            "shrink", "shrink_where_acting", "ranking", "ambiguous_with",
            "detection_limits", "observability", "at_limits", "plan", "calibration")
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


def fmt(v, se=None) -> str:
    """A number as people read it: to the standard error's second significant digit when one is
    given, else 3 significant digits; no exponent between 1e-3 and 1e6."""
    if v is None or not isinstance(v, (int, float)) or not math.isfinite(v):
        return "–"
    if se is not None and isinstance(se, (int, float)) and math.isfinite(se) and se > 0:
        d = max(0, min(6, 1 - int(math.floor(math.log10(se)))))
        return f"{v:,.{d}f}"
    if v == 0:
        return "0"
    if 1e-3 <= abs(v) < 1e6:
        d = max(0, min(6, 2 - int(math.floor(math.log10(abs(v))))))
        return f"{v:,.{d}f}"
    return f"{v:.3g}"


def _range(a, b, unit="") -> str:
    """'a … b unit', or one value when both read the same."""
    lo, hi = fmt(a), fmt(b)
    return f"{lo if lo == hi else f'{lo} … {hi}'}{(' ' + unit) if unit else ''}"


def _maps(gdir: Path, F: dict, after) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy.spatial import ConvexHull
    before = F["residual_um"]
    x, y = F["x_mm"], F["y_mm"]
    lim = float(np.percentile(np.abs(before), 99)) or 1.0
    ex, ey = max(float(np.ptp(x)), 1e-3), max(float(np.ptp(y)), 1e-3)
    w = 5.5
    h = float(np.clip(w * ey / ex, 2.0, 9.0))
    fig, ax = plt.subplots(1, 2, figsize=(2 * w + 1.5, h + 1.0), constrained_layout=True)
    outline = None
    if len(x) >= 3 and ex > 1e-3 and ey > 1e-3:
        try:
            hull = ConvexHull(np.stack([x, y], 1))
            outline = np.stack([x, y], 1)[np.r_[hull.vertices, hull.vertices[0]]]
        except Exception:          # qhull on collinear points: no outline, the points show the part
            outline = None
    for a, v, title in ((ax[0], before, "residual before (µm)"), (ax[1], after, "residual after, held-out (µm)")):
        sc = a.scatter(x, y, c=v, s=max(4.0, 2400.0 / max(len(x), 1) ** 0.5), cmap="coolwarm", vmin=-lim, vmax=lim)
        if outline is not None:
            a.plot(outline[:, 0], outline[:, 1], color="0.4", lw=0.8)
        a.set_aspect("equal")
        pad = 0.03 * max(ex, ey)
        a.set_xlim(x.min() - pad, x.max() + pad)
        a.set_ylim(y.min() - pad, y.max() + pad)
        a.set_title(title)
        a.set_xlabel("x mm")
        a.set_ylabel("y mm")
        fig.colorbar(sc, ax=a, shrink=0.8)
    fig.savefig(gdir / "residual_map.png", dpi=90)
    plt.close(fig)
    fig, a = plt.subplots(figsize=(2 * w + 1.5, 3.0), constrained_layout=True)
    a.scatter(F["t_s"], before, s=3, label="before", alpha=0.6)
    a.scatter(F["t_s"], after, s=3, label="after (held-out)", alpha=0.6)
    a.set_xlabel("machining time s")
    a.set_ylabel("residual µm")
    a.legend()
    fig.savefig(gdir / "residual_time.png", dpi=90)
    plt.close(fig)


class _Why(str):
    """A table cell of prose: wraps and reads left to right."""


def _table(head, rows) -> str:
    th = "".join(f"<th>{h}</th>" for h in head)
    body = "".join("<tr>" + "".join(f"<td class=why>{c}</td>" if isinstance(c, _Why) else f"<td>{c}</td>" for c in r)
                   + "</tr>" for r in rows)
    return f"<table><tr>{th}</tr>{body}</table>"


def report(gdir: Path, F: dict, res: dict, summary: dict) -> None:
    """Write the gap report: ``index.html``, ``residual_map.png`` and ``residual_time.png`` in ``gdir``.

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
    _maps(gdir, F, res["_after"])
    esc = _html.escape
    se_all = summary.get("params_se", {})
    obs = summary.get("observability", {})
    prm = []
    for e, p in summary["params"].items():
        for k, v in p.items():
            if not isinstance(v, (int, float)):
                continue
            se = se_all.get(e, {}).get(k)
            why = obs.get(e, {}).get(k)
            unit = UNITS.get(k, "")
            prm.append([esc(e), k, f"{fmt(v, se)} {unit}", fmt(se, se) if se is not None else "–",
                        f"{fmt(v - 2 * se, se)} … {fmt(v + 2 * se, se)}" if se is not None else "–",
                        _Why("yes" if why is None else f"<span class=warn>no</span>: {esc(why)}")])
    obs_rows = [[esc(e), ", ".join(k for k, w in d.items() if w is None) or "–",
                 ", ".join(k for k, w in d.items() if w is not None) or "–"] for e, d in obs.items()]
    ranking = [[r["rank"], esc(r["effect"]), fmt(r["rms_after_um"]), fmt(r["gain_sigma2"]), fmt(r["threshold_sigma2"]),
                "yes" if r["significant"] else "no"] for r in summary["ranking"]]
    where = [[_range(w["bbox_mm"][0], w["bbox_mm"][3]), _range(w["bbox_mm"][1], w["bbox_mm"][4]),
              _range(w["bbox_mm"][2], w["bbox_mm"][5]), f"{w['pass_range'][0]}–{w['pass_range'][1]}",
              _range(*w["contact_deg"], "°"), _range(*w["time_s"], "s"), w["n_points"], fmt(w["mean_residual_um"]),
              f"{fmt(w['ci95_um'][0])} … {fmt(w['ci95_um'][1])}"] for w in summary.get("where", [])]
    lims = [[esc(k), fmt(v["hidden_up_to_um"]), fmt(v["correlation"]), esc(v["masked_by"] or "(noise)")]
            for k, v in sorted(summary.get("detection_limits", {}).items(), key=lambda kv: -kv[1]["hidden_up_to_um"])]
    plan = summary.get("plan", {})
    bands = [[f"{fmt(b['band_deg'][0])}–{fmt(b['band_deg'][1])}°", b["measured"], b["rejected"]] for b in plan.get("bands", [])]
    dirs = [[d["direction"], d["measured"], d["rejected"]] for d in plan.get("directions", [])]
    warns = "".join(f"<p class=warn>⚠ {esc(w)}</p>" for w in plan.get("warnings", []))
    amb = "; ".join(f"{e}: cannot be told from " + ", ".join(f"{a['effect']} (correlation {a['correlation']:.3f})" for a in v)
                    for e, v in summary.get("ambiguous_with", {}).items())
    possible, why = summary.get("possible", []), summary.get("possible_why", {})
    unexpl = summary.get("unexplained")
    answer = (", ".join(f"<b>{esc(e)}</b>" for e in summary["effects"]) or "<b>none</b>")
    if unexpl and summary["effect"] == "unexplained":
        answer = f"<b>unexplained</b> ({esc(unexpl.get('description', ''))})"
    elif unexpl:                 # structure left beside effects that explain most of the gap
        answer += f"; structure left beyond them: {esc(unexpl.get('description', ''))}"
    at_lim = summary.get("at_limits", [])
    se_info = summary.get("params_se_info", {})
    html = f"""<html><head><meta charset="utf-8"><title>Gap diagnosis</title>
<style>body{{font-family:sans-serif;max-width:1150px;margin:1em auto;color:#222}}
table{{border-collapse:collapse;margin:.5em 0}}td,th{{border:1px solid #bbb;padding:3px 8px;text-align:right}}
td:first-child,th:first-child{{text-align:left}}td{{white-space:nowrap}}td.why{{white-space:normal;text-align:left}}th{{background:#eee}}.warn{{color:#a40}}img{{max-width:100%}}</style></head><body>
<h1>Sim-to-real gap</h1>
<p>Answer: {answer}{('; possible, not claimed: ' + ', '.join(esc(p) + (f" ({esc(why[p])})" if p in why else '')
                                                            for p in possible)) if possible else ''}.</p>
<p>Held-out residual RMS {fmt(summary['rms_before_um'])} → {fmt(summary['rms_after_um'])} µm (shrink {summary['shrink']:.0%}),
P95 {fmt(summary['p95_before_um'])} → {fmt(summary['p95_after_um'])} µm, max {fmt(summary['max_before_um'])} → {fmt(summary['max_after_um'])} µm;
noise σ {fmt(summary['sigma_um'])} µm; {summary['n_points']} points used, {summary['n_rejected']} rejected (rejected.csv).</p>
<h2>Measurement plan</h2>{warns}
<div style="display:flex;gap:2em">{_table(['contact angle', 'measured', 'rejected'], bands)}
{_table(['normal', 'measured', 'rejected'], dirs)}</div>
<h2>Fitted parameters and their standard errors</h2>
<p>All chosen effects fitted jointly on all points within physical limits; standard error from the model
linearised at the fit (s = {fmt(se_info.get('sigma_um'))} µm); ±2 SE is about a 95 % interval.
{('Fitted at a physical limit: ' + ', '.join(esc(a) for a in at_lim) + '.') if at_lim else ''}</p>
{_table(['effect', 'parameter', 'value', 'SE', '±2 SE', 'observable'], prm) if prm else '<p>No effect claimed.</p>'}
<h2>Residual maps</h2><img src="residual_map.png"><img src="residual_time.png">
<h2>What these points can observe</h2>
<p>Parameters the points do not determine are held at nominal (0) in every fit and not claimed.</p>
{_table(['effect', 'observable', 'not observable (held at nominal)'], obs_rows)}
<h2>Effect ranking (first round, held-out blocks)</h2>
{_table(['rank', 'effect', 'RMS after µm', 'gain / σ²', 'threshold / σ²', 'significant'], ranking)}
<h2>Not seen: detection limits next to the effects found</h2>
<p>{esc(amb) or "No effect found is ambiguous with another on these points."}</p>
{_table(['effect', 'would not be claimed up to (RMS µm)', 'signature correlation', 'with'], lims)}
<p>Limits of the fits (4 × the largest the seeds measured): thermal drift reached by the run's end {LIMITS['thermal_drift']:g} µm,
machine geometry {LIMITS['machine_geometry']:g} µm/mm per coefficient, runout {LIMITS['runout']:g} µm,
tool contour {LIMITS['tool_contour']:g} µm.</p>
<h2>Where (blocks with mean residual beyond the noise)</h2>
{_table(['x mm', 'y mm', 'z mm', 'passes', 'contact angle', 'time', 'points', 'mean µm', '95 %'], where) if where else '<p>none</p>'}
</body></html>"""
    (gdir / "index.html").write_text(html)
