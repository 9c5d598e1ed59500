"""Run report: ``<out>/report/index.html`` with pictures of the predicted error (issue 4).

Reads the run's tables (never the cache), so it can be re-made for any output directory:
``pipeline report WORKFLOW``. Pictures: the predicted error at every generating point over the
mould surface (top view and a side view, diverging colour map centred on zero: red = material left,
blue = overcut), its histogram, error against contact angle, and the worst passes with their program
line so a production engineer can open the NC file at the right place.
"""
from __future__ import annotations

import html
from pathlib import Path

import numpy as np
import pandas as pd


def _read(tables: Path, name: str) -> pd.DataFrame | None:
    d = tables / name
    files = sorted(d.glob("*.parquet")) if d.is_dir() else []
    if not files:
        return None
    return pd.concat([pd.read_parquet(f) for f in files], ignore_index=True)


def error_points(out: Path) -> pd.DataFrame | None:
    """Errors joined with their generating point and their source line; None before the errors stage."""
    tables = Path(out) / "tables"
    err, gen, passes, progs = (_read(tables, n) for n in ("errors", "generating", "passes", "programs"))
    if err is None or gen is None or passes is None or err.empty:
        return None
    df = err.merge(gen[["program_id", "pass_id", "gen_x_mm", "gen_y_mm", "gen_z_mm", "rotation_deg", "view"]],
                   on=["program_id", "pass_id"], how="left")
    df = df.merge(passes[["program_id", "pass_id", "line_no", "block_no", "t_start_s"]], on=["program_id", "pass_id"], how="left")
    if progs is not None:
        df = df.merge(progs[["program_id", "path"]], on="program_id", how="left")
    return df


def _span(ax, x, y, least_mm: float = 1.0):
    """Axis limits around the points, at least ``least_mm`` wide (one point, one line of points)."""
    for values, set_lim in ((np.asarray(x, float), ax.set_xlim), (np.asarray(y, float), ax.set_ylim)):
        v = values[np.isfinite(values)]
        if len(v) == 0:
            continue
        mid, half = 0.5 * (v.min() + v.max()), max(0.5 * (v.max() - v.min()), 0.5 * least_mm) * 1.05
        set_lim(mid - half, mid + half)


def _nothing_predicted(out: Path, title: str) -> Path | None:
    """The page of a run whose passes exist but none has a predicted error; None before passes."""
    passes = _read(out / "tables", "passes")
    if passes is None:
        return None
    cut = _read(out / "tables", "cut_filter")
    n_cut = int(cut.is_cutting.sum()) if cut is not None else 0
    rep = out / "report"
    rep.mkdir(parents=True, exist_ok=True)
    path = rep / "index.html"
    path.write_text(f"""<!doctype html><meta charset="utf-8"><title>{html.escape(title)} — predicted machining error</title>
<h1>{html.escape(title)}: predicted machining error</h1>
<p>No pass has a predicted error: {len(passes)} passes, {n_cut} of them cutting; none was predicted
(see <code>angle_prune</code>: passes whose surface's contact angle is below <code>prune.min_contact_deg</code>
are not predicted) or the run stopped before <code>errors</code>.</p>""")
    return path


def write_report(out: str | Path, title: str = "run") -> Path | None:
    """Write ``<out>/report/`` (PNG pictures + index.html). Returns the HTML path, None before passes."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    df = error_points(out)
    if df is None:
        return _nothing_predicted(out, title)
    rep = out / "report"
    rep.mkdir(parents=True, exist_ok=True)
    e = df.err_um.to_numpy()
    lim = max(float(np.nanpercentile(np.abs(e), 99)), 1e-3)
    cmap = "coolwarm"

    fig, axes = plt.subplots(1, 2, figsize=(14, 5.5), gridspec_kw={"width_ratios": [1.3, 1]})
    order = np.argsort(np.abs(e))  # largest errors drawn last, on top
    sc = axes[0].scatter(df.gen_x_mm.iloc[order], df.gen_y_mm.iloc[order], c=e[order], s=3, cmap=cmap, vmin=-lim, vmax=lim)
    axes[0].set(aspect="equal", xlabel="X mm", ylabel="Y mm", title="Predicted error, top view (generating points)")
    _span(axes[0], df.gen_x_mm, df.gen_y_mm)
    axes[1].scatter(df.gen_x_mm.iloc[order], df.gen_z_mm.iloc[order], c=e[order], s=3, cmap=cmap, vmin=-lim, vmax=lim)
    axes[1].set(xlabel="X mm", ylabel="Z mm", title="Side view (looking along +Y)")
    _span(axes[1], df.gen_x_mm, df.gen_z_mm)
    fig.colorbar(sc, ax=axes, label="err_um  (+ material left, − overcut)", shrink=0.85)
    fig.savefig(rep / "error_map.png", dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    axes[0].hist(e, bins=80, color="#4477aa")
    axes[0].set(xlabel="err_um", ylabel="passes", title="Histogram of predicted error")
    axes[1].scatter(df.contact_deg, e, s=2, alpha=0.4, color="#aa3377")
    axes[1].set(xlabel="contact angle q (deg)", ylabel="err_um", title="Error against contact angle")
    fig.tight_layout()
    fig.savefig(rep / "error_hist.png", dpi=110)
    plt.close(fig)

    worst = df.reindex(df.err_um.abs().sort_values(ascending=False).index).head(25)
    rows = "".join(
        f"<tr><td>{html.escape(str(r.program_id))}</td><td>{int(r.pass_id)}</td><td>{int(r.line_no)}</td>"
        f"<td>{r.err_um:+.2f}</td><td>{r.err_deflection_um:+.2f}</td><td>{r.err_shape_um:+.2f}</td>"
        f"<td>{r.contact_deg:.1f}</td><td>{r.gen_x_mm:.3f}, {r.gen_y_mm:.3f}, {r.gen_z_mm:.3f}</td></tr>"
        for r in worst.itertuples())
    stats = (f"{len(df)} predicted passes; err_um mean {np.nanmean(e):+.2f}, RMS {np.sqrt(np.nanmean(e ** 2)):.2f}, "
             f"P95 |err| {np.nanpercentile(np.abs(e), 95):.2f}, max |err| {np.nanmax(np.abs(e)):.2f} µm")
    page = f"""<!doctype html><meta charset="utf-8"><title>{html.escape(title)} — predicted machining error</title>
<style>body{{font-family:sans-serif;margin:2em;max-width:1400px}}td,th{{padding:2px 8px;text-align:right}}
table{{border-collapse:collapse}}tr:nth-child(even){{background:#f3f3f3}}</style>
<h1>{html.escape(title)}: predicted machining error</h1>
<p>{stats}. Sign: positive = material left (undercut), negative = overcut, along the surface normal.</p>
<img src="error_map.png" style="max-width:100%"><img src="error_hist.png" style="max-width:100%">
<h2>Worst passes</h2>
<table><tr><th>program</th><th>pass</th><th>NC line</th><th>err µm</th><th>deflection µm</th><th>shape µm</th>
<th>q deg</th><th>generating point (mm)</th></tr>{rows}</table>"""
    path = rep / "index.html"
    path.write_text(page)
    return path
