"""Workflow overlays (``pipeline run --overlay``) and the diagnosis' ``gap/model_update.yaml``.

Expected values are written out here (merged keys, absolute paths, closed forms of the effects:
±e·sin q of a runout, a·exp(−½((q−q0)/w)²) + rate·L̄ of a profile, A·(1 − e^−1) of a drift at t = τ),
never taken from the code under test.
"""
from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from pipeline.config import WorkflowError, load_workflow
from tests.gap_helpers import cli
from tests.test_engine import BOX_PROGRAM, WF

SMALL = {"name": "m", "programs": "nc/*.nc",
         "tool": [{"t": 1, "type": "ball", "diameter_mm": 6}, {"t": 2, "type": "ball", "diameter_mm": 4}],
         "material": {"name": "A", "ktc": 2000, "krc": 700, "kac": 300},
         "split": {"max_pass_mm": 5.0}, "output": "out"}


def write(path: Path, data) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(data if isinstance(data, str) else yaml.safe_dump(data))
    return path


def test_overlay_merge_semantics(tmp_path):
    """A key overridden, a sibling kept, a list entry chosen by t, a mapping without t into every
    entry, a path relative to the overlay's folder, an unknown key refused naming the overlay."""
    wf = write(tmp_path / "wf.yaml", SMALL)
    ov = write(tmp_path / "sub" / "ov.yaml", {"tool": {"t": 2, "runout_um": 3.5, "profile": "prof.csv"},
                                              "material": {"ktc": 2500}, "split": {"max_pass_mm": 2.0}})
    w, _ = load_workflow(wf, [ov])
    t1, t2 = w.tool_for(1), w.tool_for(2)
    assert (t1.runout_um, t1.profile, t1.diameter_mm) == (0.0, None, 6.0)
    assert (t2.runout_um, t2.diameter_mm) == (3.5, 4.0)
    assert t2.profile == str(tmp_path / "sub" / "prof.csv")
    assert (w.material.ktc, w.material.krc, w.split.max_pass_mm, w.split.chord_tol_mm) == (2500.0, 700.0, 2.0, 0.001)
    every = write(tmp_path / "every.yaml", {"tool": {"helix_deg": 40}})
    w, _ = load_workflow(wf, [ov, every])
    assert [t.helix_deg for t in w.tool] == [40.0, 40.0] and w.tool_for(2).runout_um == 3.5
    bad = write(tmp_path / "sub" / "bad.yaml", "material: {ktc: 1}\ntool: {runout_umm: 3}\n")
    with pytest.raises(WorkflowError, match=r"bad\.yaml:2: tool\.runout_umm: unknown key 'runout_umm'; did you mean 'runout_um'"):
        load_workflow(wf, [bad])
    neg = write(tmp_path / "neg.yaml", {"tool": {"runout_um": -1}})
    with pytest.raises(WorkflowError, match=r"neg\.yaml:1: tool\.\d\.runout_um: Input should be greater"):
        load_workflow(wf, [neg])


def box_project(root: Path) -> Path:
    wf = dict(WF, until="errors", stock={"box": [0, 0, -10, 20, 20, 0]}, render={"backend": "auto", "px_per_mm": 20},
              prune={"min_contact_deg": 0}, split={"max_pass_mm": 3.0},
              material=dict(WF["material"], kte=20, kre=15, kae=5),
              machine={"frf": {"x": [{"fn_hz": 900, "zeta": 0.03, "k_n_per_um": 0.5}],
                               "y": [{"fn_hz": 900, "zeta": 0.03, "k_n_per_um": 0.5}]}})
    (root / "nc").mkdir(parents=True)
    (root / "nc" / "box.nc").write_bytes(BOX_PROGRAM)
    return write(root / "wf.yaml", wf)


def test_run_with_overlay_changes_the_prediction_and_names_the_overlay(tmp_path):
    """tool.runout_um = 6 µm by overlay: the errors' runout part becomes ±6·sin q (0 without it);
    parse stays cached; run.json and the report name the overlay."""
    wf = box_project(tmp_path)
    r = cli("run", wf, "--workers", "1", "-q")
    assert r.exit_code == 0, r.output
    out = tmp_path / "out"
    before = pd.read_parquet(out / "tables" / "errors")
    assert np.all(before.err_runout_um == 0) and json.loads((out / "run.json").read_text())["overlay"] == []
    ov = write(tmp_path / "upd" / "model_update.yaml", {"tool": {"runout_um": 6.0}})
    r = cli("run", wf, "--overlay", ov, "--workers", "1", "-q")
    assert r.exit_code == 0, r.output
    run = json.loads((out / "run.json").read_text())
    assert run["overlay"] == [str(ov)]
    assert next(s for s in run["stages"] if s["name"] == "parse")["computed"] == 0
    after = pd.read_parquet(out / "tables" / "errors")
    q = np.radians(after.contact_deg.to_numpy())
    assert len(after) >= 10 and np.allclose(np.abs(after.err_runout_um), 6.0 * np.sin(q), atol=1e-6)
    assert not np.allclose(after.err_um, before.err_um)
    page = (out / "report" / "index.html").read_text()
    assert f"Overlay: {ov}" in page
    r = cli("status", wf, "--overlay", ov, "--json")
    assert r.exit_code == 0 and all(row["pending"] == 0 for row in json.loads(r.output))


def test_workflow_update_of_every_effect(tmp_path):
    """Each catalogue effect as workflow keys: profile = a·exp(−½((q−q0)/w)²) + rate·L̄, material × s,
    a drift model with A·(1 − e^−1) at t = τ, servo and geometry listed as not applied; the
    overlay loads over a workflow listing two tools and changes only T2's entry."""
    from stages.gap.model_update import workflow_update, write_update
    from stages.thermal.model import DriftModel
    params = {"tool_contour": {"a_um": 4.0, "q0_deg": 30.0, "width_deg": 8.0}, "tool_wear": {"rate_um_per_m": 2.0},
              "force_scale": {"scale": 1.25}, "thermal_drift": {"ax_um": 3.0, "ay_um": -2.0, "az_um": 9.0, "tau_s": 600.0},
              "servo_corner": {"a_um": 5.0, "lambda_mm": 0.5}, "machine_geometry": {"sx": 1.0}}
    obs = {"thermal_drift": {"ay_um": "not observable"}}
    gdir = tmp_path / "out" / "gap"
    mat = {"name": "A", "ktc": 2000.0, "krc": 700.0, "kac": 300.0, "kte": 20.0, "kre": 0.0, "kae": None}
    upd = workflow_update(params, obs, {"t": 2, "type": "ball", "diameter_mm": 4, "runout_um": 0.0}, mat, tool_t=2,
                          material_t=None, base=tmp_path, outdir=gdir, cut_len_mean_m=1.5)
    path = write_update(gdir / "model_update.yaml", upd, params)
    assert set(upd["unapplied"]) == {"servo_corner", "machine_geometry"}
    text = path.read_text()
    assert "# not applied: servo_corner" in text and "# not applied: machine_geometry" in text
    wf = write(tmp_path / "wf.yaml", SMALL)
    w, _ = load_workflow(wf, [path])
    assert w.tool_for(1).profile is None
    prof = pd.read_csv(w.tool_for(2).profile)
    expect = 4.0 * np.exp(-0.5 * ((prof.contact_deg - 30.0) / 8.0) ** 2) + 2.0 * 1.5
    assert np.allclose(prof.error_um, expect, atol=1e-5) and prof.contact_deg.max() == 90.0
    assert (w.material.ktc, w.material.krc, w.material.kac, w.material.kte) == (2500.0, 875.0, 375.0, 25.0)
    assert w.drift.start_s == 0.0 and Path(w.drift.model).parent == gdir
    model = DriftModel.from_dict(yaml.safe_load(Path(w.drift.model).read_text()))
    d = model.predict({"time_s": np.array([0.0, 600.0])})
    k = 1 - math.exp(-1)
    assert np.allclose(d["dx_um"], [0, 3.0 * k]) and np.allclose(d["dy_um"], 0) and np.allclose(d["dz_um"], [0, 9.0 * k])


def test_diagnose_writes_a_model_update_of_the_fitted_runout(tmp_path):
    """The first two rows of the gap sample, a 10 µm runout on the virtual machine: model_update.yaml
    sets tool.runout_um to the diagnosed e of summary.json, and a run with it as overlay predicts
    the runout part ±e·sin q."""
    from tests.gap_helpers import MAT, SAMPLE, simulate_runout_then_diagnose
    lines = (SAMPLE / "gap_t1.nc").read_text().splitlines()
    (tmp_path / "two.nc").write_text("\n".join(lines[:49] + ["G0 Z10.", "M5", "M30", "%"]) + "\n")
    for f in ("stock.stl", "plan.csv"):
        shutil.copy(SAMPLE / f, tmp_path / f)
    wf = write(tmp_path / "wf.yaml", {
        "name": "two", "programs": "two.nc", "stock": "stock.stl",
        "tool": {"type": "ball", "diameter_mm": 6.0, "flutes": 2, "helix_deg": 30.0, "stickout_mm": 30.0},
        "material": dict(MAT, name="FCD550"),
        "machine": {"frf": {"x": [{"fn_hz": 900, "zeta": 0.03, "k_n_per_um": 8.0}],
                            "y": [{"fn_hz": 950, "zeta": 0.03, "k_n_per_um": 9.0}]}},
        "prune": {"min_contact_deg": 0}, "split": {"merge_max_mm": 0.001}, "output": "out"})
    simulate_runout_then_diagnose(wf, tmp_path / "m.csv")
    g = tmp_path / "out" / "gap"
    s = json.loads((g / "summary.json").read_text())
    e = s["params"]["runout"]["e_um"]
    assert abs(e - 10.0) <= 2.0
    upd = yaml.safe_load((g / "model_update.yaml").read_text())
    assert upd["tool"] == {"runout_um": pytest.approx(e, abs=1e-9)}
    assert s["overlay"]["file"] == str(g / "model_update.yaml")
    assert s["overlay"]["applied"]["runout"] == {"tool.runout_um": pytest.approx(e, abs=1e-9)}
    assert set(s["overlay"]["unapplied"]) == {k for k in s["params"] if k in ("servo_corner", "machine_geometry")}
    r = cli("run", wf, "--overlay", g / "model_update.yaml", "--until", "errors", "--workers", "1", "-q")
    assert r.exit_code == 0, r.output
    err = pd.read_parquet(tmp_path / "out" / "tables" / "errors")
    q = np.radians(err.contact_deg.to_numpy())
    assert np.allclose(np.abs(err.err_runout_um), e * np.sin(q), atol=1e-6)


def test_the_diagnosis_profile_table_adds_the_dent_to_the_workflow_profile(tmp_path):
    """``Predictor.profile_csv`` (the re-prediction's table) = the workflow's profile (here 1 µm at
    0°, 3 µm at 90°, linear between) + a·exp(−½((q−q0)/w)²)."""
    from stages.gap.predictor import Predictor
    from tests.gap_helpers import TOOL
    base = write(tmp_path / "base.csv", "contact_deg,error_um\n0,1\n90,3\n")
    p = Predictor({}, dict(TOOL, profile=str(base)), {}, {}, workdir=tmp_path / "w")
    prof = pd.read_csv(p.profile_csv({"a_um": -2.0, "q0_deg": 45.0, "width_deg": 5.0}, "x.csv"))
    q = prof.contact_deg.to_numpy()
    assert np.allclose(prof.error_um, 1 + 2 * q / 90 - 2.0 * np.exp(-0.5 * ((q - 45) / 5) ** 2), atol=1e-5)
