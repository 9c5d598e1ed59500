"""How much of the machined error of the sample finishing program is the spindle's phase (issue 5;
a bench, not a CI test: one virtual-machine load a program, ~15 min each at 0.5 mm, side by side).

The virtual machine cuts every probe point with discrete tooth passages whose spindle angle follows
the program's clock (``stages/virtual_machine/``: θ = 360° t / T, t from the program's start). A
real spindle starts at an angle nobody sets, so the same program cut twice leaves a surface that
differs wherever the surface depends on which flute passes where (a buried ball, a corner fillet
finished by a few passages); and any correction, which changes the path's length and so every later
passage's phase, changes that part of the error as well, whether or not it changes the point's
geometry. Here each program is loaded once and probed with the spindle started at ``--angles``
angles evenly spread over one tooth period (one revolution with runout; every pass's times shifted
by the same fraction of it; angle 0 is the bench's own machining, checked against its cache):

- per program, the mean square of the error at each angle, and its split into the part the angles
  share (the mean square of each point's mean over the angles) and the part they do not (the mean
  over the points of each point's variance over the angles, with n − 1): the phase part no path
  correction controls;
- the corrected programs' RMS over the original's, at each angle and from the mean squares averaged
  over the angles.

The error is taken against the bench's rigid reference at angle 0; the rigid cut's own feed marks
move with the angle too, but at the sample's 0.125 mm a tooth on a Ø10 ball they are at most
0.4 µm deep. ``tests/test_virtual_machine.py::test_the_spindle_s_start_angle_repeats_after_a_tooth_period_without_runout_and_a_revolution_with``
checks the period the angles are spread over.

It reads a run directory of ``bench/closed_loop_pipeline_samples.py --whole`` (its ``nc/band.nc``,
``wf1.yaml`` and the rigid reference in ``<run>/../vm_cache``) and programs named there (default: the
original only). The probes of every angle are cached under the same ``vm_cache``.

    python3 bench/spindle_phase_samples.py RUN_DIR [PROGRAM.nc ...] [--angles 8] [--vm-step-mm 0.5]
"""
from __future__ import annotations

import argparse
import os
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))
WHOLE = (-1e9, 1e9, -1e9, 1e9)


def probe_at_angles(text: bytes, wf: dict, pts, nrm, ideal, angles: int, step_mm: float) -> dict:
    """Error (µm) of ``text`` machined once and probed with the spindle started at k/``angles`` of
    its period, k = 0 … angles − 1: {"err": (angles, points)}. The period is one revolution, or
    one tooth period where the flutes are alike (no runout: a start half a revolution on with two
    flutes is the same cut)."""
    import closed_loop_pipeline_samples as bench
    vm = bench._machine(text, False, wf, WHOLE, step_mm)
    t0, t1 = vm.path.t0.copy(), vm.path.t1.copy()
    period_s = 60.0 / vm.path.rpm               # per pass: one revolution at its own speed
    if vm.base_runout == 0.0:
        period_s = period_s / vm.flutes
    out = []
    for k in range(angles):
        vm.path.t0, vm.path.t1 = t0 + k / angles * period_s, t1 + k / angles * period_s
        out.append(vm.probe(pts, nrm) - ideal)
    return {"err": np.stack(out)}


def phase_split(err):
    """(angles, points) errors → mean square at each angle, the shared part (the mean square of the
    points' means over the angles) and the phase part (the mean of the points' variances, n − 1)."""
    err = np.asarray(err, float)
    return (np.mean(err ** 2, axis=1), float(np.mean(err.mean(axis=0) ** 2)),
            float(np.mean(err.var(axis=0, ddof=1))))


def main():
    import yaml

    import closed_loop_pipeline_samples as bench

    ap = argparse.ArgumentParser()
    ap.add_argument("run", type=Path, help="a run directory of bench/closed_loop_pipeline_samples.py --whole")
    ap.add_argument("programs", nargs="*", help="more programs in the run directory (file names)")
    ap.add_argument("--angles", type=int, default=8)
    ap.add_argument("--vm-step-mm", type=float, default=0.5)
    args = ap.parse_args()
    run = args.run.resolve()
    wf = yaml.safe_load((run / "wf1.yaml").read_text())
    cache = run.parent / "vm_cache"
    src = (run / "nc" / "band.nc").read_bytes()
    inputs = bench.vm_inputs(wf, WHOLE, 0.1)
    ref_file = cache / f"{bench._vm_key(src, wf, b'rigid', *inputs)}.npz"
    if not ref_file.is_file():
        raise SystemExit(f"{ref_file}: no rigid reference; run bench/closed_loop_pipeline_samples.py --whole first")
    with np.load(ref_file) as z:
        pts, nrm, ideal = z["pts"], z["nrm"], z["ideal"]
    inputs.append({"deflection_step_mm": float(args.vm_step_mm)})
    texts = {"original": src, **{name: (run / name).read_bytes() for name in args.programs}}
    keys = {name: bench._vm_key(t, wf, *inputs, b"spindle start angles a tooth period", args.angles)
            for name, t in texts.items()}
    todo = [n for n in texts if not (cache / f"{keys[n]}.npz").is_file()]
    with ProcessPoolExecutor(max(1, min(len(todo), os.cpu_count() or 1))) as pool:
        futures = {n: pool.submit(probe_at_angles, texts[n], wf, pts, nrm, ideal, args.angles, args.vm_step_mm)
                   for n in todo}
        err = {n: bench._cached(cache, keys[n], futures[n].result if n in futures else None)["err"] for n in texts}
    for name, text in texts.items():             # angle 0 is the bench's own machining
        own = cache / f"{bench._vm_key(text, wf, *inputs)}.npz"
        if own.is_file():
            with np.load(own) as z:
                if not np.allclose(z["err"], err[name][0], atol=1e-9):
                    raise SystemExit(f"{name}: angle 0 does not reproduce the machine's cached probe")
    base, _, _ = phase_split(err["original"])
    print(f"{len(pts)} probe points, {args.angles} spindle start angles, machine at {args.vm_step_mm:g} mm")
    for name in texts:
        ms, shared, phase = phase_split(err[name])
        ratio = 100 * np.sqrt(ms / base)
        print(f"{name:32s} mean square {ms.min():7.2f}…{ms.max():7.2f} um^2 (mean {ms.mean():7.2f}): shared "
              f"{shared:7.2f}, phase {phase:5.2f}; % of the original's at the same angle "
              f"{ratio.min():5.1f}…{ratio.max():5.1f}, of the means {100 * np.sqrt(ms.mean() / base.mean()):5.1f}")


if __name__ == "__main__":
    os.chdir(ROOT)
    main()
