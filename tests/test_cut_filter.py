"""The scan stage's cut_filter (claim 7) and angle_prune (claim 8) on hand-made programs with known answers."""
import numpy as np
import pyarrow as pa
import pytest

from stages import scan

from tests.cylinder_case import TOOL as CYL_TOOL, cylinder_case

BALL10 = {"type": "ball", "diameter_mm": 10.0, "flutes": 2, "stickout_mm": 30.0,
          "corner_radius_mm": None, "control_point": "tip"}
STOCK = {"box": [-50.0, -50.0, -20.0, 50.0, 50.0, 0.0]}


def _passes(rows, pid="box"):
    n = len(rows)
    p0 = np.array([r[1] for r in rows], float)
    p1 = np.array([r[2] for r in rows], float)
    return pa.table({
        "program_id": [pid] * n, "pass_id": pa.array(np.arange(n), pa.int32()),
        "block_no": pa.array(np.arange(n), pa.int32()), "line_no": pa.array(np.arange(n), pa.int32()),
        "motion": pa.array([r[0] for r in rows], pa.int8()),
        "x0_mm": p0[:, 0], "y0_mm": p0[:, 1], "z0_mm": p0[:, 2],
        "x1_mm": p1[:, 0], "y1_mm": p1[:, 1], "z1_mm": p1[:, 2],
        "feed_mm_min": np.full(n, 1000.0), "spindle_rpm": np.full(n, 10000.0),
        "tool": pa.array([1] * n, pa.int32()), "t_start_s": np.zeros(n), "t_end_s": np.zeros(n)})


BOX_PROGRAM = [
    (1, (0, 0, -1), (20, 0, -1)),        # 0 A: cuts its whole length
    (1, (0, 0, -1), (40, 0, -1)),        # 1 B: same line, longer: cuts only beyond x = 20
    (1, (0, 20, 5), (40, 20, 5)),        # 2 air move (G1 above the stock)
    (0, (0, -20, -1), (40, -20, -1)),    # 3 rapid through the stock: never cuts by definition
    (1, (0, 0, -1), (20, 0, -1)),        # 4 repeats A: fully inside removed material
    (1, (5, 0, -0.5), (15, 0, -0.5)),    # 5 above A's floor, inside its groove
    (1, (40, 30, -1), (80, 30, -1)),     # 6 leaves the stock at x = 50: cuts x < 55 only
]


def _renderers():
    out = ["cpu"]
    try:
        from stages.render import make_renderer
        make_renderer("gl")
        out.append("gl")
    except Exception:
        pass
    return out


@pytest.mark.parametrize("backend", ["cpu", "gl"])
def test_box_program_known_answers(backend):
    if backend not in _renderers():
        pytest.skip("gl back end unavailable (no EGL context)")
    params = {"tool": BALL10, "render": {"backend": backend, "px_per_mm": 10}}
    cf = scan.run({"passes": _passes(BOX_PROGRAM), "stock": STOCK}, params)["cut_filter"].to_pandas()
    assert cf.is_cutting.tolist() == [True, True, False, False, False, False, True]
    assert (cf.cut_px[~cf.is_cutting] == 0).all()
    # B cuts only beyond A's end: its prediction point is in that part
    assert 20.0 < cf.pred_x_mm[1] <= 40.0 and abs(cf.pred_y_mm[1]) < 1e-9
    # the pass leaving the stock: prediction point where the tool is over the stock
    assert 40.0 <= cf.pred_x_mm[6] < 50.0 + 5.0
    # A is cut over its whole length: prediction point near its middle
    assert abs(cf.pred_x_mm[0] - 10.0) < 3.0
    assert cf.pred_z_mm[0] == pytest.approx(-1.0)


def test_cylinder_cut_filter_gl_and_cpu_agree_and_angle_prune():
    passes, stock, q_ref, _, _ = cylinder_case(n_levels=20, length_mm=3.0)
    res = {}
    for backend in _renderers():
        params = {"tool": CYL_TOOL, "render": {"backend": backend, "px_per_mm": 20},
                  "prune": {"min_contact_deg": 45.0}}
        out = scan.run({"passes": passes, "stock": _stl(stock)}, params)
        res[backend] = (out["cut_filter"].to_pandas(), out["angle_prune"].to_pandas())
    cf, ap = res["cpu"]
    motion = passes.column("motion").to_numpy()
    contour = np.arange(len(motion)) % 2 == 1              # links and the rapid are even
    assert cf.is_cutting.to_numpy().tolist() == contour.tolist()
    assert np.all(np.abs(cf.pred_y_mm[contour]) < 0.1)      # middle of the stock
    # angle prune: the largest contact angle of each pass's surface brackets its level's angle
    lv = np.isfinite(q_ref)
    mq = ap.max_contact_deg.to_numpy()
    # (from below, walls steeper than ~80° shrink below a pixel: only an upper bound there)
    low = lv & (q_ref < 80)
    assert np.all(mq[low] >= q_ref[low] - 0.5)
    assert np.all(mq[lv & (q_ref >= 80)] >= 80.0)            # steep walls are never pruned
    assert np.all(mq[lv] <= q_ref[lv] + 4.5 + 0.5)          # half the level spacing above
    assert ap.predict.tolist() == (contour & (mq >= 45.0)).tolist()
    assert not ap.predict[~contour].any()
    if "gl" in res:
        cg, ag = res["gl"]
        assert cg.is_cutting.tolist() == cf.is_cutting.tolist()
        assert ag.predict.tolist() == ap.predict.tolist()
        assert np.allclose(cg.pred_x_mm[contour], cf.pred_x_mm[contour], atol=0.05)


_STL = {}


def _stl(stock):
    import os
    import tempfile
    key = id(stock)
    if key not in _STL:
        path = os.path.join(tempfile.mkdtemp(), "stock.stl")
        stock.export(path)
        _STL[key] = path
    return _STL[key]


def _pieces(passes, noise_mm, piece_mm=0.5):
    """The cylinder's levels cut into pieces of ``piece_mm``; the inner vertices moved by
    ±``noise_mm`` in x and z (the float noise of a corrected program's via points)."""
    t = passes.to_pandas()
    rows = []
    for r in t.itertuples():
        p0, p1 = np.array([r.x0_mm, r.y0_mm, r.z0_mm]), np.array([r.x1_mm, r.y1_mm, r.z1_mm])
        level = r.motion != 0 and abs(p1[1] - p0[1]) > 1.0
        n = int(round(np.linalg.norm(p1 - p0) / piece_mm)) if level else 1
        pts = p0 + np.linspace(0.0, 1.0, n + 1)[:, None] * (p1 - p0)
        k = np.arange(1, n)
        pts[1:-1, 0] += noise_mm * np.where(k % 2, 1.0, -1.0)
        pts[1:-1, 2] += noise_mm * np.where(k % 3, 1.0, -1.0)
        rows += [(r.motion, pts[i], pts[i + 1]) for i in range(n)]
    return _passes(rows, pid="cyl")


def test_a_chain_turned_by_float_noise_cuts_as_the_exact_chain():
    """The cylinder's levels as chains of 0.5 mm passes, exact and with every inner vertex moved by
    1e-9 mm (a turn of a few nanoradians): every pass cuts the same pixels. The sweeps' faces that
    lie along the motion belong to the joints' lunes; with a 1e-9 tolerance a nanoradian's turn
    dropped them there and the silhouette moved one face over, and whole passes' cut pixels went
    to the next pass (a corrected cylinder: 105 of 727 passes "not cutting" in round 2)."""

    passes, stock, _, _, _ = cylinder_case(n_levels=10, length_mm=3.0)
    params = {"tool": CYL_TOOL, "render": {"backend": "cpu", "px_per_mm": 20}}

    def cut_px(noise):
        return scan.run({"passes": _pieces(passes, noise), "stock": _stl(stock)},
                        params)["cut_filter"].column("cut_px").to_numpy()
    exact, noisy = cut_px(0.0), cut_px(1e-9)
    assert (exact > 0).sum() > 60                      # the pieces inside the stock cut
    np.testing.assert_array_equal(noisy, exact)
