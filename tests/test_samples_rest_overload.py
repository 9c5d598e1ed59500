"""The heavy-rest sample case (data_samples/rest_overload/, scripts/samples_rest_overload.py) is as
data_samples/README.md says: its stock 0.2 mm over the model under the semi-finishing rows, with the
rest material a raster along X leaves, and its finishing points on the nominal surface.

The reference numbers come from the source model's dimensions (inches × 25.4), from closed
forms (ball on a plane, cusp height) and from brute-force point-to-mesh distances
(``trimesh.proximity.closest_point_naive``, no spatial index), never from the generator. The NC
programs are read with a small interpreter (tests/sample_nc.py), independent of ``stages.parse``.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import trimesh

from tests.sample_nc import arc_points, distance_to, read_nc

SAMPLES = Path(__file__).resolve().parents[1] / "data_samples"
REST = SAMPLES / "rest_overload"
R = 5.0  # T1: Ø10 ball (program header)
INCH = 25.4
FLOOR_Z = -1.05 * INCH  # pocket floor of ktoolcav.stl, 1.05 in below the parting face


@pytest.fixture(scope="module")
def nominal():
    return trimesh.load(SAMPLES / "models" / "mould.stl", force="mesh")


@pytest.fixture(scope="module")
def semi():
    return trimesh.load(REST / "semi.stl", force="mesh")


@pytest.fixture(scope="module")
def finish_moves():
    return read_nc(REST / "nc" / "mould_finish_t1.nc")


@pytest.fixture(scope="module")
def contour_moves():
    return read_nc(REST / "nc" / "mould_contour_t1.nc")


# ---------------------------------------------------------------------------------- meshes
def test_semi_stock_is_a_closed_solid_over_the_machined_area(semi):
    assert semi.is_watertight and semi.is_winding_consistent and semi.volume > 0
    (x0, y0, z0), (x1, y1, z1) = semi.bounds
    assert x0 <= 12.0 and x1 >= 90.0 and y0 <= 21.0 and y1 >= 71.0  # finishing area ± ball + 2 mm
    assert z0 == pytest.approx(-1.625 * INCH, abs=1e-3)
    assert z1 == pytest.approx(0.2, abs=0.02)  # parting face + 0.2 mm stock + cusp


def test_semi_stock_is_0_2_mm_above_the_nominal(nominal, semi):
    v = semi.vertices
    top = v[v[:, 2] > -41.0]
    # 1) never closer than 0.2 mm to the nominal surface (brute-force distance, random subset)
    rng = np.random.default_rng(0)
    inner = top[(top[:, 0] > 14) & (top[:, 0] < 88) & (top[:, 1] > 24) & (top[:, 1] < 68)]
    pick = inner[rng.choice(len(inner), 400, replace=False)]
    d = distance_to(nominal, pick)
    assert d.min() >= 0.2 - 5e-4, d.min()
    # where the semi-finishing ball reaches the surface: 0.2 mm + cusp ≤ 16 µm; elsewhere
    # (the 5 mm wide relief channel, concave corners, walls parallel to X) rest material
    near = (d >= 0.2 - 5e-4) & (d <= 0.2 + 0.0165)
    assert near.mean() > 0.45 and np.median(d) < 0.25
    # 2) on the flat pocket floor, away from walls and boss by more than the ball radius:
    #    z = floor + 0.2 + cusp, cusp = R - sqrt(R² - e²) for e the distance to the nearest
    #    semi-finishing row; its largest value on a 0.8 mm step-over is 5 - sqrt(25 - 0.4²)
    box = (top[:, 0] > 30) & (top[:, 0] < 51) & (top[:, 1] > 30) & (top[:, 1] < 47)
    above = top[box, 2] - FLOOR_Z
    assert box.sum() > 1000
    assert above.min() == pytest.approx(0.2, abs=2e-4)
    assert above.max() == pytest.approx(0.2 + R - np.sqrt(R * R - 0.4 ** 2), abs=5e-4)


# -------------------------------------------------------------------------------- programs
def test_finishing_program_is_fanuc_shaped(finish_moves):
    text = (REST / "nc" / "mould_finish_t1.nc").read_text().splitlines()
    assert text[0] == "%" and text[-1] == "%" and text[1].startswith("O1001 (MOULD FINISH T1)")
    body = "\n".join(text)
    for word in ("G90 G17 G21 G40 G49 G80", "T1 M6", "S12000 M3", "M5", "M30", "F1000", "F3000"):
        assert word in body
    g = np.array([m["g"] for m in finish_moves])
    assert 2000 <= (g == 1).sum() <= 8000
    assert ((g == 2) | (g == 3)).sum() >= 20  # zig-zag links as arcs
    # collinear points removed: move lengths vary over orders of magnitude
    lin = [m for m in finish_moves if m["g"] == 1 and m["start"][2] == m["start"][2]]
    L = np.array([np.linalg.norm(m["end"] - m["start"]) for m in lin])
    assert L.min() < 0.1 and L.max() > 10


def test_finishing_tip_points_put_the_ball_on_the_nominal(nominal, finish_moves):
    """NC points are the tool tip: the ball centre (tip + R) is exactly R from the surface."""
    cut = [m for m in finish_moves if m["g"] == 1 and np.isfinite(m["start"]).all()]
    ends = np.array([m["end"] for m in cut])
    mids = np.array([(m["start"] + m["end"]) / 2 for m in cut])
    rng = np.random.default_rng(1)
    pick = rng.choice(len(ends), 400, replace=False)
    d = distance_to(nominal, ends[pick] + [0, 0, R])
    # 3-decimal coordinates: ≤ 0.9 µm; float32 STL: < 0.1 µm
    np.testing.assert_allclose(d, R, atol=2e-3)
    assert np.abs(d - R).max() < 1.5e-3
    # between kept points the CAM tolerance (2 µm) bounds the gouge/lift
    d_mid = distance_to(nominal, mids[pick] + [0, 0, R])
    assert d_mid.min() > R - 3.5e-3
    # the program covers the cavity: deep points on the floor, shallow on the parting face
    assert ends[:, 2].min() == pytest.approx(FLOOR_Z, abs=1e-3) and ends[:, 2].max() == 0.0


def test_finishing_arcs_are_tangent_row_links_in_the_air(nominal, finish_moves):
    arcs = [m for m in finish_moves if m["g"] in (2, 3)]
    for m in arcs:
        assert m["plane"] == 17
        assert np.linalg.norm(m["end"] - m["start"]) == pytest.approx(0.6, abs=1e-3)
    pts = np.vstack([arc_points(m, 9) for m in arcs[::5]])
    assert distance_to(nominal, pts + [0, 0, R]).min() > R - 1e-3


def test_contour_program_touches_walls_and_boss(nominal, contour_moves):
    text = (REST / "nc" / "mould_contour_t1.nc").read_text()
    assert ";" in text and re.search(r"\bR\d", text) and re.search(r"\bK-?\d", text)
    g1 = [m for m in contour_moves if m["g"] == 1 and m["start"][2] < -5 and m["end"][2] < -5
          and abs(m["end"][2] - m["start"][2]) < 1e-9]
    assert 100 <= len(contour_moves) <= 1000
    ends = np.array([m["end"] for m in g1])
    d = distance_to(nominal, ends + [0, 0, R])
    np.testing.assert_allclose(d, R, atol=2e-3)
    # no gouge between points (chords across the pocket's inner corners stand off instead)
    mids = np.array([(m["start"] + m["end"]) / 2 for m in g1])
    assert distance_to(nominal, mids + [0, 0, R]).min() > R - 3.5e-3
    # boss circles (G17 arcs): touch the 46-gon boss at its vertices, stand off ≤ 15 µm between
    boss = [m for m in contour_moves if m["g"] in (2, 3) and m["plane"] == 17]
    assert len(boss) >= 6
    pts = np.vstack([arc_points(m, 24) for m in boss])
    d = distance_to(nominal, pts + [0, 0, R])
    assert d.min() > R - 1e-3 and d.max() < R + 0.017
    # vertical lead-in/out arcs (G18) stay off the model
    leads = [m for m in contour_moves if m["plane"] == 18 and m["g"] in (2, 3)]
    assert len(leads) >= 2
    pts = np.vstack([arc_points(m, 9) for m in leads])
    assert distance_to(nominal, pts + [0, 0, R]).min() > R - 2e-3
