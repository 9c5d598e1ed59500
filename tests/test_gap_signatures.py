"""The virtual machine's effects against closed forms, on the sample plan, with parameters drawn at
random from stated ranges (a fresh seed per test, printed on failure).

The closed forms are this suite's own (``tests.gap_helpers.brute_force_features``: nearest
ball-centre segment, times and cut lengths summed from the passes, corners from consecutive move
directions), for the surface of the nearest pass (the virtual machine probes that pass's tooth
passages, ``stages.virtual_machine.PROBE_PASSES`` = 1). Tolerance: twice the feed-mark cusp of one
flute per revolution + 0.05 µm (``TOL``), fixed before running.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from tests.gap_helpers import (FZ, MAT, RIGID, SAMPLE, SOFT, TOL, TOOL, R, brute_force_features, fresh_rng, sample,
                               servo_closed_form, signature)


def _unit(rng) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _draw(kind: str, rng, f: dict) -> tuple[dict, np.ndarray]:
    """(parameters drawn from the stated ranges, the closed form of the surface change in µm)."""
    q = np.radians(f["q"])
    if kind == "runout":                           # e 2–15 µm towards flute 0: −e·sin q
        e = rng.uniform(2.0, 15.0)
        return {"e_um": e, "phase_deg": 0.0}, -e * np.sin(q)
    if kind == "tool_contour":                     # |a| 3–12 µm, q0 15–45°, width 5–15°
        p = {"a_um": rng.choice([-1.0, 1.0]) * rng.uniform(3.0, 12.0), "q0_deg": rng.uniform(15.0, 45.0),
             "width_deg": rng.uniform(5.0, 15.0)}
        return p, p["a_um"] * np.exp(-0.5 * ((f["q"] - p["q0_deg"]) / p["width_deg"]) ** 2)
    if kind == "tool_wear":                        # 10–60 µm per m of cut: rate·L
        rate = rng.uniform(10.0, 60.0)
        return {"rate_um_per_m": rate}, rate * f["L"] * 1e-3
    if kind == "thermal_drift":                    # |A| 5–15 µm, any direction, τ 0.1–1 × the run: n·A·(1 − e^(−t/τ))
        a = _unit(rng) * rng.uniform(5.0, 15.0)
        tau = rng.uniform(0.1, 1.0) * f["duration_s"]
        return ({"ax_um": a[0], "ay_um": a[1], "az_um": a[2], "tau_s": tau},
                (f["n"] @ a) * (1 - np.exp(-f["t"] / tau)))
    if kind == "machine_geometry":                 # each coefficient ±1 µm/mm: n·offset(tip)
        g = dict(zip(("sx", "sy", "sz", "exy", "exz", "eyz"), rng.uniform(-1.0, 1.0, 6)))
        x, y, z = f["tip"].T
        off = np.stack([g["sx"] * x + g["exy"] * y + g["exz"] * z, g["sy"] * y + g["eyz"] * z, g["sz"] * z], 1)
        return g, np.sum(off * f["n"], 1)
    raise ValueError(kind)


@pytest.mark.parametrize("kind", ["runout", "tool_contour", "tool_wear", "thermal_drift", "machine_geometry"])
def test_virtual_machine_effect_matches_its_closed_form(kind):
    seed, rng = fresh_rng()
    params, expect = _draw(kind, rng, brute_force_features())
    d = signature({kind: params})
    worst = float(np.max(np.abs(d - expect)))
    assert worst <= TOL, f"seed {seed}: {kind} {params}: {worst:.3f} um from the closed form (tolerance {TOL:.3f})"


def test_servo_corner_signature_decays_from_the_corner():
    """A lag a (±5–25 µm) with decay λ (0.3–1.5 mm) towards the inside of each turn: the smooth form
    a·(b·n)·sin(θ/2)/sin 45°·e^(−d/λ), within TOL + the change of e^(−d/λ) over the ±1 revolution
    (2·fz) the tool moves between tooth passages."""
    seed, rng = fresh_rng()
    a, lam = rng.choice([-1.0, 1.0]) * rng.uniform(5.0, 25.0), rng.uniform(0.3, 1.5)
    f = brute_force_features()
    d = signature({"servo_corner": {"a_um": a, "lambda_mm": lam}})
    expect = servo_closed_form(f, a, lam)
    slack = 0.1 + np.abs(expect) * (math.exp(2 * FZ / lam) - 1)
    assert np.all(np.abs(d - expect) <= TOL + slack), f"seed {seed}: a {a:.2f} um, lambda {lam:.3f} mm"
    assert np.max(np.abs(expect)) > 0.2 * abs(a), f"seed {seed}"       # the plan does reach the corners (0.28 at λ 0.3 mm)


def test_force_scale_scales_the_deflection_part():
    """A force scale s (0.5–2) multiplies the deflection part of the surface (soft machine − rigid
    one) by s, where every tooth passage that cuts a point (±1.5 revolutions) is on its own pass."""
    from stages.geometry.paths import nearest_pass
    from stages.virtual_machine import VirtualMachine
    seed, rng = fresh_rng()
    scale = rng.uniform(0.5, 2.0)
    passes, pts, nrm = sample()
    passes = passes.slice(0, 120)                  # the first rows: two machines built in seconds
    soft = VirtualMachine(passes, TOOL, MAT, SOFT, str(SAMPLE / "stock.stl"))
    stiff = VirtualMachine(passes, TOOL, MAT, RIGID, str(SAMPLE / "stock.stl"))
    row, u, dist = nearest_pass(soft.path, pts + R * nrm)
    # beyond a pass's end the passages carry the neighbour's deflection, and which of them cuts
    # deepest may change with the scale
    p = soft.path
    rev = p.feed[row] / p.rpm[row] * 1.5
    mine = (dist < 0.05) & (u * p.length[row] >= rev) & ((1 - u) * p.length[row] >= rev)
    pts, nrm = pts[mine], nrm[mine]
    assert len(pts) >= 50
    dfl = soft.probe(pts, nrm) - stiff.probe(pts, nrm)
    assert np.percentile(np.abs(dfl), 90) > 1.0    # deflection matters on this part
    d = soft.probe(pts, nrm, {"force_scale": {"scale": scale}}) - soft.probe(pts, nrm)
    worst = float(np.max(np.abs(d - (scale - 1.0) * dfl)))
    assert worst <= 2 * TOL, f"seed {seed}: scale {scale:.3f}: {worst:.3f} um"


def test_simulated_deflection_matches_static_compliance_for_constant_force():
    """A force constant over the revolution deflects by F/k summed over the modes."""
    from stages.virtual_machine import simulate_deflection
    seed, rng = fresh_rng()
    force, k1, k2 = rng.uniform(1.0, 50.0), rng.uniform(1.0, 10.0), rng.uniform(1.0, 10.0)
    f = np.full((2, 96), force)                    # N, constant over the revolution
    d = simulate_deflection(f, np.array([6000.0, 9000.0]), [(900.0, 0.03, k1), (2000.0, 0.05, k2)])
    assert np.allclose(d, force / k1 + force / k2, atol=1e-6), f"seed {seed}"
