"""Gap job (issue 7, DESIGN §8): ``simulate``, ``diagnose`` and ``blind-check`` commands.

The engine runs the workflow (through its cache) up to the tables a command needs: ``split`` for
the virtual machine (parsed passes only), ``errors`` for the diagnosis (the prediction). Outputs:

- ``<out>/tables/gap_points/<name>.parquet``, ``<out>/tables/gap_effects/<name>.parquet``
- ``<out>/gap/summary.json`` (where, effect, effects, params with params_se / params_cov, rms/p95/max
  before and after, shrink)
- ``<out>/gap/index.html`` + ``residual_map.png`` (before / after) + ``rejected.csv``
- ``<out>/blind/summary.json`` for the blind check.
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Optional

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

import schemas
from pipeline.config import Measurements, load_workflow, resolve
from stages import InputError


# ------------------------------------------------------------------------------ run tables
def run_tables(workflow: str, until: str, out: Optional[str] = None, workers: Optional[int] = 1,
               scheduler: Optional[str] = None) -> tuple[dict, Path, object]:
    """Run the workflow up to ``until`` (cached) and read its tables: {table: pa.Table}."""
    from pipeline.engine import Run
    from pipeline.graph import mould_graph
    r = Run(workflow, mould_graph(), out=out, until=until)
    summary = r.execute(scheduler=scheduler, workers=workers, progress=False)
    failed = [f for f in summary["failures"] if f.get("stage") != "report"]
    if failed:
        raise InputError(f"{workflow}: the run failed before the gap job could use it: {failed[0]['message']}")
    tabs = {}
    for name in ("passes", "errors", "deflection", "generating", "engagement"):
        d = r.out / "tables" / name
        files = sorted(d.glob("*.parquet")) if d.is_dir() else []
        if files:
            tabs[name] = pa.concat_tables([pq.read_table(f) for f in files], promote_options="default")
    if "passes" not in tabs:
        raise InputError(f"{workflow}: the run wrote no passes")
    return tabs, r.out, r


def _spec(wf, base) -> Measurements:
    m = wf.measurements
    if m is None:
        return Measurements(file="")
    if isinstance(m, str):
        return Measurements(file=str(resolve(base, m)))
    return m.model_copy(update={"file": str(resolve(base, m.file))})


def _tool(wf, passes: pa.Table) -> dict:
    t = None
    if "tool" in passes.column_names:
        vals = [v for v in passes.column("tool").to_pylist() if v is not None]
        t = int(vals[0]) if vals else None
    return wf.tool_for(t if isinstance(wf.tool, list) else None).model_dump()


def read_points(path: str, spec: Measurements, require_deviation: bool = True):
    from stages.measurements import read_measurements
    return read_measurements(path, spec.columns, spec.length_unit, spec.deviation_unit,
                             require_deviation=require_deviation)


# ------------------------------------------------------------------------------ the prediction, re-run
COEFFS = ("ktc", "krc", "kac", "kte", "kre", "kae")
RUNOUT_GRID_UM = (1.0, 2.0, 4.0, 7.0, 11.0, 16.0, 24.0)   # runout values the prediction is re-run at
# how each catalogue effect is added to the simulation for "how far"
HOW_ADDED = {
    "force_scale": "re-predicted: material ktc…kae × scale, forces → deflection → errors re-run",
    "runout": "re-predicted: tool.runout_um + e (flute 0 largest; the prediction has no runout phase), "
              "forces → deflection → errors re-run",
    "tool_contour": "re-predicted: tool.profile table (contact_deg, error_um) of the fitted dent, errors re-run",
}
OFFSET_ADDED = "term along the normal added to the prediction (the machine/tool offset model)"


class Predictor:
    """The pipeline's own prediction downstream of the render, re-run with changed parameters.

    The cached ``generating`` and ``engagement`` tables are reused; ``stages.forces.run`` →
    ``stages.deflection.run`` (→ ``stages.errors.machining_error`` at the measured points, the
    errors stage's kernel) are called directly, once per program and parameter set (cached here).
    ``scale`` is the baseline force-model scale (a reference-part calibration; 1 without one).
    """

    def __init__(self, tabs: dict, tool: dict, material: dict, machine: dict, scale: float = 1.0,
                 workdir: Optional[Path] = None):
        self.tabs = tabs
        self.tool, self.material, self.machine = dict(tool), dict(material), machine
        self.scale = float(scale)
        self.workdir = Path(workdir) if workdir else None
        self._defl: dict = {}
        self._n_profiles = 0

    def _deflection(self, prog: str, scale: float, runout_um: float) -> pa.Table:
        key = (prog, round(scale, 9), round(runout_um, 6))
        if key not in self._defl:
            from stages import deflection as dst
            from stages import forces as fst
            pick = lambda t: t.filter(pa.compute.equal(t.column("program_id"), prog))  # noqa: E731
            tool = dict(self.tool, runout_um=runout_um)
            mat = {k: (float(v) * scale if k in COEFFS and v is not None else v) for k, v in self.material.items()}
            f = fst.run({"passes": pick(self.tabs["passes"]), "generating": pick(self.tabs["generating"]),
                         "engagement": pick(self.tabs["engagement"])}, {"tool": tool, "material": mat})["forces"]
            self._defl[key] = dst.run({"forces": f}, {"machine": self.machine, "tool": tool})["deflection"]
            if len(self._defl) > 64:
                self._defl.pop(next(iter(self._defl)))
        return self._defl[key]

    def profile_csv(self, contour: dict, name: Optional[str] = None) -> str:
        """A tool profile table (claim 2, ``contact_deg,error_um``) with the fitted dent added to the
        workflow's profile, written where ``tool.profile`` can point at it."""
        from stages.cutting.surface_error import read_profile
        q = np.round(np.arange(0.0, 90.0 + 1e-9, 0.25), 6)
        e = contour["a_um"] * np.exp(-0.5 * ((q - contour["q0_deg"]) / contour["width_deg"]) ** 2)
        if self.tool.get("profile"):
            pq_, pe_ = read_profile(self.tool["profile"])
            e = e + np.interp(q, pq_, pe_)
        if self.workdir is None:
            import tempfile
            self.workdir = Path(tempfile.mkdtemp(prefix="gap_"))
        self.workdir.mkdir(parents=True, exist_ok=True)
        self._n_profiles += 1
        path = self.workdir / (name or f"tool_profile_fitted_{self._n_profiles}.csv")
        path.write_text("contact_deg,error_um\n" + "".join(f"{a:.4f},{b:.6f}\n" for a, b in zip(q, e)))
        return str(path)

    def tool_for(self, params: dict) -> tuple[dict, float]:
        """(tool, force scale) of the prediction with the model effects in ``params`` added."""
        tool = dict(self.tool)
        if "runout" in params:
            tool["runout_um"] = float(self.tool.get("runout_um") or 0.0) + max(float(params["runout"]["e_um"]), 0.0)
        if "tool_contour" in params:
            tool["profile"] = params["tool_contour"].get("profile_csv") or self.profile_csv(params["tool_contour"])
        scale = self.scale * float(params.get("force_scale", {}).get("scale", 1.0))
        return tool, scale

    def at_points(self, F: dict, params: dict, rows: Optional[np.ndarray] = None, runout_part: bool = False) -> np.ndarray:
        """Predicted error (µm) at the measured points ``rows`` with the model effects ``params``
        (force_scale, runout, tool_contour; others are ignored) added to the simulation (with
        ``runout_part``: its runout part −ρ·sin q alone)."""
        from stages.gap import predicted_at_points
        tool, scale = self.tool_for(params)
        runout = float(tool.get("runout_um") or 0.0)
        # each point's own pass and the neighbouring passes' tooth passages that sweep it
        return predicted_at_points(F, lambda prog: self._deflection(prog, scale, runout), tool, rows, runout_part)[0]

    def errors_table(self, params: dict) -> pa.Table:
        """The ``errors`` table re-predicted with the model effects added (errors stage re-run)."""
        from stages import errors as est
        tool, scale = self.tool_for(params)
        out = []
        for prog in dict.fromkeys(self.tabs["passes"].column("program_id").to_pylist()):
            pick = lambda t: t.filter(pa.compute.equal(t.column("program_id"), prog))  # noqa: E731
            d = self._deflection(prog, scale, float(tool.get("runout_um") or 0.0))
            out.append(est.run({"passes": pick(self.tabs["passes"]), "generating": pick(self.tabs["generating"]),
                                "deflection": d}, {"tool": tool})["errors"])
        return pa.concat_tables(out)


def make_predictor(tabs: dict, wf, tool: dict, scale: float = 1.0, workdir=None) -> Optional[Predictor]:
    """A ``Predictor`` when the run has the render tables (generating, engagement) and a machine FRF."""
    if not all(k in tabs for k in ("generating", "engagement")) or not (wf.machine and wf.machine.frf):
        return None
    mat = wf.material_for(tool.get("t") if isinstance(wf.material, list) else None).model_dump()
    return Predictor(tabs, tool, mat, wf.machine.model_dump(), scale, workdir)


def add_model_responses(F: dict, predictor: Optional[Predictor]) -> dict:
    """The prediction's own response to runout on a grid of e (for the runout effect's signature)."""
    if predictor is None:
        return F
    F = dict(F)
    base, base_geo = predictor.at_points(F, {}), predictor.at_points(F, {}, runout_part=True)
    resp = np.zeros((len(base), len(RUNOUT_GRID_UM), 2))
    for i, e in enumerate(RUNOUT_GRID_UM):
        p = {"runout": {"e_um": e}}
        total = predictor.at_points(F, p) - base
        resp[:, i, 0] = predictor.at_points(F, p, runout_part=True) - base_geo
        resp[:, i, 1] = total - resp[:, i, 0]
    F["runout_grid_um"] = np.array(RUNOUT_GRID_UM)
    F["runout_resp_um"] = resp
    return F


def how_far(F: dict, res: dict, predictor: Optional[Predictor]) -> dict:
    """Held-out "after" with the chosen effects added to the simulation itself.

    Every spatial fold is predicted with the effects fitted without it: model effects
    (force_scale, runout, tool_contour) through the re-run prediction (``Predictor``), the others
    as their term along the normal. Replaces the "after" figures of ``res``; the after of the
    fitted terms alone is kept as ``rms_after_terms_um``.
    """
    from stages.gap import _rms, _shrink_acting, fold_fits
    chosen = res["_chosen"]
    res["how_added"] = {e.name: (HOW_ADDED[e.name] if predictor is not None and e.name in HOW_ADDED else OFFSET_ADDED
                                 if e.name not in HOW_ADDED else "term of the prediction model (no render tables to re-run)")
                        for e, _ in chosen}
    if not chosen:
        return res
    y, meas = F["residual_um"], F["measured_um"]
    after, terms_after = np.zeros_like(y), np.zeros_like(y)
    for test, items in fold_fits(F, y, res["_fold"], chosen):
        terms = np.zeros(int(test.sum()))
        offsets = np.zeros_like(terms)
        model = {}
        for e, th, b in items:
            c = e.basis(F, th)[test] @ b
            terms += c
            if predictor is not None and e.name in HOW_ADDED:
                model[e.name] = e.params(b, th)
            else:
                offsets += c
        pred = (predictor.at_points(F, model, test) + np.broadcast_to(F.get("baseline_extra_um", 0.0), y.shape)[test]
                if model else F["predicted_um"][test])
        after[test] = meas[test] - pred - offsets
        terms_after[test] = y[test] - terms
    res["rms_after_terms_um"] = _rms(terms_after)
    res["rms_after_um"] = _rms(after)
    res["p95_after_um"] = float(np.percentile(np.abs(after), 95))
    res["max_after_um"] = float(np.abs(after).max())
    res["shrink"] = float(1 - res["rms_after_um"] / res["rms_before_um"]) if res["rms_before_um"] > 0 else 0.0
    res["shrink_where_acting"] = _shrink_acting(y, after, y - terms_after)
    res["_after"] = after
    return res


# ------------------------------------------------------------------------------ simulate
def simulate(workflow: str, program: Optional[str], effects: list[str], noise_um: float, seed: Optional[int],
             out_file: str, plan: Optional[str] = None, grid_mm: float = 0.5) -> dict:
    """Machine the program(s) on the virtual machine with ``effects`` and write a measurement file."""
    from stages.measurements import write_measurements
    from stages.geometry.paths import nearest_pass
    from stages.virtual_machine import VirtualMachine, grid_plan, parse_effect
    wf, base = load_workflow(workflow)
    eff = dict(parse_effect(e) for e in effects)
    tabs, outdir, run = run_tables(workflow, "split")
    passes = tabs["passes"]
    progs = list(dict.fromkeys(passes.column("program_id").to_pylist()))
    if program:
        stem = Path(program).stem
        if stem not in progs:
            raise InputError(f"--program {program}: not a program of {workflow} (programs: {', '.join(progs)})")
        progs = [stem]
    spec = _spec(wf, base)
    plan_pts = None
    if plan or spec.file:
        tab, rej, _ = read_points(plan or spec.file, spec, require_deviation=False)
        plan_pts = tab
    rng = np.random.default_rng(seed)
    pieces = []
    stock = run._static["stock"][0]
    for prog in progs:
        sub = passes.filter(pa.compute.equal(passes.column("program_id"), prog))
        vm = VirtualMachine(sub, _tool(wf, sub), wf.material_for(None if not isinstance(wf.material, list) else
                                                                  _tool(wf, sub).get("t")).model_dump(),
                            wf.machine.model_dump(), stock)
        if plan_pts is not None:
            pts = np.stack([plan_pts.column(c).to_numpy() for c in ("x_mm", "y_mm", "z_mm")], 1)
            nrm = np.stack([plan_pts.column(c).to_numpy() for c in ("nx", "ny", "nz")], 1)
            ids = plan_pts.column("point_id").to_numpy()
            # a plan point belongs to this program when one of its passes machined it (ideal ball
            # centre on a centre segment); others belong to other programs or were not machined
            _, _, d = nearest_pass(vm.path, pts + vm.R * nrm)
            mine = d < 0.05
            pts, nrm, ids = pts[mine], nrm[mine], ids[mine]
        else:
            pts, nrm = grid_plan(vm, grid_mm)
            ids = np.arange(len(pts)) + sum(len(p) for p in pieces)
        err = vm.probe(pts, nrm, eff, noise_um, rng)
        row, u, _ = nearest_pass(vm.path, pts + vm.R * nrm)
        t = vm.path.t0[row] + u * (vm.path.t1[row] - vm.path.t0[row])
        pieces.append(pa.table({"point_id": pa.array(ids.astype(np.int64)), "x_mm": pts[:, 0], "y_mm": pts[:, 1],
                                "z_mm": pts[:, 2], "nx": nrm[:, 0], "ny": nrm[:, 1], "nz": nrm[:, 2],
                                "err_um": err, "t_s": t}))
    tab = schemas.check("measurements", pa.concat_tables(pieces))
    write_measurements(tab, out_file)
    return {"points": tab.num_rows, "programs": progs, "effects": eff, "noise_um": noise_um, "out": out_file}


# ------------------------------------------------------------------------------ diagnose
def diagnose_points(F: dict, sigma: Optional[float], floor_um: float = 0.0,
                    predictor: Optional[Predictor] = None) -> dict:
    """Diagnosis of associated points: the catalogue (with the prediction's own runout response when
    a ``predictor`` is given), then "how far" with the effects added to the simulation."""
    from stages.gap import diagnose, where
    F = add_model_responses(F, predictor)
    # one BLAS thread: the selection makes ~20,000 products of ≤ 20,000 × 10 matrices, which a
    # second thread does not speed up, and whose threads spin-wait for a time slice when another
    # job holds a core (100,000-point bench at load 2–3: 154–171 s with OpenBLAS's 2 threads, 30 s with one)
    with _one_blas_thread():
        res = diagnose(F, sigma, floor_um)
        res = how_far(F, res, predictor)
    res["where"] = where(F, F["residual_um"], res["sigma_um"], res["_blocks"])
    res["where_after"] = where(F, res["_after"], res["sigma_um"], res["_blocks"])
    return res


def _one_blas_thread():
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:            # an environment installed before the dependency: run as before
        import contextlib
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


def calibrate(F0: dict, predictor: Optional[Predictor] = None) -> dict:
    """Calibration on a reference part measured without any effect to find (a test cut on a warm,
    checked machine with a measured tool): the force-model scale s0 (least squares of the
    residual on the predicted deflection), the prediction's floor near path corners as the servo
    lag it reads as (``stages.gap.corner_floor``: None unless the reference pins it to 3 standard
    errors), and the model floor left (residual RMS beyond the probe noise). With a ``predictor`` s0
    becomes its baseline; ``stages.gap.apply_baseline`` applies s0 and the corner floor to a
    measurement, the floor goes to the diagnosis's size test."""
    from stages.gap import apply_baseline, corner_floor, noise_sigma
    d = F0["pred_deflection_um"]
    s0 = float(1.0 + np.dot(d, F0["residual_um"]) / np.dot(d, d)) if np.dot(d, d) > 0 else 1.0
    F0 = apply_baseline(F0, s0)
    if predictor is not None:
        predictor.scale = s0
    corner = corner_floor(F0)
    F0 = apply_baseline(F0, 1.0, corner)
    sig0 = noise_sigma(F0, F0["residual_um"])
    floor = float(math.sqrt(max(np.mean(F0["residual_um"] ** 2) - sig0 ** 2, 0.0)))
    return {"force_scale_s0": s0, "corner_floor": corner, "floor_um": floor, "n_points": int(len(F0["residual_um"])),
            "reference_rms_um": float(np.sqrt(np.mean(F0["residual_um"] ** 2))), "noise_est_um": sig0}


def diagnose_cmd(workflow: str, measurements: str, out: Optional[str] = None,
                 reference: Optional[str] = None) -> dict:
    from stages.gap import associate, gap_effects_table, gap_points_table
    t0 = time.perf_counter()
    wf, base = load_workflow(workflow)
    spec = _spec(wf, base)
    tabs, outdir, _ = run_tables(workflow, "errors")
    outdir = Path(out) if out else outdir
    meas, rej, _ = read_points(measurements, spec)
    tool = _tool(wf, tabs["passes"])
    F, rej2 = associate(meas, tabs["passes"], tabs.get("errors"), tool, spec.off_part_mm, tabs.get("deflection"))
    t1 = time.perf_counter()
    name = Path(measurements).stem
    gdir = outdir / "gap"
    gdir.mkdir(parents=True, exist_ok=True)
    predictor = make_predictor(tabs, wf, tool, workdir=gdir / "folds")
    calibration, floor = None, 0.0
    if reference:
        # the same calibration the blind check proves the diagnosis with (``calibrate``)
        from stages.gap import apply_baseline
        ref, _, _ = read_points(reference, spec)
        F0, _ = associate(ref, tabs["passes"], tabs.get("errors"), tool, spec.off_part_mm, tabs.get("deflection"))
        calibration = dict(calibrate(F0, predictor), file=str(reference))
        F = apply_baseline(F, calibration["force_scale_s0"], calibration["corner_floor"])
        floor = calibration["floor_um"]
    res = diagnose_points(F, spec.noise_um, floor, predictor=predictor)
    if calibration is not None:
        res["calibration"] = calibration
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
        tab = schemas.check(tname, tab)
        pq.write_table(tab, d / f"{name}.parquet.tmp")
        (d / f"{name}.parquet.tmp").replace(d / f"{name}.parquet")
    rejected = [(i, ln, why) for i, ln, why in rej.rows] + [(i, None, why) for i, why in rej2]
    with open(gdir / "rejected.csv", "w") as f:
        f.write("point_id,line,reason\n")
        for i, ln, why in rejected:
            f.write(f"{i},{'' if ln is None else ln},\"{why}\"\n")
    summary = public_summary(res)
    summary.update({"measurements": str(measurements), "n_rejected": len(rejected),
                    "timing_s": {"associate": t1 - t0, "diagnose": t2 - t1}})
    (gdir / "summary.json").write_text(json.dumps(summary, indent=2))
    report(gdir, F, res, summary)
    return summary


def public_summary(res: dict) -> dict:
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
    """How each chosen effect enters the simulation model (tool, machine, force model)."""
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
    from stages.gap import LIMITS
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


# ------------------------------------------------------------------------------ blind check
def random_case(rng, kind: str, ctx: dict) -> dict:
    """Random physical parameters for one effect, within ranges set by the part (duration, size)."""
    T, qmax = ctx["duration_s"], ctx["q_max_deg"]
    sgn = lambda: rng.choice([-1.0, 1.0])
    if kind == "runout":
        # eccentricity within 45° of a flute (else with 2 flutes no flute stands out): e_eff ≥ e·cos 45°
        return {"e_um": rng.uniform(*_RANGES["runout"]), "phase_deg": rng.uniform(-45, 45) + 360.0 / _FLUTES["n"] * rng.integers(_FLUTES["n"])}
    if kind == "tool_contour":
        return {"a_um": sgn() * rng.uniform(*_RANGES["tool_contour"]), "q0_deg": rng.uniform(0.2 * qmax, 0.8 * qmax),
                "width_deg": rng.uniform(5, 15)}
    if kind == "tool_wear":
        return {"rate_um_per_m": rng.uniform(*_RANGES["tool_wear"]) * 1000.0 / max(ctx["cut_len_mm"], 1e-6)}
    if kind == "thermal_drift":
        a = rng.normal(size=3)
        a = a / np.linalg.norm(a) * rng.uniform(*_RANGES["thermal_drift"])
        return {"ax_um": a[0], "ay_um": a[1], "az_um": a[2], "tau_s": T * rng.uniform(0.1, 1.0)}
    if kind == "force_scale":
        return {"scale": float(np.exp(rng.uniform(*np.log(_RANGES["force_scale"])) * sgn()))}
    if kind == "servo_corner":
        return {"a_um": sgn() * rng.uniform(*_RANGES["servo_corner"]), "lambda_mm": rng.uniform(0.3, 1.5)}
    if kind == "machine_geometry":
        v = rng.normal(size=6)
        g = dict(zip(("sx", "sy", "sz", "exy", "exz", "eyz"), map(float, v)))
        disp = _geometry_offsets(g, ctx["tips"])
        k = rng.uniform(*_RANGES["machine_geometry"]) / max(float(np.linalg.norm(disp, axis=1).max()), 1e-9)
        return {key: val * k for key, val in g.items()}
    raise ValueError(kind)


def param_error(kind: str, true: dict, fit: dict, geom=None) -> float:
    """Relative error of the fitted parameters (vector norm for multi-parameter effects)."""
    if kind == "runout":
        return abs(fit["e_um"] - _runout_eff(true)) / _runout_eff(true)
    if kind == "force_scale":
        return abs(fit["scale"] - true["scale"]) / abs(true["scale"] - 1.0)
    if kind == "tool_contour":
        return max(abs(fit["a_um"] - true["a_um"]) / abs(true["a_um"]),
                   abs(fit["q0_deg"] - true["q0_deg"]) / true["width_deg"],
                   abs(fit["width_deg"] - true["width_deg"]) / true["width_deg"])
    if kind == "thermal_drift":
        a = np.array([true[k] for k in ("ax_um", "ay_um", "az_um")])
        b = np.array([fit[k] for k in ("ax_um", "ay_um", "az_um")])
        return max(float(np.linalg.norm(a - b) / np.linalg.norm(a)), abs(fit["tau_s"] - true["tau_s"]) / true["tau_s"])
    if kind == "servo_corner":
        return max(abs(fit["a_um"] - true["a_um"]) / abs(true["a_um"]),
                   abs(fit["lambda_mm"] - true["lambda_mm"]) / true["lambda_mm"])
    if kind == "machine_geometry" and geom is not None:
        # the six coefficients are not all identifiable on a part a few mm tall (z terms ~ an offset);
        # the error of the tool-offset field they make, over the measured points, is
        tip, n = geom
        field = lambda g: np.sum(n * _geometry_offsets(g, tip), 1)  # noqa: E731
        ft = field(true)
        return float(np.sqrt(np.mean((field(fit) - ft) ** 2)) / np.sqrt(np.mean(ft ** 2)))
    keys = list(true)
    a = np.array([true[k] for k in keys])
    b = np.array([fit[k] for k in keys])
    return float(np.linalg.norm(a - b) / np.linalg.norm(a))


def param_terms(kind: str, true: dict, fit: dict, se: dict, cov: Optional[dict] = None, geom=None) -> dict:
    """The fitted parameters of one true effect against the truth, in units of their stated standard
    errors, and the terms of ``param_error`` with the error each could have at 2 SE.

    ``z``: per parameter with a truth, |fit − truth| / se (None when the diagnosis stated no se; the
    runout's e against the largest flute offset, its force part e_force_um has no truth here).
    ``terms``: per term of ``param_error`` (same normalisation), its relative error and ``rel_2se`` =
    2·se / normaliser — above 0.2 the points cannot pin that term to 20 % (for the drift's amplitude
    vector and the machine-geometry field, the RMS of the error the covariance implies:
    √trace(Σ)/‖A‖ and √(mean over the points of (n·offset(δg))²)/RMS of the field)."""
    def z(key, t):
        s = se.get(key)
        return abs(fit[key] - t) / s if s is not None and s > 0 else None

    def rel(key, norm):
        s = se.get(key)
        return 2 * s / norm if s is not None else None

    zz, terms = {}, []
    if kind == "runout":
        eff = _runout_eff(true)
        zz["e_um"] = z("e_um", eff)
        terms.append({"param": "e_um", "rel_error": abs(fit["e_um"] - eff) / eff, "rel_2se": rel("e_um", eff)})
    elif kind == "force_scale":
        d = abs(true["scale"] - 1.0)
        zz["scale"] = z("scale", true["scale"])
        terms.append({"param": "scale", "rel_error": abs(fit["scale"] - true["scale"]) / d, "rel_2se": rel("scale", d)})
    elif kind == "tool_contour":
        w = true["width_deg"]
        for k, norm in (("a_um", abs(true["a_um"])), ("q0_deg", w), ("width_deg", w)):
            zz[k] = z(k, true[k])
            terms.append({"param": k, "rel_error": abs(fit[k] - true[k]) / norm, "rel_2se": rel(k, norm)})
    elif kind == "thermal_drift":
        keys = ("ax_um", "ay_um", "az_um")
        a = np.array([true[k] for k in keys])
        b = np.array([fit[k] for k in keys])
        for k in keys + ("tau_s",):
            zz[k] = z(k, true[k])
        ses = [se.get(k) for k in keys]
        terms.append({"param": "a_vector", "rel_error": float(np.linalg.norm(a - b) / np.linalg.norm(a)),
                      "rel_2se": (2 * math.sqrt(sum(x * x for x in ses)) / float(np.linalg.norm(a))
                                  if all(x is not None for x in ses) else None)})
        terms.append({"param": "tau_s", "rel_error": abs(fit["tau_s"] - true["tau_s"]) / true["tau_s"],
                      "rel_2se": rel("tau_s", true["tau_s"])})
    elif kind == "servo_corner":
        for k, norm in (("a_um", abs(true["a_um"])), ("lambda_mm", true["lambda_mm"])):
            zz[k] = z(k, true[k])
            terms.append({"param": k, "rel_error": abs(fit[k] - true[k]) / norm, "rel_2se": rel(k, norm)})
    elif kind == "tool_wear":
        k = "rate_um_per_m"
        zz[k] = z(k, true[k])
        terms.append({"param": k, "rel_error": abs(fit[k] - true[k]) / abs(true[k]), "rel_2se": rel(k, abs(true[k]))})
    elif kind == "machine_geometry":
        keys = ("sx", "sy", "sz", "exy", "exz", "eyz")
        for k in keys:
            zz[k] = z(k, true[k])
        if geom is not None:
            tip, n = geom
            field = lambda g: np.sum(n * _geometry_offsets(g, tip), 1)  # noqa: E731
            ft = field(true)
            norm = float(np.sqrt(np.mean(ft ** 2)))
            r2 = None
            if cov is not None:
                idx = [cov["names"].index(f"machine_geometry.{k}") if f"machine_geometry.{k}" in cov["names"] else None
                       for k in keys]
                if all(i is not None for i in idx):
                    S = np.array([[cov["matrix"][i][j] if cov["matrix"][i][j] is not None else np.nan for j in idx]
                                  for i in idx])
                    # each coefficient's field per unit, at the points: mean of (N Σ Nᵀ) diagonal
                    N = np.stack([field({kk: float(kk == k) for kk in keys}) for k in keys], 1)
                    v = float(np.mean(np.einsum("pi,ij,pj->p", N, S, N)))
                    r2 = 2 * math.sqrt(v) / norm if np.isfinite(v) and v >= 0 else None
            terms.append({"param": "field", "rel_error": float(np.sqrt(np.mean((field(fit) - ft) ** 2)) / norm),
                          "rel_2se": r2})
    for t in terms:
        t["pinnable_to_20pct"] = None if t["rel_2se"] is None else bool(t["rel_2se"] <= 0.2)
    return {"z": zz, "terms": terms}


def coefficient_error(true: dict, fit: dict) -> float:
    """Relative error of a parameter vector (norm), for the record."""
    keys = [k for k in true if k in fit]
    a = np.array([true[k] for k in keys], float)
    b = np.array([fit[k] for k in keys], float)
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(a), 1e-12))


_FLUTES = {"n": 2}


def _runout_eff(true: dict) -> float:
    """The largest flute offset e·max_j cos(2πj/N + phase): what the surface shows."""
    n = _FLUTES["n"]
    return true["e_um"] * max(math.cos(2 * math.pi * j / n + math.radians(true["phase_deg"])) for j in range(n))


def blind_check(workflow: str, cases: int, seed: int, out: Optional[str] = None, noise=(0.3, 1.0),
                pairs: int = 0, progress=None, kinds: Optional[list] = None) -> dict:
    """Random effect (or none) per case, simulated on the virtual machine, diagnosed blind."""
    from stages.virtual_machine import VirtualMachine
    wf, base = load_workflow(workflow)
    spec = _spec(wf, base)
    tabs, outdir, run = run_tables(workflow, "errors")
    outdir = Path(out) if out else outdir
    passes = tabs["passes"]
    progs = list(dict.fromkeys(passes.column("program_id").to_pylist()))
    prog = progs[0]
    sub = passes.filter(pa.compute.equal(passes.column("program_id"), prog))
    tool = _tool(wf, sub)
    _FLUTES["n"] = int(tool["flutes"])
    vm = VirtualMachine(sub, tool, wf.material_for(tool.get("t") if isinstance(wf.material, list) else None).model_dump(),
                        wf.machine.model_dump(), run._static["stock"][0])
    if spec.file:
        plan, _, _ = read_points(spec.file, spec, require_deviation=False)
        pts = np.stack([plan.column(c).to_numpy() for c in ("x_mm", "y_mm", "z_mm")], 1)
        nrm = np.stack([plan.column(c).to_numpy() for c in ("nx", "ny", "nz")], 1)
    else:
        from stages.virtual_machine import grid_plan
        pts, nrm = grid_plan(vm)
    sub_tabs = {k: (v.filter(pa.compute.equal(v.column("program_id"), prog)) if "program_id" in v.column_names else v)
                for k, v in tabs.items()}
    predictor = make_predictor(sub_tabs, wf, tool, workdir=outdir / "blind" / "profiles")
    summary = blind_cases(vm, sub, tabs.get("errors"), tool, pts, nrm, cases, seed, noise=noise, pairs=pairs,
                          off_part_mm=spec.off_part_mm, progress=progress, deflection=tabs.get("deflection"),
                          kinds=_check_kinds(kinds), predictor=predictor)
    summary["workflow"] = workflow
    bdir = outdir / "blind"
    bdir.mkdir(parents=True, exist_ok=True)
    (bdir / "summary.json").write_text(json.dumps(summary, indent=2, default=_jsonable))
    return summary


def _check_kinds(kinds):
    from stages.virtual_machine import EFFECTS
    if not kinds:
        return None
    bad = [k for k in kinds if k != "none" and k not in EFFECTS]
    if bad:
        raise InputError(f"--kinds: unknown {bad} (known: none, {', '.join(EFFECTS)})")
    return list(kinds)


def blind_cases(vm, passes: pa.Table, errors: Optional[pa.Table], tool: dict, pts: np.ndarray, nrm: np.ndarray,
                cases: int, seed: int, noise=(0.3, 1.0), pairs: int = 0, off_part_mm: float = 0.05,
                kinds: Optional[list] = None, progress=None, deflection: Optional[pa.Table] = None,
                predictor: Optional[Predictor] = None) -> dict:
    """The blind check on one program: ``cases`` single-effect (or none) cases + ``pairs`` two-effect cases.

    With a ``predictor`` (the run's render tables), the reference part's force scale s0 becomes the
    predictor's baseline, the runout signature is the prediction's own response, and "after" is
    the re-run prediction with the fitted effects (``how_far``)."""
    from stages.gap import associate
    from stages.virtual_machine import EFFECTS
    _FLUTES["n"] = int(tool["flutes"])
    ids = np.arange(len(pts))
    p = vm.path
    q = np.degrees(np.arccos(np.clip(nrm[:, 2], -1, 1)))
    ctx = {"duration_s": float(p.t1.max()), "q_max_deg": float(np.percentile(q, 98)),
           "cut_len_mm": float(p.L0[-1] + p.length[-1]),
           "size_mm": float(np.ptp(pts, axis=0).max()), "tips": pts + vm.R * nrm - [0.0, 0.0, vm.R]}
    kinds = kinds or ["none"] + list(EFFECTS)
    rng = np.random.default_rng(seed)
    plan_cases = [[kinds[i % len(kinds)]] for i in range(cases)]
    rng.shuffle(plan_cases)
    pool = [k for k in kinds if k != "none"] or list(EFFECTS)
    for _ in range(pairs):
        # the larger effect of a pair acts over the whole part (a corner effect is small in RMS)
        a = rng.choice([k for k in pool if k != "servo_corner"])
        b = rng.choice([k for k in pool if k != a])
        plan_cases.append([str(a), str(b)])
    results = []
    t_start = time.perf_counter()
    geom = (pts + vm.R * nrm - [0.0, 0.0, vm.R], nrm)      # tool tip and normal at each point
    # reference part (no effect), as a shop calibrates on a test cut (``calibrate``)
    from stages.gap import apply_baseline
    ref_sigma = float(np.mean(noise))
    err = vm.probe(pts, nrm, {}, ref_sigma, np.random.default_rng(seed + 7919))
    F0, _ = associate(_meas_table(ids, pts, nrm, err), passes, errors, tool, off_part_mm, deflection)
    calibration = dict(calibrate(F0, predictor), reference_noise_um=ref_sigma)
    s0, corner, floor = calibration["force_scale_s0"], calibration["corner_floor"], calibration["floor_um"]
    for ci, kinds_i in enumerate(plan_cases):
        if len(kinds_i) == 2:
            truth = _draw_pair(rng, kinds_i, pool, vm, pts, nrm, ctx)
        else:
            truth = {k: random_case(rng, k, ctx) for k in kinds_i if k != "none"}
        sigma = float(rng.uniform(*noise))
        err = vm.probe(pts, nrm, truth, sigma, rng)
        F, rej = associate(_meas_table(ids, pts, nrm, err), passes, errors, tool, off_part_mm, deflection)
        res = diagnose_points(apply_baseline(F, s0, corner), None, floor, predictor)
        true_order = _true_order(truth, vm, pts, nrm)
        case = {"case": ci, "truth": truth, "true_order": true_order, "noise_um": sigma,
                "true_rms_um": _true_sizes(truth, vm, pts, nrm) if len(truth) >= 2 else None,
                "found": res["effects"], "params": res["params"], "sigma_est_um": res["sigma_um"],
                "rms_before_um": res["rms_before_um"], "rms_after_um": res["rms_after_um"], "shrink": res["shrink"],
                "rms_after_terms_um": res.get("rms_after_terms_um"), "how_added": res.get("how_added"),
                "shrink_where_acting": res["shrink_where_acting"],
                "n_rejected": len(rej)}
        top = res["effect"]
        case["top1_ok"] = (top == (true_order[0] if true_order else "none"))
        case["ambiguous_with"] = res.get("ambiguous_with", {})
        if len(truth) == 1 and top in truth:
            case["param_error"] = param_error(top, truth[top], res["params"][top], geom)
            case["coefficient_error"] = coefficient_error(truth[top], res["params"][top])
        # the fitted parameters against the truth in units of their stated standard errors
        case["params_se"] = res.get("params_se", {})
        pt = {k: param_terms(k, truth[k], res["params"][k], res["params_se"].get(k, {}), res.get("params_cov"), geom)
              for k in truth if k in res["params"]}
        case["param_z"] = {k: v["z"] for k, v in pt.items()}
        if case.get("param_error", 0.0) > 0.2:
            # the terms beyond 20 %, with |fit − truth|/se of the parameters behind each
            case["param_miss"] = [dict(t, z={k: pt[top]["z"].get(k) for k in _TERM_KEYS.get(t["param"], (t["param"],))})
                                  for t in pt[top]["terms"] if t["rel_error"] > 0.2]
        if len(truth) >= 2:
            case["pair_order_ok"] = res["effects"][:len(true_order)] == true_order
        # a true effect not named: was it within what the diagnosis said it could miss (its
        # detection limit next to the effects it named)? Reported beside the strict figures
        missed = [k for k in truth if k not in res["effects"]]
        if missed:
            size = case["true_rms_um"] or _true_sizes(truth, vm, pts, nrm)
            lim = res.get("detection_limits", {})
            case["missed"] = [{"effect": k, "true_rms_um": size[k],
                               "hidden_up_to_um": lim.get(k, {}).get("hidden_up_to_um"),
                               "correlation": lim.get(k, {}).get("correlation"),
                               "masked_by": lim.get(k, {}).get("masked_by")} for k in missed]
            case["missed_within_stated_limit"] = all(m["hidden_up_to_um"] is not None
                                                     and m["true_rms_um"] <= m["hidden_up_to_um"] for m in case["missed"])
        results.append(case)
        if progress:
            progress(ci, case)
    singles = [c for c in results if len(c["truth"]) <= 1]
    eff = [c for c in singles if c["truth"]]
    zs = lambda cs: [z for c in cs for zk in c.get("param_z", {}).values() for z in zk.values()]  # noqa: E731
    none = [c for c in singles if not c["truth"]]
    perr = [c["param_error"] for c in eff if "param_error" in c]
    summary = {
        "calibration": calibration,
        "seed": seed, "cases": len(singles), "pairs": len(results) - len(singles),
        "noise_um": list(noise), "points_per_case": int(len(pts)),
        "top1_accuracy": float(np.mean([c["top1_ok"] for c in singles])) if singles else None,
        "top1_accuracy_effects": float(np.mean([c["top1_ok"] for c in eff])) if eff else None,
        "none_correct": float(np.mean([c["top1_ok"] for c in none])) if none else None,
        "median_shrink": float(np.median([c["shrink"] for c in eff])) if eff else None,
        "median_shrink_where_acting": float(np.median([c["shrink_where_acting"] or 0.0 for c in eff])) if eff else None,
        "param_error": {"median": float(np.median(perr)) if perr else None,
                        "within_20pct": float(np.mean(np.array(perr) <= 0.2)) if perr else None},
        # the stated standard errors checked: the fraction of fitted parameters (with a truth) whose
        # truth lies within 2 SE (≈ 95 % if they are honest), and for every case missing the 20 %
        # line, each term beyond it with |fit − truth|/se and 2·se/|truth| (> 0.2: the points
        # cannot pin it to 20 %)
        "param_se": _se_summary(singles, results, zs),
        "pair_order_ok": float(np.mean([c["pair_order_ok"] for c in results if "pair_order_ok" in c]))
        if len(results) > len(singles) else None,
        # the strict figures above count every miss; of the misses, those where a true effect was not
        # named although the diagnosis's stated detection limit for it (next to what it named) was
        # at least its true RMS: the data could not show it (signatures nearly collinear on the part)
        "misses_within_stated_limit": {
            "single": [c["case"] for c in singles if c["truth"] and not c["top1_ok"] and c.get("missed_within_stated_limit")],
            "pair": [c["case"] for c in results if len(c["truth"]) >= 2 and not c["pair_order_ok"]
                     and c.get("missed_within_stated_limit")]},
        "per_effect": {k: {"n": sum(1 for c in singles if (list(c["truth"]) or ["none"])[0] == k),
                           "top1": float(np.mean([c["top1_ok"] for c in singles if (list(c["truth"]) or ["none"])[0] == k]))
                           if any((list(c["truth"]) or ["none"])[0] == k for c in singles) else None}
                       for k in kinds},
        "wall_s": time.perf_counter() - t_start,
        "cases_detail": results,
    }
    return summary


# the parameters behind a vector term of ``param_terms``
_TERM_KEYS = {"a_vector": ("ax_um", "ay_um", "az_um"), "field": ("sx", "sy", "sz", "exy", "exz", "eyz")}


def _se_summary(singles: list, results: list, zs) -> dict:
    def cover(z, k):
        have = [x for x in z if x is not None]
        return float(np.mean(np.array(have) <= k)) if have else None
    zsg, zpr = zs(singles), zs([c for c in results if len(c["truth"]) >= 2])
    per = {}
    for c in singles:
        for k, zk in c.get("param_z", {}).items():
            for p, x in zk.items():
                d = per.setdefault(f"{k}.{p}", [])
                d.append(x)
    return {
        "coverage_2se": cover(zsg, 2.0), "coverage_1se": cover(zsg, 1.0),
        "n_params": sum(x is not None for x in zsg), "n_without_se": sum(x is None for x in zsg),
        "coverage_2se_pairs": cover(zpr, 2.0), "n_params_pairs": sum(x is not None for x in zpr),
        "median_z": float(np.median([x for x in zsg if x is not None])) if any(x is not None for x in zsg) else None,
        "per_parameter": {k: {"n": len(v), "within_2se": cover(v, 2.0),
                              "max_z": max((x for x in v if x is not None), default=None)} for k, v in sorted(per.items())},
        "misses_20pct": [{"case": c["case"], "effect": list(c["truth"])[0], "param_error": c["param_error"],
                          "noise_um": c["noise_um"], "terms": c["param_miss"]}
                         for c in singles if "param_miss" in c],
    }


_AMPLITUDES = {"runout": ("e_um",), "tool_contour": ("a_um",), "tool_wear": ("rate_um_per_m",),
               "thermal_drift": ("ax_um", "ay_um", "az_um"), "servo_corner": ("a_um",),
               "machine_geometry": ("sx", "sy", "sz", "exy", "exz", "eyz")}


def _scaled(name: str, params: dict, k: float) -> dict:
    out = dict(params)
    if name == "force_scale":
        out["scale"] = 1.0 + k * (params["scale"] - 1.0)
    else:
        for a in _AMPLITUDES[name]:
            out[a] = params[a] * k
    return out


# drawn sizes of each effect (random_case): runout e µm, contour |a| µm, wear at the end µm, drift |a| µm,
# force scale s (and 1/s), servo lag |a| µm, machine geometry's largest tool offset µm
_RANGES = {"runout": (4.0, 15.0), "tool_contour": (4.0, 12.0), "tool_wear": (5.0, 15.0), "thermal_drift": (8.0, 25.0),
           "force_scale": (2.0, 3.5), "servo_corner": (10.0, 30.0), "machine_geometry": (8.0, 20.0)}


def _geometry_offsets(g: dict, tip: np.ndarray) -> np.ndarray:
    """Tool offsets (µm) of the machine-geometry effect at the tool tips ``tip`` (mm)."""
    return np.stack([g["sx"] * tip[:, 0] + g["exy"] * tip[:, 1] + g["exz"] * tip[:, 2],
                     g["sy"] * tip[:, 1] + g["eyz"] * tip[:, 2], g["sz"] * tip[:, 2]], 1)


def _amplitude_range(name: str, params: dict, ctx: Optional[dict]) -> tuple[float, float]:
    """By how much an effect's amplitude may be scaled (``_scaled``) and stay within the range
    ``random_case`` draws from: (smallest, largest) factor. Without the part's context only the
    force scale's range is known; the others may then shrink freely but not grow."""
    lo, hi = _RANGES[name]
    if name == "force_scale":
        s = params["scale"]
        amp, lo, hi = (s - 1.0, lo - 1.0, hi - 1.0) if s > 1 else (1.0 - s, 1.0 - 1.0 / lo, 1.0 - 1.0 / hi)
    elif ctx is None:
        return 0.0, 1.0
    elif name == "runout":
        amp = params["e_um"]
    elif name in ("tool_contour", "servo_corner"):
        amp = abs(params["a_um"])
    elif name == "tool_wear":
        amp = params["rate_um_per_m"] * ctx["cut_len_mm"] * 1e-3
    elif name == "thermal_drift":
        amp = math.sqrt(params["ax_um"] ** 2 + params["ay_um"] ** 2 + params["az_um"] ** 2)
    elif name == "machine_geometry":
        amp = float(np.linalg.norm(_geometry_offsets(params, ctx["tips"]), axis=1).max())   # µm/mm × mm
    else:
        return 0.0, 1.0
    amp = max(amp, 1e-12)
    return lo / amp, hi / amp


def _distinct_sizes(truth: dict, vm, pts, nrm, ratio: float, ctx: Optional[dict] = None,
                    size: Optional[dict] = None) -> Optional[dict]:
    """The pair rescaled so that the second effect's RMS on the points is ``ratio`` × the first's,
    with both amplitudes kept inside the ranges ``random_case`` draws from (a second effect scaled
    below its range would be a different, smaller effect than the single-effect cases test; one
    scaled above it, a force scale below zero or a servo lag of 100+ µm): the second is scaled as
    far as its range allows and the first by the rest. None when the first would then leave its
    own range (the caller draws again). ``size``: each effect's RMS, when known (``_true_sizes``)."""
    size = size or _true_sizes(truth, vm, pts, nrm)
    first, second = list(truth)
    if size[second] <= 0 or size[first] <= 0:
        return truth
    k = ratio * size[first] / size[second]
    lo2, hi2 = _amplitude_range(second, truth[second], ctx)
    lo1, hi1 = _amplitude_range(first, truth[first], ctx)
    g = min(max(k, min(lo2, 1.0)), max(hi2, 1.0))          # the second's share, within its range
    f = g / k                                              # the first's, for the rest
    if not min(lo1, 1.0) * (1 - 1e-9) <= f <= max(hi1, 1.0) * (1 + 1e-9):
        return None                                        # not possible within the drawn ranges
    return {first: _scaled(first, truth[first], f), second: _scaled(second, truth[second], g)}


def _draw_pair(rng, kinds: list, pool: list, vm, pts, nrm, ctx: dict, tries: int = 20) -> dict:
    """Parameters of a two-effect case whose second effect's RMS on the points is 45-75 % of the
    first's, both within their drawn ranges (``_distinct_sizes``). The drawn kinds are tried in both
    orders (a corner effect is never the larger: it is small in RMS), with fresh parameters; when
    the part admits no such sizes for them (e.g. a force scale of at most 3.5 on a part with little
    deflection against a tool wear of at least 5 µm), another pair of kinds is drawn."""
    base = vm.probe(pts, nrm, {}, 0.0)
    for _ in range(10):
        a, b = kinds
        for _ in range(tries):
            truth = {k: random_case(rng, k, ctx) for k in (a, b)}
            size = _true_sizes(truth, vm, pts, nrm, base)
            ratio = float(rng.uniform(0.45, 0.75))
            for first, second in ((a, b), (b, a)):
                if first == "servo_corner":
                    continue
                pair = _distinct_sizes({first: truth[first], second: truth[second]}, vm, pts, nrm, ratio, ctx, size)
                if pair is not None:
                    return pair
        a = str(rng.choice([k for k in pool if k != "servo_corner"]))
        kinds = [a, str(rng.choice([k for k in pool if k != a]))]
    raise RuntimeError("blind check: no pair of effects within the drawn ranges has distinct sizes on this part")


def _meas_table(ids, pts, nrm, err) -> pa.Table:
    return pa.table({"point_id": pa.array(np.asarray(ids).astype(np.int64)), "x_mm": pts[:, 0], "y_mm": pts[:, 1],
                     "z_mm": pts[:, 2], "nx": nrm[:, 0], "ny": nrm[:, 1], "nz": nrm[:, 2], "err_um": err,
                     "t_s": np.full(len(err), np.nan)})


def _true_sizes(truth: dict, vm, pts, nrm, base: Optional[np.ndarray] = None) -> dict:
    """RMS (µm) of each effect's own signature on the measured points (noise-free, alone)."""
    base = vm.probe(pts, nrm, {}, 0.0) if base is None else base
    return {k: float(np.sqrt(np.mean((vm.probe(pts, nrm, {k: v}, 0.0) - base) ** 2))) for k, v in truth.items()}


def _true_order(truth: dict, vm, pts, nrm) -> list:
    """Effects of a case ordered by the RMS of their own signature on the measured points (noise-free)."""
    if len(truth) <= 1:
        return list(truth)
    size = _true_sizes(truth, vm, pts, nrm)
    return sorted(size, key=lambda k: -size[k])


def _jsonable(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.bool_,)):
        return bool(o)
    return str(o)
