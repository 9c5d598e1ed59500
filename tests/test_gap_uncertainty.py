"""Standard errors the diagnosis states (``stages.gap.uncertainty``): against the spread of repeated
fits to fresh noise (Monte Carlo, this file's own reference), and null with a reason where the
points cannot tell parameters apart, checked against this file's own (XᵀX)⁻¹. The Monte Carlo of
the tool contour (its stated SE ~10 % above the spread, 0.76–0.97 over 12 truths: too near the 25 %
line for a fresh seed) and of the servo lag (150 envelope fits, ~40 s) is
``bench/gap_standard_errors.py``.
"""
from __future__ import annotations

import numpy as np
import pytest

from stages.gap.effects import Effect
from stages.gap.uncertainty import param_uncertainty
from tests.gap_helpers import brute_force_features, fresh_rng, repeated_fits

DRAWS = 200        # noise draws: the reference's own sampling error 1/√(2·DRAWS) = 5 %


def test_stated_standard_errors_of_a_drift_match_the_spread_of_repeated_fits():
    """A thermal drift (|A| 8–12 µm about (3, −4, −8)/|·|, τ 0.3–0.5 × the run, σ 0.5–0.8 µm): the
    empirical standard deviation of every parameter over ``DRAWS`` noise draws against the median
    standard error the diagnosis states (``param_uncertainty``): within 25 %; the mean of the fits
    within half a stated SE of the truth. Linear amplitudes (A) and a nonlinear value (τ)."""
    seed, rng = fresh_rng()
    a = np.array([3.0, -4.0, -8.0]) + rng.normal(0.0, 1.0, 3)
    a *= rng.uniform(8.0, 12.0) / np.linalg.norm(a)
    truth = {"ax_um": a[0], "ay_um": a[1], "az_um": a[2], "tau_s": rng.uniform(0.3, 0.5) * brute_force_features()["duration_s"]}
    noise = rng.uniform(0.5, 0.8)
    fits, ses = repeated_fits("thermal_drift", truth, noise, DRAWS, rng)
    for k, v in fits.items():
        se = float(np.median(ses[k]))
        case = f"seed {seed}: {truth}, sigma {noise:.2f}: {k} spread {np.std(v, ddof=1):.4g}, stated {se:.4g}"
        assert np.std(v, ddof=1) == pytest.approx(se, rel=0.25), case
        assert abs(v.mean() - truth[k]) <= 0.5 * se, f"{case}, mean {v.mean():.4g}"


def test_standard_errors_of_parameters_the_points_cannot_tell_apart_are_null_with_a_reason():
    """Degenerate cases: a machine geometry on points all at z = 0 (its z terms sz, exz, eyz are
    zero on them) and, separately, a wear whose signature L equals the predicted deflection (force
    scale): those parameters get no standard error and a reason; the others stay finite and agree
    with this test's own (XᵀX)⁻¹ on the identifiable columns."""
    seed, g = fresh_rng()
    n = 300
    nrm = g.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    F = {"q_deg": np.zeros(n), "nx": nrm[:, 0], "ny": nrm[:, 1], "nz": nrm[:, 2], "tip_x_mm": g.uniform(-5, 5, n),
         "tip_y_mm": g.uniform(-5, 5, n), "tip_z_mm": np.zeros(n), "cut_len_mm": g.uniform(0, 1000, n)}
    F["pred_deflection_um"] = F["cut_len_mm"] * 1e-3
    geo = Effect("machine_geometry", [()], 6)
    coef = np.array([g.uniform(-2, 2), g.uniform(-2, 2), 0.0, g.uniform(-2, 2), 0.0, 0.0])
    y = geo.basis(F, ()) @ coef + g.normal(0, 0.5, n)
    u = param_uncertainty(F, y, [(geo, ())], coef, 0.5)
    se = u["se"]["machine_geometry"]
    assert se["sz"] is None and se["exz"] is None and se["eyz"] is None, f"seed {seed}"
    assert all("not identifiable" in u["not_identifiable"][f"machine_geometry.{k}"] for k in ("sz", "exz", "eyz"))
    X = np.stack([F["nx"] * F["tip_x_mm"], F["ny"] * F["tip_y_mm"], F["nx"] * F["tip_y_mm"]], 1)   # sx, sy, exy
    ref = u["sigma_um"] * np.sqrt(np.diag(np.linalg.inv(X.T @ X)))
    assert [se["sx"], se["sy"], se["exy"]] == pytest.approx(ref, rel=1e-6), f"seed {seed}"
    wear, fs = Effect("tool_wear", [()], 1), Effect("force_scale", [()], 1)
    u = param_uncertainty(F, y, [(wear, ()), (fs, ())], np.array([1.0, 0.0]), 0.5)
    assert u["se"] == {"tool_wear": {"rate_um_per_m": None}, "force_scale": {"scale": None}}
    assert "force_scale.scale" in u["not_identifiable"]["tool_wear.rate_um_per_m"]
