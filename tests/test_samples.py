"""The bundled sample process (data_samples/, made by scripts/make_samples.py) is as its README says.

The semi-finished stock leaves 0.2 mm over the nominal model where the finishing programs cut, up to
the scallops its passes leave; every finishing point puts its ball on the nominal surface; the
programs are Fanuc/ISO text the pipeline's reader accepts, one tool each, in machining order. The
reference numbers come from the source model's dimensions (inches × 25.4), from closed forms (ball
on a plane, scallop height, modal compliance) and from brute force (closest points and ray crossings
over every triangle), never from the generator; the NC programs are read with tests/sample_nc.py,
independent of ``stages.parse``.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import trimesh

from tests.sample_nc import closest, distance_to, distance_to_segments, feature_edges, ray_exit, read_nc

SAMPLES = Path(__file__).resolve().parents[1] / "data_samples"
INCH = 25.4
FLOOR_Z = -1.05 * INCH          # pocket floor of ktoolcav.stl, 1.05 in below the parting face
ALLOWANCE = 0.2                 # the semi-finishing's stock to leave (README)
MESH_TOL = 0.013                # the stock mesh against the exact swept surface, along the normal (README)
EDGE_TOL = 0.018                # the same on the model's sharp edges, read along a fan of normals (README)
PROGRAMS = {"10_steep_t1.nc": (1, 5.0, 3000), "20_shallow_t1.nc": (1, 5.0, 3000), "30_pencil_t2.nc": (2, 2.0, 1500)}
PER_PROGRAM = 120               # cutting points checked per program (random, seeded)


@pytest.fixture(scope="module")
def nominal():
    return trimesh.load(SAMPLES / "models" / "mould.stl", force="mesh")


@pytest.fixture(scope="module")
def semi():
    return trimesh.load(SAMPLES / "models" / "semi.stl", force="mesh")


def scallop(r, step):
    """Height of the ridge a ball of radius r leaves between passes ``step`` apart."""
    return r - np.sqrt(r * r - step * step / 4)


@pytest.fixture(scope="module")
def contacts(nominal):
    """Per program: a seeded sample of its cutting G1 end points (at the program's cutting feed), the
    ball's centre, its contact point on the nominal model and the contact normal."""
    rng = np.random.default_rng(58)
    out = {}
    for name, (_, r, feed) in PROGRAMS.items():
        moves = [m for m in read_nc(SAMPLES / "nc" / name) if m["g"] == 1 and m["feed"] == feed
                 and np.isfinite(m["start"]).all()]
        pick = rng.choice(len(moves), min(PER_PROGRAM, len(moves)), replace=False)
        ends = np.array([moves[i]["end"] for i in pick])
        mids = np.array([(moves[i]["start"] + moves[i]["end"]) / 2 for i in pick])
        centre = ends + [0, 0, r]
        cp, d = closest(nominal, centre)
        out[name] = dict(r=r, ends=ends, mids=mids, d=d, cp=cp, n=(centre - cp) / d[:, None],
                         moves=len(moves))
    return out


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


def test_semi_stock_is_a_closed_solid_over_the_machining_boundary(semi):
    assert semi.is_watertight and semi.is_winding_consistent and semi.volume > 0
    (x0, y0, z0), (x1, y1, z1) = semi.bounds
    text = (SAMPLES / "README.md").read_text()
    bx0, bx1, by0, by1 = map(float, re.search(r"boundary X([\d.]+)–([\d.]+), Y([\d.]+)–([\d.]+)", text).groups())
    assert x0 <= bx0 and x1 >= bx1 and y0 <= by0 and y1 >= by1
    assert z0 == pytest.approx(-1.625 * INCH, abs=1e-3)
    # the parting face + 0.2 mm + the semi-finishing raster's scallop (Ø10, 0.8 mm apart)
    assert ALLOWANCE - 1e-3 <= z1 <= ALLOWANCE + scallop(5.0, 0.8) + 1e-3
    assert (SAMPLES / "models" / "semi.stl").stat().st_size < 50e6


# -------------------------------------------------------------------------------- programs
def test_programs_are_fanuc_shaped_one_tool_each_in_machining_order():
    names = sorted(p.name for p in (SAMPLES / "nc").glob("*.nc"))
    assert names == sorted(PROGRAMS) == list(PROGRAMS)            # file-name order = machining order
    g1 = 0
    for name, (t, r, feed) in PROGRAMS.items():
        lines = (SAMPLES / "nc" / name).read_text().splitlines()
        assert lines[0] == "%" and lines[-1] == "%" and re.match(r"O\d{4} \(", lines[1])
        body = "\n".join(lines)
        assert re.findall(r"\bT(\d+)", re.sub(r"\(.*?\)", "", body)) == [str(t)]   # one tool change
        for word in ("G90 G17 G21 G40 G49 G80", f"T{t} M6", "M3", "M5", "M30", f"F{feed}"):
            assert word in body, (name, word)
        assert f"(T{t} BALL D{2 * r:.3f} R{r:.3f}" in body
        g1 += sum(1 for m in read_nc(SAMPLES / "nc" / name) if m["g"] == 1)
    assert 3000 <= g1 <= 15000


def test_the_pipeline_reads_every_program_with_its_tool():
    from stages import parse
    for name, (t, _, _) in PROGRAMS.items():
        path = SAMPLES / "nc" / name
        res = parse.run({"program_file": {"path": str(path), "program_id": path.stem, "sha256": ""}}, {})
        row = res["programs"].to_pylist()[0]
        assert row["status"] == "ok" and row["tool"] == t, row


def test_every_finishing_point_puts_the_ball_on_the_nominal(nominal, contacts):
    """NC points are the tool tip: the ball's centre (tip + r) is r from the surface at every cutting
    point, and never nearer between them (the chordal tolerance 5 µm and the 3-decimal rounding)."""
    for name, c in contacts.items():
        r = c["r"]
        assert np.abs(c["d"] - r).max() < 1.5e-3, (name, np.abs(c["d"] - r).max())
        d_mid = distance_to(nominal, c["mids"] + [0, 0, r])
        assert d_mid.min() > r - 6.5e-3, (name, d_mid.min())
    # the contour program keeps to walls steeper than 60°, the raster mostly to slopes up to it
    slope = {k: np.degrees(np.arccos(np.clip(c["n"][:, 2], -1, 1))) for k, c in contacts.items()}
    assert slope["10_steep_t1.nc"].min() > 59.0
    assert np.mean(slope["20_shallow_t1.nc"] <= 60.5) > 0.9


def test_the_contours_climb():
    """Each contour keeps the material on the tool's right (climb with M3): the air side, where the
    contact normal points, is on its left."""
    import trimesh as tm
    nominal = tm.load(SAMPLES / "models" / "mould.stl", force="mesh")
    moves = [m for m in read_nc(SAMPLES / "nc" / "10_steep_t1.nc") if m["g"] == 1 and m["feed"] == 3000
             and np.isfinite(m["start"]).all() and abs(m["end"][2] - m["start"][2]) < 1e-9
             and np.linalg.norm(m["end"] - m["start"]) > 0.5]
    mids = np.array([(m["start"] + m["end"]) / 2 for m in moves[::4]])
    d = np.array([m["end"] - m["start"] for m in moves[::4]])
    cp, _ = closest(nominal, mids + [0, 0, 5.0])
    n = mids + [0, 0, 5.0] - cp
    left = d[:, 0] * n[:, 1] - d[:, 1] * n[:, 0]
    assert len(left) > 50 and (left > 0).mean() > 0.95


def test_the_contours_go_down_level_by_level():
    """Z-level finishing runs top level first: a lower level's flutes never meet the stock of a level
    above that has not been cut yet (that would load the tool over the wall's whole height)."""
    z = [m["end"][2] for m in read_nc(SAMPLES / "nc" / "10_steep_t1.nc")
         if m["g"] == 1 and m["feed"] == 3000 and np.isfinite(m["start"]).all()]
    assert len(set(np.round(z, 3))) > 40 and (np.diff(z) <= 1e-9).all()


def test_the_stock_is_the_allowance_over_the_contact_points(semi, nominal, contacts):
    """Along the normal from each contact point to the stock mesh (brute-force ray crossings): at least
    the allowance (less the mesh's own tolerance) everywhere; away from the model's sharp edges and the
    stock's cut sides, on the contours' walls and the raster's slopes, at most the allowance plus the
    scallop the semi-finishing passes leave there."""
    sharp = feature_edges(nominal, 30.0)        # the faceted fillets' edges meet at less
    (x0, y0, _), (x1, y1, _) = semi.bounds
    r1 = 5.0
    for name, c in contacts.items():
        cp, n = c["cp"], c["n"]
        inside = (cp[:, 0] > x0 + 1) & (cp[:, 0] < x1 - 1) & (cp[:, 1] > y0 + 1) & (cp[:, 1] < y1 - 1)
        t = ray_exit(semi, cp[inside] - 1e-6 * n[inside], n[inside]) - 1e-6
        assert np.isfinite(t).all()
        edge = distance_to_segments(cp[inside], sharp)
        assert t[edge > 0.05].min() >= ALLOWANCE - MESH_TOL, (name, t[edge > 0.05].min())
        assert t.min() >= ALLOWANCE - EDGE_TOL, (name, t.min())
        assert abs(np.median(t) - ALLOWANCE) < 0.01, (name, np.median(t))
        if name == "30_pencil_t2.nc":
            continue                               # corners: where the semi-finishing Ø4 fits them (README)
        away = edge > 0.5
        nn = n[inside][away]
        slope = np.degrees(np.arccos(np.clip(nn[:, 2], -1, 1)))
        # the semi-finishing raster (rows along X, 0.8 mm apart) on slopes up to 60°, its contours
        # (0.3 mm apart in Z) on steeper walls, whichever leaves less
        across = 0.8 * np.sqrt(1 + (nn[:, 1] / np.maximum(nn[:, 2], 1e-9)) ** 2)
        raster = np.where(slope <= 65.0, scallop(r1, np.minimum(across, 2 * r1)), np.inf)
        wall = np.where(slope >= 55.0, scallop(r1, 0.3 / np.maximum(np.sin(np.radians(slope)), 0.5)), np.inf)
        bound = ALLOWANCE + np.minimum(raster, wall) + MESH_TOL
        assert away.sum() > 0.5 * len(away)
        # all but a few: where a semi-finishing row stops short at the slope limit it leaves up to
        # 0.05 mm more (the README's maxima, 0.25 mm)
        assert np.mean(t[away] <= bound) > 0.97, (name, np.mean(t[away] <= bound))
        assert t.max() <= 0.25 + MESH_TOL, (name, t.max())


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
