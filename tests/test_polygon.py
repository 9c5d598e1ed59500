"""Polygon (2-axis) cutting, seed 004 (issue 62), against the seed's stated results and closed forms.

References: ``/work/shared/seeds/004_notes_en.md`` (the kinematics reconstructed from JP2015-043126)
and the seed's paragraphs cited below. Closed forms used (ω1 > 0, ratio ρ = ω2/ω1):

- the edge is nearest the axis, at |R - ε|, when it points at the axis (cutter angle π); the
  workpiece has then turned π/ρ since the edge was farthest, and 2π/ρ between two such moments:
  faces at θ_k = 180° - 180°/ρ - 360°·k/ρ, a p-gon for ρ = p/q in lowest terms;
- ρ = 2, same direction: the tip's path in the workpiece frame is the ellipse with semi-axes R + ε
  (along x) and R - ε (along y): the section is that ellipse cut by the bar's circle;
- the radius of curvature of the tip's path where it is nearest the axis (a face's centre):
  (ε + (ρ-1)R)² / |ε - (ρ-1)²R|, (R+ε)²/(R-ε) for ρ = 2 (nearly flat), (3R-ε)²/(9R-ε) for ρ = -2 (a lens);
- ρ = 2 + δ: the faces turn 360°·(1 - 2/ρ)·(ρ/2) = 180°·δ per workpiece revolution, i.e.
  180°·δ / (feed per workpiece revolution) per mm.
"""
from __future__ import annotations

import json
from math import gcd
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import yaml
from click.testing import CliRunner
from hypothesis import assume, given, settings
from hypothesis import strategies as st

import schemas
from pipeline.cli import main
from stages.polygon.cut import height_map, make_grid
from stages.polygon.kinematics import Setup, ratio_fraction, tip_xy
from stages.polygon.sections import caliper_width, count_sides, face_minima
from stages.polygon.solid import machine

ROOT = Path(__file__).resolve().parent.parent
# the seed's Example 3 cutter (Fig. 21), and a generic one with deep faces for the polygons
R_EX, E_EX = 7.285, 6.28
R_P, E_P = 6.0, 3.0


def bar(ratio, R=R_P, e=E_P, rw=5.0, length=0.5, feed=0.01, per="tool", lags=(0.0,), width=0.5, wrpm=1000.0):
    return Setup(rw, length, wrpm, ratio * wrpm, R, e, feed, per, lags, width)


def faces_deg(r, grid, prom=0.005):
    return np.degrees(grid.theta[face_minima(r, prom)])


def circ_dist(a, b):
    return np.abs((np.asarray(a) - np.asarray(b) + 180.0) % 360.0 - 180.0)


def test_tip_path_is_the_notes_equations():
    s = bar(2.2, lags=(0.0,))
    t = np.linspace(0, 3, 50)                              # time, with ω in rad/time
    w1, w2, phi = 1000.0, 2200.0, np.radians(30.0)
    x, y, _ = tip_xy(w2 * t, s, 30.0)
    assert np.allclose(x, E_P * np.cos(w1 * t) + R_P * np.cos((w2 - w1) * t - phi))
    assert np.allclose(y, -E_P * np.sin(w1 * t) + R_P * np.sin((w2 - w1) * t - phi))


def test_ratio_2_same_direction_two_parallel_faces_the_ellipse():
    s = bar(2.0, R=R_EX, e=E_EX, length=0.4, width=1.0, feed=0.04)
    g = make_grid(0.4, 0.05, 0.25)
    H = height_map(s, g)
    a, b = R_EX + E_EX, R_EX - E_EX
    # the section is the ellipse within the circle, to the resolution: a tip point's angle is off
    # by at most a profile bin (a quarter column)
    ell = lambda t: a * b / np.hypot(b * np.cos(t), a * np.sin(t))  # noqa: E731
    near = ell(g.theta[:, None] + np.linspace(-1, 1, 9) * g.dtheta / 4)
    lo, hi = np.minimum(near.min(1), 5.0), np.minimum(near.max(1), 5.0)
    assert np.all(H >= lo - 1e-9) and np.all(H <= hi + 1e-9)
    m = machine(s, g, 3, 0.005)
    assert m.figures["sides"] == 2
    assert m.figures["min_thickness_mm"] == pytest.approx(2 * (R_EX - E_EX), abs=1e-3)
    assert abs(m.figures["twist_deg_per_mm"]) < 1e-6
    assert np.sort(circ_dist(faces_deg(H[3], g), 0)).tolist() == [90.0, 90.0]   # faces at θ = 90°, 270°


def test_a_cutter_radius_within_a_micron_of_the_eccentricity_leaves_no_gap():
    """R - ε = 1 µm: the tip's polar angle races past the axis (rate R/(R - ε)); the blade is 2 µm thick."""
    g = make_grid(0.2, 0.05, 0.1)
    H = height_map(bar(2.0, R=7.0, e=6.999, length=0.2, width=1.0), g)
    assert count_sides(H, 0.005).tolist() == [2] * g.nz
    assert caliper_width(H[2], g.theta) == pytest.approx(0.002, abs=1e-6)


def _face_radius_of_curvature(r, grid, face_deg, half_width_mm):
    """Fit y = c0 + c2 x² + c4 x⁴ to the section near the face centre (x along the face)."""
    d = np.radians(circ_dist(np.degrees(grid.theta), face_deg))
    sgn = np.sign(np.sin(grid.theta - np.radians(face_deg)))
    x, y = r * np.sin(d) * sgn, r * np.cos(d)
    k = (np.abs(x) < half_width_mm) & (y > 0)
    c4, c2, c0 = np.polyfit(x[k] ** 2, y[k], 2)
    return -1.0 / (2 * c2)


def test_ratio_2_opposite_directions_a_lens():
    """Seed Fig. 20: opposite directions give a spindle (lens) section, the same directions a flat blade."""
    g = make_grid(0.2, 0.05, 0.05)
    lens = height_map(bar(-2.0, R=R_EX, e=E_EX, length=0.2, width=1.0), g)[2]
    flat = height_map(bar(2.0, R=R_EX, e=E_EX, length=0.2, width=1.0), g)[2]
    assert np.sort(circ_dist(faces_deg(lens, g), 0)).tolist() == [90.0, 90.0]
    assert lens.min() == pytest.approx(R_EX - E_EX, abs=1e-6)
    assert caliper_width(lens, g.theta) == pytest.approx(2 * (R_EX - E_EX), abs=1e-3)
    rc_lens = _face_radius_of_curvature(lens, g, 90.0, 0.4)
    assert rc_lens == pytest.approx((3 * R_EX - E_EX) ** 2 / (9 * R_EX - E_EX), rel=0.02)   # 4.09 mm
    rc_flat = _face_radius_of_curvature(flat, g, 90.0, 0.4)
    assert rc_flat > 20 * rc_lens                                # (R+ε)²/(R-ε) = 183 mm: nearly flat


def test_axis_outside_the_tool_path_cuts_concave_faces():
    """Seed ¶0073-0075 (Fig. 11): R < ε, ratio 4: four arcs cut into the bar, 90° apart. The tip is nearest
    the axis, at ε - R, pointing away from it: faces at -180°/ρ - 360°k/ρ, hollow with the same radius of
    curvature (ε + (ρ-1)R)² / |ε - (ρ-1)²R| (24.0 mm), its centre now beyond the face."""
    g = make_grid(0.2, 0.05, 0.05)
    r = height_map(bar(4.0, R=10.0, e=13.0, length=0.2), g)[2]
    assert np.sort(faces_deg(r, g)).tolist() == [45.0, 135.0, 225.0, 315.0]
    assert r.min() == pytest.approx(3.0, abs=1e-4)
    rc = _face_radius_of_curvature(r, g, 45.0, 1.0)
    assert -rc == pytest.approx((13.0 + 3 * 10.0) ** 2 / (9 * 10.0 - 13.0), rel=0.03)


# the seed's Example 4 (¶0150: ratios 2.2 … 3) and the 7-gon speed pairs of ¶0151 (cutter:workpiece rpm)
SEED_POLYGONS = [(2200, 1000, 11), (2400, 1000, 12), (2500, 1000, 5), (2600, 1000, 13), (2800, 1000, 14),
                 (3000, 1000, 3), (1750, 1000, 7), (7000, 1000, 7), (1400, 1000, 7), (3500, 1000, 7)]


@pytest.mark.parametrize("n2,n1,sides", SEED_POLYGONS)
def test_ratio_p_over_q_gives_the_p_gon(n2, n1, sides):
    s = bar(n2 / n1, wrpm=n1)
    assert ratio_fraction(s.ratio).numerator == sides
    g = make_grid(0.2, 0.05, 0.25)
    H = height_map(s, g)
    assert count_sides(H, 0.005).tolist() == [sides] * g.nz
    rho = n2 / n1
    want = (180 - 180 / rho - 360 * np.arange(sides * 10) / rho) % 360
    got = faces_deg(H[2], g)
    assert all(circ_dist(want, f).min() <= 0.25 for f in got)          # at the closed-form angles
    # at |R - ε|, to the resolution: a column is within a quarter column of a face's centre
    assert H[2][face_minima(H[2], 0.005)] == pytest.approx(R_P - E_P, abs=1e-4)


@settings(max_examples=25, deadline=None)
@given(p=st.integers(3, 16), q=st.integers(1, 6), sign=st.sampled_from([1, -1]))
def test_any_ratio_p_over_q_gives_p_sides(p, q, sign):
    assume(gcd(p, q) == 1 and 1.4 <= p / q <= 4.0)
    g = make_grid(0.1, 0.05, 0.25)
    H = height_map(bar(sign * p / q, length=0.1), g)
    assert count_sides(H[1], 0.005).tolist() == [p]


def test_two_edges_half_a_turn_apart_at_ratio_2_cut_a_square():
    """Lag angles: the second edge's faces are turned by -180°/ρ = -90°: four faces, 2(R - ε) across both ways."""
    g = make_grid(0.2, 0.05, 0.25)
    H = height_map(bar(2.0, lags=(0.0, 180.0)), g)
    assert np.sort(faces_deg(H[2], g)).tolist() == [0.0, 90.0, 180.0, 270.0]
    assert caliper_width(H[2], g.theta) == pytest.approx(2 * (R_P - E_P), abs=1e-4)


def _twist(ratio, feed=0.01, wrpm=1000.0, length=1.0):
    s = bar(ratio, R=R_EX, e=E_EX, length=length, feed=feed, width=1.0, wrpm=wrpm)
    return machine(s, make_grid(length, 0.02, 0.25), 3, 0.005).figures["twist_deg_per_mm"], s


@pytest.mark.parametrize("ratio", [2.001, 1.999])
def test_ratio_2_plus_delta_turns_the_faces_180_delta_per_workpiece_revolution(ratio):
    """Seed Fig. 19 (¶0129-0132): 1.999 and 2.001 twist in opposite directions."""
    tw, s = _twist(ratio)
    per_rev = tw * s.feed_per_workpiece_mm                    # degrees per workpiece revolution
    assert per_rev == pytest.approx(180 * (ratio - 2), rel=0.01)


def test_opposite_rotations_flip_the_twist():
    """Seed ¶0112, ¶0137 (Fig. 20): with the workpiece turned the other way the twist of 2.001 reverses; only
    the workpiece's sense and |ω2/ω1| place the faces, so reversing the cutter alone changes the
    section (a lens) but not the handedness (docs/polygon.md)."""
    same, _ = _twist(2.001)
    wp_reversed, _ = _twist(-2.001, wrpm=-1000.0)
    cutter_reversed, _ = _twist(-2.001)
    assert same > 0 and wp_reversed == pytest.approx(-same, rel=0.01)
    assert cutter_reversed == pytest.approx(same, rel=0.01)


def test_slower_feed_twists_more():
    """Seed ¶0126, ¶0145 (Figs. 21-23): twist per mm ∝ 1/feed (¶0113 says the opposite; docs/polygon.md)."""
    fast, _ = _twist(2.001, feed=0.02)
    slow, _ = _twist(2.001, feed=0.01)
    assert slow == pytest.approx(2 * fast, rel=0.01)


# the seed's Example 3 (¶0141-0144): bar Ø, feed per cutter revolution, R, ε; 999/499 rpm, 2 mm edge
SEED_BLADES = [("Ti-6Al-4V Ø10", 5.0, 0.04, 7.285, 6.28), ("Ti-6Al-4V Ø8", 4.0, 0.02, 10.03, 9.03),
               ("SUS304 Ø8", 4.0, 0.01, 9.26, 8.26)]


@pytest.mark.parametrize("name,rw,feed,R,e", SEED_BLADES)
def test_seed_experiments_give_a_2mm_twisted_blade(name, rw, feed, R, e):
    s = Setup(rw, 1.0, 499.0, 999.0, R, e, feed, "tool", (0.0,), 2.0)
    m = machine(s, make_grid(1.0, 0.02, 0.25), 3, 0.005)
    assert m.figures["sides"] == 2
    assert m.figures["min_thickness_mm"] == pytest.approx(2.0, abs=0.015)     # 2(R - ε) = 2.01, 2.00, 2.00
    # δ = 999/499 - 2 = 1/499: 180°·δ per workpiece revolution of 999/499 × feed
    assert m.figures["twist_deg_per_mm"] == pytest.approx(180.0 / (999 * feed), rel=0.01)


def test_caliper_width_is_the_least_width_over_all_directions():
    rng = np.random.default_rng(4)
    theta = np.linspace(0, 2 * np.pi, 180, endpoint=False)
    r = 3 + 0.3 * np.cos(3 * theta + 1) + 0.2 * rng.random(180)
    x, y = r * np.cos(theta), r * np.sin(theta)
    # the least width is across a line through two of the points: try every pair's normal
    i, j = np.triu_indices(180, 1)
    a = np.arctan2(y[j] - y[i], x[j] - x[i]) + np.pi / 2
    proj = np.outer(np.cos(a), x) + np.outer(np.sin(a), y)
    brute = (proj.max(1) - proj.min(1)).min()
    assert caliper_width(r, theta) == pytest.approx(brute, abs=1e-9)


def test_the_solid_mesh_is_closed_and_holds_the_map_volume(tmp_path):
    import trimesh

    from stages.polygon.mesh import solid_mesh, write_stl
    g = make_grid(0.5, 0.05, 1.0)
    H = height_map(bar(2.5), g)
    write_stl(solid_mesh(H, g.theta, g.z), tmp_path / "p.stl")
    m = trimesh.load(tmp_path / "p.stl")
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    # slabs between rows: triangle fans of each row, trapezoidal in z
    fan = 0.5 * np.sum(H * np.roll(H, -1, axis=1), axis=1) * np.sin(g.dtheta)
    assert m.volume == pytest.approx(np.sum(0.5 * (fan[1:] + fan[:-1])) * g.dz, rel=2e-3)


def _workflow(tmp_path, **over):
    wf = yaml.safe_load((ROOT / "workflows" / "polygon.yaml").read_text())
    for key, val in over.items():
        head, _, sub = key.partition(".")
        wf[head][sub] = val
    p = tmp_path / "wf.yaml"
    p.write_text(yaml.safe_dump(wf, sort_keys=False))
    return p


@pytest.mark.parametrize("key,value,says", [
    ("cutter.rpm", 0, "cutter.rpm: Value error, the cutter must turn"),
    ("workpiece.rpm", 0, "workpiece.rpm: Value error, the workpiece must turn"),
    ("cutter.eccentricity_mm", 12.285, "cutter.eccentricity_mm: Value error, the edges never reach the bar"),
    ("feed.mm", -0.04, "feed.mm: Input should be greater than 0"),
])
def test_bad_input_names_the_file_line_and_key_and_writes_nothing(tmp_path, key, value, says):
    p = _workflow(tmp_path, **{key: value})
    head, _, sub = key.partition(".")
    lines = p.read_text().splitlines()
    top = lines.index(f"{head}:")
    line = next(i for i in range(top, len(lines)) if lines[i].strip().startswith(f"{sub}:")) + 1
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["run", str(p), "--out", str(out)])
    assert r.exit_code == 2, r.output
    assert f"{p}:{line}: {says}" in r.output
    assert not out.exists()


def test_pipeline_run_on_the_workflow_end_to_end(tmp_path):
    ov = tmp_path / "coarse.yaml"
    ov.write_text("resolution: {dz_mm: 0.25, dtheta_deg: 1.0}\nsections: {count: 3}\nstl: {dz_mm: 0.5, dtheta_deg: 2.0}\n")
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["run", str(ROOT / "workflows" / "polygon.yaml"), "--overlay", str(ov), "--out", str(out)])
    assert r.exit_code == 0, r.output
    run = json.loads((out / "run.json").read_text())
    summ = json.loads((out / "polygon" / "summary.json").read_text())
    assert run["job"] == "polygon" and run["failures"] == [] and run["wall_s"] > 0
    assert {"sides", "twist_deg_per_mm", "min_thickness_mm", "max_radius_mm"} <= set(summ)
    assert summ["sides"] == 2 and summ["max_radius_mm"] == pytest.approx(5.0)
    assert summ["twist_deg_per_mm"] == pytest.approx(180.0 / (999 * 0.04), rel=0.01)
    # ¶0141: 8 passes of 30 mm took 6 min: 0.04 mm per cutter (999 rpm) revolution, not per workpiece one
    assert 8 * summ["cutting_time_min"] == pytest.approx(6.0, rel=0.01)
    tab = pq.read_table(out / "tables" / "polygon_sections" / "ti64_d10_blade.parquet")
    assert tab.schema.equals(schemas.get("polygon_sections")) and tab.num_rows == 3 * 360
    assert sorted(set(tab.column("z_mm").to_pylist())) == [0.0, 15.0, 30.0]
    import trimesh
    assert trimesh.load(out / "polygon" / "ti64_d10_blade.stl").is_watertight
    page = (out / "report" / "index.html").read_text()
    for f in ("sections.png", "view3d.png"):
        assert (out / "polygon" / f).stat().st_size > 1000 and f"../polygon/{f}" in page
    assert "sides 2" in r.output
