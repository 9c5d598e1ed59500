"""Machining error at the generating point: sign, tool profile dent, runout, spindle angle, stage."""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

import schemas
from stages.geometry.cutter import Cutter
from stages import errors
from stages.cutting import forces as cutting
from stages.cutting import frf
from stages.cutting import surface_error
from stages import deflection as deflection_stage
from stages import forces as forces_stage

BALL = {"type": "ball", "diameter_mm": 10.0, "flutes": 2, "helix_deg": 30.0, "corner_radius_mm": None,
        "runout_um": 0.0, "profile": None}
FLAT = {**BALL, "type": "flat"}
BALL_C, FLAT_C = Cutter.from_params(BALL), Cutter.from_params(FLAT)
MAT = {"name": "m", "ktc": 2000.0, "krc": 700.0, "kac": 300.0, "kte": 20.0, "kre": 15.0, "kae": 5.0}
STIFF = {"x": [{"fn_hz": 20000.0, "zeta": 0.05, "k_n_per_um": 2.0}],
         "y": [{"fn_hz": 20000.0, "zeta": 0.05, "k_n_per_um": 2.0}], "table": None}
N_ROT = 128


def _const(v, n=1):
    return np.full((n, N_ROT), float(v))


def test_sign_tool_pushed_away_from_wall_leaves_material():
    """Wall on the right of a +x feed: n = (0, 1, 0) points from the material to the tool. A tool
    pushed +y (away from the wall) by 5 µm leaves 5 µm: err = +5; pushed into it: −5."""
    n = np.array([[0.0, 1.0, 0.0]])
    for dy, want in ((5.0, 5.0), (-5.0, -5.0)):
        r = surface_error.machining_error(_const(0), _const(dy), np.array([-90.0]), np.array([90.0]), n,
                                   np.array([5.0]), FLAT_C)
        assert r["err_um"][0] == pytest.approx(want) and r["err_deflection_um"][0] == pytest.approx(want)


def test_sign_from_physics_down_milling_wall():
    """Flat end mill, material on the right (down milling): the radial force pushes the tool away
    from the wall (+y), quasi-static compliance → positive error at the wall (undercut)."""
    R, a, ae, n_z, n_phi = 5.0, 2.0, 1.0, 20, 360
    z = (np.arange(n_z) + 0.5) * a / n_z
    phi = np.radians((np.arange(n_phi) + 0.5) * 360 / n_phi)
    E = (np.cos(phi) > 0) & (R * np.sin(phi) < -(R - ae))
    E = np.broadcast_to(E, (n_z, n_phi))
    F = cutting.cutting_forces(E[None], a / n_z, 0.05, FLAT_C, MAT)
    d = frf.tool_deflection(F, np.array([3000.0]), STIFF)
    assert d[0, :, 1].mean() > 0                                  # pushed away from the wall
    r = surface_error.machining_error(d[..., 0], d[..., 1], np.array([-90.0]), np.array([90.0]),
                               np.array([[0.0, 1.0, 0.0]]), np.array([z[n_z // 2]]), FLAT_C)
    assert r["err_um"][0] > 0


def test_profile_dent_moves_error_by_exactly_the_dent(tmp_path):
    """Claim 2 table with a 3 µm dent at 45° (tool smaller there): error at q = 45° grows by
    exactly 3 µm, at 30° and 60° (outside the dent) nothing changes."""
    p = tmp_path / "t1_profile.csv"
    q = np.arange(0, 91, 1.0)
    e = np.where(q == 45.0, 3.0, 0.0)
    np.savetxt(p, np.column_stack([q, e]), delimiter=",", header="contact_deg,error_um", comments="")
    prof = surface_error.read_profile(p)
    qs = np.array([30.0, 45.0, 60.0, 44.5])
    n = np.stack([np.zeros(4), np.sin(np.radians(qs)), np.cos(np.radians(qs))], axis=1)
    rng = np.random.default_rng(2)
    dx, dy = rng.normal(0, 4, (4, N_ROT)), rng.normal(0, 4, (4, N_ROT))
    args = (dx, dy, np.full(4, -90.0), qs, n, BALL_C.corner_height(qs), BALL_C)
    base = surface_error.machining_error(*args)["err_um"]
    dent = surface_error.machining_error(*args, profile=prof)["err_um"]
    assert dent - base == pytest.approx([0.0, 3.0, 0.0, 1.5], abs=1e-12)


def test_runout_term_is_minus_e_sin_q():
    """No deflection, eccentricity 6 µm toward flute 0: flute 0 cuts deepest, err = −6·sin q."""
    tool = {**BALL, "flutes": 3, "runout_um": 6.0}
    qs = np.array([10.0, 45.0, 90.0])
    n = np.stack([np.zeros(3), np.sin(np.radians(qs)), np.cos(np.radians(qs))], axis=1)
    r = surface_error.machining_error(_const(0, 3), _const(0, 3), np.full(3, -90.0), qs, n,
                               BALL_C.corner_height(qs), Cutter.from_params(tool))
    assert r["err_um"] == pytest.approx(-6.0 * np.sin(np.radians(qs)))
    assert list(r["flute"]) == [0, 0, 0]


def test_deflection_read_at_generating_spindle_angle():
    """dx(θ) = θ/10 µm, n = +x: the error equals the value at the spindle angle where a flute
    passes φ_C at C's height (θ = −φ_C − 360·j/N + z·tanβ/R), the smaller over flutes."""
    theta = cutting.rotation_grid_deg(N_ROT)
    dx = (theta / 10.0)[None, :]
    phi_c, q = 20.0, 40.0
    z = 5.0 * (1 - np.cos(np.radians(q)))
    lag = np.degrees(z * np.tan(np.radians(30.0)) / 5.0)
    cands = np.mod(-phi_c - 180.0 * np.arange(2) + lag, 360.0)
    r = surface_error.machining_error(dx, np.zeros_like(dx), np.array([phi_c]), np.array([q]),
                               np.array([[1.0, 0.0, 0.0]]), np.array([z]), BALL_C)
    j = int(np.argmin(cands))
    assert r["spindle_deg"][0] == pytest.approx(cands[j]) and r["flute"][0] == j
    assert r["err_um"][0] == pytest.approx(cands[j] / 10.0, abs=1e-9)
    # the deflection vector at that passage is kept for the correction: dx(θ_C), dy(θ_C) = 0
    assert r["defl_x_um"][0] == pytest.approx(cands[j] / 10.0, abs=1e-9) and r["defl_y_um"][0] == 0.0


@pytest.mark.parametrize("side", ["right", "left"])
@pytest.mark.parametrize("fn_hz", [900.0, 20000.0])
def test_error_vs_contact_angle_trend(side, fn_hz):
    """Seed Fig. 19 trend, seed cylinder conditions (Ø20 ball, 2 flutes, 6000 min⁻¹, 0.4 mm/tooth,
    0.2 mm stock, 0.63 mm pitch) on analytic walls from the tip to the side, down milling (wall on
    the right) and up milling (left, the zigzag's other half), a dynamic (900 Hz) and a quasi-static
    FRF: the error is bounded by |d|·sin q (the normal turns from vertical to horizontal), small
    near the tip and larger toward the wall."""
    tool = {**BALL, "diameter_mm": 20.0}
    mode = {"fn_hz": fn_hz, "zeta": 0.03, "k_n_per_um": 2.0}
    frf_params = {"x": [mode], "y": [mode]}
    qs = np.array([1.0, 3.0, 5.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 70.0, 80.0, 89.0])
    r = surface_error.error_vs_contact_angle(qs, Cutter.from_params(tool), MAT, frf_params, 4800.0, 6000.0, step_mm=0.63,
                                      stock_mm=0.2, side=side, n_z=96)
    d = frf.tool_deflection(r["forces_n"], np.full(len(qs), 6000.0), frf_params)
    dmax = np.abs(d).max(axis=(1, 2))
    assert np.all(np.abs(r["err_deflection_um"]) <= dmax * np.sin(np.radians(qs)) + 1e-9)
    err = r["err_um"]
    near_tip, mid, wall = np.abs(err[qs <= 5]), err[(qs >= 10) & (qs <= 30)], err[qs >= 40]
    assert near_tip.max() < 0.5
    assert wall.mean() > 2.0 and wall.mean() > mid.mean() and wall.min() > 5 * near_tip.mean()


# ------------------------------------------------------------------------------------------------
# the three stages chained on tables
# ------------------------------------------------------------------------------------------------
def test_stages_chain_on_tables(tmp_path):
    """passes + engagement → forces → deflection → errors, schemas checked; a flat end mill
    finishing a wall on the right of each pass (feed along +x and along −y), profile applied."""
    prof = tmp_path / "profile.csv"
    prof.write_text("contact_deg,error_um\n0,1.0\n90,1.0\n")
    tool = {**FLAT, "profile": str(prof)}
    n_z, n_phi, a, ae, R = 20, 360, 2.0, 0.5, 5.0
    phi = np.radians((np.arange(n_phi) + 0.5) * 360 / n_phi)
    E = np.broadcast_to((np.cos(phi) > 0) & (R * np.sin(phi) < -(R - ae)), (n_z, n_phi))
    feeds = [(1.0, 0.0), (0.0, -1.0)]
    n = len(feeds)
    z0 = np.full(n, 10.0)
    passes = pa.table({
        "program_id": ["p"] * n, "pass_id": pa.array(np.arange(n), pa.int32()),
        "block_no": pa.array(np.arange(n), pa.int32()), "line_no": pa.array(np.arange(n) + 1, pa.int32()),
        "motion": pa.array(np.ones(n), pa.int8()),
        "x0_mm": [0.0, 10.0], "y0_mm": [0.0, 0.0], "z0_mm": z0,
        "x1_mm": [10.0, 10.0], "y1_mm": [0.0, -10.0], "z1_mm": z0,
        "feed_mm_min": np.full(n, 1500.0), "spindle_rpm": np.full(n, 6000.0),
        "tool": pa.array([1] * n, pa.int32()), "t_start_s": np.zeros(n), "t_end_s": np.ones(n)})
    engagement = pa.table({
        "program_id": ["p"] * n, "pass_id": pa.array(np.arange(n), pa.int32()),
        "dz_mm": np.full(n, a / n_z), "n_z": pa.array([n_z] * n, pa.int32()),
        "n_phi": pa.array([n_phi] * n, pa.int32()),
        "mask": pa.array([cutting.pack_engagement(E)] * n, pa.binary()),
        "feed_dir_x": [f[0] for f in feeds], "feed_dir_y": [f[1] for f in feeds]})
    # generating point: on the wall (right of the feed) at mid depth; n points from wall to tool
    right = [(0.0, -1.0), (-1.0, 0.0)]
    generating = pa.table({
        "program_id": ["p"] * n, "pass_id": pa.array(np.arange(n), pa.int32()),
        "gen_x_mm": [5.0, 10.0 - R], "gen_y_mm": [-R, -5.0], "gen_z_mm": z0 + 1.0,
        "rotation_deg": [-90.0, -90.0], "contact_deg": [90.0, 90.0],
        "nx": [-r[0] for r in right], "ny": [-r[1] for r in right], "nz": [0.0, 0.0],
        "n_px": pa.array([10] * n, pa.int32()), "view": ["bottom"] * n,
        # pass 1 has a second contact where its first is, its normal turned 90° about z: the error
        # there is the same deflection vector along the other normal (pass 0 has none)
        "gen2_x_mm": [np.nan, 10.0 - R], "gen2_y_mm": [np.nan, -5.0], "gen2_z_mm": [np.nan, z0[1] + 1.0],
        "rotation2_deg": [np.nan, -90.0], "contact2_deg": [np.nan, 90.0],
        "nx2": [np.nan, -right[1][1]], "ny2": [np.nan, right[1][0]], "nz2": [np.nan, 0.0],
        "n2_px": pa.array([0, 10], pa.int32())})
    generating = schemas.check("generating", generating)
    params = {"tool": tool, "material": MAT, "machine": {"rapid_mm_min": 30000.0, "frf": STIFF}}
    f = schemas.check("forces", forces_stage.run(
        {"passes": passes, "generating": generating, "engagement": engagement}, params)["forces"])
    d = schemas.check("deflection", deflection_stage.run({"forces": f}, params)["deflection"])
    e = schemas.check("errors", errors.run({"passes": passes, "generating": generating, "deflection": d},
                                           params)["errors"]).to_pydict()
    # same cut in its own feed frame → the same error for both passes; material left; +1 µm profile
    assert e["err_um"][0] == pytest.approx(e["err_um"][1], rel=1e-6)
    assert e["err_deflection_um"][0] > 0
    assert e["err_shape_um"] == pytest.approx([1.0, 1.0])
    assert e["err_um"][0] == pytest.approx(e["err_deflection_um"][0] + 1.0)
    # the flat tool's C height comes from gen_z − tip z (1 mm): the helix lag of that height
    lag = np.degrees(1.0 * np.tan(np.radians(30.0)) / R)
    cands = np.mod(90.0 + lag - 180.0 * np.arange(2), 360)
    assert cands[e["flute"][0]] == pytest.approx(e["spindle_deg"][0])
    # the second contact: none on pass 0; on pass 1 the deflection vector along its normal + profile
    assert np.isnan(e["err2_um"][0]) and np.isnan(e["nx2"][0])
    n2 = np.array([-right[1][1], right[1][0]])
    assert e["err2_um"][1] == pytest.approx(e["defl_x_um"][1] * n2[0] + e["defl_y_um"][1] * n2[1] + 1.0, rel=1e-9)
    assert abs(e["err2_um"][1] - e["err_um"][1]) > 1.0          # another normal, another error
