"""The gap commands through the CLI: ``simulate`` writes a file the reader accepts, and the whole job
(prediction through the render chain, the virtual machine, the diagnosis with its tables, summary,
report, the re-predicted errors and a reference-part calibration) on the first rows of the sample.
The end-to-end job keeps its noise seeds: it checks the plumbing against the truth (a 10 µm
runout) and closed forms (the re-predicted runout part ±e·sin q), not a seed's figures.
"""
from __future__ import annotations

import json
import shutil

import numpy as np
import pyarrow.parquet as pq
import pytest
import yaml
from click.testing import CliRunner

from stages.gap.effects import LIMITS
from stages.gap.measurements import points_and_normals, read_measurements
from tests.gap_helpers import MAT, RIGID, SAMPLE, TOL, cli, fresh_rng, simulate_runout_then_diagnose


@pytest.fixture(scope="module")
def two_rows(tmp_path_factory):
    """The first two rows of the sample as a job: ``wf.yaml`` (a soft machine) and ``rigid.yaml`` (the
    same on a rigid one: no deflection); they share the output directory, so the parsed passes are
    computed once."""
    d = tmp_path_factory.mktemp("two_rows")
    lines = (SAMPLE / "gap_t1.nc").read_text().splitlines()
    (d / "two.nc").write_text("\n".join(lines[:49] + ["G0 Z10.", "M5", "M30", "%"]) + "\n")
    for f in ("stock.stl", "plan.csv"):
        shutil.copy(SAMPLE / f, d / f)
    wf = {"name": "two", "programs": "two.nc", "stock": "stock.stl",
          "tool": {"type": "ball", "diameter_mm": 6.0, "flutes": 2, "helix_deg": 30.0, "stickout_mm": 30.0},
          "material": dict(MAT, name="FCD550"),
          "machine": {"frf": {"x": [{"fn_hz": 900, "zeta": 0.03, "k_n_per_um": 8.0}],
                              "y": [{"fn_hz": 950, "zeta": 0.03, "k_n_per_um": 9.0}]}},
          "prune": {"min_contact_deg": 0}, "split": {"merge_max_mm": 0.001}, "output": "out"}
    (d / "wf.yaml").write_text(yaml.safe_dump(wf))
    (d / "rigid.yaml").write_text(yaml.safe_dump(dict(wf, machine=RIGID, measurements="plan.csv")))
    return d


def test_cli_simulate_writes_a_measurement_file_the_reader_accepts(two_rows, tmp_path):
    """A runout e (2–15 µm, noise-free) on the rigid machine: the file the reader accepts holds
    −e·sin q at the workflow's plan points (within ``TOL``); an unknown effect is an error."""
    from pipeline.cli import main
    seed, rng = fresh_rng()
    e = round(float(rng.uniform(2.0, 15.0)), 3)                   # runout e µm, flute 0 largest
    r = CliRunner().invoke(main, ["simulate", str(two_rows / "rigid.yaml"), "--effect", f"runout:e_um={e}",
                                  "--noise-um", "0", "--out", str(tmp_path / "m.csv")], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    tab, rej, _ = read_measurements(tmp_path / "m.csv")
    _, n = points_and_normals(tab)
    expect = -e * np.sqrt(1 - n[:, 2] ** 2)                     # −e·sin q
    assert tab.num_rows >= 50
    err = np.max(np.abs(tab.column("err_um").to_numpy() - expect))
    assert len(rej) == 0 and err <= TOL, f"seed {seed}: e {e} um, largest deviation from -e sin q {err:.3f} um"
    r = CliRunner().invoke(main, ["simulate", str(two_rows / "rigid.yaml"), "--effect", "spindle:x=1",
                                  "--out", str(tmp_path / "m2.csv")])
    assert r.exit_code == 2 and "unknown effect 'spindle'" in r.output


def test_cli_run_simulate_diagnose_end_to_end_on_two_rows(two_rows, tmp_path):
    """The whole job on the first two rows of the sample: prediction through the render chain, a
    runout of 10 µm on the virtual machine, the diagnosis with its tables, summary and report."""
    wf = two_rows / "wf.yaml"
    simulate_runout_then_diagnose(wf, tmp_path / "m.csv")
    g = two_rows / "out" / "gap"
    s = json.loads((g / "summary.json").read_text())
    assert s["effect"] == "runout" and abs(s["params"]["runout"]["e_um"] - 10.0) <= 2.0
    # on these two rows a thermal drift and a machine geometry fit far beyond any real machine's
    # (hundreds of µm, cancelling each other): that combination is listed, not chosen. What may
    # be named next to the runout on 123 points is one small effect within the limits (a −2 µm
    # lag before the pass-end passages were dropped, a 2–3 µm/mm geometry error since)
    assert "thermal_drift" not in s["effects"] and len(s["effects"]) <= 2
    if "machine_geometry" in s["effects"]:
        assert max(abs(v) for v in s["params"]["machine_geometry"].values()) <= LIMITS["machine_geometry"]
    # how far: the runout was added to the simulation itself (tool.runout_um) and the errors stage
    # re-run: its runout part at every generating point is ±e·sin q of the flute left (e: the fit)
    assert s["how_added"]["runout"].startswith("re-predicted")
    upd = pq.read_table(g / "errors_updated.parquet")
    e_fit = s["params"]["runout"]["e_um"]
    q = np.radians(upd.column("contact_deg").to_numpy())
    assert np.allclose(np.abs(upd.column("err_runout_um").to_numpy()), e_fit * np.sin(q), atol=1e-6)
    assert np.mean(upd.column("err_runout_um").to_numpy() < 0) > 0.9    # mostly the long flute
    assert s["rms_after_um"] < 0.5 * s["rms_before_um"] and s["shrink"] == pytest.approx(1 - s["rms_after_um"] / s["rms_before_um"])
    assert s["where"] and all(k in s["where"][0] for k in ("bbox_mm", "pass_range", "contact_deg", "time_s", "mean_residual_um"))
    assert "residual_map.png" in (g / "index.html").read_text() and (g / "residual_map.png").stat().st_size > 10_000
    assert "runout" not in s["detection_limits"] and s["detection_limits"]["tool_wear"]["hidden_up_to_um"] > 0
    assert "Not seen" in (g / "index.html").read_text()
    # every fitted parameter has a stated standard error (summary, gap_effects, report)
    se = s["params_se"]["runout"]
    assert set(se) == set(s["params"]["runout"]) and 0 < se["e_um"] < 1.0
    assert s["params_se_info"]["sigma_um"] >= s["sigma_um"] and not s["params_se_info"]["not_identifiable"]
    assert "standard errors" in (g / "index.html").read_text()
    pts = pq.read_table(two_rows / "out" / "tables" / "gap_points" / "m.parquet")
    eff = pq.read_table(two_rows / "out" / "tables" / "gap_effects" / "m.parquet")
    assert pts.num_rows == s["n_points"] and eff.column("effect").to_pylist()[0] == "runout"
    assert json.loads(eff.column("params_se").to_pylist()[0]) == pytest.approx(se)
    # with a reference part (no effect, another noise draw) the same calibration as the blind check's
    r = cli("simulate", wf, "--noise-um", "0.3", "--seed", "4", "--plan", SAMPLE / "plan.csv",
            "--out", tmp_path / "ref.csv")
    assert r.exit_code == 0, r.output
    r = cli("diagnose", wf, "--measurements", tmp_path / "m.csv", "--reference", tmp_path / "ref.csv",
            "--out", tmp_path / "cal")
    assert r.exit_code == 0, r.output
    c = json.loads((tmp_path / "cal" / "gap" / "summary.json").read_text())
    cal = c["calibration"]
    assert cal["file"].endswith("ref.csv") and cal["n_points"] == s["n_points"] and 0.5 < cal["force_scale_s0"] < 2.0
    # the truth first and closer; the prediction's floor near the two rows' corners is not pinned by
    # one reference at σ 0.3 µm (``corner_floor``: below 3 standard errors), so it is not taken
    # into the baseline; as without the reference, one small effect may be named next to the runout
    assert c["effect"] == "runout" and abs(c["params"]["runout"]["e_um"] - 10.0) <= 1.0
    assert len(c["effects"]) <= 2 and "thermal_drift" not in c["effects"]
    assert c["calibration"]["corner_floor"] is None
    # held out, the calibrated diagnosis leaves the noise and little more (0.87 µm at σ 0.3 µm; the
    # uncalibrated one 0.79 µm: the reference's s0 = 1.10 is itself read through the probe noise)
    assert c["rms_after_um"] < 0.5 * c["rms_before_um"] and c["rms_after_um"] <= s["rms_after_um"] * 1.25
    bad = (tmp_path / "m.csv").read_text().splitlines()
    (tmp_path / "dup.csv").write_text("\n".join(bad + [bad[1]]) + "\n")
    r = cli("diagnose", wf, "--measurements", tmp_path / "dup.csv")
    assert r.exit_code == 2 and "duplicated point id" in r.output
