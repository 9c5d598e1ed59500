"""The posture run's report: ``<out>/report/index.html`` with the E map over the orientation grid
(Φ1, Φ2 and E, as the seed's Fig. 3 c–d) and the part coloured by the chosen posture that first
machines each micro-region (matplotlib, Agg)."""
from __future__ import annotations

import html
from pathlib import Path

import numpy as np

COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#bcbd22", "#17becf",
          "#aec7e8", "#ffbb78", "#98df8a", "#ff9896", "#c5b0d5", "#c49c94", "#f7b6d2", "#dbdb8d", "#9edae5",
          "#393b79", "#637939")                    # tab20 without its greys: twenty postures apart
UNREACHABLE, UNCOVERED = "#d9d9d9", "#404040"


def heat_maps(path: Path, g: dict, res: dict, chosen, alpha: float) -> Path:
    """Φ1, Φ2 and E over the grid; the chosen postures numbered in the order chosen."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    polar = g.get("kind") == "polar"
    fig = plt.figure(figsize=(15, 4.8))
    for i, (key, title) in enumerate((("phi1", "Φ1 (α = 0): mean efficiency λ"), ("phi2", "Φ2 (α = 1): machinable "
                                      "area ratio"), ("e", f"E, α = {alpha:g}"))):
        v = res[key].reshape(g["shape"])
        if polar:
            ax = fig.add_subplot(1, 3, i + 1, projection="polar")
            az, tilt = np.radians(g["second"]), g["first"]
            m = ax.pcolormesh(az, tilt, v, shading="nearest", cmap="viridis", vmin=0, vmax=1)
            for s, k in enumerate(chosen):
                ax.text(np.radians(g["azimuth_deg"][k]), g["tilt_deg"][k], str(s + 1), color="w", ha="center",
                        va="center", fontsize=9, weight="bold")
        else:
            ax = fig.add_subplot(1, 3, i + 1)
            rx, ry = g["first"], g["second"]
            m = ax.imshow(v, origin="lower", cmap="viridis", vmin=0, vmax=1, aspect="equal",
                          extent=(ry[0] - _half(ry), ry[-1] + _half(ry), rx[0] - _half(rx), rx[-1] + _half(rx)))
            ax.set_xlabel("ry (°)")
            ax.set_ylabel("rx (°)")
            for s, k in enumerate(chosen):
                ax.text(g["ry_deg"][k], g["rx_deg"][k], str(s + 1), color="w", ha="center", va="center",
                        fontsize=9, weight="bold")
        ax.set_title(title, fontsize=10)
        fig.colorbar(m, ax=ax, shrink=0.8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def _half(v):
    return 0.5 * (v[1] - v[0]) if len(v) > 1 else 0.5


def cover_picture(path: Path, part, cov: dict, names=None) -> Path:
    """The part from above and obliquely from two opposite sides (a pocket's walls, undercuts too, are
    seen on its far side), each micro-region in the colour of the first chosen posture that machines it
    (light grey: no orientation of the grid reaches it; dark: not covered). ``names``: the postures' legends."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection
    from matplotlib.colors import to_rgb
    first = cov["first"]
    rgb = np.array([to_rgb(UNREACHABLE), to_rgb(UNCOVERED)] + [to_rgb(c) for c in COLORS])
    code = np.where(first >= 0, 2 + first % len(COLORS), np.where(cov["upper"], 1, 0))
    light = np.array([0.3, -0.4, 0.87])
    shade = 0.55 + 0.45 * np.abs(part.normals @ (light / np.linalg.norm(light)))
    col = rgb[code] * shade[:, None]
    labels = list(names) if names is not None else [f"posture {s + 1}" for s in range(len(cov["chosen"]))]
    labels += ["no orientation reaches", "reachable, not covered"]
    ncol = min(6, len(labels))
    legend_in = 0.3 + 0.22 * -(-len(labels) // ncol)                 # inches under the pictures for the legend
    fig, axes = plt.subplots(1, 3, figsize=(16, 5.6 + legend_in))
    for ax, (el, az, title) in zip(axes, ((90.0, -90.0, "from above"), (40.0, -60.0, "from +X, −Y"),
                                          (40.0, 120.0, "from −X, +Y"))):
        e, a = np.radians(el), np.radians(az)
        view = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])     # towards the viewer
        right = np.cross([0.0, 0.0, 1.0], view) if abs(view[2]) < 0.999 else np.array([1.0, 0, 0])
        right /= np.linalg.norm(right)
        up = np.cross(view, right)
        T = part.triangles
        xy = np.stack([T @ right, T @ up], -1)
        order = np.argsort((T @ view).mean(1))                                          # far first
        ax.add_collection(PolyCollection(xy[order], facecolors=col[order], edgecolors="none", antialiased=False))
        ax.set_xlim(xy[..., 0].min(), xy[..., 0].max())
        ax.set_ylim(xy[..., 1].min(), xy[..., 1].max())
        ax.set_aspect("equal")
        ax.set_axis_off()
        ax.set_title(title)
    handles = [plt.Rectangle((0, 0), 1, 1, color=COLORS[s % len(COLORS)]) for s in range(len(cov["chosen"]))]
    handles += [plt.Rectangle((0, 0), 1, 1, color=UNREACHABLE), plt.Rectangle((0, 0), 1, 1, color=UNCOVERED)]
    fig.legend(handles, labels, loc="lower center", ncol=ncol, fontsize=9)
    fig.tight_layout(rect=(0, legend_in / (5.6 + legend_in), 1, 0.97))
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def report(out: Path, wf, part, g: dict, res: dict, cov: dict, summary: dict) -> Path:
    """Write ``<out>/report/index.html`` and its pictures; returns the page's path."""
    rdir = Path(out) / "report"
    rdir.mkdir(parents=True, exist_ok=True)
    g = dict(g, kind=wf.orientations.kind)
    heat_maps(rdir / "posture_map.png", g, res, cov["chosen"], wf.alpha)
    cover_picture(rdir / "posture_cover.png", part, cov, [f"{s + 1}: rx {g['rx_deg'][k]:g}°, ry {g['ry_deg'][k]:g}°"
                                                          for s, k in enumerate(cov["chosen"])])
    b = summary["best"]
    up = cov["upper_mm2"]
    rows = "".join(
        f"<tr><td>{s + 1}</td><td>{g['rx_deg'][k]:g}</td><td>{g['ry_deg'][k]:g}</td><td>{g['tilt_deg'][k]:.1f}</td>"
        f"<td>{g['azimuth_deg'][k]:.1f}</td><td>{res['phi1'][k]:.3f}</td><td>{res['phi2'][k]:.3f}</td>"
        f"<td>{res['e'][k]:.3f}</td><td>{a:.1f}</td><td>{c:.1f}</td><td>{100 * c / up if up else 0:.2f} %</td></tr>"
        for s, (k, a, c) in enumerate(zip(cov["chosen"], cov["gain_mm2"], cov["covered_mm2"])))
    reached = "reaches" if cov["reached"] else "does <b>not</b> reach"
    lam = "sin 2ψ (the seed's)" if wf.efficiency == "sin2psi" else "the workflow's table"
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>{html.escape(wf.name)}: tool postures</title>
<style>body{{font-family:sans-serif;margin:2em;max-width:1300px}}table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:3px 8px;text-align:right}}img{{max-width:100%}}</style></head><body>
<h1>{html.escape(wf.name)}: tool postures for 3+2-axis machining</h1>
<p>Part <code>{html.escape(str(part.path))}</code>: {part.area:.0f} mm², {part.n} micro-regions; ball radius
{wf.ball_radius_mm:g} mm; {len(g['axis'])} orientations ({html.escape(wf.orientations.kind)} grid); z-map cells
{wf.render.cell_mm:g} mm ({html.escape(summary['backend'])}); λ = {lam}; α = {wf.alpha:g}.</p>
<p>Best single posture: E = {b['e']:.3f} at rx {b['rx_deg']:g}°, ry {b['ry_deg']:g}° (tilt {b['tilt_deg']:.1f}°,
azimuth {b['azimuth_deg']:.1f}°), Φ1 = {b['phi1']:.3f}, Φ2 = {b['phi2']:.3f}.</p>
<h2>E over the orientations</h2><img src="posture_map.png" alt="E map">
<h2>Postures that together reach the part (§6)</h2>
<p>The union of the chosen postures {reached} the upper bound {up:.1f} mm² ({100 * up / part.area:.1f} % of the
part: what some orientation of the grid reaches).</p>
<table><tr><th>step</th><th>rx °</th><th>ry °</th><th>tilt °</th><th>azimuth °</th><th>Φ1</th><th>Φ2</th><th>E</th>
<th>adds mm²</th><th>union mm²</th><th>of the bound</th></tr>{rows}</table>
<img src="posture_cover.png" alt="the part coloured by posture">
<p>Φ1: area-weighted mean of λ over the machinable micro-regions (eq. 3); Φ2: machinable area over the part's
(eq. 4); E = (1 − α)Φ1 + αΦ2 (eq. 5). ψ is the angle between the tool axis and the surface normal: the edge
point in contact, 0° at the tip. Tables: <code>tables/posture/</code>, <code>tables/posture_cover/</code>.</p>
</body></html>"""
    (rdir / "index.html").write_text(page)
    return rdir / "index.html"
