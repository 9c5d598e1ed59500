"""Vertex moves (seed 000 para 0084) against closed forms, the gouge limit, and the correction rounds.
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from stages.correction.moves import REFINE_MAX_RATIO, gouge_limit, vertex_moves
from stages.correction.rounds import apply_corrected, correct_once
from stages.nc.moves import split_blocks
from stages.nc.reader import parse_program
from tests.correct_cases import SAMPLES, SPLIT, errors_table, load, random_errors, stage_inputs


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


def test_clipping_limits_and_flags():
    _, blocks, passes = load(SAMPLES[0])
    n = passes.num_rows
    err = errors_table(passes, np.full(n, 80.0), np.tile([0, 0, 1.0], (n, 1)))
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
    err = errors_table(passes.slice(k, 1), [5.0], n)
    c = correct_once(blocks, passes, err, {"correct": {}})
    bn = c.column("block_no").to_numpy()
    d = np.stack([c.column(f"{a}_new_mm").to_numpy() - c.column(f"{a}_mm").to_numpy() for a in "xyz"], 1) * 1000
    moved = (bn >= b0[k] - 1) & (bn <= b1[k])               # start vertex (end of the block before) … end
    np.testing.assert_allclose(d[moved], np.tile(-5.0 * n, (moved.sum(), 1)), atol=1e-9)
    assert np.all(d[~moved] == 0)
    assert moved.sum() == b1[k] - b0[k] + 2


def test_stage_run_matches_schema():
    import schemas
    from stages import correct
    _, blocks, passes = load(SAMPLES[0])
    out = correct.run(stage_inputs(blocks, passes, random_errors(passes, 7)),
                      {"correct": {"max_move_um": 50.0, "tol_um": 0.1, "max_iter": 5, "ln_normals": False,
                                   "comp_table": False}})
    table = schemas.check("corrected", out["corrected"])
    motion = blocks.column("motion").to_numpy()
    assert table.num_rows == int((motion <= 3).sum())
    assert set(table.column("iteration").to_pylist()) == {1}


def test_vertex_without_a_prediction_in_a_later_round_keeps_its_move():
    """Round 2 predicts only the first half of the passes (the render lost the rest on the corrected
    path): the vertices of the second half keep round 1's moves instead of snapping back."""
    data, blocks, passes = load(SAMPLES[1])
    passes = passes.sort_by("pass_id")
    n = passes.num_rows
    normals = np.tile([0.6, 0.0, 0.8], (n, 1))
    r1 = correct_once(blocks, passes, errors_table(passes, np.full(n, 5.0), normals), {"correct": {}})
    half = passes.column("pass_id").to_numpy()[: n // 2]
    e2 = errors_table(passes, np.full(n, 7.0), normals)
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
    data, blocks, passes = load(SAMPLES[1])
    passes = passes.sort_by("pass_id")
    n = passes.num_rows
    normals = np.tile([0.6, 0.0, 0.8], (n, 1))
    first = errors_table(passes, np.full(n, 5.0), normals)
    r1 = run(stage_inputs(blocks, passes, first), {"correct": {}})["corrected"]
    err2 = np.full(n, 7.0)
    # a G1 line that is a pass of its own, between two such lines
    bno, bend = passes.column("block_no").to_numpy(), passes.column("block_end").to_numpy()
    motion = dict(zip(blocks.column("block_no").to_pylist(), blocks.column("motion").to_pylist()))
    single = (bno == bend) & np.array([motion[b] == 1 for b in bno])
    single &= np.concatenate([[False], np.diff(bno) == 1]) & np.concatenate([np.diff(bno) == 1, [False]])
    gone = int(np.flatnonzero(single[1:-1] & single[:-2] & single[2:])[len(single) // 4] + 1)
    full2 = errors_table(passes, np.where(np.arange(n) == gone, 5.0, err2), normals)   # what the fallback should give
    part2 = errors_table(passes, err2, normals).filter(pa.array(np.arange(n) != gone))
    full_step = {"correct": {"relax": 1.0}}
    got = run(stage_inputs(blocks, passes, part2, previous=r1, first=first), full_step)["corrected"]
    want = run(stage_inputs(blocks, passes, full2, previous=r1), full_step)["corrected"]
    without = run(stage_inputs(blocks, passes, part2, previous=r1), full_step)["corrected"]
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
    data, blocks, passes = load(SAMPLES[0])
    passes = passes.sort_by("pass_id")
    n = passes.num_rows
    normal = np.array([0.6, 0.0, 0.8])
    normals = np.tile(normal, (n, 1))
    params = {"correct": {"relax": relax, "max_move_um": 1e4}}
    cor = run(stage_inputs(blocks, passes, errors_table(passes, np.full(n, e0), normals)), params)["corrected"]
    dev = []
    for _ in range(rounds):
        mv = np.stack([cor.column(f"{a}_new_mm").to_numpy() - cor.column(f"{a}_mm").to_numpy()
                       for a in "xyz"], 1) * 1e3
        s = -(mv @ normal)
        moved = cor.column("move_um").to_numpy() > 0
        s_pass = float(np.median(s[moved]))           # every predicted vertex moves alike
        dev.append(e0 + k * s_pass - s_pass)
        cor = run(stage_inputs(blocks, passes, errors_table(passes, np.full(n, e0 + k * s_pass), normals),
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
    errors = errors_table(passes, err, normals).filter(pa.array(np.arange(passes.num_rows) != wall))
    inputs = stage_inputs(blocks, passes, errors, generating=generating)
    tool = {"type": "ball", "diameter_mm": 10.0, "stickout_mm": 40.0}
    vertex = int(passes.column("block_end").to_numpy()[floor])      # its last block (inclusive)
    for limit, expect in ((True, 100.0), (False, 300.0)):
        out = correct.run(inputs, {"correct": {"max_move_um": 300.0, "gouge_limit": limit}, "tool": tool})["corrected"]
        row = int(np.flatnonzero(out.column("block_no").to_numpy() == vertex)[0])
        move = (np.array([out.column(c)[row].as_py() for c in ("x_new_mm", "y_new_mm", "z_new_mm")])
                - [4.9, 0.0, 0.0]) * 1000.0
        assert move == pytest.approx([expect, 0.0, 0.0], abs=0.01)
        assert out.column("gouge_limit_um")[row].as_py() == pytest.approx(400.0 if limit else 0.0, abs=0.01)


def test_the_nominal_limits_the_move_into_a_wall_no_pass_of_the_program_finishes(tmp_path):
    """The corner above without the wall pass (a later program of the job finishes the wall): the
    nominal model (floor z 0, wall x 10) stands in for it. The shank's side is 0.1 mm from the wall,
    so the vertex moves 100 µm along +x (within the samples' spacing: the nearest sample off y 0 by
    δ allows 0.1 + δ²/10 mm), not the 300 µm move limit."""
    import trimesh
    from stages import correct
    text = b"\n".join([b"%", b"O0001", b"G90 G17 G21", b"T1 M6", b"S8000 M3", b"G0 X0. Y0. Z10.",
                       b"G1 Z0. F500", b"X4.9", b"Y2.", b"G0 Z50.", b"M30", b"%", b""])
    blocks, _ = parse_program(text, "corner.nc", "p")
    passes = split_blocks(blocks, SPLIT)
    x0, x1, z1 = (passes.column(c).to_numpy() for c in ("x0_mm", "x1_mm", "z1_mm"))
    floor = np.flatnonzero((x0 == 0.0) & (x1 == 4.9) & (z1 == 0.0))[0]
    normals = np.tile([0.0, 0.0, 1.0], (passes.num_rows, 1))
    err = np.zeros(passes.num_rows)
    normals[floor + 1], err[floor + 1] = [0.6, 0.0, 0.8], -300.0
    v = [[-20, -20, 0], [10, -20, 0], [10, 20, 0], [-20, 20, 0], [10, -20, 20], [10, 20, 20]]
    nominal = trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2]], process=False)
    assert np.allclose(nominal.face_normals, [[0, 0, 1], [0, 0, 1], [-1, 0, 0], [-1, 0, 0]])
    nominal.export(tmp_path / "nominal.stl")
    inputs = stage_inputs(blocks, passes, errors_table(passes, err, normals), generating=None)
    tool = {"type": "ball", "diameter_mm": 10.0, "stickout_mm": 40.0}
    vertex = int(passes.column("block_end").to_numpy()[floor])
    row = None
    for nominal_file, lo, hi in ((None, 299.99, 300.01), (str(tmp_path / "nominal.stl"), 99.0, 103.0)):
        out = correct.run({**inputs, "nominal": nominal_file},
                          {"correct": {"max_move_um": 300.0}, "tool": tool})["corrected"]
        row = int(np.flatnonzero(out.column("block_no").to_numpy() == vertex)[0])
        dx = (out.column("x_new_mm")[row].as_py() - 4.9) * 1000.0
        assert lo <= dx <= hi


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


@pytest.mark.parametrize("devs, stalled, kept", [
    ([30.0], False, 1),                        # one round: its correction, unpredicted
    ([30.0, 10.0, 5.0], False, 3),             # every round paid: the last correction
    ([30.0, 10.0, 9.95], True, 2),             # < 1 % better than the best: stop, keep round 2's
    ([30.0, 10.0, 12.0], True, 1),             # worse: stop, keep round 1's (predicted 10.0)
    ([30.0, 31.0], True, 0),                   # no correction deviates less than the program as written
    ([30.0, None], False, 2),                  # nothing predicted to compare: go on
])
def test_rounds_stop_when_the_predicted_deviation_stops_falling(devs, stalled, kept):
    from stages.correct import kept_round, stalled as is_stalled
    records = [{"round": k + 1, "rms_dev_um": d} for k, d in enumerate(devs)]
    assert is_stalled(records) is stalled
    assert kept_round(records, stalled) == kept
