"""Gap jobs (issue 7, DESIGN §8): the ``simulate``, ``diagnose`` and ``blind-check`` commands.

The engine runs the workflow (cached) up to the tables a command needs (``split``, ``errors``); the
diagnosis is ``stages.gap``. Writes ``<out>/tables/gap_{points,effects}/<name>.parquet``, ``<out>/gap/``
(summary.json, index.html, residual_map.png, rejected.csv, errors_updated.parquet, model_update.yaml and the
files it names), ``<out>/blind/summary.json``.
"""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Optional

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

import schemas
from pipeline.config import Measurements, load_workflow, resolve
from stages import InputError
from stages.gap.associate import associate
from stages.gap.blind import blind_cases, check_kinds
from stages.gap.calibration import baseline, calibrate
from stages.gap.measurements import points_and_normals, read_measurements, write_measurements
from stages.gap.model_update import workflow_update, write_update
from stages.gap.plans import contact_deg, plan_counts, plan_mask
from stages.gap.predictor import HOW_ADDED, Predictor, diagnose_points
from stages.gap.probe import probe_program
from stages.gap.report import public_summary, report
from stages.gap.tables import gap_effects_table, gap_points_table
from stages.virtual_machine import VirtualMachine, grid_plan, parse_effect


def run_tables(workflow: str, until: str, out: Optional[str] = None, workers: Optional[int] = 1,
               scheduler: Optional[str] = None) -> tuple[dict, Path]:
    """Run the workflow up to ``until`` (cached) and read its tables: ({table: pa.Table}, out dir)."""
    from pipeline.engine import Run
    from pipeline.graph import mould_graph
    r = Run(workflow, mould_graph(), out=out, until=until)
    summary = r.execute(scheduler=scheduler, workers=workers, progress=False)
    if summary["failures"]:
        raise InputError(f"{workflow}: the run failed before the gap job could use it: "
                         f"{summary['failures'][0]['message']}")
    tabs = {}
    for name in ("passes", "errors", "deflection", "generating", "engagement"):
        d = r.out / "tables" / name
        files = sorted(d.glob("*.parquet")) if d.is_dir() else []
        if files:
            tabs[name] = pa.concat_tables([pq.read_table(f) for f in files], promote_options="default")
    if "passes" not in tabs:
        raise InputError(f"{workflow}: the run wrote no passes")
    return tabs, r.out


def measurement_spec(wf, base) -> Measurements:
    """The workflow's ``measurements`` entry with its file resolved against the workflow's folder."""
    m = wf.measurements
    if m is None:
        return Measurements(file="")
    if isinstance(m, str):
        return Measurements(file=str(resolve(base, m)))
    return m.model_copy(update={"file": str(resolve(base, m.file))})


def program_tool(wf, passes: pa.Table) -> dict:
    """The tool entry of the passes' T number (the workflow's only tool when it lists one)."""
    t = None
    if "tool" in passes.column_names:
        vals = [v for v in passes.column("tool").to_pylist() if v is not None]
        t = int(vals[0]) if vals else None
    return wf.tool_for(t if isinstance(wf.tool, list) else None).model_dump()


def program_material(wf, tool: dict) -> dict:
    return wf.material_for(tool.get("t") if isinstance(wf.material, list) else None).model_dump()


def workflow_stock(wf, base):
    """The stock as the stages take it (the engine's source value): the mesh's path, or the box."""
    s = wf.stock
    return str(resolve(base, s).resolve()) if isinstance(s, str) else (None if s is None else s.model_dump())


def read_points(path: str, spec: Measurements, require_deviation: bool = True):
    """``stages.gap.measurements.read_measurements`` with the workflow's column mapping and units."""
    return read_measurements(path, spec.columns, spec.length_unit, spec.deviation_unit,
                             require_deviation=require_deviation)


def make_predictor(tabs: dict, wf, tool: dict, scale: float = 1.0, workdir=None) -> Optional[Predictor]:
    """A ``Predictor`` when the run has the render tables (generating, engagement) and a machine FRF."""
    if not all(k in tabs for k in ("generating", "engagement")) or not (wf.machine and wf.machine.frf):
        return None
    return Predictor(tabs, tool, program_material(wf, tool), wf.machine.model_dump(), scale, workdir)


def simulate(workflow: str, program: Optional[str], effects: list[str], noise_um: float, seed: Optional[int],
             out_file: str, plan: Optional[str] = None, grid_mm: float = 0.5) -> dict:
    """Machine the program(s) on the virtual machine with ``effects`` and write a measurement file."""
    wf, base = load_workflow(workflow)
    eff = dict(parse_effect(e) for e in effects)
    tabs, _ = run_tables(workflow, "split")
    passes = tabs["passes"]
    progs = list(dict.fromkeys(passes.column("program_id").to_pylist()))
    if program:
        stem = Path(program).stem
        if stem not in progs:
            raise InputError(f"--program {program}: not a program of {workflow} (programs: {', '.join(progs)})")
        progs = [stem]
    spec = measurement_spec(wf, base)
    plan_pts = read_points(plan or spec.file, spec, require_deviation=False)[0] if plan or spec.file else None
    rng = np.random.default_rng(seed)
    pieces = []
    for prog in progs:
        sub = passes.filter(pa.compute.equal(passes.column("program_id"), prog))
        tool = program_tool(wf, sub)
        vm = VirtualMachine(sub, tool, program_material(wf, tool), wf.machine.model_dump(), workflow_stock(wf, base))
        pieces.append(probe_program(vm, plan_pts, eff, noise_um, rng, grid_mm, sum(p.num_rows for p in pieces)))
    tab = schemas.check("measurements", pa.concat_tables(pieces))
    write_measurements(tab, out_file)
    return {"points": tab.num_rows, "programs": progs, "effects": eff, "noise_um": noise_um, "out": out_file}


def diagnose_cmd(workflow: str, measurements: str, out: Optional[str] = None,
                 reference: Optional[str] = None) -> dict:
    """Diagnose a measurement file against the workflow's prediction; write tables, summary, report."""
    t0 = time.perf_counter()
    wf, base = load_workflow(workflow)
    spec = measurement_spec(wf, base)
    tabs, outdir = run_tables(workflow, "errors")
    outdir = Path(out) if out else outdir
    meas, rej, _ = read_points(measurements, spec)
    tool = program_tool(wf, tabs["passes"])
    F, rej2 = associate(meas, tabs["passes"], tabs.get("errors"), tool, spec.off_part_mm, tabs.get("deflection"))
    t1 = time.perf_counter()
    name, gdir = Path(measurements).stem, outdir / "gap"
    gdir.mkdir(parents=True, exist_ok=True)
    predictor = make_predictor(tabs, wf, tool, workdir=gdir / "folds")
    calibration, floor = None, 0.0
    if reference:
        # the same calibration the blind check proves the diagnosis with (``calibrate``)
        ref, _, _ = read_points(reference, spec)
        F0, _ = associate(ref, tabs["passes"], tabs.get("errors"), tool, spec.off_part_mm, tabs.get("deflection"))
        calibration = dict(calibrate(F0, predictor), file=str(reference))
        F, floor = baseline(F, calibration)
    res = diagnose_points(F, spec.noise_um, floor, predictor=predictor)
    if calibration is not None:
        res["calibration"] = {k: v for k, v in calibration.items() if not k.startswith("_")}
    t2 = time.perf_counter()
    if predictor is not None and any(k in HOW_ADDED for k in res["params"]):
        # the model with the winning effects, fitted on all points: profile table and errors re-predicted
        predictor.workdir = gdir
        if "tool_contour" in res["params"]:
            res["params"]["tool_contour"]["profile_csv"] = predictor.profile_csv(res["params"]["tool_contour"],
                                                                                 "tool_profile_fitted.csv")
        pq.write_table(schemas.check("errors", predictor.errors_table(res["params"])), gdir / "errors_updated.parquet")
    for tname, tab in (("gap_points", gap_points_table(F, res["_after"])), ("gap_effects", gap_effects_table(res))):
        d = outdir / "tables" / tname
        d.mkdir(parents=True, exist_ok=True)
        pq.write_table(schemas.check(tname, tab), d / f"{name}.parquet.tmp")
        (d / f"{name}.parquet.tmp").replace(d / f"{name}.parquet")
    rejected = [(i, ln, why) for i, ln, why in rej.rows] + [(i, None, why) for i, why in rej2]
    (gdir / "rejected.csv").write_text("point_id,line,reason\n" + "".join(
        f"{i},{'' if ln is None else ln},\"{why}\"\n" for i, ln, why in rejected))
    summary = public_summary(res)
    summary["plan"] = plan_diagnostics(meas, F, rej2, len(rej))
    summary.update({"measurements": str(measurements), "n_rejected": len(rejected),
                    "timing_s": {"associate": t1 - t0, "diagnose": t2 - t1}})
    summary["overlay"] = model_update_file(wf, base, tool, res, calibration, F, gdir)
    (gdir / "summary.json").write_text(json.dumps(summary, indent=2))
    report(gdir, F, res, summary)
    return summary


def model_update_file(wf, base, tool: dict, res: dict, calibration: Optional[dict], F: dict, gdir: Path) -> dict:
    """Write ``gdir/model_update.yaml`` (``stages.gap.model_update``): the kept effects as workflow
    keys for ``pipeline run --overlay``; returns its path and the effects applied and not applied."""
    material = program_material(wf, tool)
    upd = workflow_update(res["params"], res.get("observability", {}), tool, material,
                          tool_t=tool.get("t") if isinstance(wf.tool, list) else None,
                          material_t=material.get("t") if isinstance(wf.material, list) else None,
                          base=base, outdir=gdir, has_drift=wf.drift is not None,
                          force_scale0=calibration["force_scale_s0"] if calibration else 1.0,
                          cut_len_mean_m=float(np.mean(F["cut_len_mm"])) * 1e-3 if len(F["cut_len_mm"]) else 0.0)
    path = write_update(gdir / "model_update.yaml", upd, res["params"])
    return {"file": str(path), "applied": upd["applied"], "unapplied": upd["unapplied"]}


def plan_diagnostics(meas: pa.Table, F: dict, rejected: list, unreadable: int) -> dict:
    """Measured and rejected points per contact-angle band and normal direction
    (``stages.gap.plans.plan_counts``); rows rejected while reading have no trusted normal and are
    counted apart (``unreadable``)."""
    ids = meas.column("point_id").to_numpy()
    nrm = np.stack([meas.column(c).to_numpy() for c in ("nx", "ny", "nz")], 1)
    rid = np.array([i for i, _ in rejected], dtype=ids.dtype)
    pos = {int(v): k for k, v in enumerate(ids)}
    nr = nrm[[pos[int(i)] for i in rid if int(i) in pos]] if len(rid) else np.zeros((0, 3))
    out = plan_counts(np.stack([F["nx"], F["ny"], F["nz"]], 1), nr, [why.split(":")[0] for _, why in rejected])
    out["unreadable"] = int(unreadable)
    return out


def blind_check(workflow: str, cases: int, seed: int, out: Optional[str] = None, noise=(0.3, 1.0),
                pairs: int = 0, progress=None, kinds: Optional[list] = None, plan_kind: str = "full") -> dict:
    """Random effect (or none) per case, simulated on the virtual machine, diagnosed blind, on the
    points of the plan a ``plan_kind`` inspection program probes (``stages.gap.plans.plan_mask``)."""
    wf, base = load_workflow(workflow)
    spec = measurement_spec(wf, base)
    tabs, outdir = run_tables(workflow, "errors")
    outdir = Path(out) if out else outdir
    passes = tabs["passes"]
    prog = passes.column("program_id").to_pylist()[0]
    sub = passes.filter(pa.compute.equal(passes.column("program_id"), prog))
    tool = program_tool(wf, sub)
    vm = VirtualMachine(sub, tool, program_material(wf, tool), wf.machine.model_dump(), workflow_stock(wf, base))
    if spec.file:
        pts, nrm = points_and_normals(read_points(spec.file, spec, require_deviation=False)[0])
    else:
        pts, nrm = grid_plan(vm)
    keep = plan_mask(pts, nrm, plan_kind)
    pts, nrm = pts[keep], nrm[keep]
    sub_tabs = {k: (v.filter(pa.compute.equal(v.column("program_id"), prog)) if "program_id" in v.column_names else v)
                for k, v in tabs.items()}
    predictor = make_predictor(sub_tabs, wf, tool, workdir=outdir / "blind" / "profiles")
    summary = blind_cases(vm, sub, tabs.get("errors"), tool, pts, nrm, cases, seed, noise=noise, pairs=pairs,
                          off_part_mm=spec.off_part_mm, progress=progress, deflection=tabs.get("deflection"),
                          kinds=check_kinds(kinds), predictor=predictor)
    summary["workflow"] = workflow
    summary["plan_kind"] = plan_kind
    q = contact_deg(nrm)
    summary["plan"] = {"points": int(len(pts)), "contact_deg": [float(q.min()), float(q.max())]}
    bdir = outdir / "blind"
    bdir.mkdir(parents=True, exist_ok=True)
    (bdir / "summary.json").write_text(json.dumps(summary, indent=2, default=lambda o: o.tolist() if isinstance(
        o, (np.floating, np.integer, np.bool_, np.ndarray)) else str(o)))
    return summary
