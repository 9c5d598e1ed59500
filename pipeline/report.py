"""Run report: ``<out>/report/index.html`` with pictures of the predicted error (issue 4).

Reads the run's tables (never the cache). The page: warnings, a table per program (passes,
machining time, predicted error, the corrected program and its predicted deviation against the
original's), the predicted error as a deviation map on the design model (top and oblique view,
symmetric diverging scale: red = material left, blue = overcut; :mod:`pipeline.deviation_map`) and
as ``deviation.ply``, its histogram, error against contact angle, and the worst passes with their
NC line so a production engineer can open the file at the right place.
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
    df = df.merge(passes[["program_id", "pass_id", "line_no", "block_no", "t_start_s", "x0_mm", "y0_mm", "z0_mm",
                          "x1_mm", "y1_mm", "z1_mm"]], on=["program_id", "pass_id"], how="left")
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


def write_report(out: str | Path, title: str = "run", nominal: str | Path | None = None,
                 kept: dict | None = None, overlays: list | None = None) -> Path | None:
    """Write ``<out>/report/`` (pictures, the coloured mesh, index.html). Returns the HTML path,
    None before passes.

    Parameters
    ----------
    out : the run's output directory (its ``tables/`` are read)
    title : the workflow's name
    nominal : the design model; with it the error is drawn on the part and written as
        ``deviation.ply``, else drawn at the generating points
    kept : ``run.json``'s ``kept`` (program → the correction written and its predicted deviation)
    overlays : the overlay files merged over the workflow (``--overlay``), named on the page
    """
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
    label = f"predicted error, µm (scale ±{lim:.1f}: red = material left, blue = overcut)"

    pictures = []
    if nominal is not None and Path(nominal).is_file():
        pictures.append(_deviation_map(rep, df, Path(nominal), lim, label))
    else:
        (rep / "deviation.ply").unlink(missing_ok=True)          # an earlier run's, of another model
        pictures.append(_point_map(rep, df, lim, label))

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    axes[0].hist(e, bins=80, color="#4477aa")
    axes[0].set(xlabel="err_um", ylabel="passes", title="Histogram of predicted error")
    axes[1].scatter(df.contact_deg, e, s=2, alpha=0.4, color="#aa3377")
    axes[1].set(xlabel="contact angle q (deg)", ylabel="err_um", title="Error against contact angle")
    fig.tight_layout()
    fig.savefig(rep / "error_hist.png", dpi=110)
    plt.close(fig)
    pictures.append("error_hist.png")

    worst = df.reindex(df.err_um.abs().sort_values(ascending=False).index).head(25)
    rows = "".join(
        f"<tr><td>{html.escape(str(r.program_id))}</td><td>{int(r.pass_id)}</td><td>{int(r.line_no)}</td>"
        f"<td>{r.err_um:+.2f}</td><td>{r.err_deflection_um:+.2f}</td><td>{r.err_shape_um:+.2f}</td>"
        f"<td>{r.contact_deg:.1f}</td><td>{r.gen_x_mm:.3f}, {r.gen_y_mm:.3f}, {r.gen_z_mm:.3f}</td></tr>"
        for r in worst.itertuples())
    stats = (f"{len(df)} predicted passes; err_um mean {np.nanmean(e):+.2f}, RMS {np.sqrt(np.nanmean(e ** 2)):.2f}, "
             f"P95 |err| {np.nanpercentile(np.abs(e), 95):.2f}, max |err| {np.nanmax(np.abs(e)):.2f} µm")
    programs, warnings = _programs(out, df, kept or {})
    imgs = "".join(f'<img src="{p}" alt="{p}" style="max-width:100%">' for p in pictures)
    ply = ('<p>The coloured part: <a href="deviation.ply">deviation.ply</a> (vertex colours and '
           '<code>err_um</code> per vertex; MeshLab, ParaView). Grey: no predicted pass there '
           '(not cut, or pruned: contact angle below <code>prune.min_contact_deg</code>).</p>'
           if (rep / "deviation.ply").is_file() else "")
    # which model the prediction is: the workflow alone, or with a diagnosis' model update over it
    over = (f'<p id="overlay">Overlay: {html.escape(", ".join(overlays))} (merged over the workflow)</p>\n'
            if overlays else '<p id="overlay">Overlay: none (the workflow as written)</p>\n')
    warn = ("<h2>Warnings</h2><ul>" + "".join(f"<li>{w}</li>" for w in warnings) + "</ul>") if warnings else ""
    page = f"""<!doctype html><meta charset="utf-8"><title>{html.escape(title)} — predicted machining error</title>
<style>body{{font-family:sans-serif;margin:2em;max-width:1400px}}td,th{{padding:2px 8px;text-align:right}}
table{{border-collapse:collapse}}tr:nth-child(even){{background:#f3f3f3}}#broken{{color:#b00}}</style>
<h1>{html.escape(title)}: predicted machining error</h1>
<p id="broken"></p>
{over}<p>{stats}. Sign: positive = material left (undercut), negative = overcut, along the surface normal.</p>
{warn}
<h2>Programs</h2>
<table><tr><th>program</th><th>status</th><th>passes</th><th>cutting</th><th>predicted</th><th>machining time</th>
<th>RMS err µm</th><th>max |err| µm</th><th>corrected program</th><th>predicted deviation RMS µm, original → corrected</th>
<th>vertices at the move limit</th></tr>{programs}</table>
{imgs}{ply}
<h2>Worst passes</h2>
<table><tr><th>program</th><th>pass</th><th>NC line</th><th>err µm</th><th>deflection µm</th><th>shape µm</th>
<th>q deg</th><th>generating point (mm)</th></tr>{rows}</table>
<script>
// every picture must load: a broken one is named at the top of the page (and counted for tests)
window.addEventListener("load", () => {{
  const imgs = [...document.images], bad = imgs.filter(i => !(i.complete && i.naturalWidth > 0));
  document.body.dataset.images = `${{imgs.length - bad.length}}/${{imgs.length}}`;
  if (bad.length) document.getElementById("broken").textContent =
    "Pictures that did not load: " + bad.map(i => i.getAttribute("src")).join(", ");
}});
</script>"""
    path = rep / "index.html"
    path.write_text(page)
    return path


def _point_map(rep: Path, df: pd.DataFrame, lim: float, label: str) -> str:
    """The error at the generating points, top and side view (no design model given)."""
    import matplotlib.pyplot as plt
    e = df.err_um.to_numpy()
    fig, axes = plt.subplots(1, 2, figsize=(14, 5.5), gridspec_kw={"width_ratios": [1.3, 1]})
    order = np.argsort(np.abs(e))  # largest errors drawn last, on top
    sc = axes[0].scatter(df.gen_x_mm.iloc[order], df.gen_y_mm.iloc[order], c=e[order], s=3, cmap="coolwarm",
                         vmin=-lim, vmax=lim)
    axes[0].set(aspect="equal", xlabel="X mm", ylabel="Y mm", title="Predicted error, top view (generating points)")
    _span(axes[0], df.gen_x_mm, df.gen_y_mm)
    axes[1].scatter(df.gen_x_mm.iloc[order], df.gen_z_mm.iloc[order], c=e[order], s=3, cmap="coolwarm",
                    vmin=-lim, vmax=lim)
    axes[1].set(xlabel="X mm", ylabel="Z mm", title="Side view (looking along +Y)")
    _span(axes[1], df.gen_x_mm, df.gen_z_mm)
    fig.colorbar(sc, ax=axes, label=label, shrink=0.85)
    fig.savefig(rep / "error_map.png", dpi=110)
    plt.close(fig)
    return "error_map.png"


def _deviation_map(rep: Path, df: pd.DataFrame, nominal: Path, lim: float, label: str) -> str:
    """The error on the design model: ``error_map.png`` (top and oblique) and ``deviation.ply``."""
    import matplotlib.pyplot as plt
    import trimesh
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    from pipeline import deviation_map as dm
    xyz, n, e = dm.surface_samples(df)
    radius = max(dm.interpolation_radius(xyz), dm.EDGE_MM)
    mesh = dm.refined_mesh(trimesh.load(nominal, force="mesh"), xyz, radius)
    err = dm.vertex_errors(mesh.vertices, mesh.vertex_normals, xyz, n, e, radius)
    fig, axes = plt.subplots(1, 2, figsize=(15, 6.2))
    dm.draw_views({"top": axes[0], "oblique": axes[1]}, mesh, err, lim)
    fig.colorbar(ScalarMappable(Normalize(-lim, lim), "coolwarm"), ax=axes, label=label, shrink=0.8)
    fig.suptitle("Predicted error on the part (grey: no predicted pass)")
    fig.savefig(rep / "error_map.png", dpi=110)
    plt.close(fig)
    dm.write_ply(rep / "deviation.ply", mesh, err, lim)
    return "error_map.png"


def _programs(out: Path, df: pd.DataFrame, kept: dict) -> tuple[str, list[str]]:
    """Rows of the programs table and the warnings of the run."""
    tables = out / "tables"
    progs = _read(tables, "programs")
    cut, cor, feeds = _read(tables, "cut_filter"), _read(tables, "corrected"), _read(tables, "feeds")
    listed = _read(tables, "warnings")
    rows, warnings = [], []
    if progs is None:
        return "", warnings
    for p in progs.sort_values("program_id").itertuples():
        pid = p.program_id
        esc = html.escape(str(pid))
        if p.status != "ok":
            warnings.append(f"{esc}: not predicted: {html.escape(p.message)} (every problem: the "
                            f"<code>problems</code> table)")
            rows.append(f"<tr><td>{esc}</td><td>failed</td>" + "<td></td>" * 9 + "</tr>")
            continue
        e = df.err_um[df.program_id == pid].to_numpy()
        n_cut = int(cut.is_cutting[cut.program_id == pid].sum()) if cut is not None else 0
        rms = f"{np.sqrt(np.mean(e ** 2)):.2f}" if e.size else ""
        mx = f"{np.abs(e).max():.2f}" if e.size else ""
        k = kept.get(pid)
        if k is None:
            written, dev = ("yes" if cor is not None and (cor.program_id == pid).any() else "no"), ""
        elif k["kept_round"]:
            written = f"round {k['kept_round']} of {k['rounds']}"
            after = "not predicted" if k["kept_rms_dev_um"] is None else f"{k['kept_rms_dev_um']:.2f}"
            dev = f"{k['first_rms_dev_um']:.2f} → {after}"
        else:
            written, dev = "no", f"{k['first_rms_dev_um']:.2f} → no round lowered it"
            warnings.append(f"{esc}: no coordinate correction: none was predicted to deviate less than "
                            "the program as written (a deflection that changes with the offset; lower the "
                            "feed or the rest material there)")
        if listed is not None:
            for reason, g in listed[listed.program_id == pid].groupby("reason"):
                lines = ", ".join(str(int(x)) for x in sorted(set(g.line_no))[:5])
                warnings.append(f"{esc}: {len(g)} passes <code>{reason}</code> (NC lines {lines}"
                                f"{', …' if g.line_no.nunique() > 5 else ''}), e.g. {html.escape(g.message.iloc[0])}")
        clipped = ""
        if cor is not None and (cor.program_id == pid).any():
            c = cor[cor.program_id == pid]
            clipped = f"{int(c.clipped.sum())} of {len(c)}"
            if c.clipped.any():
                warnings.append(f"{esc}: {int(c.clipped.sum())} vertices reached <code>correct.max_move_um</code>: "
                                f"the error there is larger than a correction may move (NC lines "
                                f"{', '.join(str(int(x)) for x in c.line_no[c.clipped].head(5))}"
                                f"{', …' if c.clipped.sum() > 5 else ''})")
        duration = _duration(p.duration_s)
        if feeds is not None and (feeds.program_id == pid).any():
            fd = feeds[feeds.program_id == pid]
            duration += f" → {_duration(fd.duration_new_s.sum() + p.duration_s - fd.duration_s.sum())} (scheduled feeds)"
        rows.append(f"<tr><td>{esc}</td><td>ok</td><td>{int(p.n_passes)}</td><td>{n_cut}</td><td>{e.size}</td>"
                    f"<td>{duration}</td><td>{rms}</td><td>{mx}</td><td>{written}</td>"
                    f"<td>{dev}</td><td>{clipped}</td></tr>")
    return "".join(rows), warnings


def _duration(seconds: float) -> str:
    """Machining time as h:mm:ss."""
    s = int(round(float(seconds)))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"
