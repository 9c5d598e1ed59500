"""Corrected NC programs (issue 5): vertex moves, writer, reverse check, closed loop.

The closed loop runs on an independent virtual machine written here (not the pipeline's
prediction chain): a ball end mill whose tool is pushed away from the material by a compliance ×
a load that grows with the local penetration of the (actual, deflected) tool into the stock and
depends on the feed direction, so the error changes when the path moves and iteration is needed.
The finished surface is the brute-force lower envelope of the (deflected) ball positions on a grid;
the target is the lower envelope of the same program on an ideal (rigid) machine. Per-pass errors
for the correction are read off the simulated surface (the grid points each pass generates).
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from stages.correction.moves import REFINE_MAX_RATIO, gouge_limit, vertex_moves
from stages.correction.rounds import apply_corrected, correct_iteratively, correct_once
from stages.nc.heidenhain import write_comp_table, write_ln_program
from stages.nc.via import via_blocks
from stages.nc.writer import reverse_check, write_program
from stages.nc.reader import ARC_RADIUS_TOL_MM, parse_program
from stages.nc.moves import split_blocks

SAMPLES = ("data_samples/nc/mould_contour_t1.nc", "data_samples/nc/mould_finish_t1.nc")
SPLIT = {"split": {"chord_tol_mm": 0.001, "max_pass_mm": 5.0, "merge_max_mm": 0.5},
         "machine": {"rapid_mm_min": 30000.0},
         "tool": {"type": "ball", "diameter_mm": 10.0, "control_point": "tip"}}



def _stage_inputs(blocks, passes, errors, *, previous=None, round_passes=None, first=None, generating=None):
    """The ``correct`` stage's declared inputs for one round on ``passes`` of the original program."""
    return {"blocks@first": blocks, "passes@first": passes,
            "passes": passes if round_passes is None else round_passes, "errors": errors,
            "errors@first": first, "generating@first": generating, "corrected@previous": previous}

def _load(path):
    data = open(path, "rb").read()
    blocks, _ = parse_program(data, path, "p")
    return data, blocks, split_blocks(blocks, SPLIT)


def _errors(passes, err, normals):
    n = np.asarray(normals, float)
    return pa.table({"program_id": ["p"] * len(err), "pass_id": passes.column("pass_id"),
                     "err_um": np.asarray(err, float), "nx": n[:, 0], "ny": n[:, 1], "nz": n[:, 2]})


# ------------------------------------------------------------------------------------ closed forms

def test_equal_errors_and_normals_move_minus_e_n():
    rng = np.random.default_rng(1)
    n = rng.normal(size=(50, 3))
    n /= np.linalg.norm(n, axis=1)[:, None]
    e = rng.normal(0, 20, 50)
    m = vertex_moves(e, n, np.ones(50, bool), e, n, np.ones(50, bool))
    np.testing.assert_allclose(m, -e[:, None] * n, atol=1e-12)
    # one side without a prediction: the predicted side alone, also −e·n
    m1 = vertex_moves(e, n, np.ones(50, bool), np.zeros(50), np.zeros((50, 3)), np.zeros(50, bool))
    np.testing.assert_allclose(m1, -e[:, None] * n, atol=1e-12)
    # nothing predicted: no move
    m0 = vertex_moves(e, n, np.zeros(50, bool), e, n, np.zeros(50, bool))
    assert np.all(m0 == 0)


def test_perpendicular_normals_realise_both_errors():
    # wall (n = +x) meets floor (n = +z): the move along E'i + E'j that best realises both
    ni, nj = np.array([[1.0, 0, 0]]), np.array([[0, 0, 1.0]])
    m = vertex_moves(np.array([12.0]), ni, np.array([True]), np.array([-5.0]), nj, np.array([True]))
    np.testing.assert_allclose(m[0], [-12.0, 0.0, 5.0], atol=1e-12)


def test_oblique_normals_least_squares_magnitude():
    # normals 60° apart, different errors: the magnitude along d = unit(E'i + E'j) minimises
    # Σ(m·n_k + e_k)²; compare with a brute-force scan over the magnitude
    ni = np.array([1.0, 0, 0])
    nj = np.array([np.cos(np.pi / 3), 0, np.sin(np.pi / 3)])
    ei, ej = 10.0, 4.0
    m = vertex_moves(np.array([ei]), ni[None], np.array([True]), np.array([ej]), nj[None], np.array([True]),
                     refine=False)[0]
    d = -(ei * ni + ej * nj)
    d /= np.linalg.norm(d)
    s = np.linspace(0, 40, 400001)
    cost = (s * (d @ ni) + ei) ** 2 + (s * (d @ nj) + ej) ** 2
    np.testing.assert_allclose(m, s[np.argmin(cost)] * d, atol=1e-3)
    np.testing.assert_allclose(m / np.linalg.norm(m), d, atol=1e-12)


def test_refined_move_realises_both_errors_at_oblique_normals():
    # para 0084's single magnitude leaves m·n_k + e_k ≠ 0 at oblique normals; the refinement in the
    # plane of the two normals realises both (closed form: m = Nᵀ(N Nᵀ)⁻¹(−e), damped by λ ≈ 6e-4)
    rng = np.random.default_rng(7)
    ang = np.radians(rng.uniform(10, 170, 200))
    axis_a = rng.normal(size=(200, 3))
    axis_a /= np.linalg.norm(axis_a, axis=1)[:, None]
    perp = np.cross(axis_a, rng.normal(size=(200, 3)))
    perp /= np.linalg.norm(perp, axis=1)[:, None]
    na, nb = axis_a, np.cos(ang)[:, None] * axis_a + np.sin(ang)[:, None] * perp
    ea, eb = rng.normal(0, 10, 200), rng.normal(0, 10, 200)
    yes = np.ones(200, bool)
    m = vertex_moves(ea, na, yes, eb, nb, yes)
    exact = np.empty_like(m)
    for k in range(200):
        N = np.stack([na[k], nb[k]])
        exact[k] = N.T @ np.linalg.solve(N @ N.T, -np.array([ea[k], eb[k]]))
    res = np.abs(np.stack([np.einsum("ij,ij->i", m, na) + ea, np.einsum("ij,ij->i", m, nb) + eb], 1))
    p0084 = vertex_moves(ea, na, yes, eb, nb, yes, refine=False)
    res0 = np.abs(np.stack([np.einsum("ij,ij->i", p0084, na) + ea, np.einsum("ij,ij->i", p0084, nb) + eb], 1))
    # where the exact solution lies within REFINE_MAX_RATIO·max|e| of the 0084 move it is reached
    # (damping λ/(σ² + λ) with σ² ≥ 1 − cos 10° = 0.015: ≤ 4 % of the 0084 residual, which is ≤ |e|)
    cap = REFINE_MAX_RATIO * np.maximum(np.abs(ea), np.abs(eb))
    within = np.linalg.norm(exact - p0084, axis=1) < 0.9 * cap
    assert within.sum() > 150
    assert res[within].max() <= 0.04 * np.abs(np.stack([ea, eb])).max()
    rel = np.linalg.norm(m - exact, axis=1) / np.linalg.norm(exact, axis=1)
    assert np.median(rel[within]) < 0.01
    assert np.median(res0) > 1.0 and np.median(res[within]) < 0.05
    # beyond it the refinement stops at the cap, still reducing the 0084 residual
    far = np.linalg.norm(exact - p0084, axis=1) > 1.1 * cap
    assert np.allclose(np.linalg.norm(m - p0084, axis=1)[far], cap[far], rtol=1e-6)
    assert np.all(res[far].sum(1) < res0[far].sum(1))
    # parallel normals: nothing to refine (the 0084 move is the least-squares mean); 0.5° apart:
    # below NORMAL_TOL_DEG, the move stays near the mean instead of 1/sin(0.5°) = 115× amplification
    par = vertex_moves(ea, na, yes, eb, na, yes)
    np.testing.assert_allclose(par, -((ea + eb) / 2)[:, None] * na, atol=1e-9)
    tiny = np.radians(0.5)
    nb2 = np.cos(tiny) * na + np.sin(tiny) * perp
    close = vertex_moves(ea, na, yes, eb, nb2, yes)
    assert np.abs(np.linalg.norm(close, axis=1)).max() < 2 * np.abs(np.stack([ea, eb])).max()


def test_normal_tolerance_keeps_a_climb_vertex_from_sliding_sideways():
    """``normal_tol_deg``: the sample's corner climb in round 2, passes 2.95° apart (+75.8 µm along
    (−1, −0.004, 0.027), +87.0 µm along (−0.997, −0.049, 0.052)). The exact solve slides the vertex
    Δe / sin θ ≈ 220 µm across (towards the pocket's other wall); the 2° filter keeps 83 % of that,
    capped at 2 × 87 µm. With a 5° tolerance the mode is treated as one normal (its filter
    μ²/(μ² + μ_tol²) = 0.11) and the move stays within 30 µm of the para 0084 mean; a 30° corner is
    still realised (m·n = −e within 1 %: its filter is 0.9997)."""
    unit = lambda v: np.asarray(v, float) / np.linalg.norm(v)  # noqa: E731
    na, nb = unit([-1.0, -0.004, 0.027])[None], unit([-0.997, -0.049, 0.052])[None]
    ea, eb, yes = np.array([75.781]), np.array([86.973]), np.array([True])
    mean = vertex_moves(ea, na, yes, eb, nb, yes, refine=False)[0]
    sideways = lambda m: abs(m[1] - mean[1])  # noqa: E731  (y: across both normals)
    assert sideways(vertex_moves(ea, na, yes, eb, nb, yes)[0]) > 100.0           # the default, 2°
    held = vertex_moves(ea, na, yes, eb, nb, yes, normal_tol_deg=5.0)[0]
    assert sideways(held) < 30.0
    assert np.linalg.norm(held - mean) < 30.0
    wall = unit([np.cos(np.radians(30)), 0.0, np.sin(np.radians(30))])[None]
    floor = np.array([[0.0, 0.0, 1.0]])
    m = vertex_moves(np.array([20.0]), wall, yes, np.array([-8.0]), floor, yes, normal_tol_deg=5.0)[0]
    np.testing.assert_allclose([m @ wall[0], m @ floor[0]], [-20.0, 8.0], rtol=0.01)


# ------------------------------------------------------------------------------------ writer

@pytest.mark.parametrize("path", SAMPLES)
def test_no_error_gives_byte_identical_program(path):
    data, blocks, passes = _load(path)
    n = passes.num_rows
    zero = _errors(passes, np.zeros(n), np.tile([0, 0, 1.0], (n, 1)))
    corrected = correct_once(blocks, passes, zero, {"correct": {}})
    assert np.all(corrected.column("move_um").to_numpy() == 0)
    assert write_program(data, blocks, corrected) == data
    # no error rows at all (everything pruned): same
    none = correct_once(blocks, passes, zero.slice(0, 0), {"correct": {}})
    assert write_program(data, blocks, none) == data


def _random_errors(passes, seed, scale=15.0):
    rng = np.random.default_rng(seed)
    n = passes.num_rows
    nn = rng.normal(size=(n, 3))
    nn /= np.linalg.norm(nn, axis=1)[:, None]
    keep = rng.random(n) < 0.8          # some passes pruned
    err = _errors(passes, rng.normal(0, scale, n), nn)
    return err.filter(pa.array(keep))


def _code_words(line: bytes) -> bytes:
    import re
    return re.sub(rb"\([^)]*\)|;.*", b"", line)


@pytest.mark.parametrize("path", SAMPLES)
def test_reverse_check_random_moves(path):
    data, blocks, passes = _load(path)
    corrected = correct_once(blocks, passes, _random_errors(passes, 3), {"correct": {"max_move_um": 40.0}})
    out = write_program(data, blocks, corrected, max_move_um=40.0)
    rep = reverse_check(out, blocks, corrected)
    assert rep["ok"], rep["message"]
    assert rep["max_dev_um"] <= 0.5 + 1e-6            # written on the source's 0.001 mm grid
    if "max_centre_dev_um" in rep:
        assert rep["max_centre_dev_um"] < 5.0
    # the same pass structure after splitting (count and motion kinds)
    new_blocks, _ = parse_program(out, "x", "p")
    new_passes = split_blocks(new_blocks, SPLIT)
    assert np.array_equal(new_blocks.column("motion").to_numpy(), blocks.column("motion").to_numpy())
    assert abs(new_passes.num_rows - passes.num_rows) <= 0.01 * passes.num_rows
    # non-motion lines and comments byte for byte; one header line added after the O line
    src, dst = data.split(b"\n"), out.split(b"\n")
    assert len(dst) == len(src) + 1 and dst[2].startswith(b"(CORRECTED PROGRAM") and dst[1] == src[1]
    dst = dst[:2] + dst[3:]
    motion_lines = set(blocks.column("line_no").to_numpy() - 1)
    for i, (a, b) in enumerate(zip(src, dst)):
        if i not in motion_lines:
            assert a == b
        else:   # only digits of coordinate words differ: comments, N, G, F identical
            strip = lambda s: bytes(c for c in s if c not in b"0123456789.-+ XYZIJKR")  # noqa: E731
            assert strip(a) == strip(b)
            assert a.count(b"(") == b.count(b"(") and a.split(b"(")[1:] == b.split(b"(")[1:]
    # deterministic
    assert write_program(data, blocks, corrected, max_move_um=40.0) == out


def test_modal_omission_incremental_and_inch():
    text = b"\n".join([b"%", b"O0007", b"G90 G21 G17", b"T1 M6", b"S1000 M3", b"G0 X0. Y0. Z5.", b"G1 Z0. F100",
                       b"X10.000", b"X20.000 (ROW)", b"G91 X5.000 Y1.000", b"X5.000", b"G90 G20 X1.2000",
                       b"G21 G0 Z50.", b"M30", b"%", b""])
    blocks, _ = parse_program(text, "t", "p")
    passes = split_blocks(blocks, SPLIT)
    n = passes.num_rows
    # lift every predicted pass by 10 µm along +Y (err −10 with n = +y → move +10 µm in y)
    err = _errors(passes, np.full(n, -10.0), np.tile([0, 1.0, 0], (n, 1)))
    motion = passes.column("motion").to_numpy()
    err = err.filter(pa.array(motion != 0))
    corrected = correct_once(blocks, passes, err, {"correct": {}})
    out = write_program(text, blocks, corrected)
    lines = out.split(b"\n")
    assert lines[2].startswith(b"(CORRECTED")
    # the first vertex already carries the +10 µm in Y (the plunge after it is predicted): later
    # blocks keep Y modal; increments are unchanged (both ends moved alike); the inch block gets Y on
    # its 4-decimal inch grid; the final rapid's end has no predicted pass and goes back to Y1.000
    assert lines[3:] == [b"G90 G21 G17", b"T1 M6", b"S1000 M3", b"G0 X0. Y0.010 Z5.", b"G1 Z0. F100",
                         b"X10.000", b"X20.000 (ROW)", b"G91 X5.000 Y1.000", b"X5.000",
                         b"G90 G20 X1.2000 Y0.0398", b"G21 G0 Y1.000 Z50.", b"M30", b"%", b""]
    rep = reverse_check(out, blocks, corrected)
    assert rep["ok"], rep


def test_clipping_limits_and_flags():
    _, blocks, passes = _load(SAMPLES[0])
    n = passes.num_rows
    err = _errors(passes, np.full(n, 80.0), np.tile([0, 0, 1.0], (n, 1)))
    c = correct_once(blocks, passes, err, {"correct": {"max_move_um": 30.0}})
    move = c.column("move_um").to_numpy()
    clipped = c.column("clipped").to_numpy()
    assert move.max() <= 30.0 + 1e-9
    assert clipped.any() and np.allclose(move[clipped], 30.0)
    dz = (c.column("z_new_mm").to_numpy() - c.column("z_mm").to_numpy()) * 1000
    np.testing.assert_allclose(dz[clipped], -30.0, atol=1e-9)       # along −n, shortened
    # accumulating a second round keeps the total clipped
    c2 = correct_once(apply_corrected(blocks, c), passes, err, {"correct": {"max_move_um": 30.0}}, previous=c)
    assert c2.column("move_um").to_numpy().max() <= 30.0 + 1e-9
    assert c2.column("iteration").to_numpy()[0] == 2


def test_arc_refit_stays_a_circle():
    # a G17 arc and an R arc, radial errors on their chords: a uniform radial error must grow the
    # radius by that error (concentric), and the written arcs must pass the parser's radius check
    text = b"\n".join([b"%", b"O0008", b"G90 G21 G17", b"T1 M6", b"S1000 M3", b"G0 X10.000 Y0.000 Z0.000",
                       b"G1 X10.000 Y0.000 F500", b"G3 X0.000 Y10.000 I-10.000 J0.000",
                       b"G3 X-10.000 Y0.000 R10.000", b"G1 X-10.000 Y-5.000", b"M30", b"%", b""])
    blocks, _ = parse_program(text, "t", "p")
    passes = split_blocks(blocks, SPLIT)
    mid = (np.stack([passes.column(c).to_numpy() for c in ("x0_mm", "y0_mm")], 1)
           + np.stack([passes.column(c).to_numpy() for c in ("x1_mm", "y1_mm")], 1)) / 2
    radial = mid / np.linalg.norm(mid, axis=1)[:, None]
    nrm = np.column_stack([-radial, np.zeros(len(mid))])   # inside of a ring: material outside
    motion = passes.column("motion").to_numpy()
    arcs = (motion == 2) | (motion == 3)
    err = _errors(passes, np.full(len(mid), -20.0), nrm).filter(pa.array(arcs))   # 20 µm overcut
    c = correct_once(blocks, passes, err, {"correct": {}})
    cx, cy = c.column("cx_new_mm").to_numpy(), c.column("cy_new_mm").to_numpy()
    x, y = c.column("x_new_mm").to_numpy(), c.column("y_new_mm").to_numpy()
    mo = c.column("motion").to_numpy()
    i = np.flatnonzero(mo == 3)
    # overcut on the inside of a ring → the path moves toward the centre by 20 µm: radius 9.980
    for k in i:
        np.testing.assert_allclose(np.hypot(x[k] - cx[k], y[k] - cy[k]), 9.980, atol=2e-5)
        np.testing.assert_allclose(np.hypot(x[k - 1] - cx[k], y[k - 1] - cy[k]), 9.980, atol=2e-5)
        np.testing.assert_allclose([cx[k], cy[k]], [0, 0], atol=2e-5)
    out = write_program(text, blocks, c)
    rep = reverse_check(out, blocks, c)
    assert rep["ok"], rep
    nb, _ = parse_program(out, "t", "p")        # the parser's radius check passes
    m = nb.column("motion").to_numpy()
    for k in np.flatnonzero(m == 3):
        r0 = np.hypot(nb.column("x0_mm")[k].as_py() - nb.column("cx_mm")[k].as_py(),
                      nb.column("y0_mm")[k].as_py() - nb.column("cy_mm")[k].as_py())
        r1 = np.hypot(nb.column("x1_mm")[k].as_py() - nb.column("cx_mm")[k].as_py(),
                      nb.column("y1_mm")[k].as_py() - nb.column("cy_mm")[k].as_py())
        assert abs(r0 - r1) < ARC_RADIUS_TOL_MM / 5
        assert abs(r0 - 9.98) < 2e-3
    assert b"R9.980" in out and b"I-9.980 J0.000" in out


def test_random_arc_moves_stay_consistent():
    data, blocks, passes = _load(SAMPLES[0])
    for seed in range(3):
        c = correct_once(blocks, passes, _random_errors(passes, 10 + seed, 30.0), {"correct": {}})
        out = write_program(data, blocks, c)
        nb, _ = parse_program(out, "x", "p")            # raises if any arc radius is inconsistent
        m = nb.column("motion").to_numpy()
        arc = (m == 2) | (m == 3)
        g = lambda c_: nb.column(c_).to_numpy(zero_copy_only=False)[arc].astype(float)  # noqa: E731
        pl = nb.column("plane").to_numpy()[arc]
        ax = {17: (0, 1), 18: (2, 0), 19: (1, 2)}
        s = np.stack([g("x0_mm"), g("y0_mm"), g("z0_mm")], 1)
        e = np.stack([g("x1_mm"), g("y1_mm"), g("z1_mm")], 1)
        cc = np.stack([g("cx_mm"), g("cy_mm"), g("cz_mm")], 1)
        for k in range(s.shape[0]):
            a, b = ax[int(pl[k])]
            r0 = np.hypot(s[k, a] - cc[k, a], s[k, b] - cc[k, b])
            r1 = np.hypot(e[k, a] - cc[k, a], e[k, b] - cc[k, b])
            assert abs(r0 - r1) < ARC_RADIUS_TOL_MM / 2


def test_ln_arcs_become_chords_on_the_refitted_circle():
    text = b"\n".join([b"%", b"O0011", b"G90 G21 G17", b"T1 M6", b"S1000 M3", b"G0 X10.000 Y0.000 Z0.000",
                       b"G1 X10.000 Y0.000 F500", b"G3 X0.000 Y10.000 I-10.000 J0.000", b"M30", b"%", b""])
    blocks, _ = parse_program(text, "t", "p")
    passes = split_blocks(blocks, SPLIT)
    mid = (np.stack([passes.column(c).to_numpy() for c in ("x0_mm", "y0_mm")], 1)
           + np.stack([passes.column(c).to_numpy() for c in ("x1_mm", "y1_mm")], 1)) / 2
    radial = mid / np.linalg.norm(mid, axis=1)[:, None]
    err = _errors(passes, np.full(len(mid), 10.0), np.column_stack([radial, np.zeros(len(mid))]))
    c = correct_once(blocks, passes, err, {"correct": {}})
    ln = write_ln_program(blocks, c, "ARC", chord_tol_mm=0.001).splitlines()
    full = [s.split() for s in ln if " LN " in s and " X" in s and " Y" in s]
    pts = np.array([[float(w[1:]) for w in s if w[0] in "XY" and w[1] in "+-"] for s in full])
    nrm = np.array([[float(w[2:]) for w in s if w[:2] in ("NX", "NY")] for s in full])
    r = np.linalg.norm(pts, axis=1)
    assert len(pts) > 50
    np.testing.assert_allclose(r, 9.990, atol=2e-4)                  # 10 µm left outside → radius −10 µm
    # normals radial at every chord point, within one chord angle (the end normal is that of the
    # last chord pass, whose normal is taken at its middle)
    np.testing.assert_allclose(nrm, pts / r[:, None], atol=0.03)


def test_ln_and_comp_table():
    _, blocks, passes = _load(SAMPLES[1])
    err = _random_errors(passes, 5)
    q = np.random.default_rng(0).uniform(0, 90, err.num_rows)
    err = err.append_column("contact_deg", pa.array(q))
    c = correct_once(blocks, passes, err, {"correct": {}})
    ln = write_ln_program(blocks, c, "MOULD")
    lines = ln.splitlines()
    assert lines[0] == "0 BEGIN PGM MOULD MM" and lines[-1].endswith("END PGM MOULD MM")
    lnb = [s for s in lines if " LN " in s]
    assert len(lnb) > 0.5 * c.num_rows
    v = np.array([[float(w[2:]) for w in s.split() if w[:2] in ("NX", "NY", "NZ")] for s in lnb[:200]])
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, atol=1e-6)
    tab = write_comp_table(pa.table({"contact_deg": [45.0, 45.2, 60.0], "err_um": [2.0, 4.0, -1.0]}))
    rows = {float(r.split(",")[0]): float(r.split(",")[1]) for r in tab.splitlines()[3:]}
    assert rows[45.0] == pytest.approx(-0.003)      # 3 µm left at 45° → tool 3 µm smaller there
    assert rows[60.0] == pytest.approx(0.001)
    assert rows[50.0] == pytest.approx(-0.003 + (0.004) * 5 / 15, abs=1e-5)
    assert rows[0.0] == pytest.approx(-0.003) and rows[90.0] == pytest.approx(0.001)


# ------------------------------------------------------------------------------------ virtual machine

class VirtualMachine:
    """Independent brute-force simulation of ball-end finishing with a compliant machine.

    ``centre_surface(x, y) -> (F, dF/dx, dF/dy)``: the nominal ball-centre surface the program was
    made for (an offset of the part). The load at a tool position is proportional to its penetration
    into the stock, ``allow + (F(x, y) − z_c)·n_z`` along the normal of F (so a path moved into the
    part cuts deeper and deflects more), the tool is pushed out of the material horizontally by
    ``gain·load`` along the horizontal normal (stiffness differing in x and y) plus ``side·load``
    to the left of the feed direction (up/down milling), solved for the deflected position.
    """

    def __init__(self, centre_surface, radius, allow_um, gain_xy=(0.5, 0.35), side=0.08, step=0.1):
        self.F, self.R, self.allow = centre_surface, radius, allow_um / 1000.0
        self.gain, self.side, self.step = np.array(gain_xy), side, step

    def samples(self, passes, deflect=True, box=None):
        """Ball centres along the cutting passes (mm) and the pass index of each.

        ``box`` = (x0, x1, y0, y1): only passes that come within the tool radius of it.
        """
        g = lambda c: passes.column(c).to_numpy().astype(float)  # noqa: E731
        p0 = np.stack([g("x0_mm"), g("y0_mm"), g("z0_mm")], 1)
        p1 = np.stack([g("x1_mm"), g("y1_mm"), g("z1_mm")], 1)
        cut = passes.column("motion").to_numpy() != 0
        if box is not None:
            lo, hi = np.minimum(p0, p1), np.maximum(p0, p1)
            r = self.R + 0.1
            cut &= (hi[:, 0] > box[0] - r) & (lo[:, 0] < box[1] + r) & (hi[:, 1] > box[2] - r) & (lo[:, 1] < box[3] + r)
        idx = np.flatnonzero(cut)
        length = np.linalg.norm(p1[idx] - p0[idx], axis=1)
        k = np.maximum(1, np.ceil(length / self.step)).astype(int) + 1
        owner = np.repeat(idx, k)
        first = np.concatenate(([0], np.cumsum(k)[:-1]))
        t = (np.arange(owner.size) - np.repeat(first, k)) / np.repeat(k - 1, k)
        c = p0[owner] + (p1[owner] - p0[owner]) * t[:, None]
        c[:, 2] += self.R
        if deflect:
            feed = (p1 - p0)[owner]
            feed /= np.maximum(np.linalg.norm(feed, axis=1), 1e-12)[:, None]
            c = c + self.deflection(c, feed)
        return c, owner

    def deflection(self, c, feed):
        d = np.zeros_like(c)
        for _ in range(6):                      # the load is that of the deflected position
            f, fx, fy = self.F(c[:, 0] + d[:, 0], c[:, 1] + d[:, 1])
            nz = 1 / np.sqrt(1 + fx ** 2 + fy ** 2)
            nx, ny = -fx * nz, -fy * nz
            load = np.maximum(self.allow + (f - c[:, 2]) * nz, 0.0)
            d = np.zeros_like(c)
            d[:, 0] = load * (self.gain[0] * nx - self.side * feed[:, 1])
            d[:, 1] = load * (self.gain[1] * ny + self.side * feed[:, 0])
        return d

    def surface(self, passes, xs, ys, deflect=True):
        """Lower envelope of the balls on the grid: height, generating pass, generating centre."""
        c, owner = self.samples(passes, deflect, box=(xs[0], xs[-1], ys[0], ys[-1]))
        sel = (c[:, 0] > xs[0] - self.R) & (c[:, 0] < xs[-1] + self.R) & (c[:, 1] > ys[0] - self.R) & (c[:, 1] < ys[-1] + self.R)
        c, owner = c[sel], owner[sel]
        o = np.argsort(c[:, 1], kind="stable")
        c, owner = c[o], owner[o]
        z = np.full((ys.size, xs.size), np.inf)
        gen = np.full((ys.size, xs.size), -1)
        cen = np.zeros((ys.size, xs.size, 3))
        for j, y in enumerate(ys):
            lo, hi = np.searchsorted(c[:, 1], [y - self.R, y + self.R])
            w = c[lo:hi]
            rho2 = self.R ** 2 - (w[:, 1] - y) ** 2
            dx2 = (xs[:, None] - w[None, :, 0]) ** 2
            h = np.where(dx2 < rho2, w[None, :, 2] - np.sqrt(np.maximum(rho2 - dx2, 0)), np.inf)
            a = np.argmin(h, axis=1)
            z[j] = h[np.arange(xs.size), a]
            gen[j] = owner[lo:hi][a]
            cen[j] = w[a]
        return z, gen, cen


def _closed_loop(text, vm, xs, ys, params, max_iter=4):
    """Correct ``text`` on the virtual machine; RMS machining error before and after, per round."""
    blocks0, _ = parse_program(text, "vm", "p")
    passes0 = split_blocks(blocks0, SPLIT)
    target, _, cen0 = vm.surface(passes0, xs, ys, deflect=False)
    gx, gy = np.meshgrid(xs, ys)
    normal = cen0 - np.stack([gx, gy, target], -1)           # from the contact to the ball centre
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)

    def machined_error(passes):
        z, gen, _ = vm.surface(passes, xs, ys, deflect=True)
        return (z - target) * normal[..., 2] * 1000.0, gen    # µm along the normal, + = left

    def predict(blocks):
        passes = split_blocks(blocks, SPLIT)
        err, gen = machined_error(passes)
        rms.append(float(np.sqrt(np.mean(err ** 2))))
        ids = gen.ravel()
        n = passes.num_rows
        cnt = np.bincount(ids, minlength=n)
        e = np.bincount(ids, err.ravel(), n) / np.maximum(cnt, 1)
        nn = np.stack([np.bincount(ids, normal[..., i].ravel(), n) for i in range(3)], 1)
        have = cnt >= 3
        nn[have] /= np.linalg.norm(nn[have], axis=1)[:, None]
        tab = _errors(passes, e, nn).filter(pa.array(have))
        return passes, tab

    rms = []                          # machining error of the path each round predicted on
    corrected = correct_iteratively(blocks0, predict, {"correct": dict(params, max_iter=max_iter)})
    out = write_program(text, blocks0, corrected)
    assert reverse_check(out, blocks0, corrected)["ok"]
    written, _ = parse_program(out, "vm-corrected", "p")
    final = float(np.sqrt(np.mean(machined_error(split_blocks(written, SPLIT))[0] ** 2)))
    return rms, final, corrected


def _program(rows):
    """Fanuc-style text from rows of (x, y, z) tip points per pass line, zigzag joined by G1 links."""
    lines = ["%", "O2001 (VIRTUAL MACHINE CASE)", "G90 G17 G21", "T1 M6", "S10000 M3"]
    n = 10
    x, y, z = rows[0][0]
    lines += [f"N{n} G0 X{x:.3f} Y{y:.3f}", f"N{n + 10} Z{z + 5:.3f}", f"N{n + 20} G1 Z{z:.3f} F2000"]
    n += 30
    for r in rows:
        for x, y, z in r:
            lines.append(f"N{n} X{x:.3f} Y{y:.3f} Z{z:.3f}")
            n += 10
    lines += [f"N{n} G0 Z50.000", f"N{n + 10} M30", "%", ""]
    return "\n".join(lines).encode()


def test_closed_loop_cylinder_contour():
    """Seed 000 Fig. 16/20 style: z-level passes along a cylinder (axis along Y), q from 0 to 60°."""
    rc, R = 12.0, 3.0
    pitch = 0.4
    qs = np.arange(-8, 68, np.degrees(pitch / rc)) * np.pi / 180

    def centre_surface(x, y):
        rr = rc + R
        xx = np.clip(x, -rr + 1e-6, rr - 1e-6)
        f = np.sqrt(rr ** 2 - xx ** 2)
        return f, -xx / f, np.zeros_like(f)

    ys = np.arange(-3.0, 3.01, 0.25)
    rows = []
    for k, q in enumerate(qs):
        yy = np.linspace(-7.0, 7.0, 15) * (1 if k % 2 == 0 else -1)
        cx, cz = (rc + R) * np.sin(q), (rc + R) * np.cos(q) - R
        rows.append([(cx, y, cz) for y in yy])
    text = _program(rows)
    vm = VirtualMachine(centre_surface, R, allow_um=60.0)
    xs = np.arange(0.0, rc * np.sin(np.radians(60)), 0.05)
    rms, final, corrected = _closed_loop(text, vm, xs, ys, {"max_move_um": 100.0, "tol_um": 0.2})
    print(f"\ncylinder contour: RMS error {rms[0]:.2f} µm before, rounds {['%.2f' % r for r in rms[1:]]},"
          f" written program {final:.2f} µm = {100 * final / rms[0]:.1f} % of before")
    assert rms[0] > 5.0
    assert final <= 0.2 * rms[0]
    assert corrected.column("iteration").to_numpy()[0] >= 2


def test_closed_loop_freeform_raster():
    """Zigzag raster along X over a free-form surface (bump on a saddle)."""
    R = 3.0

    def centre_surface(x, y):
        b = np.exp(-((x - 5) ** 2 + (y - 4) ** 2) / 12.0)
        f = 2.0 * b + 0.04 * (x - 5) * (y - 4) + 0.1 * x
        fx = 2.0 * b * (-(x - 5) / 6.0) + 0.04 * (y - 4) + 0.1
        fy = 2.0 * b * (-(y - 4) / 6.0) + 0.04 * (x - 5)
        return f, fx, fy

    xs = np.arange(0.0, 10.0, 0.1)
    ys = np.arange(0.0, 8.0, 0.1)
    rows = []
    for k, y in enumerate(np.arange(-3.5, 11.6, 0.5)):
        xx = np.arange(-3.5, 13.6, 0.5)[:: 1 if k % 2 == 0 else -1]
        f, _, _ = centre_surface(xx, np.full_like(xx, y))
        rows.append(list(zip(xx, np.full_like(xx, y), f - R)))
    text = _program(rows)
    vm = VirtualMachine(centre_surface, R, allow_um=60.0)
    rms, final, _ = _closed_loop(text, vm, xs, ys, {"max_move_um": 100.0, "tol_um": 0.2})
    print(f"\nfree-form raster: RMS error {rms[0]:.2f} µm before, rounds {['%.2f' % r for r in rms[1:]]},"
          f" written program {final:.2f} µm = {100 * final / rms[0]:.1f} % of before")
    assert rms[0] > 3.0
    assert final <= 0.2 * rms[0]


def test_writer_keeps_dialect_details():
    # CRLF, words without spaces, "-.500" and "+1.000" styles, ';' and '( )' comments inside
    # blocks, a G19 arc with J K
    src = [b"%", b"O0009", b"(STYLE)", b"G90G17G21", b"T1M6", b"S1000M3", b"G0X-.500Y+1.000Z5.000",
           b"G1Z0.000F100 ; plunge", b"X10.000(MID)Y+1.000", b"G19 G2 Y3.000 Z2.000 J1.000 K1.000",
           b"G0Z50.000", b"M30", b"%", b""]
    text = b"\r\n".join(src)
    blocks, _ = parse_program(text, "t", "p")
    passes = split_blocks(blocks, SPLIT)
    cut = passes.column("motion").to_numpy() != 0
    n = passes.num_rows
    # every cutting pass leaves 10 µm along n = (0.6, 0, 0.8): every vertex moves by (−6, 0, −8) µm
    err = _errors(passes, np.full(n, 10.0), np.tile([0.6, 0, 0.8], (n, 1))).filter(pa.array(cut))
    c = correct_once(blocks, passes, err, {"correct": {}})
    out = write_program(text, blocks, c).split(b"\r\n")
    assert out[2].startswith(b"(CORRECTED PROGRAM") and out[2].endswith(b")")
    assert out[:2] + out[3:] == [
        b"%", b"O0009", b"(STYLE)", b"G90G17G21", b"T1M6", b"S1000M3", b"G0X-.506Y+1.000Z4.992",
        b"G1Z-0.008F100 ; plunge", b"X9.994(MID)Y+1.000", b"G19 G2 Y3.000 Z1.992 J1.000 K1.000",
        b"G0X10.000Z50.000", b"M30", b"%", b""]        # the retract's end has no predicted pass
    assert reverse_check(b"\r\n".join(out), blocks, c)["ok"]
    # no O line and no %: the header goes first
    bare = b"\n".join(src[3:-2]) + b"\n"
    b2, _ = parse_program(bare, "t", "p")
    c2 = correct_once(b2, split_blocks(b2, SPLIT), err, {"correct": {}})
    out2 = write_program(bare, b2, c2)
    assert out2.startswith(b"(CORRECTED PROGRAM") and out2.split(b"\n")[1] == b"G90G17G21"


def _sample_centre_surface(passes, radius, x_range, y_range, step=0.05):
    """Ball-centre surface of a raster program along X: rows interpolated linearly along X (the CL
    polyline) and by cubic splines across rows; returns (F, dF/dx, dF/dy) as a function of x, y."""
    from scipy.interpolate import CubicSpline, RegularGridInterpolator
    g = lambda c: passes.column(c).to_numpy()  # noqa: E731
    row = (g("motion") != 0) & (np.abs(g("y1_mm") - g("y0_mm")) < 1e-9)
    x0, x1, y, z0, z1 = (g(c)[row] for c in ("x0_mm", "x1_mm", "y0_mm", "z0_mm", "z1_mm"))
    rows_y = np.unique(np.round(y, 3))
    gx = np.arange(x_range[0] - radius - 2, x_range[1] + radius + 2, step)
    zr = np.empty((rows_y.size, gx.size))
    for i, yy in enumerate(rows_y):
        s = np.abs(y - yy) < 1e-6
        xx, zz = np.concatenate([x0[s], x1[s]]), np.concatenate([z0[s], z1[s]])
        o = np.argsort(xx, kind="stable")
        zr[i] = np.interp(gx, xx[o], zz[o]) + radius
    spl = CubicSpline(rows_y, zr, axis=0)
    gy = np.arange(max(y_range[0] - radius - 2, rows_y[0]), min(y_range[1] + radius + 2, rows_y[-1]), step)
    f, fy = spl(gy), spl(gy, 1)
    fx = np.gradient(f, gx, axis=1)
    interp = [RegularGridInterpolator((gy, gx), a) for a in (f, fx, fy)]

    def centre_surface(x, y):
        q = np.stack([np.clip(y, gy[0], gy[-1]), np.clip(x, gx[0], gx[-1])], -1)
        return tuple(i(q) for i in interp)
    return centre_surface


@pytest.mark.parametrize("window", [(14.0, 24.0, 34.0, 44.0), (60.0, 72.0, 36.0, 44.0)])
def test_closed_loop_sample_finishing_program(window):
    """The sample finishing program (OpenCAMLib raster, Ø10 ball) on the virtual machine, in a window.

    The second window holds the foot of the pocket wall at x ≈ 73.2: every row's corner ball (two or
    three vertices 25–40 µm apart) leaves a fan of its own sphere 2–3 mm wide on the floor, with
    normals spread over ~40°, and the virtual machine pushes it sideways by up to 30 µm. The passes
    meeting at those vertices have clearly different normals; the para 0084 move along E'i + E'j
    with one magnitude cannot realise both errors there, and the iteration only slowly recovered
    the rest (27.5 % after 4 rounds; 78 % of the remaining mean square in the 20 % of the window
    covered by the fans). The least-squares refinement in the plane of the two normals
    (stages.correct.vertex_moves) realises both. The bound is the issue's 20 %.
    """
    data = open(SAMPLES[1], "rb").read()
    blocks, _ = parse_program(data, SAMPLES[1], "p")
    passes = split_blocks(blocks, SPLIT)
    x0, x1, y0, y1 = window
    vm = VirtualMachine(_sample_centre_surface(passes, 5.0, (x0, x1), (y0, y1)), 5.0, allow_um=60.0)
    rms, final, _ = _closed_loop(data, vm, np.arange(x0, x1, 0.1), np.arange(y0, y1, 0.1),
                                 {"max_move_um": 100.0, "tol_um": 0.2})
    print(f"\nsample {SAMPLES[1]} window x{x0:g}-{x1:g} y{y0:g}-{y1:g}: RMS error {rms[0]:.2f} µm before, rounds "
          f"{['%.2f' % r for r in rms[1:]]}, written program {final:.2f} µm = {100 * final / rms[0]:.1f} % of before")
    assert final <= 0.2 * rms[0]


def test_merged_pass_interior_and_untouched_neighbours():
    # ten 0.1 mm blocks merge into passes ≤ 0.5 mm; one predicted pass: its interior vertices and
    # both ends move by −e·n, every other vertex stays
    lines = [b"%", b"O0010", b"G90 G17 G21", b"T1 M6", b"S1000 M3", b"G0 X0.000 Y0.000 Z1.000", b"G1 Z0.000 F100"]
    lines += [b"X%.3f" % (0.1 * (i + 1)) for i in range(30)] + [b"G0 Z10.000", b"M30", b"%", b""]
    text = b"\n".join(lines)
    blocks, _ = parse_program(text, "t", "p")
    passes = split_blocks(blocks, SPLIT)
    b0, b1 = passes.column("block_no").to_numpy(), passes.column("block_end").to_numpy()
    k = int(np.flatnonzero(b1 - b0 >= 2)[1])             # a merged pass in the middle of the row
    n = np.array([[0.0, 0.6, 0.8]])
    err = _errors(passes.slice(k, 1), [5.0], n)
    c = correct_once(blocks, passes, err, {"correct": {}})
    bn = c.column("block_no").to_numpy()
    d = np.stack([c.column(f"{a}_new_mm").to_numpy() - c.column(f"{a}_mm").to_numpy() for a in "xyz"], 1) * 1000
    moved = (bn >= b0[k] - 1) & (bn <= b1[k])               # start vertex (end of the block before) … end
    np.testing.assert_allclose(d[moved], np.tile(-5.0 * n, (moved.sum(), 1)), atol=1e-9)
    assert np.all(d[~moved] == 0)
    assert moved.sum() == b1[k] - b0[k] + 2


class CylinderMachine:
    """Independent simulation of the seed's cylinder benchmark (seed 000 Fig. 16/20, paras 0091–0092).

    Cylinder of radius ``rc`` about the Y axis, Ø20 ball, z-level passes along Y from the top
    (q = 0°) down the +X side to q = 89°. The finished surface is the envelope of the (deflected)
    balls seen from the cylinder axis: at angle θ (from +Z toward +X) and height y it is the nearest
    ball surface along the ray, so steep walls up to the equator are exact (no height field). The
    load is the radial penetration of the deflected ball into the stock (radius rc + allow); the
    tool bends sideways (XY) by ``gain``·load along the horizontal normal, plus ``side``·load to the
    left of the feed (up- and down-milling levels differ).
    """

    def __init__(self, rc, radius, allow_um, gain=0.5, side=0.1, step=0.2):
        self.rc, self.R, self.allow, self.gain, self.side, self.step = rc, radius, allow_um / 1000, gain, side, step

    def _load(self, c):
        return np.maximum(self.allow + self.rc + self.R - np.hypot(c[:, 0], c[:, 2]), 0.0)

    def samples(self, passes, deflect=True):
        vm = VirtualMachine(None, self.R, 0.0, step=self.step)
        c, owner = vm.samples(passes, deflect=False)
        if deflect:
            g = lambda k: passes.column(k).to_numpy().astype(float)  # noqa: E731
            feed = np.stack([g("x1_mm") - g("x0_mm"), g("y1_mm") - g("y0_mm")], 1)[owner]
            feed /= np.maximum(np.linalg.norm(feed, axis=1), 1e-12)[:, None]
            d = np.zeros_like(c)
            for _ in range(6):
                p = c + d
                rho = np.hypot(p[:, 0], p[:, 2])
                nx = p[:, 0] / rho
                load = self._load(p)
                d = np.zeros_like(c)
                d[:, 0] = load * (self.gain * nx - self.side * feed[:, 1])
                d[:, 1] = load * self.side * feed[:, 0]
            c = c + d
        return c, owner

    def surface(self, passes, thetas, ys, deflect=True):
        """Finished radius at (y, θ) and the generating pass."""
        c, owner = self.samples(passes, deflect)
        rho = np.hypot(c[:, 0], c[:, 2])
        th = np.arctan2(c[:, 0], c[:, 2])
        r = np.full((ys.size, thetas.size), np.inf)
        gen = np.full((ys.size, thetas.size), -1)
        for j, y in enumerate(ys):
            near = np.abs(c[:, 1] - y) < self.R
            rr2 = self.R ** 2 - (c[near, 1] - y) ** 2
            dth = thetas[:, None] - th[near][None, :]
            along = rho[near] * np.cos(dth)
            disc = rr2 - (rho[near] * np.sin(dth)) ** 2
            t = np.where((disc >= 0) & (along > 0), along - np.sqrt(np.maximum(disc, 0)), np.inf)
            a = np.argmin(t, axis=1)
            r[j] = t[np.arange(thetas.size), a]
            gen[j] = owner[near][a]
        return r, gen


def test_closed_loop_cylinder_benchmark():
    """Seed Fig. 16 geometry (Ø20 ball, 0.63 mm pitch, 50 levels to q = 89°), closed loop."""
    R, pitch, n_levels, q_max = 10.0, 0.63, 50, 89.0
    dq = np.radians(q_max / n_levels)
    rc = pitch / dq
    qs = np.arange(-1, n_levels + 2) * dq
    rows = []
    for k, q in enumerate(qs):
        yy = np.arange(-14.0, 14.01, 2.0)[:: 1 if k % 2 == 0 else -1]
        cx, cz = (rc + R) * np.sin(q), (rc + R) * np.cos(q) - R
        rows.append([(cx, y, cz) for y in yy])
    text = _program(rows)
    vm = CylinderMachine(rc, R, allow_um=60.0)
    thetas = np.radians(np.arange(0.0, q_max + 1e-9, 0.1))
    ys = np.array([-2.0, 0.0, 2.0])
    blocks0, _ = parse_program(text, "cyl", "p")
    passes0 = split_blocks(blocks0, SPLIT)
    target, _ = vm.surface(passes0, thetas, ys, deflect=False)
    normal = np.stack([np.sin(thetas), np.zeros_like(thetas), np.cos(thetas)], 1)
    rms, q_err = [], []

    def predict(blocks):
        passes = split_blocks(blocks, SPLIT)
        r, gen = vm.surface(passes, thetas, ys)
        err = (r - target) * 1000.0                     # radial = along the normal, + = material left
        rms.append(float(np.sqrt(np.mean(err ** 2))))
        q_err.append(err[1])
        n = passes.num_rows
        ids = gen.ravel()
        cnt = np.bincount(ids, minlength=n)
        e = np.bincount(ids, err.ravel(), n) / np.maximum(cnt, 1)
        nn = np.stack([np.bincount(ids, np.broadcast_to(normal[:, i], gen.shape).ravel(), n) for i in range(3)], 1)
        have = cnt >= 3
        nn[have] /= np.linalg.norm(nn[have], axis=1)[:, None]
        return passes, _errors(passes, e, nn).filter(pa.array(have))

    corrected = correct_iteratively(blocks0, predict, {"correct": {"max_move_um": 100.0, "tol_um": 0.2, "max_iter": 4}})
    out = write_program(text, blocks0, corrected)
    assert reverse_check(out, blocks0, corrected)["ok"]
    written, _ = parse_program(out, "cyl-corrected", "p")
    predict(written)
    final = rms[-1]
    q = np.degrees(thetas)
    band = lambda e, a, b: float(np.abs(e[(q >= a) & (q < b)]).max())  # noqa: E731
    print(f"\ncylinder benchmark (Ø20, rc {rc:.2f} mm, q 0–89°): RMS error {rms[0]:.2f} µm before, rounds "
          f"{['%.2f' % r for r in rms[1:-1]]}, written program {final:.2f} µm = {100 * final / rms[0]:.1f} % of before; "
          f"max |error| at q 80–89°: {band(q_err[0], 80, 90):.1f} → {band(q_err[-1], 80, 90):.1f} µm")
    assert rms[0] > 10.0
    assert final <= 0.2 * rms[0]


def test_stage_run_matches_schema():
    import schemas
    from stages import correct
    _, blocks, passes = _load(SAMPLES[0])
    out = correct.run(_stage_inputs(blocks, passes, _random_errors(passes, 7)),
                      {"correct": {"max_move_um": 50.0, "tol_um": 0.1, "max_iter": 5, "ln_normals": False,
                                   "comp_table": False}})
    table = schemas.check("corrected", out["corrected"])
    motion = blocks.column("motion").to_numpy()
    assert table.num_rows == int((motion <= 3).sum())
    assert set(table.column("iteration").to_pylist()) == {1}


def test_incremental_program_random_moves_reverse_check():
    rng = np.random.default_rng(4)
    lines = [b"%", b"O0012", b"G90 G17 G21", b"T1 M6", b"S1000 M3", b"G0 X0.000 Y0.000 Z1.000", b"G1 Z0.000 F100", b"G91"]
    lines += [b"X%.3f Y%.3f Z%.3f" % tuple(rng.uniform(-1, 1, 3)) for _ in range(200)]
    lines += [b"G3 X1.000 Y1.000 I0.000 J1.000", b"G90 G0 Z20.000", b"M30", b"%", b""]
    text = b"\n".join(lines)
    blocks, _ = parse_program(text, "t", "p")
    passes = split_blocks(blocks, SPLIT)
    c = correct_once(blocks, passes, _random_errors(passes, 9), {"correct": {}})
    out = write_program(text, blocks, c)
    rep = reverse_check(out, blocks, c)
    assert rep["ok"], rep
    assert rep["max_dev_um"] <= 0.5 + 1e-6          # increments on the grid: no drift over 200 blocks


def test_full_circle_and_long_r_arc_stay_what_they_are():
    # a full circle (I J only) and a 270° R arc (negative R): after random moves the circle is still
    # full and the R arc still spans more than 180° with its refitted centre
    text = b"\n".join([b"%", b"O0013", b"G90 G21 G17", b"T1 M6", b"S1000 M3", b"G0 X10.000 Y0.000 Z0.000",
                       b"G1 X10.000 Y0.000 F500", b"G3 I-10.000 J0.000", b"G1 X10.000 Y-1.000",
                       b"G2 X0.000 Y-11.000 R-10.000", b"G1 X0.000 Y-12.000", b"M30", b"%", b""])
    blocks, _ = parse_program(text, "t", "p")
    passes = split_blocks(blocks, SPLIT)
    for seed in range(5):
        c = correct_once(blocks, passes, _random_errors(passes, 20 + seed, 20.0), {"correct": {}})
        out = write_program(text, blocks, c)
        assert reverse_check(out, blocks, c)["ok"]
        body = out.split(b"\n")
        circle = [ln for ln in body if ln.startswith(b"G3")][0]
        assert b"X" not in circle and b"Y" not in circle          # still a full circle (no end words)
        assert [ln for ln in body if ln.startswith(b"G2 ")][0].split(b"R")[1].startswith(b"-")
        nb, _ = parse_program(out, "t", "p")
        new_passes = split_blocks(nb, SPLIT)
        length = lambda p: float(np.sum(np.sqrt(sum((p.column(a + "1_mm").to_numpy() - p.column(a + "0_mm").to_numpy()) ** 2  # noqa: E731
                                                    for a in "xyz"))))
        assert abs(length(new_passes) - length(passes)) < 0.5             # no arc collapsed (−63 mm) or flipped


def test_near_full_arc_does_not_flip():
    # a 359.94° arc: its end lies 10 µm from its start; moves of that size must not turn it into
    # a sliver (the splitter would read a 0.06° arc)
    text = b"\n".join([b"%", b"O0014", b"G90 G21 G17", b"T1 M6", b"S1000 M3", b"G0 X10.000 Y0.000 Z0.000",
                       b"G1 X10.000 Y0.000 F500", b"G3 X9.999 Y-0.010 I-10.000 J0.000",
                       b"G3 X0.000 Y-10.000 I-9.999 J0.010", b"G1 X0.000 Y-12.000", b"M30", b"%", b""])
    blocks, _ = parse_program(text, "t", "p")
    passes = split_blocks(blocks, SPLIT)
    length = lambda p: float(np.sum(np.sqrt(sum((p.column(a + "1_mm").to_numpy() - p.column(a + "0_mm").to_numpy()) ** 2  # noqa: E731
                                                for a in "xyz"))))
    for seed in range(8):
        c = correct_once(blocks, passes, _random_errors(passes, 40 + seed, 25.0), {"correct": {}})
        out = write_program(text, blocks, c)
        assert reverse_check(out, blocks, c)["ok"]
        nb, _ = parse_program(out, "t", "p")
        assert abs(length(split_blocks(nb, SPLIT)) - length(passes)) < 0.5


# ------------------------------------------------------------------------------------ gap issue's virtual machine

def _gap_vm_closed_loop(src: bytes, stock, tool, material, k, pts, nrm, split, level_of, max_iter=4):
    """Correct ``src`` from errors measured on stages/virtual_machine/ (issue 7; shares no prediction
    code) and machine the written program there again. Errors are against the original program cut
    on a rigid machine; per pass, the mean over the probe points that ``level_of`` assigns to it."""
    from stages.virtual_machine import VirtualMachine

    def probe(blocks, stiff):
        machine = {"frf": {a: [{"fn_hz": 900, "zeta": 0.03, "k_n_per_um": stiff}] for a in "xy"}, "table": None}
        passes = split_blocks(blocks, split)
        return VirtualMachine(passes, tool, material, machine, stock).probe(pts, nrm), passes

    blocks0, _ = parse_program(src, "vm", "p")
    ideal, _ = probe(blocks0, 1e9)
    rms = []

    def predict(blocks):
        e, passes = probe(blocks, k)
        e = e - ideal
        rms.append(float(np.sqrt(np.mean(e ** 2))))
        ids = level_of(passes)
        n = passes.num_rows
        ok = ids >= 0
        cnt = np.bincount(ids[ok], minlength=n)
        em = np.bincount(ids[ok], e[ok], n) / np.maximum(cnt, 1)
        nn = np.stack([np.bincount(ids[ok], nrm[ok, i], n) for i in range(3)], 1)
        have = cnt >= 3
        nn[have] /= np.linalg.norm(nn[have], axis=1)[:, None]
        return passes, _errors(passes, em, nn).filter(pa.array(have))

    corrected = correct_iteratively(blocks0, predict, {"correct": {"max_move_um": 100.0, "tol_um": 0.2, "max_iter": max_iter}})
    out = write_program(src, blocks0, corrected)
    assert reverse_check(out, blocks0, corrected)["ok"]
    e, _ = probe(parse_program(out, "vm-corrected", "p")[0], k)
    return rms, float(np.sqrt(np.mean((e - ideal) ** 2)))


def test_closed_loop_cylinder_benchmark_on_the_gap_virtual_machine(tmp_path):
    """Seed Fig. 16 cylinder (Ø20, 0.63 mm pitch, 51 levels q 0–89°, 6 mm stock) machined on the gap
    issue's virtual machine (discrete flutes, time-domain dynamics), corrected from its measured
    error, machined again: ≤ 20 % of the error before (issue 5)."""
    import trimesh
    R, pitch, n_levels, q_max, length = 10.0, 0.63, 50, 89.0, 6.0
    dq = np.radians(q_max / n_levels)
    rc = pitch / dq
    y_end = length / 2 + R + 2.0
    lines = ["%", "O3002 (CYLINDER)", "G90 G17 G21", "T1 M6", "S6000 M3"]
    for i, kq in enumerate(range(-1, n_levels + 2)):
        x, z = (rc + R) * np.sin(kq * dq), (rc + R) * np.cos(kq * dq) - R
        ys = (-y_end, y_end) if i % 2 == 0 else (y_end, -y_end)
        lines += ([f"G0 X{x:.4f} Y{ys[0]:.4f} Z{z + 30:.4f}", f"G1 Z{z:.4f} F4800"] if i == 0
                  else [f"X{x:.4f} Y{ys[0]:.4f} Z{z:.4f}"]) + [f"Y{ys[1]:.4f}"]
    src = "\n".join(lines + ["G0 Z60.0000", "M30", "%", ""]).encode()
    stock = trimesh.creation.cylinder(radius=rc + 0.2, height=length, sections=720)
    stock.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    stock.export(tmp_path / "stock.stl")
    tool = {"type": "ball", "diameter_mm": 20.0, "flutes": 2, "helix_deg": 30.0, "runout_um": 0.0, "control_point": "tip"}
    material = {"ktc": 2000, "krc": 700, "kac": 300, "kte": 20, "kre": 15, "kae": 5}
    split = {"split": {"chord_tol_mm": 0.001, "max_pass_mm": 40.0, "merge_max_mm": 0.5},
             "machine": {"rapid_mm_min": 30000.0}, "tool": tool}
    qq, yy = np.meshgrid(np.radians(np.linspace(0.0, q_max, 716)), np.linspace(-2.5, 2.5, 11))
    nrm = np.stack([np.sin(qq.ravel()), np.zeros(qq.size), np.cos(qq.ravel())], 1)
    pts = rc * nrm + np.stack([np.zeros(qq.size), yy.ravel(), np.zeros(qq.size)], 1)

    def level_of(passes):
        """Each probe point to the level pass whose ball centre is nearest in angle about the axis."""
        g = lambda c: passes.column(c).to_numpy()  # noqa: E731
        lvl = np.flatnonzero((g("motion") != 0) & (np.abs(g("y1_mm") - g("y0_mm")) > 20))
        ang = np.arctan2(g("x0_mm")[lvl], g("z0_mm")[lvl] + R)
        qp = np.arctan2(pts[:, 0], pts[:, 2])
        return lvl[np.argmin(np.abs(qp[:, None] - ang[None, :]), axis=1)]

    rms, final = _gap_vm_closed_loop(src, str(tmp_path / "stock.stl"), tool, material, 2.0, pts, nrm, split, level_of)
    print(f"\ncylinder benchmark on the gap virtual machine: RMS error {rms[0]:.2f} um before, rounds "
          f"{['%.2f' % r for r in rms[1:]]}, written program {final:.2f} um = {100 * final / rms[0]:.1f} % of before")
    assert rms[0] > 5.0
    assert final <= 0.2 * rms[0]


def test_vertex_without_a_prediction_in_a_later_round_keeps_its_move():
    """Round 2 predicts only the first half of the passes (the render lost the rest on the corrected
    path): the vertices of the second half keep round 1's moves instead of snapping back."""
    data, blocks, passes = _load(SAMPLES[1])
    passes = passes.sort_by("pass_id")
    n = passes.num_rows
    normals = np.tile([0.6, 0.0, 0.8], (n, 1))
    r1 = correct_once(blocks, passes, _errors(passes, np.full(n, 5.0), normals), {"correct": {}})
    half = passes.column("pass_id").to_numpy()[: n // 2]
    e2 = _errors(passes, np.full(n, 7.0), normals)
    e2 = e2.filter(pa.compute.is_in(e2.column("pass_id"), value_set=pa.array(half, e2.column("pass_id").type)))
    r2 = correct_once(blocks, passes, e2, {"correct": {}}, previous=r1)
    m1, m2 = r1.column("move_um").to_numpy(), r2.column("move_um").to_numpy()
    bn = r2.column("block_no").to_numpy()
    last_first = passes.column("block_end").to_numpy()[n // 2 - 1]
    first_second = passes.column("block_no").to_numpy()[n // 2 + 1]
    late = bn > first_second + 1                      # vertices only passes of the second half touch
    early = (bn < last_first - 1) & (m1 > 0)
    assert late.sum() > 100 and early.sum() > 100
    np.testing.assert_allclose(m2[late], m1[late], rtol=1e-9)       # kept (5 µm along n)
    assert np.allclose(m2[early], 7.0, rtol=0.02)                   # re-predicted (7 µm)


def test_pass_missing_in_a_later_round_keeps_its_round_one_error():
    """A later round's render predicts every pass but one (a corner pass whose cut it lost on the
    corrected path): the vertices of that pass combine its round-1 error with the neighbours' new
    ones, as if it had been predicted again with the same error (para 0084 on both passes)."""
    from stages.correct import run
    data, blocks, passes = _load(SAMPLES[1])
    passes = passes.sort_by("pass_id")
    n = passes.num_rows
    normals = np.tile([0.6, 0.0, 0.8], (n, 1))
    first = _errors(passes, np.full(n, 5.0), normals)
    r1 = run(_stage_inputs(blocks, passes, first), {"correct": {}})["corrected"]
    err2 = np.full(n, 7.0)
    # a G1 line that is a pass of its own, between two such lines
    bno, bend = passes.column("block_no").to_numpy(), passes.column("block_end").to_numpy()
    motion = dict(zip(blocks.column("block_no").to_pylist(), blocks.column("motion").to_pylist()))
    single = (bno == bend) & np.array([motion[b] == 1 for b in bno])
    single &= np.concatenate([[False], np.diff(bno) == 1]) & np.concatenate([np.diff(bno) == 1, [False]])
    gone = int(np.flatnonzero(single[1:-1] & single[:-2] & single[2:])[len(single) // 4] + 1)
    full2 = _errors(passes, np.where(np.arange(n) == gone, 5.0, err2), normals)   # what the fallback should give
    part2 = _errors(passes, err2, normals).filter(pa.array(np.arange(n) != gone))
    full_step = {"correct": {"relax": 1.0}}
    got = run(_stage_inputs(blocks, passes, part2, previous=r1, first=first), full_step)["corrected"]
    want = run(_stage_inputs(blocks, passes, full2, previous=r1), full_step)["corrected"]
    without = run(_stage_inputs(blocks, passes, part2, previous=r1), full_step)["corrected"]
    for c in ("x_new_mm", "y_new_mm", "z_new_mm", "move_um"):
        np.testing.assert_allclose(got.column(c).to_numpy(), want.column(c).to_numpy(), rtol=0, atol=1e-12)
    # without the fallback the pass's vertices follow its neighbours alone (7 µm instead of 6)
    at = np.isin(got.column("block_no").to_numpy(), [bno[gone] - 1, bno[gone]])
    assert at.sum() == 2
    np.testing.assert_allclose(got.column("move_um").to_numpy()[at], 6.0, rtol=1e-9)
    np.testing.assert_allclose(without.column("move_um").to_numpy()[at], 7.0, rtol=1e-9)


def _linear_rounds(relax: float, e0: float, k: float, rounds: int):
    """Rounds of ``correct.run`` on a synthetic prediction whose error grows with the move:
    e(s) = e0 + k·s, s = how far the pass has moved into the material (µm along −n). The surface
    then deviates from the original by e(s) − s; its fixed point is s* = e0 / (1 − k)."""
    from stages.correct import run
    data, blocks, passes = _load(SAMPLES[0])
    passes = passes.sort_by("pass_id")
    n = passes.num_rows
    normal = np.array([0.6, 0.0, 0.8])
    normals = np.tile(normal, (n, 1))
    params = {"correct": {"relax": relax, "max_move_um": 1e4}}
    cor = run(_stage_inputs(blocks, passes, _errors(passes, np.full(n, e0), normals)), params)["corrected"]
    dev = []
    for _ in range(rounds):
        mv = np.stack([cor.column(f"{a}_new_mm").to_numpy() - cor.column(f"{a}_mm").to_numpy()
                       for a in "xyz"], 1) * 1e3
        s = -(mv @ normal)
        moved = cor.column("move_um").to_numpy() > 0
        s_pass = float(np.median(s[moved]))           # every predicted vertex moves alike
        dev.append(e0 + k * s_pass - s_pass)
        cor = run(_stage_inputs(blocks, passes, _errors(passes, np.full(n, e0 + k * s_pass), normals),
                                previous=cor), params)["corrected"]
    return np.array(dev)


def test_rounds_take_half_steps_where_they_do_not_contract():
    """An error that falls by 1.5 µm per µm the path moves in (k = −1.5): the plain fixed point
    P = P0 − e(P)·n would flip and grow by k each round; the vertices see their change grow, halve
    their step and the deviation from the original surface goes to 0. A mild dependence (k = 0.2)
    contracts by itself: full steps, the deviation falls by k each round. References: the linear
    map's closed forms (fixed point e0 / (1 − k)), not the code."""
    dev = _linear_rounds(1.0, 10.0, -1.5, 8)
    # round 1 leaves k·e0 = −15; round 2 would overshoot to 22.5 (|change| 25 > 10): half step
    np.testing.assert_allclose(dev[:2], [-15.0, 3.75], rtol=1e-9)
    assert np.all(np.abs(dev[2:]) < np.abs(dev[1:-1]))
    assert abs(dev[-1]) < 0.01 * abs(dev[0])
    mild = _linear_rounds(1.0, 10.0, 0.2, 4)
    np.testing.assert_allclose(mild[1:] / mild[:-1], 0.2, rtol=1e-6)
    # relax caps the step: 0.5 from round 2 on, factor 1 − 0.5·(1 − k) = 0.6
    capped = _linear_rounds(0.5, 10.0, 0.2, 4)
    np.testing.assert_allclose(capped[1:] / capped[:-1], 0.6, rtol=1e-6)


def _ball_clearance(points, tip, radius):
    """Distance of points from a ball-end tool (tip ``tip``, axis +z), written out for the test."""
    centre = np.asarray(tip) + [0.0, 0.0, radius]
    rel = np.asarray(points) - centre
    side = np.hypot(rel[:, 0], rel[:, 1]) - radius
    return np.where(rel[:, 2] >= 0, side, np.linalg.norm(rel, axis=1) - radius)


def test_gouge_limit_keeps_the_tool_off_the_wall_beside_a_corner_pass():
    """Pocket corner: floor z 0, wall x 10 (material at x > 10), ball Ø10 with its tip at
    (4.9, 0, 0): its side 0.1 mm from the wall. A corner pass (normal (0.6, 0, 0.8)) and a floor
    pass meet at the vertex; their errors ask for 500 µm along +x (into the wall, the sample's
    pocket corner). The wall's generating points allow 100 µm (the clearance): the closed form.
    Moves away from the wall, along the floor's own surface and moves smaller than the clearance
    keep their size; after the limit no wall point lies inside the moved tool (brute force)."""
    from stages.geometry.cutter import Cutter
    ball = Cutter("ball", 5.0, 5.0, 40.0)
    ys, zs = np.meshgrid(np.linspace(-4, 4, 33), np.linspace(5.0, 20.0, 16))
    wall = np.stack([np.full(ys.size, 10.0), ys.ravel(), zs.ravel()], 1)
    xs, ys2 = np.meshgrid(np.linspace(-1, 9, 21), np.linspace(-4, 4, 17))
    floor = np.stack([xs.ravel(), ys2.ravel(), np.zeros(xs.size)], 1)
    gen = np.vstack([wall, floor])
    gen_n = np.vstack([np.tile([-1.0, 0, 0], (len(wall), 1)), np.tile([0, 0, 1.0], (len(floor), 1))])
    gen_pass = np.arange(len(gen)) + 10                 # other passes
    moves = np.array([[500.0, 0, 0], [400.0, 300.0, 0], [-200.0, 0, 50], [0, 0, -20], [80.0, 0, 0]])
    tips = np.tile([4.9, 0.0, 0.0], (len(moves), 1))
    own = np.array([[0, 1]] * len(moves))
    own_n = np.tile(np.array([[0.6, 0, 0.8], [0, 0, 1.0]]), (len(moves), 1, 1))
    out, cut = gouge_limit(moves, tips, own, own_n, gen, gen_n, gen_pass, ball)
    assert out[0] == pytest.approx([100.0, 0, 0], abs=1e-6)
    assert cut[0] == pytest.approx(400.0, abs=1e-6)
    np.testing.assert_allclose(out[2:], moves[2:], atol=1e-9)        # away, along the floor, small
    assert cut[2:] == pytest.approx([0, 0, 0])
    for tip, m in zip(tips, out):
        assert _ball_clearance(wall, tip + m / 1000.0, 5.0).min() >= -0.002
    # the diagonal move keeps its part along the wall: only the excess towards it is taken off
    assert out[1][1] > 250.0 and out[1][0] <= 101.0
    # the floor's points (the surface of the vertex's floor pass) set no limit
    own_all = np.array([[10 + len(wall), 10 + len(wall) + 1]] * len(moves))
    _, cut_floor_only = gouge_limit(moves, tips, own_all, own_n, floor, gen_n[len(wall):],
                                    gen_pass[len(wall):], ball)
    assert cut_floor_only == pytest.approx(np.zeros(len(moves)))


def test_stage_limits_the_corner_vertex_by_the_wall_pass_generating_point():
    """The same corner through ``run``: a floor pass ends at X4.9 where a pass along the wall foot
    starts; the wall pass beside them has its generating point on the wall x 10, 6 mm up (the
    shank's side 0.1 mm from it). The errors ask for 500 µm along +x; with the gouge limit the
    vertex moves the 100 µm clearance, without it the 300 µm move limit."""
    from stages import correct
    text = b"\n".join([b"%", b"O0001", b"G90 G17 G21", b"T1 M6", b"S8000 M3", b"G0 X0. Y0. Z10.",
                       b"G1 Z0. F500", b"X4.9", b"Y2.", b"Z6.", b"G0 Z50.", b"M30", b"%", b""])
    blocks, _ = parse_program(text, "corner.nc", "p")
    passes = split_blocks(blocks, SPLIT)
    z1 = passes.column("z1_mm").to_numpy()
    x1 = passes.column("x1_mm").to_numpy()
    x0 = passes.column("x0_mm").to_numpy()
    floor = np.flatnonzero((x0 == 0.0) & (x1 == 4.9) & (z1 == 0.0))[0]
    normals = np.tile([0.0, 0.0, 1.0], (passes.num_rows, 1))
    err = np.zeros(passes.num_rows)
    normals[floor + 1], err[floor + 1] = [0.6, 0.0, 0.8], -300.0     # along the wall foot: overcut
    wall = floor + 2
    generating = pa.table({"program_id": ["p"], "pass_id": passes.column("pass_id").take([wall]),
                           "gen_x_mm": [10.0], "gen_y_mm": [0.0], "gen_z_mm": [6.0],
                           "nx": [-1.0], "ny": [0.0], "nz": [0.0]})
    errors = _errors(passes, err, normals).filter(pa.array(np.arange(passes.num_rows) != wall))
    inputs = _stage_inputs(blocks, passes, errors, generating=generating)
    tool = {"type": "ball", "diameter_mm": 10.0, "stickout_mm": 40.0}
    vertex = int(passes.column("block_end").to_numpy()[floor])      # its last block (inclusive)
    for limit, expect in ((True, 100.0), (False, 300.0)):
        out = correct.run(inputs, {"correct": {"max_move_um": 300.0, "gouge_limit": limit}, "tool": tool})["corrected"]
        row = int(np.flatnonzero(out.column("block_no").to_numpy() == vertex)[0])
        move = (np.array([out.column(c)[row].as_py() for c in ("x_new_mm", "y_new_mm", "z_new_mm")])
                - [4.9, 0.0, 0.0]) * 1000.0
        assert move == pytest.approx([expect, 0.0, 0.0], abs=0.01)
        assert out.column("gouge_limit_um")[row].as_py() == pytest.approx(400.0 if limit else 0.0, abs=0.01)


def test_normals_a_few_degrees_apart_do_not_slide_the_vertex_along_a_straight_path():
    """The sample's row y 61.2 down a convex profile: passes 8610 and 8611 (normals 4.8° apart in
    the plane of the path, −154.8 and −129.8 µm; the path turns 4.7° at the vertex). Realising both
    takes (Δe/2)/sin(θ/2) = 298 µm along the path; with the path direction the move keeps out of
    it: along the path only the para 0084 move's own tilt (≤ Δe/2·sin(θ/2) + 1 µm), along the mean
    normal its least-squares magnitude. Across a path's corner (the same normals, the path turning
    90°) the refinement realises both errors."""
    na = np.array([[-0.661, 0.0, 0.750]])
    nb = np.array([[-0.596, 0.0, 0.803]])
    na /= np.linalg.norm(na)
    nb /= np.linalg.norm(nb)
    ea, eb = np.array([-154.767]), np.array([-129.765])
    yes = np.array([True])
    half = np.arccos(na[0] @ nb[0]) / 2
    assert abs(ea[0] - eb[0]) / 2 / np.sin(half) == pytest.approx(298, abs=2)   # what exact would slide
    mean_n = (na + nb)[0] / np.linalg.norm(na + nb)
    path = np.cross(mean_n, [0.0, 1.0, 0.0])[None]                  # ⊥ both normals' mean, in their plane
    m = vertex_moves(ea, na, yes, eb, nb, yes, along_path=path)[0]
    assert abs(m @ path[0]) <= abs(ea[0] - eb[0]) / 2 * np.sin(half) + 1.0
    assert m @ mean_n == pytest.approx(-(ea[0] + eb[0]) / 2 / np.cos(half), abs=2.0)
    # the nodes of a polyline: straight through (4.7°) restricted, a 90° corner and the ends free
    pts = np.array([[0.0, 0, 0], [0.5, 0, -0.4], [1.0, 0, -0.84], [1.0, 0, 2.0]])
    from stages.correction.moves import straight_through
    t = straight_through(pts[:-1], pts[1:])
    assert np.allclose(t[[0, 2, 3]], 0.0) and np.linalg.norm(t[1]) == pytest.approx(1.0)
    free = vertex_moves(ea, na, yes, eb, nb, yes, along_path=np.zeros((1, 3)))[0]
    assert np.abs([free @ na[0] + ea[0], free @ nb[0] + eb[0]]).max() < 0.05 * abs(ea[0])


# ------------------------------------------------------------------------------------ via points

_VIA_PROGRAM = b"\n".join([
    b"%", b"O0011", b"N2 G90 G21 G17", b"N4 T1 M6", b"N6 S1000 M3", b"N8 G0 X0. Y0. Z5.",
    b"N10 G1 Z0. F100",
    b"N12 X20.000 F300 (LONG PLAIN LINE)",      # 4 pieces of 5 mm
    b"N14 Y12.000 M8",                          # long, but an M word: not cut
    b"N16 X8.000 Y3.000",                       # 15 mm: 3 pieces
    b"N18 G91 X-12.000",                        # long, incremental: not cut
    b"N20 G90 G0 Z50.000", b"M30", b"%", b""])


def test_via_points_cut_long_plain_lines_into_the_split_stage_passes():
    blocks, _ = parse_program(_VIA_PROGRAM, "v", "p")
    vb = via_blocks(_VIA_PROGRAM, blocks, 5.0)
    lines = vb.column("line_no").to_numpy()
    # the plain G1 lines are cut (line 8: 20 mm → 4, line 10: 15 mm → 3); M8 and G91 lines are not
    assert [int((lines == k).sum()) for k in (8, 9, 10, 11)] == [4, 1, 3, 1]
    assert np.array_equal(vb.column("block_no").to_numpy(), np.arange(1, vb.num_rows + 1))
    # the passes are the same as without the cut
    a, b = split_blocks(blocks, SPLIT), split_blocks(vb, SPLIT)
    cols = ("x0_mm", "y0_mm", "z0_mm", "x1_mm", "y1_mm", "z1_mm", "motion", "line_no")
    assert a.num_rows == b.num_rows
    for c in cols:
        assert np.allclose(a.column(c).to_numpy(), b.column(c).to_numpy(), atol=1e-12), c


def test_via_points_are_written_as_inserted_lines_where_the_errors_differ_along_a_cut():
    blocks, _ = parse_program(_VIA_PROGRAM, "v", "p")
    vb = via_blocks(_VIA_PROGRAM, blocks, 5.0)
    passes = split_blocks(vb, SPLIT)
    cut = passes.column("motion").to_numpy() != 0
    pid_line = passes.column("line_no").to_numpy()
    # the four passes of the 20 mm line: errors 40, 30, 20, 10 µm along −y (material left at −y):
    # each via point between passes i, i+1 of one normal moves by (e_i + e_{i+1}) / 2 along +y
    e = np.where(pid_line == 8, 0.0, 0.0)
    e[pid_line == 8] = [40.0, 30.0, 20.0, 10.0]
    err = _errors(passes, e, np.tile([0, -1.0, 0], (passes.num_rows, 1))).filter(pa.array(cut & (pid_line == 8)))
    c = correct_once(vb, passes, err, {"correct": {}})
    out = write_program(_VIA_PROGRAM, vb, c)
    got = out.split(b"\n")
    i = got.index(b"N12 X20.000 Y0.010 F300 (LONG PLAIN LINE)")
    # three lines inserted before it; the feed of the line moves onto the first
    assert got[i - 3:i] == [b"G1 X5.000 Y0.035 Z0.000 F300", b"G1 X10.000 Y0.025 Z0.000", b"G1 X15.000 Y0.015 Z0.000"]
    assert b"3 VIA LINES INSERTED" in got[2]
    # every other line as before (the line before the cut gets the first pass's move: 40 µm)
    src = _VIA_PROGRAM.split(b"\n")
    rest = got[:2] + got[3:i - 3] + got[i:]
    assert len(rest) == len(src)
    diff = [(a, b) for a, b in zip(src, rest) if a != b]
    assert diff == [(b"N10 G1 Z0. F100", b"N10 G1 Y0.040 Z0. F100"),
                    (b"N12 X20.000 F300 (LONG PLAIN LINE)", b"N12 X20.000 Y0.010 F300 (LONG PLAIN LINE)")]
    rep = reverse_check(out, vb, c)
    assert rep["ok"], rep["message"]
    assert rep["n_blocks"] == (blocks.num_rows + 3, blocks.num_rows + 3)
    # the same errors everywhere along the cut: its pieces stay on the straight line, nothing inserted
    e[pid_line == 8] = 25.0
    err = _errors(passes, e, np.tile([0, -1.0, 0], (passes.num_rows, 1))).filter(pa.array(cut & (pid_line == 8)))
    c = correct_once(vb, passes, err, {"correct": {}})
    out = write_program(_VIA_PROGRAM, vb, c)
    assert b"VIA" not in out and b"\nG1 X" not in out
    assert reverse_check(out, vb, c)["ok"]
    # no error: byte-identical
    c = correct_once(vb, passes, err.slice(0, 0), {"correct": {}})
    assert write_program(_VIA_PROGRAM, vb, c) == _VIA_PROGRAM


def test_a_corrected_program_splits_into_the_passes_of_the_original():
    """Deliver 4's reverse check, through the split: the 20 mm line cut into four 5 mm passes, its
    via points moved 35, 25, 15 µm across it, is parsed and split again into the same passes, each
    end within the largest move (40 µm) of the original's. The moved pieces are 5.00001 mm long;
    rounding any excess up to a piece more cut each in two, and round 2 predicted other passes."""
    blocks, _ = parse_program(_VIA_PROGRAM, "v", "p")
    vb = via_blocks(_VIA_PROGRAM, blocks, 5.0)
    passes = split_blocks(vb, SPLIT)
    cut = passes.column("motion").to_numpy() != 0
    line = passes.column("line_no").to_numpy()
    e = np.zeros(passes.num_rows)
    e[line == 8] = [40.0, 30.0, 20.0, 10.0]
    err = _errors(passes, e, np.tile([0, -1.0, 0], (passes.num_rows, 1))).filter(pa.array(cut & (line == 8)))
    out = write_program(_VIA_PROGRAM, vb, correct_once(vb, passes, err, {"correct": {}}))
    ends = ("x0_mm", "y0_mm", "z0_mm", "x1_mm", "y1_mm", "z1_mm")

    def again():
        return split_blocks(parse_program(out, "v", "p")[0], SPLIT)
    got = again()
    assert got.num_rows == passes.num_rows
    moved = np.stack([got.column(c).to_numpy() - passes.column(c).to_numpy() for c in ends], 1)
    assert np.abs(moved).max() <= 0.040 + 1e-9


def test_a_via_point_between_pieces_of_one_line_moves_along_the_mean_normal():
    """The 20 mm line cut into four 5 mm passes, errors 40, 30, 20, 10 µm with the passes' normals
    scattered ±0.45° about −y (tilted in the y–z plane, across the line: a prediction's scatter on
    one surface). Each via point moves along the mean of its two normals by the mean of its two
    errors (para 0084; closed form 35, 25, 15 µm) and slides across the line by less than 0.5 µm."""
    blocks, _ = parse_program(_VIA_PROGRAM, "v", "p")
    vb = via_blocks(_VIA_PROGRAM, blocks, 5.0)
    passes = split_blocks(vb, SPLIT)
    cut = passes.column("motion").to_numpy() != 0
    line = passes.column("line_no").to_numpy()
    on = cut & (line == 8)
    tilt = np.radians(0.45) * np.where(np.arange(on.sum()) % 2, 1.0, -1.0)
    nrm = np.tile([0.0, -1.0, 0.0], (passes.num_rows, 1))
    nrm[on] = np.stack([np.zeros_like(tilt), -np.cos(tilt), np.sin(tilt)], 1)
    e = np.zeros(passes.num_rows)
    e[on] = [40.0, 30.0, 20.0, 10.0]
    err = _errors(passes, e, nrm).filter(pa.array(on))

    def via_moves():
        c = correct_once(vb, passes, err, {"correct": {}})
        lines = c.column("line_no").to_numpy()
        new = np.stack([c.column(k).to_numpy() - c.column(o).to_numpy()
                        for k, o in (("x_new_mm", "x_mm"), ("y_new_mm", "y_mm"), ("z_new_mm", "z_mm"))], 1)
        return new[lines == 8][:3] * 1000.0               # the three via points of line 8, µm
    m = via_moves()
    np.testing.assert_allclose(m[:, 1], [35.0, 25.0, 15.0], atol=0.01)   # along +y (against −n)
    assert np.abs(m[:, 2]).max() < 0.5 and np.abs(m[:, 0]).max() < 1e-9


def test_via_lines_follow_the_program_style():
    # CRLF, no spaces, G01: the inserted lines are written the same way
    text = b"\r\n".join([b"%", b"O0012", b"G90G21G17", b"T1M6", b"S1000M3", b"G0X0.Y0.Z5.", b"G01Z0.F100",
                         b"N12G01X15.000F300", b"G0Z50.", b"M30", b"%", b""])
    blocks, _ = parse_program(text, "v", "p")
    vb = via_blocks(text, blocks, 5.0)
    passes = split_blocks(vb, SPLIT)
    line = passes.column("line_no").to_numpy()
    e = np.zeros(passes.num_rows)
    e[line == 8] = [30.0, 10.0, 30.0]
    err = _errors(passes, e, np.tile([0, -1.0, 0], (passes.num_rows, 1))).filter(pa.array(line == 8))
    c = correct_once(vb, passes, err, {"correct": {}})
    out = write_program(text, vb, c)
    assert b"\r\nG01Y0.030Z0.F100\r\nG1X5.000Y0.020Z0.000F300\r\nG1X10.000Y0.020Z0.000\r\nN12G01X15.000Y0.030F300\r\n" in out
    assert reverse_check(out, vb, c)["ok"]


_ARC_PROGRAM = b"\n".join([
    b"%", b"O0013", b"N2 G90 G21 G17", b"N4 T1 M6", b"N6 S1000 M3", b"N8 G0 X-2. Y-10. Z5.",
    b"N10 G1 Z0. F100",
    b"N12 G18 G3 X0. Z-2. I0. K-2. F300",        # lead-in arc in XZ, plane word on the line: cut
    b"N14 G17 G2 X0. Y10. I0. J10.",             # boss contour, two half circles about (0, 0): cut
    b"N16 G2 Y-10. I0. J-10.",
    b"N18 X7.071 Y-7.071 R10.",                  # modal G2 (no G word on the line): not cut
    b"N20 G2 X10. Y0. R10. M8",                  # an M word: not cut
    b"N22 G1 X12.", b"N24 G0 Z50.", b"M30", b"%", b""])


def test_via_points_cut_arcs_into_chords_that_follow_an_error_changing_along_the_arc():
    """``via_blocks`` with the chord tolerance cuts a plain arc into the split stage's chords (G1
    pieces, the last chord staying the arc): the passes are those of the uncut program, a program
    without error comes out byte for byte, and an error that changes around a circle (the sample
    boss: +35 µm on one side, +7 µm a quarter turn on) is followed where one refitted arc cannot."""
    tol = SPLIT["split"]["chord_tol_mm"]
    blocks, _ = parse_program(_ARC_PROGRAM, "a", "p")
    vb = via_blocks(_ARC_PROGRAM, blocks, 5.0, chord_tol_mm=tol)
    line = vb.column("line_no").to_numpy()
    mot = vb.column("motion").to_numpy()
    a, b = split_blocks(blocks, SPLIT), split_blocks(vb, SPLIT)
    # a chord spans at most 2 acos(1 − tol / r) of sweep (its sagitta ≤ tol): the half circles of
    # r 10 → ceil(π / 2 acos(1 − 0.0001)) = 112 chords each, the lead-in quarter of r 2 → 25
    n_half = int(np.ceil(np.pi / (2 * np.arccos(1 - tol / 10.0))))
    n_lead = int(np.ceil(np.pi / 2 / (2 * np.arccos(1 - tol / 2.0))))
    assert [int((line == k).sum()) for k in (8, 9, 10, 11, 12)] == [n_lead, n_half, n_half, 1, 1]
    # pieces are G1 but the last, which keeps the arc and its centre
    for k, m in ((8, 3), (9, 2), (10, 2)):
        assert list(mot[line == k]) == [1] * (int((line == k).sum()) - 1) + [m]
    # the lead-in's pieces take the plane held before its line (G17), its arc keeps G18
    assert list(vb.column("plane").to_numpy()[line == 8][[0, -1]]) == [17, 18]
    assert a.num_rows == b.num_rows
    for c in ("x0_mm", "y0_mm", "z0_mm", "x1_mm", "y1_mm", "z1_mm", "line_no"):
        assert np.allclose(a.column(c).to_numpy(), b.column(c).to_numpy(), atol=1e-12), c
    # no error: byte for byte
    cut = b.column("motion").to_numpy() != 0
    bl = b.column("line_no").to_numpy()
    on = cut & np.isin(bl, (9, 10))
    none = _errors(b, np.zeros(b.num_rows), np.tile([0, 0, 1.0], (b.num_rows, 1))).filter(pa.array(on)).slice(0, 0)
    assert write_program(_ARC_PROGRAM, vb, correct_once(vb, b, none, {"correct": {}})) == _ARC_PROGRAM

    # material left e(θ) = 20 + 15 cos 2θ µm around the boss, along the outward normal (a cos θ
    # term would be a shifted circle, which a refitted arc follows): the tool goes in by e, so the
    # corrected contour is r = 10 − e(θ) / 1000 (closed form)
    def target(theta):
        return 20.0 + 15.0 * np.cos(2 * theta)

    mid = 0.5 * (np.stack([b.column(c).to_numpy() for c in ("x0_mm", "y0_mm")], 1)
                 + np.stack([b.column(c).to_numpy() for c in ("x1_mm", "y1_mm")], 1))
    th = np.arctan2(mid[:, 1], mid[:, 0])
    nrm = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], 1)
    err = _errors(b, target(th), nrm).filter(pa.array(on))

    def radius_error(text):
        """Largest |r − (10 − e(θ)/1000)| (µm) over the pass ends of the written full circle (at
        Z−2, before line N18)."""
        blk, _ = parse_program(text, "c", "p")
        pts = split_blocks(blk, SPLIT)
        n18 = [i for i, t in enumerate(text.split(b"\n")) if t.startswith(b"N18")][0] + 1
        p = np.stack([pts.column(c).to_numpy() for c in ("x1_mm", "y1_mm", "z1_mm")], 1)
        r = np.hypot(p[:, 0], p[:, 1])
        keep = (pts.column("line_no").to_numpy() < n18) & (np.abs(p[:, 2] + 2.0) < 0.01) & (np.abs(r - 10) < 0.5)
        t = np.arctan2(p[keep, 1], p[keep, 0])
        return np.abs(r[keep] - (10.0 - target(t) / 1000.0)).max() * 1000.0

    c = correct_once(vb, b, err, {"correct": {}})
    out = write_program(_ARC_PROGRAM, vb, c)
    assert reverse_check(out, vb, c)["ok"]
    dev = radius_error(out)
    # the chord points follow e(θ) to within the written grid (0.5 µm) and what one error per
    # 0.28 mm chord leaves (0.49 µm measured)
    assert dev < 1.0
    # lines N18, N20 (not cut) are still single arcs; the M8 line is untouched
    assert out.count(b"N18 ") == 1 and out.count(b"N20 ") == 1
    assert b" M8" in out.split(b"N20")[1].split(b"\n")[0]
    # without the arcs cut: each half circle is refitted through its moved ends (5 µm in at ±90°),
    # its centre shifted along their bisector to fit the chord points: the best circle of that
    # family misses e(θ) by 5.2 µm: the reason for the chords
    c1 = correct_once(blocks, a, _errors(a, target(th), nrm).filter(pa.array(on)), {"correct": {}})
    dev1 = radius_error(write_program(_ARC_PROGRAM, blocks, c1))
    assert dev1 > 5.0


# ------------------------------------------------------------------------------------ corners

_CORNER_PROGRAM = b"\n".join([
    b"%", b"O0013", b"G90 G21 G17", b"T1 M6", b"S8000 M3", b"G0 X0. Y0. Z5.",
    b"G1 Z0. F100",               # 5 mm plunge (a rapid before it is no corner): 4.5 + 0.5
    b"X10. F300",                 # 10 mm, 90° at both ends: 0.5 + 4.5 + 4.5 + 0.5
    b"Y10.",                      # 10 mm, corners at both ends (90°, 45°): 0.5 + 4.5 + 4.5 + 0.5
    b"X10.8 Y10.8",               # 1.13 mm between two 45° corners: too short for two pieces
    b"X13.8",                     # 3 mm, 45° at its start; 18.4° at its end is no corner: 0.5 + 2.5
    b"X16.8 Z1.",                 # 3.16 mm, no corner
    b"G0 Z50.", b"M30", b"%", b""])


def _xyz_of(passes, end):
    return np.stack([passes.column(f"{a}{end}_mm").to_numpy() for a in "xyz"], 1)


def test_corner_via_points_keep_the_passes_and_carry_each_line_s_own_move_beside_the_corner():
    """``correct.corner_via_mm``: a line at a path corner gets a via point 0.5 mm from the corner
    inside its pass (lengths by hand on the corner program: a 1.13 mm line between two corners is
    too short for two); the split stage joins the blocks on either side, so the passes are those of
    the uncut program; at the pocket corner (walls +y 200 µm, −x 88 µm left) the corner vertex
    realises both walls, (+88, −200) µm, and the via points the walls' own moves, (0, −200) and
    (+88, 0), so neither line's body is dragged towards the other wall; no error gives the source
    byte for byte, the written via lines reverse-check."""
    blocks, _ = parse_program(_CORNER_PROGRAM, "c", "p")
    vb = via_blocks(_CORNER_PROGRAM, blocks, 5.0, corner_via_mm=0.5)
    line, via = vb.column("line_no").to_numpy(), vb.column("via_only").to_numpy()
    length = np.linalg.norm(_xyz_of(vb, 1) - _xyz_of(vb, 0), axis=1)
    expect = {7: ([4.5, 0.5], [True, False]), 8: ([0.5, 4.5, 4.5, 0.5], [True, False, True, False]),
              9: ([0.5, 4.5, 4.5, 0.5], [True, False, True, False]), 10: ([np.sqrt(1.28)], [False]),
              11: ([0.5, 2.5], [True, False]), 12: ([np.sqrt(10.0)], [False])}
    for k, (v, w) in expect.items():
        np.testing.assert_allclose(length[line == k], v, atol=1e-12, err_msg=f"line {k}")
        if w:
            assert via[line == k].tolist() == w, k
    plain = split_blocks(blocks, SPLIT)
    joined = split_blocks(vb, SPLIT)
    assert joined.num_rows == plain.num_rows
    for c in ("x0_mm", "y0_mm", "z0_mm", "x1_mm", "y1_mm", "z1_mm", "motion", "line_no", "t_end_s"):
        np.testing.assert_allclose(joined.column(c).to_numpy(), plain.column(c).to_numpy(), atol=1e-12, err_msg=c)
    none = correct_once(vb, joined, _errors(joined, np.zeros(joined.num_rows), np.zeros((joined.num_rows, 3))).slice(0, 0),
                        {"correct": {}})
    assert write_program(_CORNER_PROGRAM, vb, none) == _CORNER_PROGRAM

    # a wall climbed down to the foot of the next wall (the sample's pocket corner): the descent
    # finishes the wall with normal −x (88 µm left), the row along −x the wall with normal −y
    # (200 µm left); the corner's move for the row, +y, lies across the descent's path
    text = b"\n".join([b"%", b"O0001", b"G90 G17 G21", b"T1 M6", b"S8000 M3", b"G0 X0. Y0. Z10.",
                       b"G1 Z0. F500", b"X-20.", b"G0 Z50.", b"M30", b"%", b""])
    blocks, _ = parse_program(text, "corner.nc", "p")
    vb = via_blocks(text, blocks, 5.0, corner_via_mm=0.5)
    passes = split_blocks(vb, SPLIT)
    assert passes.num_rows == split_blocks(blocks, SPLIT).num_rows
    p0, p1 = _xyz_of(passes, 0), _xyz_of(passes, 1)
    down = (p1[:, 2] < p0[:, 2]) & (passes.column("motion").to_numpy() == 1)
    row = p1[:, 0] < p0[:, 0]
    normals = np.where(down[:, None], [-1.0, 0, 0], [0, -1.0, 0])
    errors = _errors(passes, np.where(down, 88.0, 200.0), normals).filter(pa.array(down | row))

    def moved(v):
        c = correct_once(v, split_blocks(v, SPLIT), errors, {"correct": {"max_move_um": 300.0}})
        xyz = np.stack([c.column(k).to_numpy() for k in ("x_mm", "y_mm", "z_mm")], 1)
        new = np.stack([c.column(k).to_numpy() for k in ("x_new_mm", "y_new_mm", "z_new_mm")], 1)
        return c, {tuple(np.round(p, 6)): (n - p) * 1000.0 for p, n in zip(xyz, new)}

    c, at = moved(vb)
    np.testing.assert_allclose(at[(0.0, 0.0, 0.0)], [88.0, 200.0, 0], atol=1e-6)
    np.testing.assert_allclose(at[(0.0, 0.0, 0.5)], [88.0, 0, 0], atol=1e-6)
    np.testing.assert_allclose(at[(-0.5, 0.0, 0.0)], [0, 200.0, 0], atol=1e-6)
    np.testing.assert_allclose(at[(0.0, 0.0, 5.0)], [88.0, 0, 0], atol=1e-6)
    # without the via point the descent's last 5 mm runs from (88, 0) to (88, 200) µm: its middle
    # 100 µm into the other wall
    _, at_plain = moved(via_blocks(text, blocks, 5.0))
    assert (0.0, 0.0, 0.5) not in at_plain
    np.testing.assert_allclose(at_plain[(0.0, 0.0, 0.0)], [88.0, 200.0, 0], atol=1e-6)
    out = write_program(text, vb, c)
    assert b"G1 X0.088 Y0.000 Z5.000" in out and b"G1 X0.088 Y0.000 Z0.500" in out
    rep = reverse_check(out, vb, c)
    assert rep["ok"], rep["message"]


def test_a_corner_via_point_moved_off_its_pass_splits_the_corrected_program_there():
    """The next round predicts the path the machine will cut. The descent of the pocket corner
    above runs Z5 → Z0.5 (via) → Z0 in one pass; the correction moves its ends (88, 0, 0) and
    (88, 200, 0) µm and the via point (88, 0, 0) µm, 180 µm off the chord between the ends
    (at z 0.5 the chord is at y 0.9 · 0.2 mm). Split again, the corrected program has a pass
    boundary at the via point, at its written coordinates; a via point on the chord, or within the
    chord tolerance (1 µm) of it, keeps the one pass."""
    text = b"\n".join([b"%", b"O0001", b"G90 G17 G21", b"T1 M6", b"S8000 M3", b"G0 X0. Y0. Z10.",
                       b"G1 Z0. F500", b"X-20.", b"G0 Z50.", b"M30", b"%", b""])
    blocks, _ = parse_program(text, "corner.nc", "p")
    vb = via_blocks(text, blocks, 5.0, corner_via_mm=0.5)
    passes = split_blocks(vb, SPLIT)
    down = ((_xyz_of(passes, 1)[:, 2] < _xyz_of(passes, 0)[:, 2]) & (passes.column("motion").to_numpy() == 1))
    row = _xyz_of(passes, 1)[:, 0] < _xyz_of(passes, 0)[:, 0]
    normals = np.where(down[:, None], [-1.0, 0, 0], [0, -1.0, 0])
    errors = _errors(passes, np.where(down, 88.0, 200.0), normals).filter(pa.array(down | row))
    c = correct_once(vb, passes, errors, {"correct": {"max_move_um": 300.0}})
    again = split_blocks(apply_corrected(vb, c), SPLIT)
    assert again.num_rows == passes.num_rows + 1
    a0, a1 = _xyz_of(again, 0), _xyz_of(again, 1)
    k = int(np.flatnonzero(np.all(np.abs(a1 - [0.088, 0.0, 0.5]) < 1e-9, axis=1))[0])
    np.testing.assert_allclose(a0[k], [0.088, 0.0, 5.0], atol=1e-9)       # the descent's body
    np.testing.assert_allclose(a0[k + 1], [0.088, 0.0, 0.5], atol=1e-9)   # its last 0.5 mm
    np.testing.assert_allclose(a1[k + 1], [0.088, 0.2, 0.0], atol=1e-9)
    # the via point on the chord, and 0.5 µm off it: one pass
    for off_mm in (0.0, 0.0005):
        nb = vb.to_pandas()
        for e in ("1", "0"):
            at = (nb[f"z{e}_mm"] == 0.5) & (nb[f"x{e}_mm"] == 0.0)
            nb.loc[at, f"y{e}_mm"] = off_mm
        assert split_blocks(pa.Table.from_pandas(nb, schema=vb.schema), SPLIT).num_rows == passes.num_rows

