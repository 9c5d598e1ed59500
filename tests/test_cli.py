"""The auxiliary commands end to end through the CLI: calibrate-forces and tool-profile."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from pipeline.cli import main
from tests.test_cutting import KE, analytic_flat_forces

ROOT = Path(__file__).resolve().parent.parent


def test_calibrate_forces_recovers_the_coefficients(tmp_path):
    N, a, rpm = 3, 2.0, 6000.0
    wf = {"name": "cal", "programs": "*.nc", "tool": {"type": "flat", "diameter_mm": 10, "flutes": N, "helix_deg": 0},
          "material": {"name": "m", "ktc": 1, "krc": 1, "kac": 1}}
    (tmp_path / "wf.yaml").write_text(yaml.safe_dump(wf))
    theta = (np.arange(720) + 0.5) * 0.5
    rng = np.random.default_rng(1)
    cuts = []
    for i, (feed, width) in enumerate([(900.0, None), (2400.0, None), (1500.0, 2.5)]):
        st, ex = (0.0, np.pi) if width is None else (np.pi - np.arccos(1 - width / 5.0), np.pi)
        f = analytic_flat_forces(theta, N, a, feed / (rpm * N), KE, st, ex) + rng.normal(0, 1.0, (theta.size, 3))
        np.savetxt(tmp_path / f"r{i}.csv", np.column_stack([theta, -f]), delimiter=",",
                   header="rotation_deg,fx_n,fy_n,fz_n", comments="")
        cuts.append({"file": f"r{i}.csv", "axial_depth_mm": a, "radial_width_mm": width, "side": "right",
                     "feed_mm_min": feed, "spindle_rpm": rpm})
    (tmp_path / "cuts.yaml").write_text(yaml.safe_dump(cuts))
    out = tmp_path / "fit.json"
    r = CliRunner().invoke(main, ["calibrate-forces", str(tmp_path / "wf.yaml"), "--cuts", str(tmp_path / "cuts.yaml"),
                                  "--out", str(out)])
    assert r.exit_code == 0, r.output
    fit = json.loads(out.read_text())
    for k, v in KE.items():
        assert fit[k] == pytest.approx(v, rel=0.02), k


def test_tool_profile_command_on_sample_images(tmp_path):
    out = tmp_path / "p.csv"
    r = CliRunner().invoke(main, ["tool-profile", "--images", str(ROOT / "data_samples/tool_images/t1"),
                                  "--um-per-px", "8", "--diameter-mm", "10", "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert out.is_file() and out.with_suffix(".json").is_file() and out.with_suffix(".png").is_file()
    # the sample images were drawn with 4 µm of runout (scripts/make_tool_images.py)
    assert json.loads(out.with_suffix(".json").read_text())["eccentricity_um"] == pytest.approx(4.0, abs=0.5)


def test_tool_profile_bad_image_names_the_file_and_writes_nothing(tmp_path):
    imgs = tmp_path / "imgs"
    shutil.copytree(ROOT / "data_samples/tool_images/t1", imgs)
    (imgs / "t1_060deg.png").write_bytes(b"not a png")
    out = tmp_path / "o" / "p.csv"
    r = CliRunner().invoke(main, ["tool-profile", "--images", str(imgs), "--um-per-px", "8", "--diameter-mm", "10",
                                  "--out", str(out)])
    assert r.exit_code == 2 and "t1_060deg.png" in r.output
    assert not out.exists()


def test_run_names_an_unknown_job_with_its_line(tmp_path):
    wf = tmp_path / "w.yaml"
    wf.write_text("name: x\njob: turning\n")
    r = CliRunner().invoke(main, ["run", str(wf)])
    assert r.exit_code == 2
    assert f"{wf}:2: job: unknown job 'turning'" in r.output
