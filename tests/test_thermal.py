"""Thermal drift fit (seed 003, ``pipeline thermal-fit``): histories written here with their own
formulas (sums of first-order responses), recovered by the fit; bad files refused with file:line."""
from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from click.testing import CliRunner
from hypothesis import Phase, given, settings, strategies as st
from scipy.integrate import solve_ivp

from pipeline.cli import main
from stages.thermal import responses

TAU1, TAU2 = 20 * 60.0, 2 * 3600.0


def history(path, t, cols: dict):
    header = ["time_s", *cols]
    rows = np.column_stack([t, *cols.values()])
    path.write_text(",".join(header) + "\n" + "\n".join(",".join(f"{v:.6g}" for v in r) for r in rows) + "\n")
    return path


def fit(tmp_path, csv, *extra):
    r = CliRunner().invoke(main, ["thermal-fit", "--measurements", str(csv), "--out", str(tmp_path / "drift.yaml"),
                                  *extra])
    return r


def two_sources(t, a1, a2):
    return a1 * (1 - np.exp(-t / TAU1)) + a2 * (1 - np.exp(-t / TAU2))


# the seed's magnitude: ≈ 50 µm in X after a 3-hour warm-up (each X source 20–35 µm); a reference
# measured every minute. (With a 15 µm fast source alone, sampled every 2 min, τ1's standard error
# is 6.6 % and one history in ten misses 10 %: the bound is the data's, not the fit's.)
@settings(max_examples=6, deadline=None, phases=[Phase.explicit, Phase.reuse, Phase.generate])
@given(ax=st.tuples(st.floats(20, 35), st.floats(20, 35)), ay=st.tuples(st.floats(-15, 15), st.floats(-15, 15)),
       az=st.tuples(st.floats(-10, 10), st.floats(-10, 10)), seed=st.integers(0, 2 ** 16))
def test_an_eight_hour_history_of_two_heat_sources_is_recovered(tmp_path_factory, ax, ay, az, seed):
    """Must show: 8 h, τ 20 min and 2 h, noise 0.5 µm: the drift within 1 µm RMS over the whole
    history, both time constants within 10 %."""
    tmp = tmp_path_factory.mktemp("drift")
    t = np.arange(0, 8 * 3600 + 1, 60.0)
    true = {"dx_um": two_sources(t, *ax), "dy_um": two_sources(t, *ay), "dz_um": two_sources(t, *az)}
    rng = np.random.default_rng(seed)
    csv = history(tmp / "m.csv", t, {k: v + rng.normal(0, 0.5, len(t)) for k, v in true.items()})
    r = fit(tmp, csv, "--predict", str(history(tmp / "times.csv", np.linspace(0, 8 * 3600, 1000), {})),
            "--predicted", str(tmp / "pred.csv"))
    assert r.exit_code == 0, r.output
    rep = json.loads((tmp / "drift.json").read_text())
    taus = sorted(x["value"] for x in rep["time_constants_s"])
    assert taus[0] == pytest.approx(TAU1, rel=0.10) and taus[1] == pytest.approx(TAU2, rel=0.10), taus
    pred = np.loadtxt(tmp / "pred.csv", delimiter=",", skiprows=1)
    tt = pred[:, 0]
    for i, (a1, a2) in enumerate((ax, ay, az)):
        err = pred[:, 1 + i] - two_sources(tt, a1, a2)
        assert np.sqrt(np.mean(err ** 2)) < 1.0, (i, np.sqrt(np.mean(err ** 2)))
    # the residual is the noise, the picture exists
    assert all(0.35 < v < 0.65 for v in rep["rms_um"].values()), rep["rms_um"]
    assert (tmp / "drift.png").stat().st_size > 10_000


def test_responses_follow_the_first_order_law_under_a_switching_heat_input():
    """Spindle at full speed, off, half speed: the closed form against a numerical ODE solution."""
    t = np.unique(np.r_[np.linspace(0, 5 * 3600, 301), [3599.0, 3601.0, 7199.0, 7201.0]])
    u = np.where(t < 3600, 1.0, np.where(t < 7200, 0.0, 0.5))
    r = responses(t, u, np.array([TAU1, TAU2]))
    for k, tau in enumerate((TAU1, TAU2)):
        def rhs(tt, y):
            return [((1.0 if tt < 3600 else 0.0 if tt < 7200 else 0.5) - y[0]) / tau]
        sol = solve_ivp(rhs, (0, t[-1]), [0.0], t_eval=t, max_step=20.0, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(r[:, k], sol.y[0], atol=2e-4)


def test_heat_input_and_position_cross_terms_are_recovered(tmp_path):
    """The seed's X → Y error grows linearly with X; the spindle stops for an hour mid-run."""
    rng = np.random.default_rng(3)
    t = np.arange(0, 8 * 3600 + 1, 90.0)
    rpm = np.where((t >= 3 * 3600) & (t < 4 * 3600), 0.0, 12000.0)
    x = rng.uniform(-20, 20, len(t))                                   # the reference's X stop, mm
    r = responses(t, rpm / 12000.0, np.array([TAU1, TAU2]))
    dx = 35 * r[:, 0] + 15 * r[:, 1]
    dy = (4 + 1.2 * x) * r[:, 1] + 3 * r[:, 0]                          # 0–50 µm across ±20 mm of X
    dz = -6 * r[:, 0]
    csv = history(tmp_path / "m.csv", t, {"dx_um": dx + rng.normal(0, .5, len(t)), "dy_um": dy + rng.normal(0, .5, len(t)),
                                          "dz_um": dz + rng.normal(0, .5, len(t)), "spindle_rpm": rpm, "x_mm": x})
    res = fit(tmp_path, csv)
    assert res.exit_code == 0, res.output
    model = yaml.safe_load((tmp_path / "drift.yaml").read_text())
    assert model["heat_input"]["column"] == "spindle_rpm" and model["positions"]["columns"] == ["x_mm"]
    taus = model["time_constants_s"]
    assert taus[0] == pytest.approx(TAU1, rel=0.1) and taus[1] == pytest.approx(TAU2, rel=0.1)
    y = model["axes"]["y"]
    # slope per mm of X on the slow source, at the fitted origin
    assert y["gain2_um_per_x_mm"] == pytest.approx(1.2, abs=0.05)
    # predict on a fresh schedule (spindle stop elsewhere) and position
    tt = np.arange(0, 8 * 3600 + 1, 60.0)
    rpm2 = np.where(tt < 5 * 3600, 12000.0, 6000.0)
    times = history(tmp_path / "times.csv", tt, {"spindle_rpm": rpm2, "x_mm": np.full(len(tt), 15.0)})
    res = CliRunner().invoke(main, ["thermal-fit", "--model", str(tmp_path / "drift.yaml"), "--predict", str(times),
                                    "--predicted", str(tmp_path / "p.csv")])
    assert res.exit_code == 0, res.output
    p = np.loadtxt(tmp_path / "p.csv", delimiter=",", skiprows=1)
    r2 = responses(tt, rpm2 / 12000.0, np.array([TAU1, TAU2]))
    want = np.column_stack([35 * r2[:, 0] + 15 * r2[:, 1], (4 + 1.2 * 15) * r2[:, 1] + 3 * r2[:, 0], -6 * r2[:, 0]])
    assert np.sqrt(np.mean((p[:, 1:] - want) ** 2, axis=0)).max() < 1.0


@pytest.mark.parametrize("text, where, what", [
    ("time_s,dx_um,dy_um,dz_um\n0,0,0,0\n120,1,1,1\n60,2,2,2\n", ":4:", "not after the previous line's 120"),
    ("time_s,dx_um,dz_um\n0,0,0\n", ":1:", "missing column(s) dy_um"),
    ("time_s,dx_um,dy_um,dz_um\n0,0,0,0\n60,1,abc,1\n", ":3:", "column 'dy_um': 'abc' is not a number"),
    ("time_s,dx_um,dy_um,dz_um\n0,0,0,0\n60,1,1,1\n120,2,2,2\n", ":", "fewer than the model's"),
])
def test_bad_files_are_refused_naming_file_and_line(tmp_path, text, where, what):
    csv = tmp_path / "bad.csv"
    csv.write_text(text)
    r = fit(tmp_path, csv)
    assert r.exit_code == 2 and f"bad.csv{where}" in r.output and what in r.output, r.output
    assert not (tmp_path / "drift.yaml").exists()
