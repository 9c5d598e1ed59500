"""Iterated correction in ``pipeline run`` (DESIGN §7): the stage graph's repeated correction rounds.

A small workflow through the whole chain on the seed's cylinder geometry (Ø20 ball, 0.63 mm pitch,
three levels on the steep side where deflection leaves 10–20 µm): ``correct.max_iter: 3`` predicts again on
the corrected path and corrects again. The check that iterating helps does not use the run's own
numbers: the written programs (one round, three rounds) are predicted again by a separate run of
the pipeline on those NC files; a prediction is relative to the path it is made for, so the test
adds each pass's shift from the original path along the normal, and the resulting deviation from
the original surface must be smaller for the three-round program than for the one-round program,
itself smaller than the original's error. Finally the three programs are machined on the virtual
machine of the gap issue (an independent simulation): the error left by the three-round program must
be ≤ 20 % of the original's (issue 5's closed loop).
"""
from __future__ import annotations

import json
import shutil

import numpy as np
import pandas as pd
import pytest
import pyarrow.parquet as pq
import trimesh
import yaml
from click.testing import CliRunner

from pipeline.cli import main
from stages.nc.reader import parse_program

R, PITCH, DEPTH = 10.0, 0.63, 0.2
DQ = np.radians(89.0 / 50)            # the Fig. 16 level spacing (tests/cylinder_case.py)
RC = PITCH / DQ                        # cylinder radius, 20.28 mm
LEVELS = range(37, 40)                 # q ≈ 66°–69°
YS = np.array([-13.0, -3.0, 3.0, 13.0])  # vertices along the cylinder axis (the stock is 4 mm long):
# one pass per level crosses the stock (max_pass_mm 12), the passes beyond generate no surface


def _program() -> bytes:
    lines = ["%", "O3001 (CYLINDER LEVELS)", "G90 G17 G21", "T1 M6", "S6000 M3"]
    first = True
    for i, k in enumerate(LEVELS):
        q = k * DQ
        x, z = (RC + R) * np.sin(q), (RC + R) * np.cos(q) - R      # tool tip below the ball centre
        ys = YS if i % 2 == 0 else YS[::-1]
        for y in ys:
            if first:
                lines += [f"G0 X{x:.3f} Y{y:.3f} Z{z + 20:.3f}", f"G1 Z{z:.3f} F4800"]
                first = False
            else:
                lines.append(f"G1 X{x:.3f} Y{y:.3f} Z{z:.3f}")
    lines += ["G0 Z60.000", "M30", "%", ""]
    return "\n".join(lines).encode()


def _workflow(root, programs="nc/*.nc", max_iter=3, until=None):
    wf = {"name": "iter", "programs": programs, "stock": "stock.stl",
          "tool": {"type": "ball", "diameter_mm": 20, "flutes": 2, "helix_deg": 30, "stickout_mm": 40},
          "material": {"name": "FCD550", "ktc": 2000, "krc": 700, "kac": 300, "kte": 20, "kre": 15, "kae": 5},
          "machine": {"frf": {"x": [{"fn_hz": 900, "zeta": 0.03, "k_n_per_um": 1.0}],
                              "y": [{"fn_hz": 900, "zeta": 0.03, "k_n_per_um": 1.0}]}},
          "render": {"backend": "auto", "px_per_mm": 20}, "prune": {"min_contact_deg": 0},
          "split": {"max_pass_mm": 12.0}, "output": "out",
          "correct": {"max_move_um": 200, "tol_um": 0.05, "max_iter": max_iter}, "until": until}
    path = root / f"wf_{max_iter}_{until}.yaml"
    path.write_text(yaml.safe_dump(wf))
    return path


def _run(*args):
    r = CliRunner().invoke(main, ["run", *map(str, args), "--workers", "1", "-q"], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    return r.output


def _rms(x):
    x = np.asarray(x, float)
    return float(np.sqrt(np.mean(x[np.isfinite(x)] ** 2)))


def _residual_um(errors, passes, passes0):
    """Predicted deviation from the ORIGINAL program's surface of a (corrected) program.

    A prediction is relative to the path it is made for: the surface of path P is P + e(P)·n. With
    the original path P0 (the design), the deviation at a pass is e + (P − P0)·n, the path shift
    taken at the pass midpoint (same pass structure: same pass ids and blocks).
    """
    p = passes.set_index("pass_id").sort_index()
    p0 = passes0.set_index("pass_id").sort_index()
    assert (p.block_no == p0.block_no).all() and len(p) == len(p0)
    mid = lambda t: np.stack([(t[f"{a}0_mm"] + t[f"{a}1_mm"]).to_numpy() / 2 for a in "xyz"], 1)  # noqa: E731
    shift = pd.DataFrame(mid(p) - mid(p0), index=p.index, columns=list("xyz"))
    s = shift.loc[errors.pass_id.to_numpy()].to_numpy()
    n = errors[["nx", "ny", "nz"]].to_numpy()
    return errors.err_um.to_numpy() + 1000.0 * np.einsum("ij,ij->i", s, n)


def _virtual_machine_rms(stock, programs: dict) -> dict:
    from stages.nc.moves import split_blocks
    from stages.virtual_machine import VirtualMachine
    tool = {"type": "ball", "diameter_mm": 20.0, "flutes": 2, "helix_deg": 30.0, "stickout_mm": 40.0,
            "runout_um": 0.0, "control_point": "tip"}
    material = {"ktc": 2000, "krc": 700, "kac": 300, "kte": 20, "kre": 15, "kae": 5}
    modes = lambda k: {"frf": {a: [{"fn_hz": 900, "zeta": 0.03, "k_n_per_um": k}] for a in "xy"}, "table": None}  # noqa: E731
    split = {"split": {"chord_tol_mm": 0.001, "max_pass_mm": 12.0, "merge_max_mm": 0.5},
             "machine": {"rapid_mm_min": 30000.0}, "tool": tool}
    q = np.array([k * DQ for k in LEVELS])
    qq, yy = np.meshgrid(np.linspace(q[0], q[-1], 25), np.linspace(-1.5, 1.5, 7))   # inside the 4 mm stock
    n = np.stack([np.sin(qq.ravel()), np.zeros(qq.size), np.cos(qq.ravel())], 1)
    pts = RC * n + np.stack([np.zeros(qq.size), yy.ravel(), np.zeros(qq.size)], 1)

    def probe(text, k):
        blocks, _ = parse_program(text, "vm.nc", "cyl")
        return VirtualMachine(split_blocks(blocks, split), tool, material, modes(k), str(stock)).probe(pts, n)
    ideal = probe(programs["original"], 1e9)                    # rigid machine: cusps only
    return {name: float(np.sqrt(np.mean((probe(text, 1.0) - ideal) ** 2))) for name, text in programs.items()}


def cylinder_job(root, program: bytes) -> None:
    """``root/nc/cyl.nc`` and the cylinder's stock ``root/stock.stl`` (DEPTH over RC, 4 mm long in Y)."""
    (root / "nc").mkdir()
    (root / "nc" / "cyl.nc").write_bytes(program)
    stock = trimesh.creation.cylinder(radius=RC + DEPTH, height=4.0, sections=720)
    stock.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    stock.export(root / "stock.stl")


def test_iterated_correction_through_the_engine(tmp_path):
    src = _program()
    cylinder_job(tmp_path, src)
    out = tmp_path / "out"
    check = tmp_path / "check"
    (check / "nc").mkdir(parents=True)

    # one round (the prediction chain is cached in `out` for the iterated run)
    _run(_workflow(tmp_path, max_iter=1))
    one = pd.read_parquet(out / "tables" / "corrected")
    assert set(one.iteration) == {1}
    shutil.copy(out / "nc" / "cyl.nc", check / "nc" / "one.nc")
    errors0 = pd.read_parquet(out / "tables" / "errors")

    # three rounds: predict again on the corrected path, correct again
    _run(_workflow(tmp_path, max_iter=3))
    summary = json.loads((out / "run.json").read_text())
    rounds = summary["rounds"]["cyl"]
    corrected = pd.read_parquet(out / "tables" / "corrected")
    print("\nrounds: " + "; ".join(f"{r['round']}: predicted RMS {r['rms_err_um']:.3f} um (deviation from the original {r['rms_dev_um']:.3f}) on {r['n_errors']} passes, "
                                   f"max change {r['max_change_um']:.3f} um" for r in rounds))
    assert len(rounds) == 3 and set(corrected.iteration) == {3}          # tol 0.05 µm is not reached in 3
    # round 1 (the whole chain and its correction) is the one-round run's: max_iter is not in its keys
    assert all(s["computed"] == 0 for s in summary["stages"] if "@" not in s["name"])
    round_stages = [s for s in summary["stages"] if "@" in s["name"]]
    assert {s["name"] for s in round_stages} == {f"{m}@{r}" for r in (2, 3) for m in (
        "correct_blocks", "split", "scan", "forces", "deflection", "errors", "correct")}
    assert all(s["computed"] == 1 for s in round_stages)
    # the table keeps the ORIGINAL coordinates and the new ones after all rounds
    blocks, _ = parse_program(src, "cyl.nc", "cyl")
    b = blocks.to_pandas()
    b = b[b.motion <= 3].sort_values("block_no")
    c = corrected.sort_values("block_no")
    np.testing.assert_array_equal(c.block_no.to_numpy(), b.block_no.to_numpy())
    for a in "xyz":
        np.testing.assert_allclose(c[f"{a}_mm"].to_numpy(), b[f"{a}1_mm"].to_numpy(), atol=1e-12)
    moved = np.sqrt(sum((c[f"{a}_new_mm"] - c[f"{a}_mm"]) ** 2 for a in "xyz")).to_numpy() * 1000
    np.testing.assert_allclose(moved, c.move_um.to_numpy(), atol=1e-6)
    assert np.abs(c.move_um.to_numpy() - one.sort_values("block_no").move_um.to_numpy()).max() > 0.5
    shutil.copy(out / "nc" / "cyl.nc", check / "nc" / "three.nc")
    errors_table = pq.read_table(out / "tables" / "errors" / "cyl.parquet")
    assert errors_table.num_rows == len(errors0)                        # tables keep round 1's prediction

    # a rerun is served from the cache, round by round, with the same result
    _run(_workflow(tmp_path, max_iter=3))
    again = json.loads((out / "run.json").read_text())
    assert all(s["computed"] == 0 and s["cached"] == s["partitions"] for s in again["stages"])
    assert (out / "nc" / "cyl.nc").read_bytes() == (check / "nc" / "three.nc").read_bytes()

    # independent check: predict the written programs again, each in a run of its own (two
    # programs of one workflow are machined one after the other on one stock; these are
    # alternatives), and take the deviation from the original surface (prediction + path shift
    # along the normal)
    passes0 = pd.read_parquet(out / "tables" / "passes")
    res = {}
    for k in ("one", "three"):
        alone = check / k
        shutil.copytree(check / "nc", alone / "nc", ignore=lambda d, names: [n for n in names if n != f"{k}.nc"])
        shutil.copy(tmp_path / "stock.stl", alone / "stock.stl")
        _run(_workflow(alone, max_iter=1, until="errors"))
        e = pd.read_parquet(alone / "out" / "tables" / "errors")
        p = pd.read_parquet(alone / "out" / "tables" / "passes")
        res[k] = _residual_um(e, p, passes0)
    rms0, rms1, rms3 = _rms(errors0.err_um), _rms(res["one"]), _rms(res["three"])
    print(f"re-predicted deviation from the original surface, RMS: original program {rms0:.3f} um, "
          f"corrected once {rms1:.3f} um, corrected in three rounds {rms3:.3f} um "
          f"(max {np.abs(errors0.err_um).max():.2f} / {np.nanmax(np.abs(res['one'])):.2f} / "
          f"{np.nanmax(np.abs(res['three'])):.2f} um)")
    assert rms0 > 3.0                       # the case has something to correct
    assert rms1 < rms0
    assert rms3 < rms1

    # closed loop on the virtual machine of the gap issue (stages/virtual_machine/: discrete
    # flutes, time-domain dynamics, its own engagement; shares no prediction code): the programs
    # machined there, probed on the design cylinder, against the original program on a rigid machine
    vm_rms = _virtual_machine_rms(tmp_path / "stock.stl", {"original": src, "one": (check / "nc" / "one.nc").read_bytes(),
                                                           "three": (check / "nc" / "three.nc").read_bytes()})
    print("virtual machine (issue 7), error RMS over the finished cylinder: " + ", ".join(
        f"{k} {v:.3f} um ({100 * v / vm_rms['original']:.1f} %)" for k, v in vm_rms.items()))
    assert vm_rms["original"] > 10.0
    assert vm_rms["three"] <= 0.2 * vm_rms["original"]          # issue 5: ≤ 20 % of before


def _two_splits():
    """The cylinder program split into 2.5 mm (fine) and 5 mm (coarse) passes."""
    from stages.nc.moves import split_blocks
    blocks, _ = parse_program(_program(), "cyl.nc", "cyl")
    base = {"machine": {"rapid_mm_min": 30000.0}, "tool": {"type": "ball", "diameter_mm": 20.0, "control_point": "tip"}}
    fine = split_blocks(blocks, dict(base, split={"chord_tol_mm": 0.001, "max_pass_mm": 2.5, "merge_max_mm": 0.5}))
    coarse = split_blocks(blocks, dict(base, split={"chord_tol_mm": 0.001, "max_pass_mm": 5.0, "merge_max_mm": 0.5}))
    assert fine.num_rows > coarse.num_rows
    return fine, coarse


def test_errors_follow_their_pass_when_the_corrected_program_splits_differently():
    # the same blocks split into 5 mm and 2.5 mm passes: every error row of the fine split goes to
    # the coarse pass of the same block whose midpoint is nearest (brute force reference)
    from stages.correction.rounds import errors_on_passes
    import pyarrow as pa
    fine, coarse = _two_splits()
    f = fine.to_pandas()
    err = pa.table({"program_id": ["cyl"] * len(f), "pass_id": f.pass_id.to_numpy(), "err_um": np.arange(len(f), dtype=float),
                    "nx": np.zeros(len(f)), "ny": np.zeros(len(f)), "nz": np.ones(len(f))})
    out = errors_on_passes(err, fine, coarse).to_pandas()
    c = coarse.to_pandas()
    for _, row in out.iterrows():
        src = f[f.pass_id == int(row.err_um)].iloc[0]
        mid = np.array([(src[f"{a}0_mm"] + src[f"{a}1_mm"]) / 2 for a in "xyz"])
        cand = c[c.block_no == src.block_no]
        cm = np.stack([(cand[f"{a}0_mm"] + cand[f"{a}1_mm"]).to_numpy() / 2 for a in "xyz"], 1)
        dist = np.linalg.norm(cm - mid, axis=1)
        nearest = set(cand.pass_id.to_numpy()[dist <= dist.min() + 1e-9].tolist())   # ties: either
        assert int(row.pass_id) in nearest
    assert len(out) == len(f)
    # identical splits: the table comes back as it is
    assert errors_on_passes(err, fine, fine) is err


def test_round_deviation_is_the_error_plus_the_path_shift_when_the_split_differs():
    # the fine split moved 10 µm along +z and predicted −10 µm along +z: the surface it leaves is
    # the original one (deviation 0); a shift along x (perpendicular to the normal) adds nothing
    from stages.correct import round_record
    import pyarrow as pa
    import pyarrow.compute as pc
    fine, coarse = _two_splits()
    moved = fine
    for c, d in (("z0_mm", 0.010), ("z1_mm", 0.010), ("x0_mm", 0.003), ("x1_mm", 0.003)):
        moved = moved.set_column(moved.schema.get_field_index(c), c, pc.add(moved.column(c), d))
    n = fine.num_rows
    corrected = pa.table({"change_um": np.zeros(n), "move_um": np.full(n, 10.0), "clipped": np.zeros(n, bool)})

    f = fine.to_pandas()
    along_y = ((f.x0_mm == f.x1_mm) & (f.z0_mm == f.z1_mm) & (f.y0_mm != f.y1_mm)).to_numpy()   # the cutting passes
    m = int(along_y.sum())
    assert m > 10

    def record(err_um):
        errors = pa.table({"program_id": ["cyl"] * m, "pass_id": f.pass_id.to_numpy()[along_y], "err_um": np.full(m, err_um),
                           "nx": np.zeros(m), "ny": np.zeros(m), "nz": np.ones(m)})
        return round_record({"errors": errors, "corrected": corrected, "passes": moved, "passes@first": coarse})
    assert record(-10.0)["rms_dev_um"] == pytest.approx(0.0, abs=1e-6)
    assert record(-4.0)["rms_dev_um"] == pytest.approx(6.0, abs=1e-6)
    assert record(-4.0)["rms_err_um"] == pytest.approx(4.0)
