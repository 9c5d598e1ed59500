"""The posture job (``job: posture``, issue 61, seed 001): evaluate fixed tool orientations of a ball
end mill on a part for 3+2-axis machining, and choose the few that together reach what can be reached.

Reads the workflow (:mod:`pipeline.posture_config`), the part and the efficiency table; the
computation is :mod:`stages.posture`. Writes ``<out>/tables/posture/<name>.parquet`` (one row per
orientation), ``<out>/tables/posture_cover/<name>.parquet`` (the greedy union of postures),
``<out>/report/index.html`` (:mod:`pipeline.posture_report`) and ``<out>/run.json``. The job has no
cache: a run evaluates every orientation (seconds to a minute or two); ``--fresh`` changes nothing and
``--workers`` is not used (one process holds the GL context).
"""
from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

import schemas
from pipeline.config import resolve
from pipeline.posture_config import PostureWorkflow, key_line, load_posture
from stages.posture import efficiency as eff
from stages.posture.cover import greedy_cover
from stages.posture.evaluate import evaluate
from stages.posture.offset import inverse_offset
from stages.posture.orientations import grid
from stages.posture.part import load_part
from stages.posture.zmap import backend_name

log = logging.getLogger(__name__)


load = load_posture      # the runner contract (pipeline.jobs): the job's workflow reader


def efficiency_of(wf: PostureWorkflow, path: Path, base: Path):
    """λ(ψ) of the workflow: the seed's sin 2ψ, a CSV table or inline points."""
    if wf.efficiency == "sin2psi":
        return eff.sin2psi
    if wf.efficiency.table is not None:
        return eff.read_table(resolve(base, wf.efficiency.table))
    pts = np.asarray(wf.efficiency.points, float)
    return eff.Table(pts[:, 0], pts[:, 1], f"{key_line(path, ('efficiency', 'points'))}: efficiency.points")


def posture_table(name: str, g: dict, res: dict) -> pa.Table:
    n = len(g["axis"])
    cols = {"name": [name] * n, "orientation": np.arange(n, dtype=np.int32),
            "rx_deg": g["rx_deg"], "ry_deg": g["ry_deg"], "tilt_deg": g["tilt_deg"], "azimuth_deg": g["azimuth_deg"],
            "axis_x": g["axis"][:, 0], "axis_y": g["axis"][:, 1], "axis_z": g["axis"][:, 2],
            "phi1": res["phi1"], "phi2": res["phi2"], "e": res["e"], "machinable_area_mm2": res["area_mm2"]}
    return schemas.check("posture", pa.table(cols))


def cover_table(name: str, g: dict, res: dict, cov: dict, total: float) -> pa.Table:
    k = cov["chosen"]
    n = len(k)
    upper = cov["upper_mm2"]
    cols = {"name": [name] * n, "step": np.arange(1, n + 1, dtype=np.int32), "orientation": k.astype(np.int32),
            "rx_deg": g["rx_deg"][k], "ry_deg": g["ry_deg"][k], "tilt_deg": g["tilt_deg"][k],
            "azimuth_deg": g["azimuth_deg"][k], "e": res["e"][k], "added_area_mm2": cov["gain_mm2"],
            "covered_area_mm2": cov["covered_mm2"],
            "covered_fraction": cov["covered_mm2"] / upper if upper > 0 else np.zeros(n),
            "upper_bound_mm2": np.full(n, upper), "total_area_mm2": np.full(n, total)}
    return schemas.check("posture_cover", pa.table(cols))


def write_table(out: Path, table: str, name: str, tab: pa.Table) -> Path:
    d = out / "tables" / table
    d.mkdir(parents=True, exist_ok=True)
    tmp = d / f"{name}.parquet.tmp"
    pq.write_table(tab, tmp)
    tmp.replace(d / f"{name}.parquet")
    return d / f"{name}.parquet"


def run(path, *, out=None, overlays=(), fresh=False, workers=None, quiet=False) -> dict:
    """Run a posture workflow (the runner contract of :mod:`pipeline.jobs`); returns the summary."""
    t0 = time.perf_counter()
    wf, base = load_posture(path, overlays)
    outdir = Path(out) if out else resolve(base, wf.output)
    lam = efficiency_of(wf, Path(path), base)
    o = wf.orientations
    g = grid(o.kind, *o.ranges())
    part = load_part(resolve(base, wf.part), wf.micro_region_mm)
    cell = wf.render.cell_mm
    offset = inverse_offset(part, wf.ball_radius_mm, cell)
    t1 = time.perf_counter()
    bar = None
    if not quiet:
        from tqdm import tqdm
        bar = tqdm(total=len(g["axis"]), desc="orientations", unit="θ")
    res = evaluate(part, offset, g, lam, wf.alpha, cell, backend=wf.render.backend, tile_px=wf.render.tile_px,
                   progress=(lambda done, n: bar.update(1)) if bar is not None else None)
    if bar is not None:
        bar.close()
    t2 = time.perf_counter()
    cov = greedy_cover(res["delta"], part.areas, res["e"], wf.cover.max_postures, wf.cover.tolerance)
    t3 = time.perf_counter()
    files = [write_table(outdir, "posture", wf.name, posture_table(wf.name, g, res)),
             write_table(outdir, "posture_cover", wf.name, cover_table(wf.name, g, res, cov, part.area))]
    summary = summarize(wf, path, outdir, part, offset, g, res, cov, {"prepare": t1 - t0, "evaluate": t2 - t1,
                                                                       "cover": t3 - t2})
    summary["tables"] = [str(f) for f in files]
    try:
        from pipeline.posture_report import report
        summary["report"] = str(report(outdir, wf, part, g, res, cov, summary))
    except Exception as e:                                # a report that fails is a warning, never a failed run
        log.warning("posture report not written: %s: %s", type(e).__name__, e)
        summary["warnings"].append(f"report not written: {type(e).__name__}: {e}")
    summary["wall_s"] = time.perf_counter() - t0
    outdir.mkdir(parents=True, exist_ok=True)
    (outdir / "run.json").write_text(json.dumps(summary, indent=2, default=str))
    return summary


def summarize(wf, path, outdir, part, offset, g, res, cov, timing) -> dict:
    best = int(np.argmax(res["e"]))
    chosen = [{"rx_deg": float(g["rx_deg"][k]), "ry_deg": float(g["ry_deg"][k]), "tilt_deg": float(g["tilt_deg"][k]),
               "azimuth_deg": float(g["azimuth_deg"][k]), "covered_mm2": float(c)}
              for k, c in zip(cov["chosen"], cov["covered_mm2"])]
    return {"name": wf.name, "job": "posture", "workflow": str(path), "output": str(outdir), "failures": [],
            "warnings": [], "part": str(part.path), "micro_regions": int(part.n), "area_mm2": part.area,
            "offset_triangles": int(len(offset.faces)), "orientations": int(len(g["axis"])),
            "grid": {"kind": wf.orientations.kind, "shape": list(g["shape"])},
            "backend": backend_name(wf.render.backend), "cell_mm": wf.render.cell_mm, "alpha": wf.alpha,
            "best": {"rx_deg": float(g["rx_deg"][best]), "ry_deg": float(g["ry_deg"][best]),
                     "tilt_deg": float(g["tilt_deg"][best]), "azimuth_deg": float(g["azimuth_deg"][best]),
                     "phi1": float(res["phi1"][best]), "phi2": float(res["phi2"][best]), "e": float(res["e"][best])},
            "cover": {"postures": chosen, "upper_bound_mm2": cov["upper_mm2"], "reached": cov["reached"]},
            "timing_s": timing}


def echo_summary(summary: dict) -> None:
    """The lines ``pipeline run`` prints for a posture run."""
    import click
    b = summary["best"]
    click.echo(f"{summary['name']}: {summary['orientations']} orientations of a {summary['area_mm2']:.0f} mm² part "
               f"({summary['micro_regions']} micro-regions, {summary['backend']}, {summary['cell_mm']:g} mm cells) "
               f"in {summary['wall_s']:.1f} s")
    click.echo(f"best E = {b['e']:.3f} at rx {b['rx_deg']:g}°, ry {b['ry_deg']:g}° (tilt {b['tilt_deg']:.1f}°, "
               f"azimuth {b['azimuth_deg']:.1f}°): Φ1 {b['phi1']:.3f}, Φ2 {b['phi2']:.3f}")
    c = summary["cover"]
    up = c["upper_bound_mm2"]
    steps = ", ".join(f"({p['rx_deg']:g}°, {p['ry_deg']:g}°) {100 * p['covered_mm2'] / up:.1f} %" if up else "-"
                      for p in c["postures"])
    click.echo(f"cover: {len(c['postures'])} postures (rx, ry) → union {steps} of the upper bound {up:.0f} mm² "
               f"({100 * up / summary['area_mm2']:.1f} % of the part){'' if c['reached'] else ' — not reached'}")
    for w in summary["warnings"]:
        click.echo(f"warning: {w}")
    if "report" in summary:
        click.echo(f"report: {summary['report']}")
