"""Command line: ``pipeline run WORKFLOW`` and friends."""
from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from pipeline.config import WorkflowError
from stages import InputError


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def main():
    """Machining-error prediction for mould finishing programs (see README)."""


@main.command()
@click.argument("workflow", type=click.Path(dir_okay=False))
@click.option("--out", "out", type=click.Path(file_okay=False), help="Output directory (default: workflow's `output`).")
@click.option("--scheduler", help="Address of an existing Dask scheduler (default: a LocalCluster).")
@click.option("--workers", type=click.IntRange(1, 256), help="Workers of the LocalCluster (default: CPU count).")
@click.option("--until", help="Stop after this stage.")
@click.option("--fresh", is_flag=True, help="Ignore and delete the cache of this output directory.")
@click.option("--quiet", "-q", is_flag=True, help="No progress bars.")
@click.option("--overlay", "overlays", multiple=True, type=click.Path(exists=True, dir_okay=False),
              help="YAML of workflow keys merged over WORKFLOW before validation (e.g. gap/model_update.yaml "
                   "of `pipeline diagnose`); repeatable, later ones win; paths relative to the overlay's folder.")
def run(workflow, out, scheduler, workers, until, fresh, quiet, overlays):
    """Run WORKFLOW: only partitions not already in the cache are computed."""
    from pipeline.engine import Run
    from pipeline.graph import mould_graph
    from pipeline.jobs import JobError, job_name, runner
    try:
        job = job_name(workflow)
        if job != "mould":
            mod = runner(job)
            summary = mod.run(workflow, out=out, overlays=overlays, fresh=fresh, workers=workers, quiet=quiet)
        else:
            r = Run(workflow, mould_graph(), out=out, until=until, fresh=fresh, overlays=overlays)
            summary = r.execute(scheduler=scheduler, workers=workers, progress=not quiet)
    except (WorkflowError, InputError, JobError) as e:
        click.echo(f"error: {e}", err=True)
        sys.exit(2)
    if job != "mould":
        mod.echo_summary(summary)
        sys.exit(1 if summary["failures"] else 0)
    _print_summary(summary)
    sys.exit(1 if summary["failures"] else 0)


@main.command()
@click.argument("workflow", type=click.Path(dir_okay=False))
@click.option("--out", "out", type=click.Path(file_okay=False))
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
@click.option("--overlay", "overlays", multiple=True, type=click.Path(exists=True, dir_okay=False),
              help="YAML of workflow keys merged over WORKFLOW before validation (e.g. gap/model_update.yaml "
                   "of `pipeline diagnose`); repeatable, later ones win; paths relative to the overlay's folder.")
def status(workflow, out, as_json, overlays):
    """Show which stages and partitions of WORKFLOW are done."""
    from pipeline.engine import Run
    from pipeline.graph import mould_graph
    try:
        rows = Run(workflow, mould_graph(), out=out, overlays=overlays).status()
    except WorkflowError as e:
        click.echo(f"error: {e}", err=True)
        sys.exit(2)
    if as_json:
        click.echo(json.dumps(rows, indent=2))
        return
    click.echo(f"{'stage':>12}  {'done':>6}  {'pending':>7}  {'blocked':>7}")
    for r in rows:
        click.echo(f"{r['stage']:>12}  {r['done']:>6}  {r['pending']:>7}  {r['blocked']:>7}")


@main.command("bench")
@click.option("--passes", "n_passes", type=click.IntRange(min=100), default=30000, show_default=True,
              help="Size of the generated finishing job.")
@click.option("--workers", type=click.IntRange(1, 256), help="Workers of the LocalCluster (default: CPU count).")
@click.option("--scheduler", help="Address of an existing Dask scheduler.")
@click.option("--rerun", is_flag=True, help="Run again with nothing changed and report its seconds.")
@click.option("--programs", "n_programs", type=click.IntRange(1, 64), default=1, show_default=True,
              help="Deal the raster's rows to this many programs (a mould finished region by region).")
@click.option("--dir", "root", type=click.Path(file_okay=False), help="Where the jobs are made (default runs/bench).")
@click.option("--json", "json_path", type=click.Path(dir_okay=False), help="Write the figures to this file.")
def bench_cmd(n_passes, workers, scheduler, rerun, n_programs, root, json_path):
    """Run the whole chain on a generated finishing job of N passes and print its figures."""
    from pipeline import bench
    res = bench.bench(n_passes, Path(root) if root else bench.default_root(), workers=workers, scheduler=scheduler,
                      rerun=rerun, n_programs=n_programs)
    click.echo(bench.write_json(res, json_path))
    sys.exit(1 if res["failures"] else 0)


@main.command("tool-profile")
@click.option("--images", "images", required=True, type=click.Path(exists=True, file_okay=False),
              help="Directory of backlit silhouette images of the rotating tool (tip down).")
@click.option("--um-per-px", required=True, type=click.FloatRange(min=0, min_open=True), help="Image scale.")
@click.option("--diameter-mm", required=True, type=click.FloatRange(min=0, min_open=True), help="Nominal diameter.")
@click.option("--type", "tool_type", type=click.Choice(["ball", "bull"]), default="ball", show_default=True)
@click.option("--corner-radius-mm", type=float, help="Nominal corner radius (bull-nose).")
@click.option("--cutoff-deg", type=float, default=5.0, show_default=True, help="Low-pass cutoff (CV1 -> CV2).")
@click.option("--reference", type=click.Choice(["lsq", "tip"]), default="lsq", show_default=True,
              help="Axial placement of the ideal profile: least squares, or on the tip.")
@click.option("--centre-z-px", type=float, help="Centre row of an earlier measurement (wear in a fixed frame).")
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False), help="Profile CSV to write (+ .json, .png).")
def tool_profile(images, um_per_px, diameter_mm, tool_type, corner_radius_mm, cutoff_deg, reference, centre_z_px, out):
    """Tool contour error per contact angle, runout and envelope from silhouette images."""
    from stages.tool_measure import tool_profile_command
    try:
        res = tool_profile_command(images, um_per_px, diameter_mm, tool_type, out, corner_radius_mm=corner_radius_mm,
                                   cutoff_deg=cutoff_deg, reference=reference, centre_z_px=centre_z_px)
    except InputError as e:
        click.echo(f"error: {e}", err=True)
        sys.exit(2)
    ecc = res.get("eccentricity_um")
    click.echo(f"{res.get('n_images')} images; eccentricity {ecc} um; wrote {out} (+ .json, .png)")


@main.command("thermal-fit")
@click.option("--measurements", type=click.Path(dir_okay=False),
              help="On-machine drift CSV: time_s, dx_um, dy_um, dz_um [, spindle_rpm, x_mm, y_mm, z_mm, temp_*].")
@click.option("--model", "model_path", type=click.Path(dir_okay=False),
              help="An existing drift model (instead of --measurements): only --predict.")
@click.option("--out", "out", type=click.Path(dir_okay=False), help="Drift model to write (+ .json, .png).")
@click.option("--sources", type=click.IntRange(1, 4), default=2, show_default=True, help="Heat sources (time constants).")
@click.option("--predict", "times", type=click.Path(dir_okay=False),
              help="CSV of times (time_s and the model's heat/position columns) to predict the drift at.")
@click.option("--predicted", type=click.Path(dir_okay=False), help="Where --predict writes time_s, dx_um, dy_um, dz_um.")
def thermal_fit(measurements, model_path, out, sources, times, predicted):
    """Fit a thermal drift model per axis to on-machine reference measurements (seed 003)."""
    from stages.thermal import load_model, predict_file, thermal_fit_command
    if bool(measurements) == bool(model_path) or (measurements and not out) or bool(times) != bool(predicted):
        raise click.UsageError("give --measurements with --out, or --model; --predict goes with --predicted")
    try:
        if measurements:
            rep = thermal_fit_command(measurements, out, sources)
            taus = ", ".join(f"{t['value'] / 60:.1f} ± {t['se'] / 60:.1f} min" for t in rep["time_constants_s"])
            rms = ", ".join(f"{a} {v:.2f}" for a, v in rep["rms_um"].items())
            click.echo(f"{rep['points']} measurements; time constants {taus}; residual RMS um: {rms}; "
                       f"wrote {out} (+ .json, .png)")
            model = load_model(out)
        else:
            model = load_model(model_path)
        if times:
            n = predict_file(model, times, predicted)
            click.echo(f"predicted the drift at {n} times -> {predicted}")
    except InputError as e:
        click.echo(f"error: {e}", err=True)
        sys.exit(2)


@main.command("tool-wear")
@click.option("--before", "before", required=True, type=click.Path(dir_okay=False),
              help="Tool-profile CSV measured before the job (contact_deg, error_um).")
@click.option("--after", "after", required=True, type=click.Path(dir_okay=False),
              help="Tool-profile CSV of the same tool after the job, in the same frame (--centre-z-px).")
@click.option("--run", "run_dir", type=click.Path(file_okay=False), help="Run directory: cut length from its tables.")
@click.option("--program", "programs", multiple=True, help="With --run: only these program ids (repeatable).")
@click.option("--tool", "tool", type=int, help="With --run: only passes of this T number.")
@click.option("--cut-length-m", type=float, help="Cutting length of the job, metres (instead of --run).")
@click.option("--tool-id", help="Name of the tool in the table (default: the after file's stem).")
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False), help="Parquet file to write.")
def tool_wear(before, after, run_dir, programs, tool, cut_length_m, tool_id, out):
    """Wear per contact angle and wear rate per metre of cut, as a Parquet table (schema tool_wear)."""
    from stages.tool_measure import wear_table, write_wear
    if run_dir is None and cut_length_m is None:
        click.echo("error: give --run RUN_DIR or --cut-length-m X (the wear rate needs the cut length)", err=True)
        sys.exit(2)
    if (programs or tool is not None) and run_dir is None:
        click.echo("error: --program and --tool select passes of a run; they need --run", err=True)
        sys.exit(2)
    try:
        t = wear_table(before, after, cut_length_m=cut_length_m, run_dir=run_dir,
                       run_tables=_run_tables(run_dir) if run_dir is not None else None,
                       programs=list(programs) or None, tool=tool, tool_id=tool_id)
    except InputError as e:
        click.echo(f"error: {e}", err=True)
        sys.exit(2)
    write_wear(t, out)
    w = t.column("wear_um").to_numpy()
    q = t.column("contact_deg").to_numpy()
    k = int(abs(w).argmax())
    L = t.column("cut_length_m")[0].as_py()
    click.echo(f"{t.num_rows} contact angles; largest wear {w[k]:+.2f} um at {q[k]:.1f} deg; cut length "
               f"{L:.3f} m ({t.column('cut_length_source')[0].as_py()}); wrote {out}")


def _run_tables(run_dir):
    """(passes, cut_filter) tables of a run directory; None for one it has not written."""
    from pathlib import Path

    import pyarrow.parquet as pq
    root = Path(run_dir) / "tables"
    return tuple(pq.read_table(root / name) if (root / name).is_dir() and any((root / name).glob("*.parquet"))
                 else None for name in ("passes", "cut_filter"))


@main.command("calibrate-forces")
@click.argument("workflow", type=click.Path(dir_okay=False))
@click.option("--cuts", required=True, type=click.Path(exists=True, dir_okay=False),
              help="YAML list of measured cuts: file (CSV rotation_deg,fx_n,fy_n,fz_n), axial_depth_mm, "
                   "radial_width_mm (null = slot), side, feed_mm_min, spindle_rpm.")
@click.option("--tool", "t", type=int, help="T number of the tool (when the workflow lists several).")
@click.option("--forces-on", type=click.Choice(["tool", "workpiece"]), default="workpiece", show_default=True,
              help="What the dynamometer measured (a table dynamometer measures the workpiece).")
@click.option("--out", "out", type=click.Path(dir_okay=False), help="Write the fit as JSON.")
def calibrate_forces(workflow, cuts, t, forces_on, out):
    """Fit the material's cutting coefficients to measured force records (least squares)."""
    import yaml
    from pathlib import Path
    from pipeline.config import load_workflow
    from stages.cutting.calibrate import calibrate_from_csv
    from stages.geometry.cutter import Cutter
    try:
        wf, _ = load_workflow(workflow)
        tool = wf.tool_for(t).model_dump()
        spec = yaml.safe_load(Path(cuts).read_text())
        if not isinstance(spec, list) or not spec:
            raise WorkflowError(f"{cuts}: a list of cuts is expected")
        base = Path(cuts).resolve().parent
        paths = []
        for i, c in enumerate(spec):
            if not isinstance(c, dict) or "file" not in c:
                raise WorkflowError(f"{cuts}: cut {i + 1} has no 'file'")
            paths.append(str(base / c.pop("file")))
        fit = calibrate_from_csv(paths, spec, Cutter.from_params(tool), forces_on=forces_on)
    except (WorkflowError, InputError, KeyError) as e:
        click.echo(f"error: {e}", err=True)
        sys.exit(2)
    text = json.dumps(fit, indent=2, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))
    if out:
        Path(out).write_text(text)
    click.echo(text)


@main.command()
@click.argument("workflow", type=click.Path(dir_okay=False))
@click.option("--program", type=click.Path(dir_okay=False), help="Only this program of the workflow.")
@click.option("--effect", "effects", multiple=True, metavar="NAME:key=value,...",
              help="Unmodelled effect to switch on (runout, tool_contour, tool_wear, thermal_drift, force_scale, "
                   "servo_corner, machine_geometry); repeatable.")
@click.option("--noise-um", type=click.FloatRange(min=0), default=0.5, show_default=True, help="Probe noise σ.")
@click.option("--seed", type=int, help="Noise seed.")
@click.option("--plan", type=click.Path(exists=True, dir_okay=False),
              help="Measurement plan (points + normals); default the workflow's measurements file, else a grid.")
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False), help="Measurement file (.csv or .parquet).")
def simulate(workflow, program, effects, noise_um, seed, plan, out):
    """Machine WORKFLOW on the virtual machine and write probed deviations (gap job)."""
    from pipeline.gap_jobs import simulate as sim
    try:
        r = sim(workflow, program, list(effects), noise_um, seed, out, plan=plan)
    except (WorkflowError, InputError) as e:
        click.echo(f"error: {e}", err=True)
        sys.exit(2)
    click.echo(f"{r['points']} points of {', '.join(r['programs'])}, effects {r['effects'] or 'none'}, "
               f"noise {noise_um} um -> {out}")


@main.command()
@click.argument("workflow", type=click.Path(dir_okay=False))
@click.option("--measurements", required=True, type=click.Path(exists=True, dir_okay=False))
@click.option("--out", "out", type=click.Path(file_okay=False), help="Output directory (default: workflow's `output`).")
@click.option("--reference", type=click.Path(exists=True, dir_okay=False),
              help="Measurement of a reference part with no effect to find (same program and plan): "
                   "calibrates the force-model scale, the corner floor and the model floor (subtracted point by point "
                   "when above the probe noise), as the blind check does.")
def diagnose(workflow, measurements, out, reference):
    """Sim-to-real gap: where, which unmodelled effect, how far it shrinks (held-out)."""
    from pipeline.gap_jobs import diagnose_cmd
    try:
        s = diagnose_cmd(workflow, measurements, out, reference=reference)
    except (WorkflowError, InputError) as e:
        click.echo(f"error: {e}", err=True)
        sys.exit(2)
    click.echo(f"effect: {s['effect']} (all: {s['effects']}); params {json.dumps(s['params'])}")
    for e in s.get("possible", []):
        click.echo(f"possible, not claimed: {e}" + (f" ({s['possible_why'][e]})" if e in s.get("possible_why", {}) else ""))
    click.echo(f"held-out RMS {s['rms_before_um']:.3f} -> {s['rms_after_um']:.3f} um (shrink {s['shrink']:.1%}); "
               f"{len(s['where'])} regions beyond noise; {s['n_points']} points, {s['n_rejected']} rejected")
    pl = s["plan"]
    click.echo("points by contact angle: " + ", ".join(
        f"{b['band_deg'][0]:g}-{b['band_deg'][1]:g}° {b['measured']} (+{b['rejected']} rejected)" for b in pl["bands"])
        + "; by normal: " + ", ".join(f"{d['direction']} {d['measured']} (+{d['rejected']} rejected)" for d in pl["directions"]))
    for w in pl["warnings"]:
        click.echo(f"warning: {w}")
    ov = s.get("overlay") or {}
    if ov:
        click.echo(f"model update: {ov['file']} (applied: {', '.join(ov['applied']) or 'none'}"
                   + (f"; not applied: {', '.join(ov['unapplied'])}" if ov["unapplied"] else "") + ")")
    hidden = [f"{e}.{k}" for e, d in s.get("observability", {}).items() for k, why in d.items() if why]
    if hidden:
        click.echo("not observable from these points (held at nominal): " + ", ".join(hidden))


@main.command("blind-check")
@click.argument("workflow", type=click.Path(dir_okay=False))
@click.option("--cases", type=click.IntRange(1), default=56, show_default=True)
@click.option("--pairs", type=click.IntRange(0), default=0, show_default=True, help="Extra cases with two effects.")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--kinds", help="Comma-separated effects (and 'none') the single cases cycle through (default: all); "
              "'periodic' and 'bump' are errors outside the catalogue (the answer should be 'unexplained').")
@click.option("--plan-kind", type=click.Choice(["full", "floors", "sections", "walls"]), default="full", show_default=True,
              help="The plan's points an inspection program of that kind probes (floors: normal within 5° of +z).")
@click.option("--out", "out", type=click.Path(file_okay=False))
def blind_check(workflow, cases, pairs, seed, kinds, plan_kind, out):
    """Random effect (or none) per case on the virtual machine, diagnosed without telling it."""
    from pipeline.gap_jobs import blind_check as bc
    try:
        s = bc(workflow, cases, seed, out, pairs=pairs, kinds=kinds.split(",") if kinds else None, plan_kind=plan_kind,
               progress=lambda i, c: click.echo(f"case {i}: truth {list(c['truth']) or ['none']} found {c['found'] or ['none']} "
                                                f"shrink {c['shrink']:.2f}"
                                                + (f" (missed within its stated limit: {[m['effect'] for m in c['missed']]})"
                                                   if c.get("missed_within_stated_limit") else ""), err=True))
    except (WorkflowError, InputError) as e:
        click.echo(f"error: {e}", err=True)
        sys.exit(2)
    click.echo(json.dumps({k: s[k] for k in ("plan_kind", "points_per_case", "cases", "pairs", "top1_accuracy", "none_correct", "median_shrink",
                                             "param_error", "pair_order_ok", "misses_within_stated_limit", "wall_s")},
                          indent=2))


def _print_summary(s: dict) -> None:
    c = s["counts"]
    click.echo(f"{s['name']}: {c['programs']} programs ({c['programs_failed']} failed), {c['passes']} passes, "
               f"{s['wall_s']:.2f} s -> {s['output']}")
    click.echo(f"{'stage':>12}  {'parts':>5}  {'cached':>6}  {'computed':>8}  {'failed':>6}  {'wall_s':>7}")
    for st in s["stages"]:
        click.echo(f"{st['name']:>12}  {st['partitions']:>5}  {st['cached']:>6}  {st['computed']:>8}  "
                   f"{st['failed']:>6}  {st['wall_s']:>7.3f}")
    for pid, w in (s.get("warnings") or {}).items():
        parts = [f"{v['passes']} {r} (lines {', '.join(map(str, v['lines']))}{', …' if v['passes'] > len(v['lines']) else ''})"
                 for r, v in w.items()]
        click.echo(f"warning: {pid}: " + "; ".join(parts) + " - table warnings", err=True)
    for pid, f in (s.get("feeds") or {}).items():
        click.echo(f"{pid}: scheduled feeds: machining time {f['duration_s'] / 60:.1f} -> {f['duration_new_s'] / 60:.1f} min"
                   + (f"; {f['overloaded']} passes over feed.max_deflection_um even at feed.min_mm_min"
                      if f["overloaded"] else ""))
    for pid, k in (s.get("kept") or {}).items():
        if not k["stalled"]:
            continue
        first = f"{k['first_rms_dev_um']:.1f}"
        if k["kept_round"]:
            click.echo(f"{pid}: rounds stopped at {k['rounds']} (the predicted deviation stopped falling); "
                       f"round {k['kept_round']}'s correction is written: deviation RMS {first} -> "
                       f"{k['kept_rms_dev_um']:.1f} um predicted")
        else:
            click.echo(f"warning: {pid}: no coordinate correction is written: none was predicted to deviate less "
                       f"than the program as written ({first} um RMS); a path offset does not help there",
                       err=True)
    if s.get("report_error"):
        click.echo(f"warning: no report ({s['report_error']['message']}); the tables and programs are written", err=True)
    if s["failures"]:
        click.echo(f"{len(s['failures'])} failure(s):", err=True)
        problems = _problems(Path(s["output"]))
        for f in s["failures"]:
            click.echo(f"  [{f['stage']}] {f['message']}", err=True)
            rows = problems.get(f["program_id"], [])
            if len(rows) > 1:
                for r in rows[:SHOWN_PROBLEMS]:
                    click.echo(f"      {r}", err=True)
                if len(rows) > SHOWN_PROBLEMS:
                    click.echo(f"      … {len(rows) - SHOWN_PROBLEMS} more in the problems table", err=True)


# problems of a failed program printed under its failure (all are in <out>/tables/problems)
SHOWN_PROBLEMS = 5


def _problems(out: Path) -> dict[str, list[str]]:
    """program id → its problems as ``path:line: message at column c`` lines, from the run's table."""
    import pyarrow.parquet as pq
    from stages.nc.lexer import where
    d = out / "tables" / "problems"
    rows: dict[str, list[str]] = {}
    for f in sorted(d.glob("*.parquet")) if d.is_dir() else []:
        for r in pq.read_table(f).to_pylist():
            rows.setdefault(r["program_id"], []).append(
                f"{r['path']}:{r['line']}: {where(r['message'], r['column'])}")
    return rows


if __name__ == "__main__":
    main()
