"""Calibration on a reference part (``stages.gap.calibration``): the force scale is taken only where
the reference pins it, and a model floor above the probe noise is subtracted point by point. Truths
come from this file's own formulas; fresh seeds (``GAP_TEST_SEED`` replays one)."""
from __future__ import annotations

import numpy as np

from stages.gap.calibration import baseline, calibrate
from tests.gap_helpers import associated, fresh_rng, sample


def _reference(rng, residual, deflection):
    F = associated(np.asarray(residual, float))
    F["pred_deflection_um"] = np.asarray(deflection, float)
    return F


def test_the_force_scale_is_taken_only_where_the_reference_pins_it():
    """A reference whose residual is (s − 1)·d + noise: with a predicted deflection of 5–15 µm the
    scale comes back within 0.05 of s; with one of 0.01–0.05 µm (a floor plan: the deflection acts
    across the normals) the noise alone would give any scale, and the model is kept as it is (1)."""
    seed, rng = fresh_rng()
    n = len(sample()[1])
    s = rng.uniform(0.7, 1.4)
    for lo, hi, pinned in ((5.0, 15.0, True), (0.01, 0.05, False)):
        d = rng.uniform(lo, hi, n) * rng.choice([-1, 1], n)
        cal = calibrate(_reference(rng, (s - 1) * d + rng.normal(0, 0.5, n), d))
        case = f"seed {seed}: s {s:.3f}, deflection {lo}-{hi} um -> {cal['force_scale_s0']:.3f} (SE {cal['force_scale_se']})"
        assert (abs(cal["force_scale_s0"] - s) <= 0.05) if pinned else cal["force_scale_s0"] == 1.0, case


def test_a_model_floor_above_the_noise_is_subtracted_point_by_point():
    """The prediction's own error on this plan: a pattern of 2–4 µm RMS (this file's formula along
    x and y) on the reference and on the measured part, probe noise σ 0.3–0.6 µm on each. After the
    baseline the measured residual is the part's own error + the difference of two noises: its RMS
    within 15 % of hypot(σ, σ_ref) around that error, and the floor left for the size test is 0.
    A pattern under the noise is not subtracted: the floor goes to the size test instead."""
    seed, rng = fresh_rng()
    _, pts, _ = sample()
    n = len(pts)
    sig, sig_ref = rng.uniform(0.3, 0.6, 2)
    k = 2 * np.pi / rng.uniform(1.5, 4.0, 2)
    shape = np.sin(k[0] * pts[:, 0] + rng.uniform(0, 6)) * np.cos(k[1] * pts[:, 1])
    own = rng.uniform(2, 5) * (pts[:, 0] - pts[:, 0].mean()) / np.ptp(pts[:, 0])     # the part's own error
    for size, subtracted in ((rng.uniform(2, 4), True), (0.05, False)):
        pattern = size * shape / np.sqrt(np.mean(shape ** 2))
        cal = calibrate(_reference(rng, pattern + rng.normal(0, sig_ref, n), np.zeros(n)))
        F, floor = baseline(_reference(rng, pattern + own + rng.normal(0, sig, n), np.zeros(n)), cal)
        left = F["residual_um"] - own
        case = (f"seed {seed}: pattern {size:.2f} um RMS, sigma {sig:.2f}/{sig_ref:.2f} -> floor {cal['floor_um']:.2f}, "
                f"subtracted {cal['floor_subtracted']}, left {np.sqrt(np.mean(left ** 2)):.3f} um")
        assert cal["floor_subtracted"] == subtracted, case
        if subtracted:
            assert floor == 0.0 and "_floor_map" in cal, case
            assert abs(np.sqrt(np.mean(left ** 2)) / np.hypot(sig, sig_ref) - 1) <= 0.15, case
        else:
            assert floor == cal["floor_um"] and "_floor_map" not in cal, case
            assert np.allclose(left, F["measured_um"] - own), case
