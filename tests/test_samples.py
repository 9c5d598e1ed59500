"""The bundled sample data (data_samples/, made by scripts/make_samples.py) is honest.

The reference numbers come from the source model's dimensions (inches × 25.4), from closed
forms (ball on a plane, cusp height, modal compliance) and from brute-force point-to-mesh
distances (``trimesh.proximity.closest_point_naive``, no spatial index), never from the
generator. The NC programs are read with a small interpreter written here, independent of
``stages.parse``.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import trimesh

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


def distance_to(mesh, points):
    """Brute-force unsigned distance from points to the mesh surface."""
    _, d, _ = trimesh.proximity.closest_point_naive(mesh, np.asarray(points, float))
    return d


# ------------------------------------------------------------------------- a tiny NC reader
def read_nc(path):
    """Interpret G0/G1/G2/G3 (G17 I J or R, G18 I K), absolute, modal. Returns a list of moves.

    Each move: dict(g, plane, start (3,), end (3,), centre (3,) or None).
    """
    pos = np.full(3, np.nan)
    g, plane = None, 17
    moves = []
    for line in Path(path).read_text().splitlines():
        line = re.sub(r"\(.*?\)", "", line).split(";")[0].strip()
        if not line or line == "%" or line.startswith("O"):
            continue
        words = dict()
        gs = []
        for a, v in re.findall(r"([A-Z])\s*([-+]?\d*\.?\d+)", line):
            if a == "G":
                gs.append(int(float(v)))
            else:
                words[a] = float(v)
        for code in gs:
            if code in (0, 1, 2, 3):
                g = code
            elif code in (17, 18, 19):
                plane = code
        end = pos.copy()
        for i, a in enumerate("XYZ"):
            if a in words:
                end[i] = words[a]
        if not any(a in words for a in "XYZ"):
            continue
        centre = None
        if g in (2, 3):
            axes = {17: (0, 1, "IJ"), 18: (0, 2, "IK")}[plane]
            i0, i1, names = axes
            if "R" in words:
                # minor arc (R > 0) of radius R from start to end; centre on the side of the turn
                s2, e2 = pos[[i0, i1]], end[[i0, i1]]
                mid, chord = (s2 + e2) / 2, e2 - s2
                h = np.sqrt(words["R"] ** 2 - (chord @ chord) / 4)
                left = np.array([-chord[1], chord[0]]) / np.linalg.norm(chord)
                c2 = mid + (left if g == 3 else -left) * h
            else:
                c2 = pos[[i0, i1]] + [words.get(names[0], 0.0), words.get(names[1], 0.0)]
            centre = pos.copy()
            centre[[i0, i1]] = c2
        moves.append(dict(g=g, plane=plane, start=pos.copy(), end=end.copy(), centre=centre))
        pos = end
    return moves


def arc_points(m, n=16):
    """Points along an arc move (G17 or G18), direction per ISO (G2 clockwise seen from +axis)."""
    i0, i1 = (0, 1) if m["plane"] == 17 else (2, 0)  # G18: the ZX plane, Z first
    c, s, e = m["centre"], m["start"], m["end"]
    a0 = np.arctan2(s[i1] - c[i1], s[i0] - c[i0])
    a1 = np.arctan2(e[i1] - c[i1], e[i0] - c[i0])
    sweep = (a1 - a0) % (2 * np.pi) if m["g"] == 3 else -((a0 - a1) % (2 * np.pi))
    if abs(sweep) < 1e-9:
        sweep = 2 * np.pi if m["g"] == 3 else -2 * np.pi
    r = np.hypot(s[i1] - c[i1], s[i0] - c[i0])
    t = a0 + sweep * np.linspace(0, 1, n)
    p = np.repeat(s[None], n, 0)
    p[:, i0] = c[i0] + r * np.cos(t)
    p[:, i1] = c[i1] + r * np.sin(t)
    # the third axis moves linearly (helix); flat arcs here
    k = 3 - i0 - i1
    p[:, k] = s[k] + (e[k] - s[k]) * np.linspace(0, 1, n)
    return p


@pytest.fixture(scope="module")
def finish_moves():
    return read_nc(REST / "nc" / "mould_finish_t1.nc")


@pytest.fixture(scope="module")
def contour_moves():
    return read_nc(REST / "nc" / "mould_contour_t1.nc")


# ---------------------------------------------------------------------------------- meshes
def test_nominal_is_the_ktool_insert_in_the_machine_frame(nominal):
    assert nominal.is_watertight and nominal.is_winding_consistent and nominal.volume > 0
    # 4 x 3.3125 x 1.625 in, min corner at X0 Y0, parting face at Z0
    expect = np.array([[0, 0, -1.625 * INCH], [4 * INCH, 3.3125 * INCH, 0]])
    np.testing.assert_allclose(nominal.bounds, expect, atol=1e-3)
    # the finished (cavity) side looks up: the faces at Z0 and on the pocket floor face +Z
    c, n, a = nominal.triangles_center, nominal.face_normals, nominal.area_faces
    top = np.abs(c[:, 2]) < 1e-4
    floor = np.abs(c[:, 2] - FLOOR_Z) < 1e-3
    assert (n[top, 2] > 0.999).all() and a[top].sum() > 4000  # mm², most of the 101.6 x 84.1 face
    assert (n[floor, 2] > 0.999).all() and a[floor].sum() > 1000  # 54 x 30 mm pocket floor


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


# ------------------------------------------------------------------------- tool and machine
def test_tool_profile_is_a_smooth_few_micron_undersize():
    t = np.loadtxt(SAMPLES / "tools" / "t1_profile.csv", delimiter=",", skiprows=1)
    header = (SAMPLES / "tools" / "t1_profile.csv").read_text().splitlines()[0]
    assert header == "contact_deg,error_um"
    np.testing.assert_allclose(t[:, 0], np.arange(901) * 0.1, atol=1e-9)
    e = t[:, 1]
    assert 0 < e.min() and e.max() < 6 and e[-1] > e[0] + 1.5
    assert np.abs(np.diff(e, 2)).max() < 0.01  # µm per 0.1° step²: smooth


def test_frf_matches_its_modal_parameters():
    f, xr, xi, yr, yi = np.loadtxt(SAMPLES / "machine" / "frf_xy.csv", delimiter=",",
                                   skiprows=1).T
    np.testing.assert_allclose(f, np.arange(0, 5001, 2))
    gx = xr + 1j * xi
    # static compliance 1/2 + 1/6 µm/N; first resonance near 850 Hz with |G| ≈ 1/(2ζk)
    assert gx[0].real == pytest.approx(1 / 2 + 1 / 6, rel=0.03)
    peak = np.argmax(np.abs(gx[(f > 500) & (f < 1500)])) + np.flatnonzero(f > 500)[0]
    assert abs(f[peak] - 850) <= 6
    assert abs(gx[peak]) == pytest.approx(1 / (2 * 0.03 * 2.0), rel=0.1)
    assert xi[peak] < 0  # compliance lags the force
    gy = yr + 1j * yi
    assert abs(f[np.argmax(np.abs(gy[:1000]))] - 910) <= 6
