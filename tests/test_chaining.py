"""Programs chained on one stock (DESIGN §3): each program meets what the stock and the earlier
programs of its job leave, and a changed program recomputes itself and the later ones only."""
from __future__ import annotations

import json

import numpy as np
import pandas as pd
import yaml
from hypothesis import given, settings, strategies as st

from tests.test_iterate import _run, _workflow

R = 5.0                  # Ø10 ball
TOP = 0.3                # box stock top over the floor z = 0
FIRST_Z = 0.15           # program 1 takes the stock down to here over rows y = 4…9


def _program(number: int, z: float, ys, x_end: float = 18.0) -> str:
    zig = []
    for k, y in enumerate(ys):
        zig += [f"G1 Y{y:.1f}", f"G1 X{x_end if k % 2 == 0 else 2.0:.1f} Y{y:.1f}"]
    return "\n".join(["%", f"O{number} (ROWS)", "G90 G17 G21", "T1 M6", "S8000 M3", f"G0 X2.0 Y{ys[0]:.1f} Z5.0",
                      f"G1 Z{z:.2f} F1500", *zig, "G0 Z5.0", "M30", "%", ""])


def _job(tmp_path):
    (tmp_path / "nc").mkdir()
    (tmp_path / "nc" / "a_first.nc").write_text(_program(1, FIRST_Z, range(4, 10)))
    (tmp_path / "nc" / "b_second.nc").write_text(_program(2, 0.0, range(6, 14)))
    import trimesh
    trimesh.creation.box(bounds=[[0, 0, -5], [20, 20, TOP]]).export(tmp_path / "stock.stl")
    path = _workflow(tmp_path, max_iter=1, until="warn")
    wf = yaml.safe_load(path.read_text())
    wf["tool"]["diameter_mm"] = 2 * R
    path.write_text(yaml.safe_dump(wf))
    return path, wf


def _in_capsules(pts, c0, c1):
    """Whether points lie inside any of the balls' sweeps (centre segments c0 → c1, radius R − 1 µm)."""
    out = np.zeros(len(pts), bool)
    for a0, a1 in zip(c0, c1):
        d = a1 - a0
        s = np.clip(((pts - a0) @ d) / max(d @ d, 1e-12), 0, 1)
        out |= np.linalg.norm(pts - (a0 + s[:, None] * d), axis=1) < R - 1e-3
    return out


def test_program_2_meets_the_stock_program_1_left(tmp_path):
    # brute force, sharing nothing with the scans: the material before a pass of program 2 at its
    # prediction point is the box less the capsules swept by the ball centres of every pass of
    # program 1, of the earlier passes of program 2 and of its own path up to that point; the
    # stock met is the largest (p − G)·n over the tool's envelope points in it
    path, wf = _job(tmp_path)
    _run(path)
    t = tmp_path / "out" / "tables"
    a = pd.read_parquet(t / "allowance")
    a = a[a.program_id == "b_second"].dropna().set_index("pass_id").stock_mm
    gen = pd.read_parquet(t / "generating").query("program_id == 'b_second'").set_index("pass_id")
    cf = pd.read_parquet(t / "cut_filter").query("program_id == 'b_second'").set_index("pass_id")
    passes = pd.read_parquet(t / "passes")
    p1 = passes[passes.program_id == "a_first"]
    p2 = passes[passes.program_id == "b_second"].set_index("pass_id")
    centres = lambda p, e: p[[f"x{e}_mm", f"y{e}_mm", f"z{e}_mm"]].to_numpy() + [0, 0, R]  # noqa: E731
    z = (np.arange(360) + 0.5) * R / 180
    z = z[z < R]
    r = np.sqrt(R ** 2 - (R - z) ** 2)
    ang = np.radians(np.arange(0, 360, 2.0))
    ids = p2.index.to_numpy()
    tol = R / 180 + 1.0 / wf["render"]["px_per_mm"]
    inside_first = 0
    assert len(a) >= 8
    for pid, got in a.items():
        tip = cf.loc[pid, ["pred_x_mm", "pred_y_mm", "pred_z_mm"]].to_numpy(float)
        pts = np.stack([tip[0] + r[:, None] * np.cos(ang), tip[1] + r[:, None] * np.sin(ang),
                        np.broadcast_to(tip[2] + z[:, None], (len(z), len(ang)))], -1).reshape(-1, 3)
        mat = (pts[:, 2] < TOP) & (pts[:, :2] > 0).all(1) & (pts[:, :2] < 20).all(1)
        mat &= ~_in_capsules(pts, centres(p1, 0), centres(p1, 1))
        k = int(np.flatnonzero(ids == pid)[0])
        mat &= ~_in_capsules(pts, centres(p2, 0)[:k], centres(p2, 1)[:k])
        mat &= ~_in_capsules(pts, centres(p2, 0)[k:k + 1], (tip + [0, 0, R] - 1e-3 * (centres(p2, 1)[k] - centres(p2, 0)[k]))[None])
        G = gen.loc[pid, ["gen_x_mm", "gen_y_mm", "gen_z_mm"]].to_numpy(float)
        n = gen.loc[pid, ["nx", "ny", "nz"]].to_numpy(float)
        brute = ((pts[mat] - G) @ n).max()
        assert abs(got - brute) <= tol, (pid, got, brute)
        # a row inside program 1's area, its tool short of the area's edge at y ≈ 10.2: the floor
        # program 1 left (the box's 0.3 mm would be outside the bound)
        if tip[1] <= 8.0 and abs(n[2]) > 0.999:
            inside_first += 1
            assert abs(got - FIRST_Z) <= tol + R - np.sqrt(R ** 2 - 0.25), (pid, got)   # + program 1's cusp
    assert inside_first >= 3


def _stage_counts(out):
    run = json.loads((out / "run.json").read_text())
    return {s["name"]: (s["computed"], s["cached"]) for s in run["stages"]}


def test_a_changed_program_recomputes_itself_and_the_later_programs_only(tmp_path):
    path, _ = _job(tmp_path)
    _run(path)
    out = tmp_path / "out"
    (tmp_path / "nc" / "b_second.nc").write_text(_program(2, 0.0, range(6, 14), x_end=17.5))
    _run(path)
    counts = _stage_counts(out)
    assert counts["parse"] == (1, 1) and counts["scan"] == (1, 1) and counts["forces"] == (1, 1), counts
    (tmp_path / "nc" / "a_first.nc").write_text(_program(1, FIRST_Z, range(4, 10), x_end=17.5))
    _run(path)
    counts = _stage_counts(out)
    assert counts["parse"] == (1, 1) and counts["scan"] == (2, 0), counts


def test_a_failed_earlier_program_fails_the_later_ones_with_the_reason(tmp_path):
    path, _ = _job(tmp_path)
    (tmp_path / "nc" / "a_first.nc").write_text("%\nO1\nG1 X1 Y1 Z1 F100\nG66 P9010\nM30\n%\n")
    from click.testing import CliRunner
    from pipeline.cli import main
    r = CliRunner().invoke(main, ["run", str(path), "--workers", "1", "-q"], catch_exceptions=False)
    assert r.exit_code != 0
    assert "machined after a_first, which failed" in r.output, r.output
    failures = json.loads((tmp_path / "out" / "run.json").read_text())["failures"]
    second = [f for f in failures if f["program_id"] == "b_second"]
    assert len(second) == 1 and second[0]["stage"] == "scan", failures
    assert "machined after a_first, which failed (nc/a_first.nc:4" in second[0]["message"], second


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2 ** 31 - 1))
def test_removed_points_are_those_inside_any_earlier_sweep(seed):
    # the binned look-up of Earlier.removed against every (point, pass) pair tested directly
    from stages.geometry.clearance import inside_sweep
    from stages.geometry.cutter import Cutter
    from stages.geometry.passes import PassGeometry
    from stages.geometry.workpiece import box_workpiece
    from stages.surface.chain import Earlier
    rng = np.random.default_rng(seed)
    wp = box_workpiece([0, 0, -5, 30, 30, 1])
    programs = []
    for d in (10.0, 4.0):
        n = int(rng.integers(1, 40))
        p0 = rng.uniform([0, 0, -3], [30, 30, 1], (n, 3))
        p1 = p0 + rng.normal(0, 4, (n, 3)) * [1, 1, 0.2]
        pg = PassGeometry("p", np.arange(n), np.ones(n, np.int8), p0, p1, np.full(n, 1000.0), np.full(n, 8000.0))
        programs.append((pg, Cutter.from_params({"type": "ball", "diameter_mm": d, "stickout_mm": 20})))
    pts = rng.uniform([-2, -2, -4], [32, 32, 2], (3000, 3))
    got = Earlier(programs, wp, 0.005).removed(pts, 0.001)
    want = np.zeros(len(pts), bool)
    for pg, cutter in programs:
        for j in range(len(pg.p0)):
            want |= inside_sweep(pts, np.repeat(pg.p0[j:j + 1], len(pts), 0), np.repeat(pg.p1[j:j + 1], len(pts), 0),
                                 cutter, eps=0.001)
    assert want.sum() > 0 and np.array_equal(got, want)
