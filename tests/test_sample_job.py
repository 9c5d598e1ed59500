"""The README's first command, as a user runs it: the main job on ``data_samples/``, every stage,
then what users touch: the DuckDB file and the README's queries on it, the report in a real
headless browser, the coloured mesh, the corrected programs."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import duckdb
import numpy as np
import pandas as pd
import pytest
import trimesh
import yaml

from tests.test_engine import readme_queries

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
# where CI provides a browser (.ci/run installs Debian's chromium) its absence is a failure, not a skip
BROWSER_REQUIRED = os.environ.get("REQUIRE_BROWSER") == "1"


@pytest.fixture(scope="module")
def job(tmp_path_factory):
    out = tmp_path_factory.mktemp("mould") / "out"
    p = subprocess.run([sys.executable, "-m", "pipeline", "run", "workflows/mould.yaml", "--out", str(out), "-q"],
                       cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stdout + p.stderr
    return out, p.stdout + p.stderr


def test_every_stage_runs_and_every_output_is_written(job):
    out, log = job
    summary = json.loads((out / "run.json").read_text())
    names = {s["name"] for s in summary["stages"]}
    assert {"parse", "split", "scan", "forces", "deflection", "errors", "correct"} <= names
    assert not summary["failures"] and summary["report_error"] is None
    programs = pd.read_parquet(out / "tables" / "programs")
    assert set(programs.status) == {"ok"} and all(not Path(p).is_absolute() for p in programs.path)
    wf = yaml.safe_load((ROOT / "workflows" / "mould.yaml").read_text())
    assert sorted(programs.path) == sorted(str(p.relative_to(ROOT)) for p in ROOT.glob(wf["programs"]))
    # the correction written is the one predicted to deviate least, and less than the program as written
    for pid, k in summary["kept"].items():
        devs = [r["rms_dev_um"] for r in summary["rounds"][pid]]
        if k["kept_round"]:
            assert (out / "nc" / f"{pid}.nc").is_file()
            if k["stalled"]:
                assert k["kept_rms_dev_um"] == min(devs) < devs[0]
        else:
            assert not (out / "nc" / f"{pid}.nc").exists() and min(devs) >= 0.99 * devs[0]
            assert f"warning: {pid}: no coordinate correction" in log


def test_readme_queries_on_the_sample_job(job):
    out, _ = job
    con = duckdb.connect(str(out / "mould.duckdb"), read_only=True)
    errors = pd.read_parquet(out / "tables" / "errors")
    passes = pd.read_parquet(out / "tables" / "passes")
    top, per_program, bands = (con.sql(q).df() for q in readme_queries())
    # the ten largest |err| of the errors table, with their NC line
    expect = errors.reindex(errors.err_um.abs().sort_values(ascending=False).index).head(10)
    np.testing.assert_allclose(np.sort(np.abs(top.err_um)), np.sort(np.abs(expect.err_um.round(2))), atol=0.006)
    lines = passes.set_index(["program_id", "pass_id"]).line_no
    # their lines: those of the passes at or above the tenth |err| (equal errors tie: repeated rows)
    tied = errors[errors.err_um.abs() >= expect.err_um.abs().min() - 0.005]
    assert set(top.line_no) <= {lines[(r.program_id, r.pass_id)] for r in tied.itertuples()}
    # per program: every pass, the predicted ones, their RMS
    per_program = per_program.set_index("program_id")
    for pid, g in passes.groupby("program_id"):
        e = errors[errors.program_id == pid].err_um
        assert per_program.loc[pid, "passes"] == len(g) and per_program.loc[pid, "predicted"] >= len(e) > 0
        assert per_program.loc[pid, "rms_err_um"] == pytest.approx(np.sqrt(np.mean(e ** 2)), rel=1e-9)
    # contact-angle bands partition the predicted passes
    assert bands.n.sum() == len(errors) and (np.diff(bands.q_band_deg) > 0).all()
    con.close()


def test_the_coloured_mesh_has_one_colour_per_vertex_matching_its_error(job):
    out, _ = job
    mesh = trimesh.load(out / "report" / "deviation.ply", process=False)
    colours = mesh.visual.vertex_colors
    assert colours.shape == (len(mesh.vertices), 4)
    err = mesh.metadata["_ply_raw"]["vertex"]["data"]["err_um"]
    red, blue = colours[:, 0].astype(int), colours[:, 2].astype(int)
    big = np.abs(err) > 0.3 * np.abs(err).max()
    assert big.sum() > 100
    assert (red[big & (err > 0)] > blue[big & (err > 0)]).all()      # material left: red
    assert (blue[big & (err < 0)] > red[big & (err < 0)]).all()      # overcut: blue
    # the mesh is the design model (refined): every vertex lies on it
    nominal = trimesh.load(ROOT / "data_samples" / "models" / "mould.stl")
    assert np.allclose(mesh.bounds, nominal.bounds, atol=1e-6)


def test_the_report_loads_in_a_headless_browser(job, tmp_path):
    if CHROMIUM is None:
        if BROWSER_REQUIRED:
            pytest.fail("REQUIRE_BROWSER=1 but no chromium on PATH")
        pytest.skip("no chromium on PATH (CI installs it)")
    out, _ = job
    page = (out / "report" / "index.html").as_uri()
    flags = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             f"--user-data-dir={tmp_path / 'profile'}"]
    dom = subprocess.run(flags + ["--virtual-time-budget=10000", "--dump-dom", page],
                         capture_output=True, text=True, timeout=120).stdout
    n_img = dom.count("<img ")
    assert n_img >= 2 and f'data-images="{n_img}/{n_img}"' in dom, dom[:300]
    assert '<p id="broken"></p>' in dom                                 # no picture named as broken
    shot = tmp_path / "report.png"
    subprocess.run(flags + ["--window-size=1400,2400", f"--screenshot={shot}", page],
                   capture_output=True, timeout=120, cwd=tmp_path)
    import cv2
    img = cv2.imread(str(shot))[..., ::-1].astype(int)                       # RGB
    # the deviation map is on screen: strongly red and strongly blue pixels, not only page grey
    reds = ((img[..., 0] > 150) & (img[..., 2] < 100)).sum()
    blues = ((img[..., 2] > 150) & (img[..., 0] < 100)).sum()
    assert reds > 200 and blues > 50, (reds, blues)
