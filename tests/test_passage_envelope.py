"""Which tooth passage finishes a surface point: tool and sweep distances against brute force, and the
errors stage's deepest passage against a wall whose answer follows from its construction."""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from stages import errors
from stages.cutting import passages as pe
from stages.nc.reader import parse_program
from stages.nc.moves import split_blocks
from tests.ncprograms import wall_program

TOOLS = {"ball": (5.0, 5.0), "bull": (5.0, 1.5), "flat": (5.0, 0.0)}
STICK = 20.0



def _cutter(R, rc):
    from stages.geometry.cutter import Cutter
    kind = "ball" if rc == R else ("flat" if rc == 0 else "bull")
    return Cutter(kind, R, rc, STICK)

def _tool_surface(R, rc, n=1000, az=(0.0, 360.0), n_az=360):
    """Dense points on the tool surface (its profile revolved over the azimuths ``az``, degrees)."""
    a = R - rc
    prof = []
    if a > 0:
        r = np.linspace(0, a, n)
        prof.append(np.stack([r, np.zeros(n)], 1))                      # flat bottom
    if rc > 0:
        q = np.linspace(0, np.pi / 2, n)
        prof.append(np.stack([a + rc * np.sin(q), rc * (1 - np.cos(q))], 1))   # corner
    h = np.linspace(rc, STICK, n)
    prof.append(np.stack([np.full(n, R), h], 1))                         # side
    prof = np.concatenate(prof)
    th = np.radians(np.linspace(az[0], az[1], n_az))
    return np.stack([prof[:, None, 0] * np.cos(th), prof[:, None, 0] * np.sin(th),
                     np.broadcast_to(prof[:, None, 1], (len(prof), len(th)))], -1).reshape(-1, 3)


@pytest.mark.parametrize("kind", sorted(TOOLS))
def test_tool_distance_against_dense_surface_points(kind):
    R, rc = TOOLS[kind]
    rng = np.random.default_rng(3)
    # points outside the tool: below, beside, around the corner
    pts = np.concatenate([rng.uniform([-7, -7, -2], [7, 7, 0], (30, 3)),
                          rng.uniform([-8, -8, 0], [8, 8, 12], (30, 3))])
    d, q, h, nrm = _cutter(R, rc).distance(pts)
    outside = d > 0.05
    def nearest(p):           # over the surface within ±10° of the point's azimuth, 0.05° apart
        a = np.degrees(np.arctan2(p[1], p[0]))
        surf = _tool_surface(R, rc, az=(a - 10, a + 10), n_az=401)
        return np.sqrt(np.min(np.sum((surf - p) ** 2, axis=1)))

    brute = np.array([nearest(p) for p in pts[outside]])
    # points of the dense surface (≤ 0.02 mm apart) are on the tool: their distances are upper bounds
    assert np.all(d[outside] <= brute + 1e-9)
    np.testing.assert_allclose(d[outside], brute, atol=1.5e-3)
    # the nearest tool point (point − d·n) lies on the surface, at the height h above the tip
    foot = pts - d[:, None] * nrm
    assert max(nearest(f) for f in foot[outside]) < 0.03
    np.testing.assert_allclose(foot[outside, 2], h[outside], atol=1e-9)


@pytest.mark.parametrize("kind", sorted(TOOLS))
def test_sweep_distance_against_sampled_positions(kind):
    R, rc = TOOLS[kind]
    rng = np.random.default_rng(4)
    k = 200
    tip0 = rng.uniform(-1, 1, (k, 3))
    tip1 = tip0 + rng.normal(0, 1.0, (k, 3))
    pts = tip0 + rng.uniform([-7, -7, -3], [7, 7, 6], (k, 3))
    d, t, *_ = pe.sweep_distance(pts, tip0, tip1, _cutter(R, rc))
    ts = np.linspace(0, 1, 4001)
    brute = np.min(np.stack([_cutter(R, rc).distance(pts - tip0 - s * (tip1 - tip0))[0] for s in ts]), axis=0)
    # outside the swept tool the distance is convex along the move and the search exact; inside it
    # is an approximate depth (only its sign is used)
    out = brute > 0
    assert out.sum() > 120
    np.testing.assert_allclose(d[out], brute[out], atol=1e-6)
    assert np.all(d[~out] <= 1e-6)
    assert np.all((t >= 0) & (t <= 1))


def _standoff_um(dx_mm, off_um, R=5.0):
    """Distance from a point on the wall (equator height) to a ball whose centre is dx along the
    wall and off_um farther from it."""
    return (np.hypot(dx_mm, R + off_um * 1e-3) - R) * 1e3


@pytest.mark.parametrize("offset_um, by", [(0.0, "C"), (3.0, "C"), (8.0, "A")])
def test_short_pass_is_finished_by_the_deepest_neighbouring_passage(offset_um, by):
    """Deflection pushes A, B, C away from the wall by 10, 30, 5 µm (err = d·n). B is shorter than
    the feed per revolution (0.1 mm): the passages of A and C sweep its generating point too, so
    the wall there is left by the deepest of 30, 10 + A's stand-off and 5 + C's stand-off (the ball
    at the nearest end of each, 0.025 mm along the wall; C also ``offset_um`` farther from it). A
    point in the middle of A, farther than 1.5 revolutions from B, keeps A's 10 µm."""
    want = min(30.0, 10.0 + _standoff_um(0.025, 0.0), 5.0 + _standoff_um(0.025, offset_um))
    passes = wall_program(offset_um)
    pid = passes.column("pass_id").to_numpy()
    x0, x1 = passes.column("x0_mm").to_numpy(), passes.column("x1_mm").to_numpy()
    mot = passes.column("motion").to_numpy()
    cut = (mot == 1) & (passes.column("z0_mm").to_numpy() == 0) & (passes.column("z1_mm").to_numpy() == 0)
    a = int(pid[cut & (x0 == 0) & (x1 == 10)][0])
    b = int(pid[cut & (x0 == 10) & (x1 == 10.05)][0])
    c = int(pid[cut & (x0 == 10.05) & (x1 == 20)][0])
    names = {a: "A", b: "B", c: "C"}
    n_rot = 64
    # deflection over one revolution: constant, along +y (away from the wall)
    defl = pa.table({"program_id": ["w"] * 3, "pass_id": pa.array([a, b, c], pa.int32()),
                     "rotation_deg": [list(np.arange(n_rot) * 360.0 / n_rot)] * 3,
                     "dx_um": [[0.0] * n_rot] * 3,
                     "dy_um": [[10.0] * n_rot, [30.0] * n_rot, [5.0] * n_rot]})
    # generating points on the wall (q = 90°: the ball's equator, 5 mm above the tip): mid B, mid A
    gx = np.array([10.025, 5.0])
    gen = pa.table({"program_id": ["w"] * 2, "pass_id": pa.array([b, a], pa.int32()),
                    "gen_x_mm": gx, "gen_y_mm": [-5.0, -5.0], "gen_z_mm": [5.0, 5.0],
                    "rotation_deg": [-90.0, -90.0], "contact_deg": [90.0, 90.0],
                    "nx": [0.0, 0.0], "ny": [1.0, 1.0], "nz": [0.0, 0.0],
                    "n_px": pa.array([100, 100], pa.int32()), "view": ["below", "below"]})
    tool = {"type": "ball", "diameter_mm": 10.0, "flutes": 2, "helix_deg": 0.0, "stickout_mm": 20.0,
            "runout_um": 0.0}
    out = errors.run({"passes": passes, "generating": gen, "deflection": defl}, {"tool": tool})["errors"]
    err = dict(zip(out.column("pass_id").to_pylist(), out.column("err_um").to_pylist()))
    fin = dict(zip(out.column("pass_id").to_pylist(), out.column("finished_by").to_pylist()))
    assert err[b] == pytest.approx(want, abs=1e-6)
    assert names[fin[b]] == by
    assert err[a] == pytest.approx(10.0, abs=1e-9) and fin[a] == a
    parts = out.column("err_deflection_um").to_numpy() + out.column("err_shape_um").to_numpy() \
        + out.column("err_runout_um").to_numpy()
    np.testing.assert_allclose(parts, out.column("err_um").to_numpy(), atol=1e-12)


def test_a_line_cut_into_pieces_leaves_the_surface_of_the_line():
    """A wall finished along +x (as above) by one 10 mm line, and by the same line cut into 0.5 mm
    passes, every pass with the same deflection, which swings steeply with the spindle angle:
    dy(θ) = 30 + 60·sin 6θ µm (away from the wall). With the helix 0, flute j passes the contact
    (φ = −90° from the feed) at θ = 90° − 180°·j: dy = 30 µm for both flutes, the error of every
    pass. The pieces' neighbours are the same line: read at their ends, 0.25 mm off, the contact's
    azimuth turns by atan(0.25/5) = 2.9° and the deflection there is 30 ∓ 18 µm, 12 + 6.25 µm of
    stand-off under 30. Those ends are more than half a tooth's feed (0.1 mm) from the tool's
    position nearest C, where the tool carries on along the line: no passage there."""
    n_rot = 720
    theta = np.arange(n_rot) * 360.0 / n_rot
    dy = 30.0 + 60.0 * np.sin(np.radians(6 * theta))
    tool = {"type": "ball", "diameter_mm": 10.0, "flutes": 2, "helix_deg": 0.0, "stickout_mm": 20.0,
            "runout_um": 0.0}
    src = b"%\nO1\nT1 M6\nS1000 M3\nG0 X0 Y0 Z5\nG1 Z0 F400\nX10\nG0 Z5\nM30\n%\n"
    blocks, _ = parse_program(src, "line.nc", "w")
    for max_pass in (50.0, 0.5):
        split = {"split": {"chord_tol_mm": 0.001, "max_pass_mm": max_pass, "merge_max_mm": 0.0},
                 "machine": {"rapid_mm_min": 30000.0}, "tool": {"type": "ball", "diameter_mm": 10.0}}
        passes = split_blocks(blocks, split)
        col = lambda c: passes.column(c).to_numpy()  # noqa: E731
        line = (col("motion") == 1) & (col("z0_mm") == 0) & (col("z1_mm") == 0)
        pid = col("pass_id")[line].astype(np.int32)
        xm = 0.5 * (col("x0_mm") + col("x1_mm"))[line]
        k = len(pid)
        assert k == (1 if max_pass > 10 else 20)
        defl = pa.table({"program_id": ["w"] * k, "pass_id": pa.array(pid, pa.int32()),
                         "rotation_deg": [list(theta)] * k, "dx_um": [[0.0] * n_rot] * k,
                         "dy_um": [list(dy)] * k})
        gen = pa.table({"program_id": ["w"] * k, "pass_id": pa.array(pid, pa.int32()),
                        "gen_x_mm": xm, "gen_y_mm": np.full(k, -5.0), "gen_z_mm": np.full(k, 5.0),
                        "rotation_deg": np.full(k, -90.0), "contact_deg": np.full(k, 90.0),
                        "nx": np.zeros(k), "ny": np.ones(k), "nz": np.zeros(k),
                        "n_px": pa.array(np.full(k, 100), pa.int32()), "view": ["below"] * k})
        out = errors.run({"passes": passes, "generating": gen, "deflection": defl}, {"tool": tool})["errors"]
        np.testing.assert_allclose(out.column("err_um").to_numpy(), 30.0, atol=1e-6)
        assert out.column("finished_by").to_pylist() == out.column("pass_id").to_pylist()
