"""Thermal drift compensation in stage ``correct`` (workflow section ``drift``): every written vertex
moves against the drift a model written here predicts at the time the tool reaches it, the job's
programs machined one after the other; without the section nothing changes."""
from __future__ import annotations

import json

import numpy as np
import pytest
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import trimesh
import yaml
from click.testing import CliRunner

from pipeline.cli import main
from stages.nc.reader import parse_program
from tests.test_iterate import _run, _workflow

FEED = 300.0             # mm/min: the programs take ≈ 11 s each
RAPID = 30000.0          # machine.rapid_mm_min's default
TAU, AX, AY = 30.0, 40.0, -25.0      # one heat source: τ = 30 s, 40 µm in X and −25 µm in Y at steady state
START = 20.0             # the job starts 20 s after the machine's cold start


def _program(number: int, z: float, ys) -> str:
    zig = []
    for k, y in enumerate(ys):
        zig += [f"G1 Y{y:.1f}", f"G1 X{18.0 if k % 2 == 0 else 2.0:.1f} Y{y:.1f}"]
    return "\n".join(["%", f"O{number}", "G90 G17 G21", "T1 M6", "S8000 M3", f"G0 X2.0 Y{ys[0]:.1f} Z5.0",
                      f"G1 Z{z:.2f} F{FEED:g}", *zig, "G0 Z5.0", "M30", "%", ""])


PROGRAMS = {"a": _program(1, 0.15, range(4, 7)), "b": _program(2, 0.0, range(6, 9))}


def _model(gain_x=AX) -> dict:
    zero = {"offset_um": 0.0, "gain1_um": 0.0}
    return {"kind": "thermal_drift", "time_constants_s": [TAU], "heat_input": None,
            "positions": {"columns": [], "origin_mm": []}, "temperatures": {"columns": [], "origin_c": []},
            "axes": {"x": {**zero, "gain1_um": gain_x}, "y": {**zero, "gain1_um": AY}, "z": zero}}


def _job(tmp_path):
    (tmp_path / "nc").mkdir()
    for name, text in PROGRAMS.items():
        (tmp_path / "nc" / f"{name}.nc").write_text(text)
    trimesh.creation.box(bounds=[[0, 0, -5], [20, 20, 0.3]]).export(tmp_path / "stock.stl")
    path = _workflow(tmp_path, max_iter=1)
    wf = yaml.safe_load(path.read_text())
    wf["tool"]["diameter_mm"] = 10.0
    path.write_text(yaml.safe_dump(wf))
    return path, wf


def _hand_times(text: str) -> list[float]:
    """Time each G0/G1 block's end is reached, from the program's start: lengths over the feed (G0
    at the rapid rate); the first G0 starts where the program does not say, so it takes no time."""
    t, pos, out, first = 0.0, None, [], True
    for line in text.splitlines():
        words = line.split()
        if not words or words[0] not in ("G0", "G1"):
            continue
        new = dict(pos or {"X": 0.0, "Y": 0.0, "Z": 0.0})
        new.update({w[0]: float(w[1:]) for w in words[1:] if w[0] in "XYZ"})
        if not first:
            d = np.linalg.norm([new[a] - pos[a] for a in "XYZ"])
            t += 60.0 * d / (RAPID if words[0] == "G0" else FEED)
        first, pos = False, new
        out.append(t)
    return out


def _written(path) -> np.ndarray:
    blocks, _ = parse_program(path.read_bytes(), str(path), "p")
    b = blocks.to_pandas()
    return b.loc[b.motion <= 1, ["x1_mm", "y1_mm", "z1_mm"]].to_numpy()


def test_written_vertices_move_against_the_drift_at_their_time(tmp_path):
    path, wf = _job(tmp_path)
    out = tmp_path / "out"
    _run(path)                                            # error correction only
    before = {n: (out / "nc" / f"{n}.nc").read_bytes() for n in PROGRAMS}
    model = tmp_path / "thermal" / "drift.yaml"
    model.parent.mkdir()
    model.write_text(yaml.safe_dump(_model()))
    wf["drift"] = {"model": "thermal/drift.yaml", "start_s": START}
    path.write_text(yaml.safe_dump(wf))
    _run(path)
    stages = {s["name"]: (s["computed"], s["cached"]) for s in json.loads((out / "run.json").read_text())["stages"]}
    assert stages["scan"] == (0, 2) and stages["correct"] == (2, 0), stages    # only the correction is new
    cor = pd.read_parquet(out / "tables" / "corrected")
    passes = pd.read_parquet(out / "tables" / "passes")
    offset = START
    for name, text in PROGRAMS.items():
        t = offset + np.array(_hand_times(text))
        c = cor[cor.program_id == name].sort_values("block_no")
        assert len(c) == len(t)
        rise = 1.0 - np.exp(-t / TAU)
        np.testing.assert_allclose(c.drift_x_um, -AX * rise, atol=1e-9)
        np.testing.assert_allclose(c.drift_y_um, -AY * rise, atol=1e-9)
        assert (c.drift_z_um == 0).all()
        # the error correction is that of the run without drift: the rounds predict the path in
        # the workpiece frame, where drift and compensation cancel
        old, new = _written_from(before[name], tmp_path / f"{name}_old.nc"), _written(out / "nc" / f"{name}.nc")
        shift = np.column_stack([-AX * rise, -AY * rise, np.zeros_like(t)]) / 1000.0
        np.testing.assert_allclose(new - old, shift, atol=1.0e-3 + 1e-9)          # both on the 1 µm grid
        np.testing.assert_allclose(new, c[["x_new_mm", "y_new_mm", "z_new_mm"]].to_numpy() + shift, atol=0.5e-3 + 1e-9)
        # the hand times are the passes table's (its program's last pass ends when the next program starts)
        duration = float(passes[passes.program_id == name].t_end_s.max())
        assert abs(duration - _hand_times(text)[-1]) < 1e-9
        offset += duration
    # a program whose error correction is not kept (corrected None) still gets its drift
    # compensation, from the first round's table, on the coordinates as programmed
    _drift_without_correction(tmp_path, pq.read_table(out / "tables" / "corrected"))
    # a refitted model under the same path is a new cache key: the correction is computed again
    model.write_text(yaml.safe_dump(_model(gain_x=2 * AX)))
    _run(path)
    cor2 = pd.read_parquet(out / "tables" / "corrected")
    np.testing.assert_allclose(cor2.drift_x_um, 2 * cor.drift_x_um, atol=1e-9)


def _drift_without_correction(tmp_path, first):
    from stages.nc.output import corrected_programs
    src = tmp_path / "nc" / "b.nc"
    blocks, _ = parse_program(src.read_bytes(), str(src), "b")
    first = first.filter(pc.equal(first.column("program_id"), "b"))
    inputs = {"program_file": {"path": str(src), "sha256": "0" * 64, "program_id": "b"}, "blocks": blocks,
              "corrected": None, "corrected@first": first, "errors": None, "passes": None, "feeds": None}
    text = corrected_programs(inputs, {"correct": {}})["b.nc"]
    assert b"THERMAL DRIFT COMPENSATED: MAX" in text and b"MAX MOVE 0.0 UM" in text
    got = _written_from(text, tmp_path / "b_drift_only.nc")
    f = first.to_pandas()
    want = f[["x_mm", "y_mm", "z_mm"]].to_numpy() + f[["drift_x_um", "drift_y_um", "drift_z_um"]].to_numpy() / 1000
    np.testing.assert_allclose(got, want, atol=0.5e-3 + 1e-9)
    zero = first.drop_columns(["drift_x_um", "drift_y_um", "drift_z_um"])
    assert corrected_programs({**inputs, "corrected@first": zero}, {"correct": {}}) == {}


def _written_from(data: bytes, path):
    path.write_bytes(data)
    return _written(path)


def test_without_a_drift_section_programs_with_nothing_to_correct_are_written_unchanged(tmp_path):
    from stages.nc.output import corrected_programs
    from stages.thermal.compensate import with_drift
    path, _ = _job(tmp_path)
    _run(path)
    cor = pd.read_parquet(tmp_path / "out" / "tables" / "corrected")
    assert (cor[["drift_x_um", "drift_y_um", "drift_z_um"]] == 0).all().all()
    # a table with no compensation is handed to the writers as it is
    table = pq.read_table(tmp_path / "out" / "tables" / "corrected")
    assert with_drift(table) is table
    # no move and no feeds: the program as written, byte for byte
    src = tmp_path / "nc" / "a.nc"
    blocks, _ = parse_program(src.read_bytes(), str(src), "a")
    a = table.filter(pc.equal(table.column("program_id"), "a"))
    still = a.set_column(a.schema.get_field_index("x_new_mm"), "x_new_mm", a.column("x_mm"))
    for c in ("y", "z"):
        still = still.set_column(still.schema.get_field_index(f"{c}_new_mm"), f"{c}_new_mm", a.column(f"{c}_mm"))
    files = corrected_programs({"program_file": {"path": str(src), "sha256": "0" * 64, "program_id": "a"},
                                "blocks": blocks, "corrected": still, "errors": None, "passes": None,
                                "feeds": None}, {"correct": {}})
    assert files["a.nc"] == src.read_bytes()


def test_a_bad_drift_model_fails_the_programs_naming_the_file(tmp_path):
    path, wf = _job(tmp_path)
    (tmp_path / "drift.yaml").write_text("kind: thermal_drift\ntime_constants_s: [30]\naxes: {x: {}}\n")
    wf["drift"] = {"model": "drift.yaml"}
    path.write_text(yaml.safe_dump(wf))
    r = CliRunner().invoke(main, ["run", str(path), "--workers", "1", "-q"], catch_exceptions=False)
    assert r.exit_code == 1, r.output
    failures = json.loads((tmp_path / "out" / "run.json").read_text())["failures"]
    assert {f["stage"] for f in failures} == {"correct"}, failures
    assert all(f"{tmp_path / 'drift.yaml'}: not a drift model" in f["message"] for f in failures), failures
    # a missing file and an unknown key are the workflow's own errors, naming the key
    wf["drift"] = {"model": "nowhere.yaml"}
    path.write_text(yaml.safe_dump(wf))
    r = CliRunner().invoke(main, ["run", str(path), "--workers", "1", "-q"])
    assert r.exit_code != 0 and "model: file" in r.output and "nowhere.yaml" in r.output, r.output
    wf["drift"] = {"model": "drift.yaml", "start": 5}
    path.write_text(yaml.safe_dump(wf))
    r = CliRunner().invoke(main, ["run", str(path), "--workers", "1", "-q"])
    assert r.exit_code != 0 and "drift.start" in r.output, r.output


def _passes(t_edges, rpm, program_id="p"):
    """A passes table of straight 1 mm moves in X, one block each, timed at ``t_edges``."""
    import pyarrow as pa
    n = len(rpm)
    x = np.arange(n + 1, dtype=float)
    return pa.table({"program_id": [program_id] * n, "pass_id": np.arange(n, dtype=np.int32),
                     "block_no": np.arange(1, n + 1, dtype=np.int32), "block_end": np.arange(1, n + 1, dtype=np.int32),
                     "x0_mm": x[:-1], "y0_mm": np.zeros(n), "z0_mm": np.zeros(n),
                     "x1_mm": x[1:], "y1_mm": np.zeros(n), "z1_mm": np.zeros(n),
                     "spindle_rpm": np.asarray(rpm, float),
                     "t_start_s": np.asarray(t_edges[:-1], float), "t_end_s": np.asarray(t_edges[1:], float)})


def test_a_heat_input_model_follows_the_spindle_of_the_whole_job():
    from stages import InputError
    from stages.thermal import DriftModel
    from stages.thermal.compensate import drift_compensation
    tau, a = 20.0, 10.0
    model = DriftModel(np.array([tau]), {"x": np.array([0.0, a]), "y": np.zeros(2), "z": np.zeros(2)},
                       heat_column="spindle_rpm", heat_reference=10000.0)
    # earlier program: 10 s at full speed; this one: 10 s at half speed, then 20 s stopped
    earlier = [(_passes([0.0, 10.0], [10000.0], "e"), {})]
    passes = _passes([0.0, 10.0, 30.0], [5000.0, 0.0])
    end = np.array([[1.0, 0, 0], [2.0, 0, 0]])
    comp = drift_compensation(model, np.array([1, 2]), end, passes, earlier)
    # first-order lag by hand: r(10) = 1 − e^(−1/2); r(20) = 0.5 + (r(10) − 0.5)e^(−1/2); r(40) = r(20)e^(−1)
    r10 = 1 - np.exp(-0.5)
    r20 = 0.5 + (r10 - 0.5) * np.exp(-0.5)
    np.testing.assert_allclose(comp[:, 0], -a * np.array([r20, r20 * np.exp(-1.0)]), rtol=1e-12)
    no_speed = passes.drop_columns(["spindle_rpm"])
    with pytest.raises(InputError, match="m.yaml: the model's heat input is spindle_rpm"):
        drift_compensation(model, np.array([1, 2]), end, no_speed, None, where="m.yaml")
    model.temperatures = ("temp_spindle",)
    with pytest.raises(InputError, match="m.yaml: the model needs temperature readings"):
        drift_compensation(model, np.array([1, 2]), end, passes, None, where="m.yaml")


def test_a_vertex_inside_a_merged_pass_is_reached_at_its_fraction_of_the_pass():
    from stages.thermal.compensate import vertex_times
    p = _passes([0.0, 4.0, 6.0], [0.0, 0.0])
    p = p.set_column(p.schema.get_field_index("block_no"), "block_no", pa_array([1, 3]))
    p = p.set_column(p.schema.get_field_index("block_end"), "block_end", pa_array([2, 3]))
    # blocks 1 and 2 merged into pass 0 (x 0 → 1, t 0 → 4): block 1 ends at x = 0.25
    t = vertex_times(np.array([1, 2, 3]), np.array([[0.25, 0, 0], [1.0, 0, 0], [2.0, 0, 0]]), p)
    np.testing.assert_allclose(t, [1.0, 4.0, 6.0])


def pa_array(v):
    import pyarrow as pa
    return pa.array(np.asarray(v, np.int32))


def test_an_arc_moves_with_its_end_point(tmp_path):
    """Arc centres move by their end point's compensation: the written arc is the programmed one
    moved by it (the reverse check parses the centre back from I J)."""
    from schemas.corrected import SCHEMA
    from stages.nc.output import corrected_programs
    src = tmp_path / "arc.nc"
    src.write_text("%\nO5\nG90 G17 G21\nT1 M6\nS6000 M3\nG0 X10.0 Y0.0 Z1.0\nG1 Z0.0 F600\nG3 X0.0 Y10.0 I-10.0 J0.0\nG1 X-5.0\nM30\n%\n")
    blocks, _ = parse_program(src.read_bytes(), str(src), "arc")
    b = blocks.to_pandas()
    b = b[b.motion <= 3].reset_index(drop=True)
    n = len(b)
    drift = np.column_stack([np.linspace(-3.0, -12.0, n), np.linspace(2.0, 8.0, n), np.zeros(n)])
    first = pa.table({**{c: b[c].to_numpy() for c in ("program_id", "block_no", "line_no", "motion")},
                      **{f"{a}_mm": b[f"{a}1_mm"].to_numpy() for a in "xyz"},
                      **{f"{a}_new_mm": b[f"{a}1_mm"].to_numpy() for a in "xyz"},
                      **{f"c{a}_new_mm": np.full(n, np.nan) for a in "xyz"},
                      "move_um": np.zeros(n), "change_um": np.zeros(n), "clipped": np.zeros(n, bool),
                      "gouge_limit_um": np.zeros(n), "iteration": np.ones(n, np.int32), "relax": np.ones(n),
                      **{f"step_{a}_um": np.zeros(n) for a in "xyz"}, **{f"n{a}": np.full(n, np.nan) for a in "xyz"},
                      **{f"drift_{a}_um": drift[:, j] for j, a in enumerate("xyz")}}, schema=SCHEMA)
    inputs = {"program_file": {"path": str(src), "sha256": "0" * 64, "program_id": "arc"}, "blocks": blocks,
              "corrected": None, "corrected@first": first, "errors": None, "passes": None, "feeds": None}
    text = corrected_programs(inputs, {"correct": {}})["arc.nc"]
    new, _ = parse_program(text, "arc_new.nc", "arc")
    arc_row = int(np.flatnonzero(b.motion == 3)[0])
    got = new.to_pandas().query("motion == 3").iloc[0]
    shift = drift[arc_row] / 1000
    np.testing.assert_allclose([got.x1_mm, got.y1_mm], np.array([0.0, 10.0]) + shift[:2], atol=0.5e-3 + 1e-9)
    np.testing.assert_allclose([got.cx_mm, got.cy_mm], shift[:2], atol=0.5e-3 + 1e-9)
