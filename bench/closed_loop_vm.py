"""Closed loop of the whole pipeline on the seed's cylinder benchmark, checked on the gap issue's
virtual machine (issue 5 must-show; not a CI test: the render chain takes minutes here).

Seed 000 Fig. 16 set-up (Ø20 ball, 2 flutes, 6000 min⁻¹, 0.4 mm/tooth, 0.63 mm pitch, 0.2 mm depth,
51 z-level passes along a cylinder from q = 0° to 89°, a 6 mm long stock): ``pipeline run`` predicts
the error of every level (render → forces → deflection → errors) and writes the corrected program
with ``correct.max_iter`` = 1 and = 3. The original and both corrected programs are then machined on
``stages/virtual_machine/`` (discrete flutes, time-domain dynamics, its own engagement; no shared
prediction code) and probed on the design cylinder; the error is measured against the original
program machined on a rigid machine (so the cusps, which no correction removes, are not counted).

    python3 bench/closed_loop_vm.py [--out /tmp/closed_loop_vm] [--correct KEY=VALUE ...]
        [--max-pass-mm MM] [--vm-step-mm MM] [--workers N] [--rounds 1,3] [--keep]

``--keep`` reuses the pipeline cache of an earlier run in ``--out`` (same options), so a run that
was cut off resumes where it stopped.
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

R, PITCH, DEPTH, LENGTH = 10.0, 0.63, 0.2, 6.0
N_LEVELS, Q_MAX = 50, 89.0
DQ = np.radians(Q_MAX / N_LEVELS)
RC = PITCH / DQ
Y_END = LENGTH / 2 + R + 2.0
TOOL = {"type": "ball", "diameter_mm": 20.0, "flutes": 2, "helix_deg": 30.0, "stickout_mm": 40.0,
        "runout_um": 0.0, "control_point": "tip"}
MATERIAL = {"name": "FCD550", "ktc": 2000, "krc": 700, "kac": 300, "kte": 20, "kre": 15, "kae": 5}
K = 2.0   # N/µm, the machine of tests/test_chain_cylinder.py


def program() -> bytes:
    lines = ["%", "O3002 (CYLINDER BENCHMARK FIG 16)", "G90 G17 G21", "T1 M6", "S6000 M3"]
    for i, k in enumerate(range(-1, N_LEVELS + 2)):
        q = k * DQ
        x, z = (RC + R) * np.sin(q), (RC + R) * np.cos(q) - R
        ys = (-Y_END, Y_END) if i % 2 == 0 else (Y_END, -Y_END)
        if i == 0:
            lines += [f"G0 X{x:.4f} Y{ys[0]:.4f} Z{z + 30:.4f}", f"G1 Z{z:.4f} F4800"]
        else:
            lines.append(f"X{x:.4f} Y{ys[0]:.4f} Z{z:.4f}")
        lines.append(f"Y{ys[1]:.4f}")
    lines += ["G0 Z60.0000", "M30", "%", ""]
    return "\n".join(lines).encode()


def workflow(root: Path, max_iter: int, correct_opts=(), max_pass_mm: float = 40.0) -> Path:
    import yaml
    wf = {"name": "cyl", "programs": "nc/*.nc", "stock": "stock.stl", "tool": TOOL, "material": MATERIAL,
          "machine": {"frf": {a: [{"fn_hz": 900, "zeta": 0.03, "k_n_per_um": K}] for a in "xy"}},
          "render": {"backend": "auto", "px_per_mm": 20}, "prune": {"min_contact_deg": 0},
          "split": {"max_pass_mm": max_pass_mm}, "output": "out",
          "correct": {"max_move_um": 100, "tol_um": 0.05, "max_iter": max_iter}}
    for kv in correct_opts:                      # e.g. relax=0.5
        k, _, v = kv.partition("=")
        wf["correct"][k] = yaml.safe_load(v)
    p = root / f"wf{max_iter}.yaml"
    p.write_text(yaml.safe_dump(wf))
    return p


def vm_errors(stock: Path, programs: dict, step_mm: float | None = None) -> dict:
    from stages.nc.reader import parse_program
    from stages.nc.moves import split_blocks
    from stages.virtual_machine import VirtualMachine
    split = {"split": {"chord_tol_mm": 0.001, "max_pass_mm": 40.0, "merge_max_mm": 0.5},
             "machine": {"rapid_mm_min": 30000.0}, "tool": TOOL}
    qq, yy = np.meshgrid(np.radians(np.linspace(0.0, Q_MAX, 179)), np.linspace(-2.5, 2.5, 11))
    n = np.stack([np.sin(qq.ravel()), np.zeros(qq.size), np.cos(qq.ravel())], 1)
    pts = RC * n + np.stack([np.zeros(qq.size), yy.ravel(), np.zeros(qq.size)], 1)

    def probe(text, k):
        b, _ = parse_program(text, "vm.nc", "cyl")
        machine = {"frf": {a: [{"fn_hz": 900, "zeta": 0.03, "k_n_per_um": k}] for a in "xy"}, "table": None}
        return VirtualMachine(split_blocks(b, split), TOOL, MATERIAL, machine, str(stock),
                              deflection_step_mm=step_mm).probe(pts, n)
    ideal = probe(programs["original"], 1e9)
    out = {}
    for name, text in programs.items():
        e = probe(text, K) - ideal
        qd = np.degrees(qq.ravel())
        out[name] = {"rms_um": float(np.sqrt(np.mean(e ** 2))), "max_abs_um": float(np.abs(e).max()),
                     "rms_q60_89_um": float(np.sqrt(np.mean(e[qd >= 60] ** 2)))}
    return out


def main():
    import trimesh
    from click.testing import CliRunner
    from pipeline.cli import main as cli
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="/tmp/closed_loop_vm")
    ap.add_argument("--correct", action="append", default=[], metavar="KEY=VALUE",
                    help="a workflow `correct` option for both runs (repeatable), e.g. relax=0.5")
    ap.add_argument("--max-pass-mm", type=float, default=40.0,
                    help="the pipeline's split.max_pass_mm (the machine cuts the levels as 40 mm passes)")
    ap.add_argument("--vm-step-mm", type=float, default=None,
                    help="the virtual machine's deflection resolution along the path, mm (default: one "
                         "deflection a pass)")
    ap.add_argument("--workers", type=int, default=1, help="Dask workers of the pipeline runs")
    ap.add_argument("--rounds", default="1,3", help="round counts of the corrected programs, comma-separated")
    ap.add_argument("--keep", action="store_true", help="keep the pipeline's cache of an earlier run in --out")
    args = ap.parse_args()
    root = Path(args.out)
    if not args.keep:
        shutil.rmtree(root, ignore_errors=True)
    (root / "nc").mkdir(parents=True, exist_ok=True)
    src = program()
    (root / "nc" / "cyl.nc").write_bytes(src)
    stock = trimesh.creation.cylinder(radius=RC + DEPTH, height=LENGTH, sections=720)
    stock.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    stock.export(root / "stock.stl")
    written, timings = {"original": src}, {}
    for mi in sorted(int(r) for r in args.rounds.split(",")):
        name = f"{mi} round{'s' if mi > 1 else ''}"
        t0 = time.perf_counter()
        r = CliRunner().invoke(cli, ["run", str(workflow(root, mi, args.correct, args.max_pass_mm)),
                                     "--workers", str(args.workers), "-q"], catch_exceptions=False)
        timings[name] = round(time.perf_counter() - t0, 1)
        if r.exit_code != 0:
            raise SystemExit(r.output)
        written[name] = (root / "out" / "nc" / "cyl.nc").read_bytes()
    rounds = json.loads((root / "out" / "run.json").read_text())["correct_rounds"]["cyl"]
    res = vm_errors(root / "stock.stl", written, args.vm_step_mm)
    base = res["original"]["rms_um"]
    print(f"cylinder benchmark (Ø20, rc {RC:.2f} mm, {N_LEVELS + 1} levels q 0–{Q_MAX:g}°, k {K} N/µm); "
          f"pipeline run wall s: {timings}")
    for r in rounds:
        dev = "–" if r["rms_dev_um"] is None else f"{r['rms_dev_um']:.3f}"   # only the first round has one
        print(f"  round {r['round']}: predicted deviation from the original surface RMS {dev} um "
              f"({r['n_errors']} passes), max change {r['max_change_um']:.3f} um")
    for name, v in res.items():
        print(f"  virtual machine, {name:>12}: error RMS {v['rms_um']:.3f} um ({100 * v['rms_um'] / base:.1f} % of before), "
              f"max |e| {v['max_abs_um']:.2f} um, RMS at q 60–89° {v['rms_q60_89_um']:.3f} um")


if __name__ == "__main__":
    main()
