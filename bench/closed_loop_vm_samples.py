"""Measured-error correction of the sample finishing program on the gap issue's virtual machine
(issue 5 closed loop; a bench, not a CI test: ~30–60 s per window).

For a window of data_samples/nc/mould_finish_t1.nc: the passes near it are machined on
``stages/virtual_machine.py`` (discrete flutes, time-domain dynamics, the semi-finished stock) and
probed on its own plan (``grid_plan``, 0.1 mm); the error is against the original program cut on a
rigid machine. Each probe point's error goes to the pass nearest its ball centre (per-pass mean),
``stages.correct.correct_iteratively`` corrects (4 rounds, tol 0.2 µm, like tests/test_correct.py),
the written program is machined again.

    python3 bench/closed_loop_vm_samples.py [X0 X1 Y0 Y1 ...]   (default: three windows)
"""
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow as pa

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def window(win, K=2.0):
    import tests.test_correct as T
    from stages.correct import correct_iteratively
    from stages.gap_geometry import nearest_pass
    from stages.nc_writer import reverse_check, write_program
    from stages.parse import parse_program
    from stages.split import split_blocks
    from stages.virtual_machine import VirtualMachine, grid_plan
    x0, x1, y0, y1 = win
    src = open("data_samples/nc/mould_finish_t1.nc", "rb").read()
    tool = {"type": "ball", "diameter_mm": 10.0, "flutes": 2, "helix_deg": 30.0, "runout_um": 0.0, "control_point": "tip"}
    material = {"ktc": 2000, "krc": 700, "kac": 300, "kte": 20, "kre": 15, "kae": 5}
    split = T.SPLIT
    _b0, _ = parse_program(src, "vm", "p")
    _p0 = split_blocks(_b0, split)
    def _sub0(passes):
        g = lambda c: passes.column(c).to_numpy()
        lo = np.minimum(g("x0_mm"), g("x1_mm")); hi = np.maximum(g("x0_mm"), g("x1_mm"))
        ylo = np.minimum(g("y0_mm"), g("y1_mm")); yhi = np.maximum(g("y0_mm"), g("y1_mm"))
        return passes.filter(pa.array((hi > x0 - 7) & (lo < x1 + 7) & (yhi > y0 - 7) & (ylo < y1 + 7)))
    _vm0 = VirtualMachine(_sub0(_p0), tool, material, {"frf": {a: [{"fn_hz": 900, "zeta": 0.03, "k_n_per_um": 1e9}] for a in "xy"}, "table": None}, "data_samples/models/semi.stl")
    pts, nrm = grid_plan(_vm0, 0.1)
    ok = (pts[:, 0] >= x0) & (pts[:, 0] < x1) & (pts[:, 1] >= y0) & (pts[:, 1] < y1)
    pts, nrm = pts[ok], nrm[ok]
    print("probe points", len(pts))
    def sub(passes):
        g = lambda c: passes.column(c).to_numpy()
        lo = np.minimum(g("x0_mm"), g("x1_mm")); hi = np.maximum(g("x0_mm"), g("x1_mm"))
        ylo = np.minimum(g("y0_mm"), g("y1_mm")); yhi = np.maximum(g("y0_mm"), g("y1_mm"))
        m = (hi > x0 - 7) & (lo < x1 + 7) & (yhi > y0 - 7) & (ylo < y1 + 7)
        return passes.filter(pa.array(m))
    def probe(blocks, stiff):
        machine = {"frf": {a: [{"fn_hz": 900, "zeta": 0.03, "k_n_per_um": stiff}] for a in "xy"}, "table": None}
        passes = split_blocks(blocks, split)
        s = sub(passes)
        vm = VirtualMachine(s, tool, material, machine, "data_samples/models/semi.stl")
        return vm.probe(pts, nrm), passes, vm
    t0 = time.time()
    b0, _ = parse_program(src, "vm", "p")
    ideal, _, _ = probe(b0, 1e9)
    print("ideal probe %.1f s" % (time.time() - t0), "ideal mean %.2f" % ideal.mean())
    rms = []
    def predict(blocks):
        e, passes, vm = probe(blocks, K)
        e = e - ideal
        rms.append(float(np.sqrt(np.mean(e ** 2))))
        row, _, _ = nearest_pass(vm.path, pts + 5.0 * nrm)
        pid = vm.path.pass_id[row]
        n = passes.num_rows
        cnt = np.bincount(pid, minlength=n)
        em = np.bincount(pid, e, n) / np.maximum(cnt, 1)
        nn = np.stack([np.bincount(pid, nrm[:, i], n) for i in range(3)], 1)
        have = cnt >= 3
        nn[have] /= np.linalg.norm(nn[have], axis=1)[:, None]
        return passes, T._errors(passes, em, nn).filter(pa.array(have))
    cor = correct_iteratively(b0, predict, {"correct": {"max_move_um": 100.0, "tol_um": 0.2, "max_iter": 4}})
    out = write_program(src, b0, cor)
    assert reverse_check(out, b0, cor)["ok"]
    e, _, _ = probe(parse_program(out, "c", "p")[0], K)
    final = float(np.sqrt(np.mean((e - ideal) ** 2)))
    print(f"window x{x0:g}-{x1:g} y{y0:g}-{y1:g}, {len(pts)} probe points:", "RMS error per round", ["%.2f" % r for r in rms], "written %.2f = %.1f %%  (%.0f s)" % (final, 100 * final / rms[0], time.time() - t0))


if __name__ == "__main__":
    import os
    os.chdir(Path(__file__).resolve().parents[1])
    args = [float(a) for a in sys.argv[1:]]
    wins = [tuple(args[i:i + 4]) for i in range(0, len(args), 4)] or [
        (14.0, 24.0, 34.0, 44.0), (45.0, 57.0, 40.0, 50.0), (75.0, 87.0, 36.0, 44.0)]
    for w in wins:
        window(w)
