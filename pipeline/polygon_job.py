"""``pipeline run`` of a ``job: polygon`` workflow (issue 62, seed 004): polygon (2-axis) cutting.

Machines the bar on the height map (``stages.polygon``) and writes

- ``<out>/tables/polygon_sections/<name>.parquet``: the cross-sections (z_mm, theta_deg, r_mm);
- ``<out>/polygon/summary.json``: sides, twist, thickness, largest radius and the set-up's figures;
- ``<out>/polygon/sections.png``, ``view3d.png``, ``<name>.stl`` (the solid, for CAD);
- ``<out>/report/index.html`` and ``<out>/run.json`` (the summary ``run`` returns).

A bad workflow raises ``WorkflowError`` (file, line, key) before anything is written.
"""
from __future__ import annotations

import html
import json
import os
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

import schemas
from pipeline.polygon_config import PolygonWorkflow, load_polygon, output_dir
from stages.polygon.kinematics import ratio_fraction
from stages.polygon.mesh import solid_mesh, write_stl
from stages.polygon.pictures import sections_png, view3d_png
from stages.polygon.solid import MAX_SIDES, Machined, machine


load = load_polygon      # the runner contract (pipeline.jobs): the job's workflow reader


def sections_table(part: Machined) -> pa.Table:
    """The station sections as rows (z_mm, theta_deg, r_mm)."""
    g, k = part.grid, len(part.stations)
    return schemas.check("polygon_sections", pa.table({
        "z_mm": np.repeat(g.z[part.stations], g.ntheta),
        "theta_deg": np.tile(np.degrees(g.theta), k),
        "r_mm": part.sections.ravel()}))


def warnings_of(wf: PolygonWorkflow, fig: dict) -> list[str]:
    """What the user should know about the set-up before trusting the shape."""
    s = wf.setup()
    f, w = s.feed_per_tool_mm, s.edge_width_mm
    pq_ = ratio_fraction(s.ratio)
    out = []
    if f >= w:
        out.append(f"feed per cutter revolution {f:g} mm ≥ edge width {w:g} mm: uncut ridges between the cuts "
                   "(the seed assumes the feed smaller than the edge)")
    if pq_.numerator <= MAX_SIDES and pq_.numerator * f > w and fig["sides"] != pq_.numerator:
        out.append(f"ratio {pq_.numerator}/{pq_.denominator}: its {pq_.numerator}-gon needs {pq_.numerator} cuts "
                   f"within the edge width ({pq_.numerator} × {f:g} mm > {w:g} mm); the section has "
                   f"{fig['sides']} faces instead")
    if fig["sides"] == 0:
        out.append("no faces: the section is round within sections.prominence_mm (the faces of the cuts within "
                   "one edge width are spread round the circle: a strong twist, or ε = 0)")
    return out


def polygon_summary(wf: PolygonWorkflow, part: Machined) -> dict:
    s, g, fig = wf.setup(), part.grid, part.figures
    q = ratio_fraction(s.ratio)
    return {
        **fig,
        "ratio": s.ratio, "ratio_pq": f"{q.numerator}/{q.denominator}", "sides_rule": q.numerator,
        "feed_per_tool_mm": s.feed_per_tool_mm, "feed_per_workpiece_mm": s.feed_per_workpiece_mm,
        "blade_half_thickness_mm": abs(s.radius_mm - s.eccentricity_mm),
        "cutting_time_min": s.length_mm / (s.feed_per_tool_mm * abs(s.cutter_rpm)),
        "rows": g.nz, "columns": g.ntheta, "dz_mm": g.dz, "dtheta_deg": float(np.degrees(g.dtheta)),
        "simulate_s": round(part.seconds, 3), "warnings": warnings_of(wf, fig),
    }


def write_report(path: Path, wf: PolygonWorkflow, summ: dict) -> None:
    """``report/index.html``: the set-up, the figures and the pictures."""
    rows = [("speed ratio ω2/ω1", f"{summ['ratio']:.6g} ({summ['ratio_pq']})"),
            ("sides", f"{summ['sides']} (sections: {summ['sides_range'][0]}–{summ['sides_range'][1]}; "
                      f"p/q rule: {summ['sides_rule']})"),
            ("twist", "—" if summ["twist_deg_per_mm"] is None else f"{summ['twist_deg_per_mm']:.4f} °/mm"),
            ("least thickness", f"{summ['min_thickness_mm']:.4f} mm (2|R − ε| = {2 * summ['blade_half_thickness_mm']:.4f})"),
            ("largest radius", f"{summ['max_radius_mm']:.4f} mm"),
            ("feed", f"{summ['feed_per_tool_mm']:.4g} mm / cutter rev, {summ['feed_per_workpiece_mm']:.4g} mm / workpiece rev"),
            ("cutting time (one pass)", f"{summ['cutting_time_min']:.2f} min"),
            ("grid", f"{summ['rows']} × {summ['columns']} (dz {summ['dz_mm']:.4g} mm, dθ {summ['dtheta_deg']:.4g}°), "
                     f"{summ['simulate_s']:.2f} s")]
    table = "\n".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>" for k, v in rows)
    warn = "".join(f"<li>{html.escape(w)}</li>" for w in summ["warnings"])
    setup = html.escape(json.dumps(wf.model_dump(), indent=1))
    text = f"""<!doctype html><html><head><meta charset="utf-8"><title>{html.escape(wf.name)}: polygon cutting</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:2em auto}}th{{text-align:left;padding-right:1em}}
img{{max-width:100%}}</style></head><body>
<h1>{html.escape(wf.name)}: polygon cutting (seed 004)</h1>
<table>{table}</table>{f'<h2>Warnings</h2><ul>{warn}</ul>' if warn else ''}
<h2>Cross-sections</h2><img src="../polygon/sections.png" alt="cross-sections">
<h2>3-D view</h2><img src="../polygon/view3d.png" alt="3-D view">
<p>The solid: <a href="../polygon/{html.escape(wf.name)}.stl">{html.escape(wf.name)}.stl</a>;
the sections: <code>tables/polygon_sections/{html.escape(wf.name)}.parquet</code>.</p>
<h2>Workflow</h2><pre>{setup}</pre></body></html>
"""
    tmp = path.with_suffix(".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def run(path, *, out=None, overlays=(), fresh=False, workers=None, quiet=False) -> dict:
    """Run a polygon workflow (``pipeline.jobs`` runner contract; ``fresh`` and ``workers`` do not
    apply: nothing is cached and the height map is one process's numpy)."""
    t0 = time.perf_counter()
    wf, base = load_polygon(path, overlays)
    setup, grid = wf.setup(), wf.grid()
    outdir = output_dir(wf, base, out)
    stride = (max(1, int(round(wf.stl.dz_mm / grid.dz))),
              max(1, int(round(wf.stl.dtheta_deg / np.degrees(grid.dtheta)))))
    part = machine(setup, grid, wf.sections.count, wf.sections.prominence_mm, stride)
    summ = polygon_summary(wf, part)
    pdir, tdir, rdir = outdir / "polygon", outdir / "tables" / "polygon_sections", outdir / "report"
    for d in (pdir, tdir, rdir):
        d.mkdir(parents=True, exist_ok=True)
    tab = tdir / f"{wf.name}.parquet"
    pq.write_table(sections_table(part), tab.with_suffix(".tmp"))
    os.replace(tab.with_suffix(".tmp"), tab)
    title = f"{wf.name}: ratio {setup.ratio:.6g}, ε {setup.eccentricity_mm:g}, R {setup.radius_mm:g} mm"
    sections_png(part.sections, grid.theta, grid.z[part.stations], setup.workpiece_radius_mm,
                 pdir / "sections.png", title)
    view3d_png(part.mesh_r, grid.theta[part.mesh_cols], grid.z[part.mesh_rows], pdir / "view3d.png", title)
    stl = pdir / f"{wf.name}.stl"
    write_stl(solid_mesh(part.mesh_r, grid.theta[part.mesh_cols], grid.z[part.mesh_rows]), stl)
    (pdir / "summary.json").write_text(json.dumps(summ, indent=1))
    write_report(rdir / "index.html", wf, summ)
    result = {"name": wf.name, "job": "polygon", "output": str(outdir), "workflow": str(path),
              "overlay": [str(o) for o in overlays], "failures": [], **summ,
              "files": {"table": str(tab), "summary": str(pdir / "summary.json"), "stl": str(stl),
                        "sections_png": str(pdir / "sections.png"), "view3d_png": str(pdir / "view3d.png"),
                        "report": str(rdir / "index.html")}}
    result["wall_s"] = round(time.perf_counter() - t0, 3)
    (outdir / "run.json").write_text(json.dumps(result, indent=1))
    return result


def echo_summary(summary: dict) -> None:
    """The lines ``pipeline run`` prints."""
    import click
    s = summary
    tw = "—" if s["twist_deg_per_mm"] is None else f"{s['twist_deg_per_mm']:.4f} °/mm"
    click.echo(f"polygon {s['name']}: ratio {s['ratio']:.6g} ({s['ratio_pq']}), feed {s['feed_per_tool_mm']:.4g} mm "
               f"per cutter rev, {s['rows']} × {s['columns']} cells in {s['simulate_s']:.2f} s")
    click.echo(f"  sides {s['sides']}, twist {tw}, least thickness {s['min_thickness_mm']:.4f} mm, "
               f"largest radius {s['max_radius_mm']:.4f} mm")
    for w in s["warnings"]:
        click.echo(f"  warning: {w}")
    click.echo(f"  wrote {s['files']['summary']}, {s['files']['stl']}, {s['files']['report']} ({s['wall_s']:.1f} s)")
