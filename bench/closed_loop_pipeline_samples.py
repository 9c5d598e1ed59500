"""Closed loop of the whole pipeline on the sample mould, checked on the gap issue's virtual machine
(issue 5 must-show on the samples; a bench, not a CI test: minutes per band on llvmpipe).

For each probe window on ``data_samples/rest_overload/nc/mould_finish_t1.nc`` (the raster rows crossing
it, each cut to the moves within ``MARGIN_MM`` of it, as a program of their own: the sample's header, then
per row piece a retract, rapid, plunge and the row's lines verbatim; the windows lie on the pocket
walls and the boss, where the error is):

1. ``pipeline run`` predicts the error of every pass (render → forces → deflection → errors, the
   sample workflow's tool, material, machine FRF table, stock and prune) and writes the corrected
   program after ``correct.max_iter`` rounds (1 and 3);
2. the original and the corrected programs are machined on ``stages/virtual_machine/`` (discrete
   flutes, time-domain dynamics of the modes it fits to the same FRF table, the tool's measured
   profile, its own engagement on the semi-finished stock; no prediction code) and probed inside the window on its own plan
   (``grid_plan``, 0.1 mm along the passes' contact lines);
3. the error is the probed surface minus the original program machined with the nominal tool on a
   rigid machine (cusps and feed marks, which no path correction removes, are not counted).

    python3 bench/closed_loop_pipeline_samples.py [--out DIR] [--keep] [--prune DEG] [--max-move UM]
        [--correct KEY=VALUE ...] [--set SECTION.KEY=VALUE ...] [--program NC] [--workflow YAML] [X0 X1 Y0 Y1 ...]
    python3 bench/closed_loop_pipeline_samples.py --whole [--out DIR] [--prune DEG] [--workers 2] [--spacing MM]
        [--rounds 1] (one round of the pipeline 16–21 min on 2 workers at prune 0; the virtual machine
        13–70 min per program on one core, 43,326 probe points at 0.1 mm; the programs not in its
        cache are machined side by side, one process a core)

``--program`` and ``--workflow`` run another program with another workflow (default the finishing
program with ``workflows/rest_overload.yaml``, its ``feed`` section left out: the path correction alone;
e.g. ``--whole --program data_samples/rest_overload/nc/mould_contour_t1.nc``, or ``--whole --program data_samples/gap/gap_t1.nc --workflow workflows/gap.yaml``).
``--rounds`` lists the round counts to run (default 1 and 3). The virtual machine cuts every program
as passes of the workflow's chord tolerance, pass length and merge length only (:data:`VM_SPLIT`:
the end and corner pieces of ``--set split.…`` change what the pipeline predicts, not the machine).
Its probes are kept under ``<out>/vm_cache`` keyed by a hash of those passes, the machine's own
source, the workflow's tool, material, machine and stock, the window and the spacing: the rigid
reference and the original program are machined once for any number of pipeline experiments. ``points.parquet``
beside the summary holds every probe point with its error per program and the pass nearest it
(the machine's own association) with that pass's predicted error from the first round's tables:
where the prediction and the machine disagree.

``--second-walls`` also probes the walls the balls touch besides the plan's own contact (a ball in a
pocket's vertical corner finishes two walls, the plan probes one: :func:`second_wall_plan`),
reported apart from the figures above.

``--whole`` runs the whole finishing program as written (no window cut, no band edges) and probes
the whole finished surface; every run reports the RMS also by contact-angle band of the probe
points (floors q < 30°, slopes 30–60°, walls ≥ 60°).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

PROGRAM = ROOT / "data_samples/rest_overload/nc/mould_finish_t1.nc"
WORKFLOW = ROOT / "workflows/rest_overload.yaml"
WINDOWS = ((22.0, 32.0, 41.0, 45.0), (68.0, 78.0, 41.0, 45.0), (54.0, 62.0, 53.0, 57.0))
MARGIN_MM = 6.0          # passes machined on the VM: within this of the window (they shape its surface)


def window_program(src: bytes, x0: float, x1: float, y0: float, y1: float, name: str = PROGRAM.name) -> bytes:
    """The raster rows of the program with Y in [y0, y1], each cut to its moves with X in [x0, x1],
    as a program of their own: the sample's header, then per row a retract, a rapid to the row
    piece's start, a plunge at the row's feed and the row's lines verbatim."""
    from stages.nc.reader import parse_program
    lines = src.decode().splitlines()
    blocks, _ = parse_program(src, name, "window")
    col = lambda c: blocks.column(c).to_numpy(zero_copy_only=False)  # noqa: E731
    line_no, mot = col("line_no"), col("motion")
    xa, xb, ya, yb, za = col("x0_mm"), col("x1_mm"), col("y0_mm"), col("y1_mm"), col("z0_mm")
    keep = ((mot != 0) & (ya == yb) & (ya >= y0) & (ya <= y1)
            & (np.minimum(xa, xb) >= x0) & (np.maximum(xa, xb) <= x1))
    idx = np.flatnonzero(keep)
    if idx.size == 0:
        raise SystemExit(f"no cutting move inside x {x0}-{x1}, y {y0}-{y1}")
    # a new piece wherever the kept moves are not consecutive blocks
    starts = idx[np.concatenate([[True], np.diff(idx) > 1])]
    ends = idx[np.concatenate([np.diff(idx) > 1, [True]])]
    out = lines[:int(line_no[0]) - 1]                       # %, O-number, comments, G90…, T, S
    out.append(f"(WINDOW X{x0:g}-{x1:g} Y{y0:g}-{y1:g} OF {name}: {len(starts)} ROW PIECES)")
    for s_, e_ in zip(starts, ends):
        out += ["G0 Z25.000", f"X{xa[s_]:.3f} Y{ya[s_]:.3f}", f"Z{za[s_] + 2:.3f}",
                f"G1 Z{za[s_]:.3f} F{col('feed_mm_min')[s_]:g}"]
        out += lines[int(line_no[s_]) - 1:int(line_no[e_])]
    out += ["G0 Z25.000", "M5", "M30", "%", ""]
    return "\n".join(out).encode()


def workflow(root: Path, max_iter: int, prune_deg=None, max_move_um=None, correct_opts=(), other_opts=(),
             base: Path = WORKFLOW) -> Path:
    import yaml
    wf = yaml.safe_load(Path(base).read_text())
    # the run directory is elsewhere: the workflow's input files by absolute path
    for k in ("stock", "nominal"):
        if wf.get(k):
            wf[k] = str(ROOT / wf[k])
    if wf["tool"].get("profile"):
        wf["tool"]["profile"] = str(ROOT / wf["tool"]["profile"])
    if wf["machine"]["frf"].get("table"):
        wf["machine"]["frf"]["table"] = str(ROOT / wf["machine"]["frf"]["table"])
    # the path correction alone: the programs' own feeds (no feed schedule)
    for k in ("until", "measurements", "feed"):
        wf.pop(k, None)
    # one output (cache) for both runs: the three-round run takes round 1 from the cache
    wf.update({"name": "band", "programs": "nc/*.nc", "output": "out"})
    wf["correct"] = {**wf.get("correct", {}), "max_iter": max_iter}
    if max_move_um is not None:
        wf["correct"]["max_move_um"] = float(max_move_um)
    for kv in correct_opts:                      # e.g. relax=0.5
        k, v = kv.split("=", 1)
        wf["correct"][k] = yaml.safe_load(v)
    for kv in other_opts:                        # e.g. split.max_pass_mm=0.5
        k, v = kv.split("=", 1)
        section, _, key = k.partition(".")
        if not key:
            raise SystemExit(f"--set {kv}: expected SECTION.KEY=VALUE")
        wf.setdefault(section, {})[key] = yaml.safe_load(v)
    if prune_deg is not None:
        wf["prune"] = {**wf.get("prune", {}), "min_contact_deg": float(prune_deg)}
    p = root / f"wf{max_iter}.yaml"
    p.write_text(yaml.safe_dump(wf))
    return p


Q_BANDS = ((0.0, 30.0, "q<30"), (30.0, 60.0, "q30-60"), (60.0, 91.0, "q>=60"))


# the machine cuts every program as passes of the same length, whatever the predicting workflow's
# split options: the machine's physics (one deflection per pass) must not change with them
VM_SPLIT = ("chord_tol_mm", "max_pass_mm", "merge_max_mm")


def _vm_split(wf: dict) -> dict:
    return {k: wf["split"][k] for k in VM_SPLIT}


def _vm_passes(text: bytes, wf: dict):
    """The passes the virtual machine cuts ``text`` as (parse, then split with :data:`VM_SPLIT`)."""
    from stages.nc.reader import parse_program
    from stages.nc.moves import split_blocks
    nominal = {k: v for k, v in wf["tool"].items() if k != "profile"}
    b, _ = parse_program(text, "vm.nc", "band")
    return split_blocks(b, {"split": _vm_split(wf), "machine": wf["machine"], "tool": nominal})


def _vm_key(text: bytes, wf: dict, *parts) -> str:
    """Content key of a virtual-machine probe: the machine's own code, the passes it cuts ``text``
    as (not the parser's source: a change there that leaves the passes alone keeps the cache) and
    every other input it reads."""
    import hashlib
    h = hashlib.sha256()
    files = sorted((ROOT / "stages" / "virtual_machine").glob("*.py"))
    for f in files + [ROOT / "stages/geometry/paths.py", ROOT / "stages/geometry/cutter.py"]:
        h.update(f.read_bytes())
    import pyarrow as pa
    sink = pa.BufferOutputStream()
    passes = _vm_passes(text, wf)
    with pa.ipc.new_stream(sink, passes.schema) as writer:
        writer.write_table(passes)
    h.update(sink.getvalue().to_pybytes())
    for part in parts:
        h.update(part if isinstance(part, bytes) else json.dumps(part, sort_keys=True, default=str).encode())
    return h.hexdigest()[:24]


def _cached(cache: Path, key: str, compute):
    """``compute()`` (a dict of arrays) once per key, kept as an .npz under ``cache``."""
    f = cache / f"{key}.npz"
    if f.is_file():
        with np.load(f) as z:
            return {k: z[k] for k in z.files}
    out = compute()
    cache.mkdir(parents=True, exist_ok=True)
    tmp = cache / f".{key}.{os.getpid()}.npz"
    np.savez(tmp, **out)
    tmp.replace(f)                              # a killed run leaves no partial entry
    return out


def _machine(text: bytes, rigid: bool, wf: dict, window, step_mm=None):
    """The virtual machine loaded with the passes of ``text`` within ``MARGIN_MM`` of the window.
    The real machine cuts with the real tool (its measured profile); the reference is the nominal
    tool on a rigid machine: the error is deflection plus tool shape, both of which the prediction
    corrects. ``step_mm``: the machine's deflection resolution along the path (None: one deflection
    a pass; the rigid reference has none to resolve)."""
    import pyarrow as pa
    from stages.virtual_machine import VirtualMachine
    x0, x1, y0, y1 = window
    nominal = {k: v for k, v in wf["tool"].items() if k != "profile"}
    passes = _vm_passes(text, wf)
    g = lambda c: passes.column(c).to_numpy()  # noqa: E731
    lo, hi = np.minimum(g("x0_mm"), g("x1_mm")), np.maximum(g("x0_mm"), g("x1_mm"))
    ylo, yhi = np.minimum(g("y0_mm"), g("y1_mm")), np.maximum(g("y0_mm"), g("y1_mm"))
    near = (hi > x0 - MARGIN_MM) & (lo < x1 + MARGIN_MM) & (yhi > y0 - MARGIN_MM) & (ylo < y1 + MARGIN_MM)
    frf = ({a: [{"fn_hz": 900.0, "zeta": 0.03, "k_n_per_um": 1e9}] for a in "xy"} if rigid
           else wf["machine"]["frf"])
    return VirtualMachine(passes.filter(pa.array(near)), nominal if rigid else wf["tool"], wf["material"],
                          {"frf": frf}, wf["stock"], deflection_step_mm=None if rigid else step_mm)


def _machined_error(text: bytes, wf: dict, window, pts, nrm, ideal, step_mm=None) -> dict:
    """Error (µm) of ``text`` machined on the virtual machine at the probe points."""
    return {"err": _machine(text, False, wf, window, step_mm).probe(pts, nrm) - ideal}


SECOND_WALL_DIRS = 72        # horizontal directions tried around each probe's ball centre (5° apart)
SECOND_WALL_DEG = 30.0       # … more than this off the probe's normal
SECOND_WALL_TOUCH_UM = 5.0   # no other pass of the rigid cut deeper than this there
SECOND_WALL_BEHIND_MM = 0.05  # the stock this far behind the point (against d) stands above it
SECOND_WALL_SPACING_MM = 0.05


def second_wall_plan(vm, pts, nrm):
    """Probe points on the walls the ball touches besides the plan's own contact (``--second-walls``).

    The plan (``grid_plan``) has one point per ball-centre position, on the surface its normal
    sees: of a ball in a vertical corner, which finishes both walls, one wall is never probed. Here
    each plan point's ball centre c is tried in :data:`SECOND_WALL_DIRS` horizontal directions d
    more than :data:`SECOND_WALL_DEG` off its normal: the point c − R·d with normal d is kept where
    the stock stands above it :data:`SECOND_WALL_BEHIND_MM` behind it (against d: the ball's side
    meets a wall of the stock there, not the air of the pocket) and no other pass of the rigid cut
    of the original program cuts deeper than :data:`SECOND_WALL_TOUCH_UM` there (the machine's
    probe measures the cut along d from the ball centres of the passes), one point per
    :data:`SECOND_WALL_SPACING_MM`. Returns (points, normals, the rigid cut's deviation there)."""
    c = pts + vm.R * nrm
    a = np.radians(np.arange(SECOND_WALL_DIRS) * 360.0 / SECOND_WALL_DIRS)
    d = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], 1)
    i, k = np.nonzero(nrm @ d.T < np.cos(np.radians(SECOND_WALL_DEG)))
    p, n = c[i] - vm.R * d[k], d[k]
    ideal = vm.probe(p, n) if len(p) else np.zeros(0)
    touch = np.abs(ideal) < SECOND_WALL_TOUCH_UM
    p, n, ideal = p[touch], n[touch], ideal[touch]
    behind = p - SECOND_WALL_BEHIND_MM * n
    keep = p[:, 2] < vm.stock_h(behind[:, 0], behind[:, 1])
    p, n, ideal = p[keep], n[keep], ideal[keep]
    _, first = np.unique(np.round(p / SECOND_WALL_SPACING_MM).astype(np.int64), axis=0, return_index=True)
    first = np.sort(first)
    return p[first], n[first], ideal[first]


def vm_inputs(wf: dict, window, spacing_mm: float) -> list:
    """What the machine's probes depend on besides the program (parts of :func:`_vm_key`); the
    input files by their bytes, not their paths: a run from another checkout (a snapshot
    elsewhere) with the same files keeps the cache."""
    tool = {k: v for k, v in wf["tool"].items() if k != "profile"}
    machine = {**wf["machine"], "frf": {k: v for k, v in wf["machine"]["frf"].items() if k != "table"}}
    inputs = [tool, wf["material"], machine, _vm_split(wf), list(window), spacing_mm]
    for f in (wf["stock"], wf["tool"].get("profile"), wf["machine"]["frf"].get("table")):
        if f:
            inputs.append(Path(f).read_bytes())
    return inputs


def vm_errors(window, programs: dict, wf: dict, spacing_mm: float = 0.1, cache: Path | None = None,
              dump: Path | None = None, predicted=None, vm_step_mm: float | None = None,
              second_walls: bool = False) -> dict:
    """Machine ``programs`` (name → text, "original" first) on the virtual machine and probe them;
    the programs not in ``cache`` are machined side by side, one process a core. ``vm_step_mm``:
    the machine's deflection resolution along the path (None: one deflection a pass, whose
    resolution then follows the program's blocks). ``second_walls``: also probe the walls the
    plan's balls touch besides their own contact (:func:`second_wall_plan`), reported apart
    (``out["second_walls"]``); each program is machined again for them."""
    from concurrent.futures import ProcessPoolExecutor

    import pyarrow as pa
    import pyarrow.parquet as pq
    from stages.virtual_machine import grid_plan, near_passes
    x0, x1, y0, y1 = window
    inputs = vm_inputs(wf, window, spacing_mm)

    def reference():
        vm = _machine(programs["original"], True, wf, window)
        pts, nrm = grid_plan(vm, spacing_mm)
        ok = (pts[:, 0] >= x0) & (pts[:, 0] < x1) & (pts[:, 1] >= y0) & (pts[:, 1] < y1)
        pts, nrm = pts[ok], nrm[ok]
        rows = near_passes(vm.path, pts + vm.R * nrm, 1)[0][:, 0] if len(pts) else np.zeros(0, np.int64)
        return {"pts": pts, "nrm": nrm, "ideal": vm.probe(pts, nrm), "pass_id": vm.path.pass_id[rows]}

    machined = {}

    def probed(text):
        def run():
            return (machined[text] if text in machined
                    else _machined_error(text, wf, window, pts, nrm, ideal, vm_step_mm))
        return (_cached(cache, _vm_key(text, wf, *inputs), run) if cache else run())["err"]

    ref = _cached(cache, _vm_key(programs["original"], wf, b"rigid", *inputs), reference) if cache else reference()
    if vm_step_mm is not None:                  # the machined programs' key; not the rigid reference's
        inputs.append({"deflection_step_mm": float(vm_step_mm)})
    pts, nrm, ideal = ref["pts"], ref["nrm"], ref["ideal"]
    if len(pts) == 0:
        return None
    q = np.degrees(np.arccos(np.clip(nrm[:, 2], -1, 1)))
    out = {"points": int(len(pts)), "q_p50_deg": float(np.median(q)), "q_p90_deg": float(np.percentile(q, 90))}
    cols = {"x_mm": pts[:, 0], "y_mm": pts[:, 1], "z_mm": pts[:, 2], "nx": nrm[:, 0], "ny": nrm[:, 1],
            "nz": nrm[:, 2], "contact_deg": q, "pass_id": ref["pass_id"]}
    if predicted is not None:                   # (pass_id, err_um) of the first round's prediction
        pid, perr = predicted
        lut = dict(zip(pid.tolist(), perr.tolist()))
        cols["predicted_um"] = np.array([lut.get(int(i), np.nan) for i in ref["pass_id"]])
    todo = list(dict.fromkeys(t for t in programs.values()
                              if cache is None or not (cache / f"{_vm_key(t, wf, *inputs)}.npz").is_file()))
    if len(todo) > 1:                           # the machine runs on one core: one program a core
        with ProcessPoolExecutor(min(len(todo), os.cpu_count() or 1)) as pool:
            futures = [pool.submit(_machined_error, t, wf, window, pts, nrm, ideal, vm_step_mm) for t in todo]
            machined.update(zip(todo, (f.result() for f in futures)))
    for name, text in programs.items():
        e = probed(text)
        cols[f"err_{name.replace(' ', '_')}_um"] = e
        out[name] = {"rms_um": float(np.sqrt(np.mean(e ** 2))), "p95_abs_um": float(np.percentile(np.abs(e), 95)),
                     "max_abs_um": float(np.abs(e).max())}
        for lo, hi, band in Q_BANDS:
            m = (q >= lo) & (q < hi)
            out[name][band] = {"points": int(m.sum()), "rms_um": float(np.sqrt(np.mean(e[m] ** 2))) if m.any() else None}
    if dump is not None:
        pq.write_table(pa.table(cols), dump)
    if second_walls:
        def plan2():
            vm = _machine(programs["original"], True, wf, window)
            p2, n2, i2 = second_wall_plan(vm, pts, nrm)
            ok = (p2[:, 0] >= x0) & (p2[:, 0] < x1) & (p2[:, 1] >= y0) & (p2[:, 1] < y1)
            return {"pts": p2[ok], "nrm": n2[ok], "ideal": i2[ok]}
        plan_parts = [b"second-walls", SECOND_WALL_DIRS, SECOND_WALL_DEG, SECOND_WALL_TOUCH_UM,
                      SECOND_WALL_BEHIND_MM, SECOND_WALL_SPACING_MM]
        ref2 = (_cached(cache, _vm_key(programs["original"], wf, b"rigid", *plan_parts, *inputs), plan2) if cache
                else plan2())
        p2, n2, i2 = ref2["pts"], ref2["nrm"], ref2["ideal"]
        out["second_walls"] = {"points": int(len(p2))}
        if len(p2):
            key2 = lambda t: _vm_key(t, wf, *plan_parts, *inputs)  # noqa: E731
            todo2 = list(dict.fromkeys(t for t in programs.values()
                                       if cache is None or not (cache / f"{key2(t)}.npz").is_file()))
            done2 = {}
            with ProcessPoolExecutor(max(1, min(len(todo2), os.cpu_count() or 1))) as pool:
                futures = [pool.submit(_machined_error, t, wf, window, p2, n2, i2, vm_step_mm) for t in todo2]
                done2.update(zip(todo2, (f.result() for f in futures)))
            for name, text in programs.items():
                e = (_cached(cache, key2(text), lambda text=text: done2[text]) if cache else done2[text])["err"]
                out["second_walls"][name] = {"rms_um": float(np.sqrt(np.mean(e ** 2))),
                                             "max_abs_um": float(np.abs(e).max())}
    return out


def run_in_group(cmd: list, cwd: Path) -> tuple[int, str, str]:
    """Run ``cmd`` (the pipeline and its Dask workers) in a process group of its own, killed with
    the bench: a bench stopped by SIGTERM or Ctrl-C leaves no pipeline writing into its run
    directory behind it."""
    import signal
    proc = subprocess.Popen(cmd, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        out, err = proc.communicate()
    except BaseException:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait()
        raise
    return proc.returncode, out, err


def main():
    import yaml
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="/tmp/closed_loop_pipeline_samples")
    ap.add_argument("--keep", action="store_true", help="keep the pipeline's cache of an earlier run")
    ap.add_argument("--prune", type=float, default=None,
                    help="predict (and so correct) passes from this contact angle on; default: the "
                         "sample workflow's 45° (floors below it are left as machined)")
    ap.add_argument("--max-move", type=float, default=None,
                    help="clip of the vertex moves, µm; default: the sample workflow's correct.max_move_um")
    ap.add_argument("--whole", action="store_true", help="the whole program, probed over the whole part")
    ap.add_argument("--correct", action="append", default=[], metavar="KEY=VALUE",
                    help="a workflow `correct` option for both runs (repeatable), e.g. relax=0.5")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE", dest="other",
                    help="any other workflow value for both runs (repeatable), e.g. split.max_pass_mm=0.5")
    ap.add_argument("--workers", type=int, default=1, help="Dask workers of the pipeline runs")
    ap.add_argument("--spacing", type=float, default=0.1, help="probe spacing along the passes, mm")
    ap.add_argument("--vm-step-mm", type=float, default=None,
                    help="the virtual machine's deflection resolution along the path, mm (default: one "
                         "deflection a pass)")
    ap.add_argument("--rounds", default="1,3", help="round counts of the corrected programs, comma-separated")
    ap.add_argument("--program", type=Path, default=PROGRAM,
                    help="the NC program (windows are cut from it as raster rows along X)")
    ap.add_argument("--workflow", type=Path, default=WORKFLOW,
                    help="the workflow whose tool, material, machine, stock and settings the runs use")
    ap.add_argument("--second-walls", action="store_true",
                    help="also probe the walls the balls touch besides the plan's own contact (a ball in a "
                         "vertical corner finishes two walls; the plan probes one), reported apart")
    ap.add_argument("window", nargs="*", type=float)
    args = ap.parse_args()
    wins = [tuple(args.window[i:i + 4]) for i in range(0, len(args.window), 4)] or list(WINDOWS)
    if args.whole:
        wins = [(-1e9, 1e9, -1e9, 1e9)]
    src = args.program.resolve().read_bytes()
    report = []
    for w in wins:
        root = Path(args.out) / ("whole" if args.whole else "x%g-%g_y%g-%g" % w)
        if not args.keep:
            shutil.rmtree(root / "out", ignore_errors=True)
        (root / "nc").mkdir(parents=True, exist_ok=True)
        band = src if args.whole else window_program(src, w[0] - MARGIN_MM, w[1] + MARGIN_MM, w[2] - 1.0, w[3] + 1.0,
                                                      args.program.name)
        (root / "nc" / "band.nc").write_bytes(band)
        written, wall = {"original": band}, {}
        for mi in sorted(int(r) for r in args.rounds.split(",")):
            t0 = time.perf_counter()
            rc, out, err = run_in_group([sys.executable, "-m", "pipeline.cli", "run",
                                         str(workflow(root, mi, args.prune, args.max_move, args.correct, args.other,
                                                      args.workflow.resolve())),
                                         "--workers", str(args.workers), "-q"], cwd=root)
            wall[mi] = round(time.perf_counter() - t0, 1)
            if rc != 0:
                raise SystemExit(out + err)
            written[f"{mi} round{'s' if mi > 1 else ''}"] = (root / "out" / "nc" / "band.nc").read_bytes()
        run = json.loads((root / "out" / "run.json").read_text())
        rounds = run.get("correct_rounds", {}).get("band", [])
        t0 = time.perf_counter()
        import pyarrow.parquet as pq
        errs = pq.read_table(root / "out" / "tables" / "errors", columns=["pass_id", "err_um"])
        wf_used = yaml.safe_load(next(root.glob("wf*.yaml")).read_text())
        # the machine cuts the program as the base workflow splits it, whatever `--set split.*` gave
        # the pipeline: finer predicted passes must not change the machine, its probe points or the
        # cache of the original's machined error
        base_split = yaml.safe_load(args.workflow.read_text())["split"]
        wf_used["split"].update({k: base_split[k] for k in VM_SPLIT})
        res = vm_errors(w, written, wf_used, args.spacing, cache=Path(args.out) / "vm_cache",
                        dump=root / "points.parquet",
                        predicted=(errs.column("pass_id").to_numpy(), errs.column("err_um").to_numpy()),
                        vm_step_mm=args.vm_step_mm, second_walls=args.second_walls)
        if res is None:
            print(f"window x {w[0]:g}–{w[1]:g}, y {w[2]:g}–{w[3]:g}: no probe point of the plan in it, skipped")
            continue
        res.update({"window": w, "pipeline_wall_s": wall, "vm_wall_s": round(time.perf_counter() - t0, 1),
                    "rounds": [{k: r[k] for k in ("round", "n_errors", "rms_dev_um", "max_change_um")} for r in rounds]})
        base = res["original"]["rms_um"]
        where = "whole program" if args.whole else f"window x {w[0]:g}–{w[1]:g}, y {w[2]:g}–{w[3]:g}"
        print(f"{where}: {res['points']} probe points "
              f"(median q {res['q_p50_deg']:.0f}°), pipeline wall s {wall}, VM {res['vm_wall_s']} s")
        for r in res["rounds"]:
            print(f"  round {r['round']}: {r['n_errors']} predicted passes, predicted deviation RMS "
                  f"{r['rms_dev_um']} um, max change {r['max_change_um']:.3f} um")
        for name in written:
            v = res[name]
            print(f"  virtual machine, {name:>12}: error RMS {v['rms_um']:.3f} um ({100 * v['rms_um'] / base:.1f} % of before), "
                  f"P95 {v['p95_abs_um']:.2f} um, max {v['max_abs_um']:.2f} um; by q: "
                  + ", ".join(f"{b} {v[b]['rms_um']:.2f} um ({v[b]['points']} pts)" for _, _, b in Q_BANDS
                              if v[b]['rms_um'] is not None))
        if "second_walls" in res:
            sw = res["second_walls"]
            print(f"  second walls (not in the figures above): {sw['points']} probe points"
                  + "".join(f"; {name} RMS {sw[name]['rms_um']:.2f} um ({100 * sw[name]['rms_um'] / sw['original']['rms_um']:.1f} %), "
                            f"max {sw[name]['max_abs_um']:.1f} um" for name in written if name in sw))
        report.append(res)
    Path(args.out, "summary.json").write_text(json.dumps(report, indent=1, default=str))


if __name__ == "__main__":
    import signal
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))   # SystemExit reaches run_in_group
    os.chdir(ROOT)
    main()
