"""Engine: cache, incrementality, crash resume, real Dask cluster, bad input, workflow errors."""
from __future__ import annotations

import json
import shutil
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import duckdb
import numpy as np
import pandas as pd
import pytest
import yaml
from click.testing import CliRunner

from pipeline.cli import main
from tests.ncprograms import raster_program

WF = {
    "name": "t",
    "programs": "nc/*.nc",
    "stock": {"box": [-5, -5, -5, 120, 120, 1]},
    "tool": {"type": "ball", "diameter_mm": 6, "flutes": 2},
    "material": {"name": "FCD550", "ktc": 2000, "krc": 700, "kac": 300},
    "output": "out",
    "until": "split",  # engine behaviour is tested on parse/split; the full chain on a small box below
}


def make_project(root: Path, n_programs: int = 3, blocks: int = 2000, wf: dict | None = None) -> Path:
    (root / "nc").mkdir(parents=True, exist_ok=True)
    for i in range(n_programs):
        (root / "nc" / f"p{i:02d}.nc").write_bytes(raster_program(blocks, seed=i))
    path = root / "wf.yaml"
    path.write_text(yaml.safe_dump(wf or WF))
    return path


def run_cli(*args) -> tuple[int, str]:
    r = CliRunner().invoke(main, list(args), catch_exceptions=False)
    return r.exit_code, r.output


def readme_queries() -> list[str]:
    """The SQL statements of the README's sql blocks."""
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    blocks = [b.split("```", 1)[0] for b in text.split("```sql")[1:]]
    stmts = [s.strip() for b in blocks for s in b.split(";")]
    return [s for s in ("\n".join(ln for ln in st.splitlines() if not ln.startswith("--")) for st in stmts) if s.strip()]


def run_json(out: Path) -> dict:
    return json.loads((out / "run.json").read_text())


def stage(summary: dict, name: str) -> dict:
    return next(s for s in summary["stages"] if s["name"] == name)


def read_table(out: Path, name: str) -> pd.DataFrame:
    df = pd.read_parquet(out / "tables" / name)
    keys = [c for c in ("program_id", "pass_id", "block_no") if c in df]
    return df.sort_values(keys).reset_index(drop=True)


def test_run_tables_queryable_and_second_run_served_from_cache(tmp_path):
    wf = make_project(tmp_path)
    code, out = run_cli("run", str(wf), "--workers", "1", "-q")
    assert code == 0, out
    o = tmp_path / "out"
    n_passes = duckdb.sql(f"select count(*) from read_parquet('{o}/tables/passes/*.parquet')").fetchall()[0][0]
    progs = read_table(o, "programs")
    assert list(progs.status) == ["ok"] * 3 and progs.n_passes.sum() == n_passes > 1000
    s1 = run_json(o)
    assert stage(s1, "parse")["computed"] == 3 and s1["counts"]["passes"] == n_passes

    code, out = run_cli("run", str(wf), "-q")
    assert code == 0
    s2 = run_json(o)
    for st in s2["stages"]:
        assert st["computed"] == 0 and st["cached"] == st["partitions"] == 3
        assert st["wall_s"] < 1.0, st
    pd.testing.assert_frame_equal(read_table(o, "passes"), read_table(o, "passes"))
    code, out = run_cli("status", str(wf))
    assert "parse" in out and "3" in out


def test_changes_invalidate_exactly_what_depends_on_them(tmp_path):
    wf_path = make_project(tmp_path)
    o = tmp_path / "out"
    assert run_cli("run", str(wf_path), "--workers", "1", "-q")[0] == 0
    # a split parameter: parse stays cached, split recomputes
    wf = dict(WF, split={"max_pass_mm": 2.0})
    wf_path.write_text(yaml.safe_dump(wf))
    assert run_cli("run", str(wf_path), "--workers", "1", "-q")[0] == 0
    s = run_json(o)
    assert stage(s, "parse")["cached"] == 3 and stage(s, "split")["computed"] == 3
    # a material coefficient: neither parse nor split depends on it
    wf["material"] = dict(WF["material"], ktc=2500)
    wf_path.write_text(yaml.safe_dump(wf))
    assert run_cli("run", str(wf_path), "--until", "split", "-q")[0] == 0
    s = run_json(o)
    assert stage(s, "parse")["cached"] == 3 and stage(s, "split")["cached"] == 3
    # nightly: one new program and one edited program → only those two are parsed
    (tmp_path / "nc" / "p99.nc").write_bytes(raster_program(1000, seed=99))
    (tmp_path / "nc" / "p00.nc").write_bytes(raster_program(1000, seed=42))
    assert run_cli("run", str(wf_path), "--workers", "1", "--until", "split", "-q")[0] == 0
    s = run_json(o)
    assert stage(s, "parse")["computed"] == 2 and stage(s, "parse")["cached"] == 2
    assert sorted(read_table(o, "programs").program_id) == ["p00", "p01", "p02", "p99"]


def test_via_points_make_parsing_depend_on_the_split_length(tmp_path):
    wf_path = make_project(tmp_path, n_programs=1)
    rows = [f"N{10 + i} X{60 * (i % 2)}.000 Y{0.5 * (i // 2):.3f}" for i in range(20)]
    (tmp_path / "nc" / "p00.nc").write_text("\n".join(
        ["%", "O1", "G90 G17 G21", "T1 M6", "S12000 M3", "G0 X0. Y0. Z5.", "G1 Z0. F1000", *rows, "G0 Z50.", "M30", "%", ""]))
    o = tmp_path / "out"
    wf = dict(WF, correct={"via_points": True})
    wf_path.write_text(yaml.safe_dump(wf))
    assert run_cli("run", str(wf_path), "--workers", "1", "--until", "split", "-q")[0] == 0
    n_via = len(read_table(o, "blocks"))
    # with via points the blocks are cut at the split length: a new length parses again
    wf["split"] = {"max_pass_mm": 2.0}
    wf_path.write_text(yaml.safe_dump(wf))
    assert run_cli("run", str(wf_path), "--workers", "1", "--until", "split", "-q")[0] == 0
    assert stage(run_json(o), "parse")["computed"] == 1
    assert len(read_table(o, "blocks")) > n_via
    # switched off: the file's own blocks, one per motion line
    wf["correct"] = {"via_points": False}
    wf_path.write_text(yaml.safe_dump(wf))
    assert run_cli("run", str(wf_path), "--workers", "1", "--until", "split", "-q")[0] == 0
    assert len(read_table(o, "blocks")) < n_via


def test_stage_version_bump_invalidates_that_stage_and_its_successors(tmp_path):
    from dataclasses import replace

    from pipeline.engine import Run
    from pipeline.graph import mould_graph
    wf_path = make_project(tmp_path, n_programs=1)
    graph = mould_graph()
    Run(str(wf_path), graph).execute(workers=1, progress=False)
    bumped = replace(graph, stages=(replace(graph.stages[0], version=graph.stages[0].version + "-test"),)
                     + graph.stages[1:])
    r = Run(str(wf_path), bumped)
    rows = {row["stage"]: row for row in r.status()}
    assert rows["parse"]["pending"] == 1 and rows["split"]["pending"] == 1


def _cli_cmd(*args):
    return [sys.executable, "-c", "from pipeline.cli import main; main()", *args]


def test_sigkill_mid_run_then_rerun_equals_uninterrupted_run(tmp_path):
    wf_path = make_project(tmp_path, n_programs=8, blocks=30000)
    o_killed, o_clean = tmp_path / "killed", tmp_path / "clean"
    proc = subprocess.Popen(_cli_cmd("run", str(wf_path), "--out", str(o_killed), "--workers", "1", "-q"),
                            start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    cache = o_killed / "cache" / "parse"
    deadline = time.time() + 120
    while time.time() < deadline:
        done = [p for p in cache.glob("*/*") if not p.name.startswith(".")] if cache.exists() else []
        if len(done) >= 2:
            break
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)  # the CLI and its Dask worker processes
    proc.wait()
    partial = len([p for p in cache.glob("*/*") if not p.name.startswith(".")])
    assert 2 <= partial < 8, f"kill did not land mid-run ({partial} of 8 parsed)"
    assert not (o_killed / "run.json").exists()

    r = subprocess.run(_cli_cmd("run", str(wf_path), "--out", str(o_killed), "--workers", "1", "-q"),
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    s = run_json(o_killed)
    assert stage(s, "parse")["cached"] >= partial and stage(s, "parse")["computed"] == 8 - stage(s, "parse")["cached"]
    r = subprocess.run(_cli_cmd("run", str(wf_path), "--out", str(o_clean), "--workers", "1", "-q"),
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    for t in ("programs", "passes", "blocks"):
        a, b = read_table(o_killed, t), read_table(o_clean, t)
        if "path" in a:
            a, b = a.drop(columns="path"), b.drop(columns="path")
        pd.testing.assert_frame_equal(a, b)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_existing_dask_cluster_on_loopback(tmp_path):
    wf_path = make_project(tmp_path, n_programs=2)
    port = _free_port()
    addr = f"tcp://127.0.0.1:{port}"
    procs = [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                               "--port", str(port), "--dashboard-address", ":0"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        time.sleep(1.5)
        procs.append(subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", addr, "--nthreads", "1",
                                       "--nworkers", "1", "--dashboard-address", ":0", "--host", "127.0.0.1"],
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        from distributed import Client
        with Client(addr, timeout="30s") as c:
            c.wait_for_workers(1, timeout=60)
        code, out = run_cli("run", str(wf_path), "--scheduler", addr, "--out", str(tmp_path / "remote"), "-q")
        assert code == 0, out
        assert run_json(tmp_path / "remote")["stages"][0]["computed"] == 2
        code, _ = run_cli("run", str(wf_path), "--workers", "1", "--out", str(tmp_path / "local"), "-q")
        pd.testing.assert_frame_equal(read_table(tmp_path / "remote", "passes"), read_table(tmp_path / "local", "passes"))
    finally:
        for p in procs:
            p.terminate()
        for p in procs:
            p.wait(timeout=30)


BROKEN = {
    "truncated.nc": None,  # filled in below from a valid program cut in the middle of a word
    "garbage.nc": b"%\nG90 G21\nT1 M6\nS9000 M3\nG0 X0 Y0 Z5\n@@@ not g-code @@@\n%\n",
    "unknown_g.nc": b"G90 G21\nT1 M6\nS9000 M3\nG0 X0 Y0 Z5\nG1 Z0 F200\nG66 X5\n",
    "bad_arc.nc": b"G90 G21\nT1 M6\nS9000 M3\nG0 X0 Y0 Z5\nG1 Z0 F200\nG2 X10 Y0 I3 J0\n",
    "no_feed.nc": b"G90 G21\nT1 M6\nS9000 M3\nG0 X0 Y0 Z5\nG1 Z0\n",
    "junk.nc": bytes(range(256)) * 4,
    "prose.nc": b"G90 G21\nT1 M6\nThis program was checked by Tanaka\nS9000 M3\nG0 X0 Y0 Z5 A30\nG1 Z0 F200 G66\nThe end\n",
}
EXPECT = {"truncated.nc": ":", "garbage.nc": ":6: unexpected character '@'", "unknown_g.nc": ":6: unknown or unsupported G code G66",
          "bad_arc.nc": ":6: arc radius inconsistent", "no_feed.nc": ":5: cutting move without a feed",
          "junk.nc": ":1: binary data", "prose.nc": ":3: unrecognised word 'This' at column 1"}
# every problem of a broken program: (line, column, what); column None: the whole block
ALL_PROBLEMS = {"prose.nc": [(3, 1, "unrecognised word 'This'"), (5, 13, "rotary axis"),
                             (6, 12, "unknown or unsupported G code G66"), (7, 1, "unrecognised word 'The'")],
                "garbage.nc": [(6, c, "unexpected character '@'") for c in (1, 2, 3)] + [(6, 5, "unrecognised word 'not'")]
                + [(6, c, "unexpected character '@'") for c in (16, 17, 18)]}


def test_broken_programs_listed_failed_valid_one_processed(tmp_path):
    wf_path = make_project(tmp_path, n_programs=1)
    valid = raster_program(2000)
    BROKEN["truncated.nc"] = valid[: len(valid) // 2].rsplit(b"\n", 1)[0] + b"\nN99 G2 X1.5 Y"
    for name, data in BROKEN.items():
        (tmp_path / "nc" / name).write_bytes(data)
    code, out = run_cli("run", str(wf_path), "--workers", "1", "-q")
    assert code == 1
    progs = read_table(tmp_path / "out", "programs").set_index("program_id")
    assert progs.loc["p00", "status"] == "ok" and progs.loc["p00", "n_passes"] > 500
    for name, what in EXPECT.items():
        row = progs.loc[name[:-3]]
        assert row.status == "failed"
        assert row.message.startswith(f"nc/{name}:") and what in row.message, row.message  # relative to the workflow
        assert row.message in out  # the CLI summary names every failure
    problems = read_table(tmp_path / "out", "problems")
    assert set(problems.program_id) == {n[:-3] for n in BROKEN}              # a row at least per failed program
    for name, expected in ALL_PROBLEMS.items():
        rows = problems[problems.program_id == name[:-3]].sort_values(["line", "column"])
        assert len(rows) == len(expected), rows
        for k, ((line, col, what), r) in enumerate(zip(expected, rows.itertuples())):
            assert r.line == line and r.column == col and what in r.message and r.path == f"nc/{name}"
            if k < 5:                                                         # the CLI lists the first five
                assert any(s.strip().startswith(f"nc/{name}:{line}: {what}") and f"at column {col}" in s
                           for s in out.splitlines()), (name, line, col)
    assert "… 2 more in the problems table" in out                           # garbage.nc's 6th and 7th
    passes = read_table(tmp_path / "out", "passes")
    assert set(passes.program_id) == {"p00"}
    assert len(run_json(tmp_path / "out")["failures"]) == len(BROKEN)


@pytest.mark.parametrize("patch,needle", [
    ({"tool": {"type": "ball", "diameter_mm": 6, "flute": 2}}, "tool.flute: unknown key"),
    ({"tool": {"type": "ball", "diameter_mm": -6}}, "tool.diameter_mm"),
    ({"render": {"backend": "vulkan"}}, "render.backend"),
    ({"prune": {"min_contact_deg": 120}}, "prune.min_contact_deg"),
    ({"stok": "x.stl"}, "stok: unknown key"),
    ({"programs": "nothing/*.nc"}, "programs: pattern 'nothing/*.nc' matches no file"),
])
def test_workflow_errors_name_the_key(tmp_path, patch, needle):
    wf_path = make_project(tmp_path, n_programs=1, wf=dict(WF, **patch))
    code, out = run_cli("run", str(wf_path), "-q")
    assert code == 2 and needle in out, out


def test_repo_workflow_is_valid():
    from pipeline.jobs import load_any
    root = Path(__file__).resolve().parent.parent
    for wf in (root / "workflows").glob("*.yaml"):
        load_any(wf)


BOX_PROGRAM = b"""%
O2001 (BOX RASTER)
G90 G17 G21
T1 M6
S6000 M3
G0 X2. Y6. Z5.
G1 Z-0.3 F500
G1 X12. F1200
G1 Y6.6
G1 X2.
G1 Y7.2
G1 X12.
G0 Z5.
M5
M30
%
"""


def test_full_chain_on_a_box_writes_every_table_report_and_corrected_program(tmp_path):
    """parse → … → correct through the engine: every table, the report, a corrected program whose
    non-motion lines are the source's and that parses back to the same blocks."""
    wf = dict(WF, until=None, stock={"box": [0, 0, -10, 20, 20, 0]}, render={"backend": "auto", "px_per_mm": 20},
              prune={"min_contact_deg": 0}, split={"max_pass_mm": 3.0},
              material=dict(WF["material"], kte=20, kre=15, kae=5),
              machine={"frf": {"x": [{"fn_hz": 900, "zeta": 0.03, "k_n_per_um": 0.5}],
                               "y": [{"fn_hz": 900, "zeta": 0.03, "k_n_per_um": 0.5}]}})
    (tmp_path / "nc").mkdir()
    (tmp_path / "nc" / "box.nc").write_bytes(BOX_PROGRAM)
    (tmp_path / "wf.yaml").write_text(yaml.safe_dump(wf))
    code, out = run_cli("run", str(tmp_path / "wf.yaml"), "--workers", "1", "-q")
    assert code == 0, out
    o = tmp_path / "out"
    for t in ("programs", "passes", "cut_filter", "angle_prune", "generating", "engagement", "forces",
              "deflection", "errors", "corrected"):
        assert (o / "tables" / t / "box.parquet").is_file(), t
    cf = read_table(o, "cut_filter")
    passes = read_table(o, "passes")
    assert not cf[passes.motion == 0].is_cutting.any() and cf.is_cutting.sum() >= 10
    err = read_table(o, "errors")
    assert len(err) >= 10 and np.isfinite(err.err_um).all() and (err.err_um.abs() < 50).all()
    assert (o / "report" / "index.html").is_file() and (o / "report" / "error_map.png").stat().st_size > 10_000
    src, new = BOX_PROGRAM.decode().splitlines(), (o / "nc" / "box.nc").read_text().splitlines()
    assert len(new) == len(src) + 1 and new[2].startswith("(CORRECTED PROGRAM")
    motion = {i for i, ln in enumerate(src) if ln.startswith(("G0", "G1"))}
    assert [ln for i, ln in enumerate(src) if i not in motion] == [ln for i, ln in enumerate(new[:2] + new[3:]) if i not in motion]
    corrected = read_table(o, "corrected")
    assert corrected.move_um.max() > 0
    # the README's queries run on the run's DuckDB file; its joined view agrees with the tables
    con = duckdb.connect(str(o / "t.duckdb"), read_only=True)
    for query in readme_queries():
        assert len(con.sql(query).fetchall()) >= 1, query
    view = con.sql("select * from pass_errors order by pass_id").df()
    assert len(view) == len(passes) and set(view.motion) <= {"rapid", "linear", "arc_cw", "arc_ccw"}
    assert (view.motion == "rapid").sum() == (passes.motion == 0).sum()
    e = view.dropna(subset=["err_um"]).set_index("pass_id").err_um.sort_index()
    assert np.array_equal(e.to_numpy(), err.set_index("pass_id").err_um.sort_index().to_numpy())
    con.close()
    # a report that cannot be written (here its directory is a file) is a warning, not a failed run
    shutil.rmtree(o / "report")
    (o / "report").write_text("not a directory")
    code, out = run_cli("run", str(tmp_path / "wf.yaml"), "--workers", "1", "-q")
    summary = json.loads((o / "run.json").read_text())
    assert code == 0 and not summary["failures"], out
    assert "warning: no report" in out and summary["report"] is None and "report" in summary["report_error"]["message"]
    assert (o / "tables" / "errors" / "box.parquet").is_file() and (o / "nc" / "box.nc").is_file()


def test_progress_in_a_log_is_a_line_every_interval_and_one_at_the_end():
    """Without a terminal (a nightly job's log) a stage whose tasks run long still prints lines."""
    import io
    import time

    from pipeline.executor import Progress
    log = io.StringIO()
    meter = Progress("scan", 4, True, every_s=0.05, stream=log)
    time.sleep(0.3)                                   # no task finished yet: lines all the same
    meter.update()
    meter.update()
    meter.close()
    lines = log.getvalue().splitlines()
    assert len(lines) >= 4
    assert all("scan: " in ln and " tasks, " in ln for ln in lines)
    assert "0/4 tasks" in lines[0] and "time left unknown" in lines[0]
    assert "2/4 tasks" in lines[-1] and "s left" in lines[-1]
    n = len(lines)
    time.sleep(0.2)
    assert len(log.getvalue().splitlines()) == n        # closed: no more lines
    quiet = io.StringIO()
    Progress("scan", 1, False, every_s=0.01, stream=quiet).close()
    assert quiet.getvalue() == ""


SLOT_PROGRAM = b"""%
O3001 (ONE SLOT)
G90 G17 G21
T1 M6
S6000 M3
G0 X-6. Y10. Z5.
G1 Z-1. F300
G1 X26. F600
G0 Z5.
M5
M30
%
"""


@pytest.mark.parametrize("case", ["one cutting pass", "one slot in pieces", "nothing predicted"])
def test_degenerate_jobs_get_a_report_and_exit_0(tmp_path, case):
    """One move of a flat end mill slotting a box (exact forces, one predicted pass), the same slot in
    pieces, and a ball skimming a flat top 0.3 mm deep (its contact angle 26° < 45°: nothing is
    predicted): each gets a report and exits 0."""
    flat = case != "nothing predicted"
    wf = dict(WF, until=None, stock={"box": [0, 0, -10, 20, 20, 0]},
              tool={"type": "flat", "diameter_mm": 10, "flutes": 2} if flat else WF["tool"],
              render={"backend": "auto", "px_per_mm": 20},
              prune={"min_contact_deg": 0 if flat else 45},
              split={"max_pass_mm": 100.0 if case == "one cutting pass" else 3.0},
              machine={"frf": {"x": [{"fn_hz": 900, "zeta": 0.03, "k_n_per_um": 2.0}],
                               "y": [{"fn_hz": 900, "zeta": 0.03, "k_n_per_um": 2.0}]}})
    (tmp_path / "nc").mkdir()
    (tmp_path / "nc" / "job.nc").write_bytes(SLOT_PROGRAM if flat else BOX_PROGRAM)
    (tmp_path / "wf.yaml").write_text(yaml.safe_dump(wf))
    code, out = run_cli("run", str(tmp_path / "wf.yaml"), "--workers", "1", "-q")
    summary = run_json(tmp_path / "out")
    assert code == 0 and not summary["failures"] and summary["report_error"] is None, out
    page = (tmp_path / "out" / "report" / "index.html").read_text()
    cut = read_table(tmp_path / "out", "cut_filter")
    pred = int(read_table(tmp_path / "out", "angle_prune").predict.sum())
    if case == "one cutting pass":
        assert cut.is_cutting.sum() == 1 and pred == 1     # the slot (the plunge is off the box)
    if case == "nothing predicted":
        assert cut.is_cutting.sum() >= 3 and pred == 0 and "No pass has a predicted error" in page
    else:
        assert pred >= 1 and (tmp_path / "out" / "report" / "error_map.png").is_file()
