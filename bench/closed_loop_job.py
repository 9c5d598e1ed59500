"""The closed loop of a whole job, checked on the virtual machine (issue 58; a bench, not a CI test).

``pipeline run`` predicts every program of the workflow and writes the corrected programs. Then
every program, in machining order on one stock, is machined on ``stages/virtual_machine/`` (discrete
flutes, time-domain dynamics of the modes it fits to the workflow's FRF, the tool's measured
profile, its own engagement with the earlier programs' cuts; no prediction code) three times:

- the reference: the programs as written, nominal tool, rigid machine (cusps and feed marks, which
  no path correction removes, are not counted as error);
- the programs as written on the real machine;
- the corrected programs (the kept correction of each, else the program as written) on the real
  machine, each after the earlier corrected programs.

The finished surface is probed on the reference's own plan (``grid_plan`` of each program, every
``--spacing`` mm along the passes' contact lines); at each point the surface is the deepest cut of
any program. The spindle's start angle is not something a path correction controls: each machining
is probed with the spindle started at ``--angles`` angles spread over one tooth period (one
revolution with runout), and the figure is the RMS over the points of all angles, after / before.

    python bench/closed_loop_job.py [workflows/mould.yaml] [--out runs/closed_loop] [--angles 8]
        [--spacing 0.25] [--vm-step-mm 0.5] [--workers 2]

``--set feed=null`` runs a copy of the workflow without its feed section (the coordinates-only
correction), ``--set split.max_pass_mm=1`` … another value. Writes ``<out>/closed_loop.json``
(figures by program and by contact-angle band, timings), ``<out>/closed_loop_points.parquet``
(every probe point: program, q, error before and after over the angles) and
``<out>/closed_loop_peaks.parquet`` (the machine's peak deflection per pass and NC line, each
program and variant); a ``--set`` run names them after its settings, its pipeline run too. The machinings are kept
under ``<out>/vm_cache`` by content (the machine's code, the programs, the plan): a rerun machines
only what changed.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
Q_BANDS = ((0.0, 30.0, "q<30"), (30.0, 60.0, "q30-60"), (60.0, 91.0, "q>=60"))


def job(workflow: Path, out: Path) -> list[dict]:
    """The workflow's programs in machining order: id, T number, text as written and as corrected,
    and the workflow entries the machine reads for it."""
    import pyarrow.parquet as pq

    from pipeline.config import load_workflow, program_paths, resolve
    from pipeline.engine import program_ids
    wf, base = load_workflow(workflow)
    tools = dict(zip(*(pq.read_table(out / "tables" / "programs").column(c).to_pylist() for c in ("program_id", "tool"))))
    paths = program_paths(wf, base)
    stock = str(resolve(base, wf.stock)) if isinstance(wf.stock, str) else wf.stock.model_dump()
    progs = []
    for pid, path in zip(program_ids(paths, base), paths):
        corrected = out / "nc" / path.name
        p = {**wf.params(("tool", "material", "machine", "split"), tools.get(pid), base), "stock": stock}
        progs.append({"id": pid, "t": tools.get(pid), "text": path.read_bytes(),
                      "corrected": corrected.read_bytes() if corrected.is_file() else None, "params": p})
    return progs


def passes(text: bytes, p: dict):
    from stages.nc.moves import split_blocks
    from stages.nc.reader import parse_program
    b, _ = parse_program(text, "vm.nc", "vm")
    return split_blocks(b, {"split": p["split"], "machine": p["machine"], "tool": nominal(p["tool"])})


def nominal(tool: dict) -> dict:
    return {k: v for k, v in tool.items() if k != "profile"}


def text_of(g: dict, variant: str) -> bytes:
    return (g["corrected"] or g["text"]) if variant == "corrected" else g["text"]


def machine(progs: list[dict], k: int, variant: str, step_mm: float):
    """Program ``k`` of the job loaded on the virtual machine after the earlier ones."""
    from stages.virtual_machine import VirtualMachine
    rigid = variant == "reference"
    def text(g):
        return (g["corrected"] or g["text"]) if variant == "corrected" else g["text"]
    earlier = [(passes(text(g), g["params"]), nominal(g["params"]["tool"]) if rigid else g["params"]["tool"])
               for g in progs[:k]]
    p = progs[k]["params"]
    frf = {a: [{"fn_hz": 900.0, "zeta": 0.03, "k_n_per_um": 1e9}] for a in "xy"} if rigid else p["machine"]["frf"]
    return VirtualMachine(passes(text(progs[k]), p), nominal(p["tool"]) if rigid else p["tool"], p["material"],
                          {"frf": frf}, p["stock"], deflection_step_mm=None if rigid else step_mm, earlier=earlier)


def probe_angles(vm, pts, nrm, angles: int, deflection=None) -> np.ndarray:
    """(angles, points) deviation (µm) with the spindle started k/``angles`` of its period on."""
    t0, t1 = vm.path.t0.copy(), vm.path.t1.copy()
    period = 60.0 / vm.path.rpm / (1 if vm.base_runout else vm.flutes)
    out = []
    for a in range(angles):
        vm.path.t0, vm.path.t1 = t0 + a / angles * period, t1 + a / angles * period
        out.append(vm.probe(pts, nrm, deflection=deflection))
    vm.path.t0, vm.path.t1 = t0, t1
    return np.stack(out)


def machined(progs, k, variant, step_mm, pts, nrm, angles):
    """(deviation (angles, points), the machine's peak deflection (µm) and NC line of each cutting
    pass, seconds)."""
    t = time.perf_counter()
    vm = machine(progs, k, variant, step_mm)
    dev = probe_angles(vm, pts, nrm, angles)
    dx, dy = vm.deflection()
    peak = np.zeros(len(vm.path.pass_id))
    np.maximum.at(peak, vm.stations.pass_row, np.hypot(dx, dy).max(axis=1))
    p = passes(text_of(progs[k], variant), progs[k]["params"])
    line = dict(zip(p.column("pass_id").to_pylist(), p.column("line_no").to_pylist()))
    return dev, peak, np.array([line[i] for i in vm.path.pass_id]), time.perf_counter() - t


def plan(progs, spacing):
    """The reference's probe plan of every program and its rigid, nominal-tool surface there."""
    from stages.virtual_machine import N_ROT, grid_plan
    vms = [machine(progs, k, "reference", None) for k in range(len(progs))]
    parts = [grid_plan(vm, spacing) for vm in vms]
    pts = np.concatenate([p for p, _ in parts])
    nrm = np.concatenate([n for _, n in parts])
    owner = np.repeat(np.arange(len(parts)), [len(p) for p, _ in parts])
    still = [(np.zeros((len(vm.stations.pass_row), N_ROT)),) * 2 for vm in vms]
    ideal = np.min([vm.probe(pts, nrm, deflection=s) for vm, s in zip(vms, still)], axis=0)
    return pts, nrm, owner, ideal


def feeds(progs, res, run: Path, workflow) -> dict | None:
    """With a ``feed:`` section: the machine's peak deflection per pass against the limit, for the
    scheduled programs (``corrected``: coordinates and F words) and the programs as written, and
    whether the passes over it are in the ``warnings`` table (program, NC line)."""
    import pyarrow.parquet as pq

    from pipeline.config import load_workflow
    wf, _ = load_workflow(workflow)
    if wf.feed is None:
        return None
    limit = float(wf.feed.max_deflection_um)
    w = pq.read_table(run / "tables" / "warnings").to_pydict()
    warned = set(zip(w["program_id"], w["line_no"]))
    out = {"limit_um": limit}
    for v, tol, name in (("corrected", 1.1, "scheduled"), ("original", 1.0, "original")):
        over, total, hit, worst = 0, 0, 0, []
        for k, g in enumerate(progs):
            if (k, v) not in res:
                continue
            _, peak, line, _ = res[(k, v)]
            bad = peak > tol * limit
            total += len(peak)
            over += int(bad.sum())
            hit += sum((g["id"], int(x)) in warned for x in line[bad])
            worst += [(float(p), g["id"], int(x)) for p, x in zip(peak[bad], line[bad])]
        out.update({f"{name}_passes": total, f"{name}_over": over, f"{name}_over_warned": hit,
                    f"{name}_worst": sorted(worst, reverse=True)[:10]})
    return out


def variant_workflow(path: Path, settings, out: Path) -> Path:
    """A copy of the workflow under ``out`` with ``settings`` applied and its file references made
    absolute (they are relative to the project)."""
    import yaml

    from pipeline.config import load_workflow, resolve
    _, base = load_workflow(path)
    wf = yaml.safe_load(path.read_text())

    def absolute(v, key=""):
        if isinstance(v, dict):
            return {k: absolute(x, k) for k, x in v.items()}
        if isinstance(v, list):                   # programs, or tool / material lists keyed by t
            return [absolute(x, key) for x in v]
        if isinstance(v, str) and key in ("programs", "stock", "nominal", "output", "profile", "table", "measurements"):
            return str(resolve(base, v))
        return v
    wf = absolute(wf)
    for kv in settings:
        key, _, value = kv.partition("=")
        *head, last = key.split(".")
        d = wf
        for h in head:
            d = d.setdefault(h, {})
        d[last] = yaml.safe_load(value)
    out.mkdir(parents=True, exist_ok=True)
    p = out / f"{path.stem}_variant.yaml"
    p.write_text(yaml.safe_dump(wf, sort_keys=False))
    return p


def machine_key(progs, k, variant, step_mm, pts, nrm, angles) -> str:
    """Content key of one machining: the machine's own code, every program text it reads (this one
    and the earlier ones), their workflow entries, the probe plan and the options."""
    import hashlib
    h = hashlib.sha256()
    for f in sorted((ROOT / "stages" / "virtual_machine").glob("*.py")) + [ROOT / "stages/geometry/paths.py"]:
        h.update(f.read_bytes())
    for g in progs[:k + 1]:
        h.update(text_of(g, variant))
        h.update(json.dumps(g["params"], sort_keys=True, default=str).encode())
    h.update(json.dumps([k, variant, step_mm, angles]).encode())
    h.update(np.ascontiguousarray(pts).tobytes() + np.ascontiguousarray(nrm).tobytes())
    return h.hexdigest()[:24]


def load_cached(cache: Path, key: str):
    f = cache / f"{key}.npz"
    if not f.is_file():
        return None
    with np.load(f) as z:
        return z["dev"], z["peak"], z["line"], float(z["seconds"])


def save_cached(cache: Path, key: str, res) -> None:
    cache.mkdir(parents=True, exist_ok=True)
    tmp = cache / f".{key}.{os.getpid()}.npz"
    np.savez(tmp, dev=res[0], peak=res[1], line=res[2], seconds=res[3])
    tmp.replace(cache / f"{key}.npz")                 # a killed run leaves no partial entry


def rms(x) -> float:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x ** 2))) if len(x) else float("nan")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workflow", nargs="?", default=str(ROOT / "workflows/mould.yaml"))
    ap.add_argument("--out", type=Path, default=ROOT / "runs/closed_loop")
    ap.add_argument("--angles", type=int, default=8)
    ap.add_argument("--spacing", type=float, default=0.25, help="probe spacing along the passes, mm")
    ap.add_argument("--vm-step-mm", type=float, default=0.5, help="the machine's deflection step along the path")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="run a copy of the workflow with this value (YAML; `feed=null` drops the section)")
    args = ap.parse_args(argv)
    if args.set:
        args.workflow = str(variant_workflow(Path(args.workflow), args.set, args.out))
    from click.testing import CliRunner

    from pipeline.cli import main as cli
    t0 = time.perf_counter()
    # each variant of the workflow predicts into a run directory of its own (the machinings are
    # shared through the content-keyed cache)
    run = args.out / ("run" if not args.set else "run-" + "-".join(k.replace("=", "_") for k in args.set))
    r = CliRunner().invoke(cli, ["run", args.workflow, "--out", str(run), "--workers", str(args.workers), "-q"])
    t_pipe = time.perf_counter() - t0
    if r.exit_code != 0:
        print(r.output)
        return 1
    progs = job(Path(args.workflow), run)
    t1 = time.perf_counter()
    pts, nrm, owner, ideal = plan(progs, args.spacing)
    t_plan = time.perf_counter() - t1
    # a program is machined again for the corrected job when it or an earlier one was corrected
    changed = np.cumsum([g["corrected"] is not None for g in progs]) > 0
    jobs = [(k, v) for v in ("original", "corrected") for k in range(len(progs)) if v == "original" or changed[k]]
    cache = args.out / "vm_cache"
    keys = {j: machine_key(progs, *j, args.vm_step_mm, pts, nrm, args.angles) for j in jobs}
    res = {j: load_cached(cache, keys[j]) for j in jobs}
    todo = [j for j in jobs if res[j] is None]
    with ProcessPoolExecutor(max(1, min(args.workers, len(todo) or 1))) as pool:
        futs = {j: pool.submit(machined, progs, j[0], j[1], args.vm_step_mm, pts, nrm, args.angles) for j in todo}
        for j, f in futs.items():
            res[j] = f.result()
            save_cached(cache, keys[j], res[j])
    feed_check = feeds(progs, res, run, args.workflow)
    dev = {}
    for v in ("original", "corrected"):
        per = [res[(k, v)][0] if (k, v) in res else res[(k, "original")][0] for k in range(len(progs))]
        dev[v] = np.min(per, axis=0) - ideal[None, :]           # (angles, points)
    q = np.degrees(np.arccos(np.clip(nrm[:, 2], -1, 1)))
    before, after = dev["original"], dev["corrected"]
    summary = {
        "workflow": args.workflow, "points": int(len(pts)), "angles": args.angles, "spacing_mm": args.spacing,
        "rms_before_um": rms(before), "rms_after_um": rms(after), "ratio_pct": 100 * rms(after) / rms(before),
        "by_angle_pct": [100 * rms(a) / rms(b) for a, b in zip(after, before)],
        "by_program": {g["id"]: {"points": int((owner == k).sum()), "corrected": g["corrected"] is not None,
                                 "rms_before_um": rms(before[:, owner == k]), "rms_after_um": rms(after[:, owner == k])}
                       for k, g in enumerate(progs)},
        "by_band": {name: {"points": int(((q >= lo) & (q < hi)).sum()), "rms_before_um": rms(before[:, (q >= lo) & (q < hi)]),
                           "rms_after_um": rms(after[:, (q >= lo) & (q < hi)])} for lo, hi, name in Q_BANDS},
        "feed": feed_check,
        "time_s": {"pipeline": t_pipe, "plan": t_plan, "machine": {f"{progs[k]['id']}:{v}": res[(k, v)][-1]
                                                                   for k, v in res},
                   "total": time.perf_counter() - t0},
    }
    args.out.mkdir(parents=True, exist_ok=True)
    tag = run.name.replace("run", "closed_loop", 1)
    (args.out / f"{tag}.json").write_text(json.dumps(summary, indent=1))
    import pandas as pd
    pd.DataFrame({"program_id": [progs[k]["id"] for k in owner], "x_mm": pts[:, 0], "y_mm": pts[:, 1], "z_mm": pts[:, 2],
                  "q_deg": q, "before_um": before.mean(0), "after_um": after.mean(0),
                  "before_rms_um": np.sqrt((before ** 2).mean(0)), "after_rms_um": np.sqrt((after ** 2).mean(0))}
                 ).to_parquet(args.out / f"{tag}_points.parquet")
    pd.concat([pd.DataFrame({"program_id": progs[k]["id"], "variant": v, "line_no": r[2], "peak_um": r[1]})
               for (k, v), r in res.items()]).to_parquet(args.out / f"{tag}_peaks.parquet")
    print(f"{len(pts)} points × {args.angles} spindle start angles: error RMS {summary['rms_before_um']:.2f} µm → "
          f"{summary['rms_after_um']:.2f} µm = {summary['ratio_pct']:.1f} % (per angle "
          f"{min(summary['by_angle_pct']):.1f}–{max(summary['by_angle_pct']):.1f} %)")
    for pid, f in summary["by_program"].items():
        print(f"  {pid}: {f['points']} points, {f['rms_before_um']:.2f} → {f['rms_after_um']:.2f} µm")
    for name, f in summary["by_band"].items():
        print(f"  {name}: {f['points']} points, {f['rms_before_um']:.2f} → {f['rms_after_um']:.2f} µm")
    if feed_check:
        print(f"  feed limit {feed_check['limit_um']:g} µm: the machine's peak deflection over it +10 % on "
              f"{feed_check['scheduled_over']} of {feed_check['scheduled_passes']} passes of the scheduled programs "
              f"({feed_check['scheduled_over_warned']} of them warned); the programs as written over it on "
              f"{feed_check['original_over']} passes, {feed_check['original_over_warned']} of them in `warnings`")
    print(f"time: pipeline {t_pipe:.0f} s, plan {t_plan:.0f} s, total {summary['time_s']['total']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
