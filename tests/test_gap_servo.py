"""The servo lag near path corners: the diagnosis's tooth-passage envelope against this file's brute
force, its fit against the virtual machine's lag, and the corner floor a reference part gives.
Lags and decay lengths are drawn at random from the stated ranges (a fresh seed per test).
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from stages.gap.calibration import apply_baseline, corner_floor
from stages.gap.effects import catalogue
from stages.gap.fit import fit_effects
from stages.gap.servo import refine_servo, servo_signature, servo_smooth
from stages.nc.moves import split_blocks
from stages.nc.reader import parse_program
from tests.gap_helpers import FZ, TOOL, R, associated, fresh_rng, rms, signature


def corner_job():
    """A 20 mm move along +x turning 90° into +y (F800, S8000: fz = FZ), ball centres of the first leg
    d mm before the corner, contact points on the outer side of the turn at q = 45°."""
    nc = "%\nG90 G17 G21\nS8000 M3\nG0 X-10. Y0. Z5.\nG1 Z0. F400\nG1 X10. F800\nG1 Y10.\nG0 Z10.\nM30\n%\n"
    blocks, _ = parse_program(nc.encode(), "corner.nc", "corner")
    passes = split_blocks(blocks, {"split": {"chord_tol_mm": 0.001, "max_pass_mm": 5.0, "merge_max_mm": 0.0},
                                   "machine": {"rapid_mm_min": 30000.0}, "tool": TOOL})
    q = math.radians(45.0)
    d = np.concatenate([np.linspace(0.01, 0.5, 25), np.linspace(0.6, 3.0, 13)])
    n = np.tile([0.0, math.sin(q), math.cos(q)], (len(d), 1))
    pts = np.stack([10 - d, np.zeros_like(d), np.full_like(d, R)], 1) - R * n
    F = associated(np.zeros(len(d)), passes, pts, n)
    return F, np.argsort(F["point_id"]), d, pts, n


def brute_force_lag_surface(d, pts, n, a_um, lam, phases=64, reach_mm=3.0):
    """This test's own surface of the corner job with a servo lag: every tooth passage (one per FZ,
    ±reach_mm along the two legs, lag a·e^(−|s − corner|/λ) towards the inside of the 90° turn)
    is a ball; the surface along n is the lowest entry into any of them, averaged over `phases`
    spindle phases, less the same without the lag (µm)."""
    b = np.array([-1.0, 1.0, 0.0]) / math.sqrt(2)
    k = np.arange(-int(reach_mm / FZ), int(reach_mm / FZ) + 1)
    out = np.zeros(len(d))
    for i in range(len(d)):
        s = 20.0 - d[i] + ((np.arange(phases) + 0.5) / phases - 0.5)[:, None] * FZ + k[None, :] * FZ
        cen = np.where((s <= 20.0)[..., None], np.stack([-10 + s, 0 * s, R + 0 * s], -1),
                       np.stack([10 + 0 * s, s - 20, R + 0 * s], -1))

        def entry(lag_um):
            cp = cen + lag_um[..., None] * b * 1e-3 - pts[i]
            A = cp @ n[i]
            inner = R * R - (np.sum(cp * cp, -1) - A * A)
            return np.where(inner >= 0, A - np.sqrt(np.maximum(inner, 0.0)), np.inf).min(axis=1)
        lag = a_um * np.exp(-np.abs(s - 20.0) / lam)       # sin(90°/2)/sin 45° = 1
        out[i] = np.mean(entry(lag) - entry(0 * lag)) * 1e3
    return out


def test_servo_signature_is_the_tooth_passage_envelope():
    """The diagnosis's servo-lag signature (8 phases, its own passage window) against this file's
    brute force (64 phases, ±3 mm of passages) at a straight 90° corner, for a lag a of ±10–30 µm
    with decay λ 0.3–0.8 mm: within 0.1 µm (a third of the smallest probe noise the blind check
    draws); for strongly curved lags (|a|/λ² ≥ 50 µm/mm²) the smooth form a·(b·n)·e^(−d/λ) is not
    (the passage nearer the corner, with the larger lag, cuts deepest)."""
    F, o, d, pts, n = corner_job()
    seed, rng = fresh_rng()
    for _ in range(3):
        a_um, lam = rng.choice([-1.0, 1.0]) * rng.uniform(10.0, 30.0), rng.uniform(0.3, 0.8)
        ref = brute_force_lag_surface(d, pts, n, a_um, lam)
        case = f"seed {seed}: a {a_um:.2f} um, lambda {lam:.3f} mm"
        assert np.abs(ref).max() > 0.4 * abs(a_um), case                    # the corner is reached
        assert np.max(np.abs(servo_signature(F, a_um, lam)[o] - ref)) <= 0.1, case
        if abs(a_um) / lam ** 2 >= 50.0:
            assert np.max(np.abs(a_um * servo_smooth(F, lam)[o] - ref)) > 0.1, case


def test_servo_fit_recovers_the_virtual_machines_lag():
    """A noise-free servo lag of the virtual machine (its own tooth passages at their real phase) on
    the sample plan, a ±15–30 µm with λ 0.25–0.6 mm: the fitted a and λ within 3 % (the smooth form
    alone read 30 → 27.7 µm and −30 → −34.5 µm at λ 0.3 mm)."""
    seed, rng = fresh_rng()
    a_um, lam = rng.choice([-1.0, 1.0]) * rng.uniform(15.0, 30.0), rng.uniform(0.25, 0.6)
    F = associated(signature({"servo_corner": {"a_um": a_um, "lambda_mm": lam}}))
    eff = {e.name: e for e in catalogue(F)}["servo_corner"]
    allp = np.ones(len(F["q_deg"]), bool)
    th, beta = fit_effects(F, F["measured_um"], allp, [], eff)
    ch, beta = refine_servo(F, F["measured_um"], allp, [(eff, th)], beta)
    p = eff.params(beta, ch[0][1])
    case = f"seed {seed}: a {a_um:.2f} um, lambda {lam:.3f} mm -> {p}"
    assert p["a_um"] == pytest.approx(a_um, rel=0.03) and p["lambda_mm"] == pytest.approx(lam, rel=0.03), case


def test_corner_floor_taken_from_a_reference_part_leaves_the_other_effects():
    """A reference part whose residual near corners is a lag (the virtual machine's, ±15–30 µm with
    λ 0.25–0.5 mm, noise-free): ``corner_floor`` reads it back within 3 %, and as part of the
    baseline it leaves of a part with that floor and a tool wear (20–60 µm/m) the wear alone, within
    0.03 µm RMS (a tenth of the smallest probe noise the blind check draws; the two are not exactly
    additive: the deepest tooth passage takes both, ~0.015 µm here)."""
    seed, rng = fresh_rng()
    a_um, lam = rng.choice([-1.0, 1.0]) * rng.uniform(15.0, 30.0), rng.uniform(0.25, 0.5)
    lag = {"servo_corner": {"a_um": a_um, "lambda_mm": lam}}
    wear = {"tool_wear": {"rate_um_per_m": rng.uniform(20.0, 60.0)}}
    case = f"seed {seed}: {lag}, {wear}"
    y0 = signature(lag)
    a, lam_fit = corner_floor(associated(y0))
    assert a == pytest.approx(a_um, rel=0.03) and lam_fit == pytest.approx(lam, rel=0.03), case
    left = apply_baseline(associated(signature(dict(lag, **wear))), 1.0, (a, lam_fit))["residual_um"]
    assert rms(left - signature(wear)) < 0.03, case
