"""Stage ``feed``: scheduled feeds checked by predicting the forces and deflections again at them."""
from __future__ import annotations

import numpy as np
import pytest
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import trimesh
import yaml
from hypothesis import given, settings, strategies as st

from stages.cutting.feeds import smooth_down
from tests.test_iterate import DEPTH, RC, _program, _run, _workflow

LIMIT_UM = 100.0         # the soft machine of the case: 104–278 µm at the programmed feed, < 80 at no feed


def _job(tmp_path, feed):
    (tmp_path / "nc").mkdir()
    (tmp_path / "nc" / "cyl.nc").write_bytes(_program())
    stock = trimesh.creation.cylinder(radius=RC + DEPTH, height=4.0, sections=720)
    stock.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    stock.export(tmp_path / "stock.stl")
    path = _workflow(tmp_path, max_iter=1)
    wf = yaml.safe_load(path.read_text())
    wf["feed"] = feed
    path.write_text(yaml.safe_dump(wf))
    _run(path)
    return tmp_path / "out", wf


def test_scheduled_feeds_keep_the_repredicted_deflection_at_the_limit(tmp_path):
    feed = {"max_deflection_um": LIMIT_UM, "max_chip_mm": 0.5, "max_mm_min": 20000, "min_mm_min": 10, "max_change": 10.0}
    out, wf = _job(tmp_path, feed)
    f = pd.read_parquet(out / "tables" / "feeds").set_index("pass_id")
    lim = f[(f.limited_by == "deflection") & ~f.overloaded]
    assert len(lim) >= 3 and (lim.peak_deflection_um > LIMIT_UM).all()     # the case needs slowing down
    # independent check: the forces and deflection stages run again on the passes at the new feeds
    from stages import forces
    from stages.cutting.frf import deflection_xy
    from stages.tables import list_values
    passes = pq.read_table(out / "tables" / "passes")
    new = f.feed_new_mm_min.reindex(passes.column("pass_id").to_numpy()).to_numpy()
    passes = passes.set_column(passes.schema.get_field_index("feed_mm_min"), "feed_mm_min", pa.array(new.astype(float)))
    params = {"tool": wf["tool"], "material": wf["material"]}
    fr = forces.run({"passes": passes, "engagement": pq.read_table(out / "tables" / "engagement")}, params)["forces"]
    dx, dy = deflection_xy(list_values(fr.column("fx_n"), "fx"), list_values(fr.column("fy_n"), "fy"),
                           fr.column("spindle_rpm").to_numpy(), wf["machine"]["frf"])
    peak = pd.Series(np.hypot(dx, dy).max(1), index=fr.column("pass_id").to_numpy())
    np.testing.assert_allclose(peak[lim.index], LIMIT_UM, rtol=1e-6)          # at the limit, not below it
    np.testing.assert_allclose(peak[lim.index], lim.peak_deflection_new_um, rtol=1e-9)
    assert (lim.feed_new_mm_min < lim.feed_mm_min).all()
    # every pass the program as written overloads is a warning with its NC line
    w = pd.read_parquet(out / "tables" / "warnings").query("reason == 'overloaded_as_programmed'").set_index("pass_id")
    over = f[(f.peak_deflection_um > LIMIT_UM) & ~f.overloaded]
    assert set(w.index) == set(over.index) and (w.line_no == over.line_no.reindex(w.index)).all()
    # the corrected program carries the feeds: each cutting block at the slowest of its passes
    from stages.nc.reader import parse_program
    text = (out / "nc" / "cyl.nc").read_bytes()
    assert b"FEEDS SCHEDULED" in text
    blocks, _ = parse_program(text, "cyl.nc", "cyl")
    b = blocks.to_pandas().set_index("block_no")
    p = pd.read_parquet(out / "tables" / "passes")
    for blk in p.block_no[p.motion.isin([1, 2, 3])]:
        over = p.pass_id[(p.block_no <= blk) & (p.block_end >= blk)]
        assert abs(b.feed_mm_min[blk] - f.feed_new_mm_min[over].min()) <= 0.5 + 1e-9, blk
    # time: each pass's duration scales with programmed / scheduled feed
    moving = f.limited_by != "rapid"
    np.testing.assert_allclose(f.duration_new_s[moving], f.duration_s[moving] * f.feed_mm_min[moving] / f.feed_new_mm_min[moving])


def test_limits_are_kept_and_an_overload_at_the_minimum_feed_is_flagged(tmp_path):
    # a limit under what the edge forces alone give: every predicted pass is overloaded at the minimum
    feed = {"max_deflection_um": 1e-3, "max_chip_mm": 0.5, "max_mm_min": 6000, "min_mm_min": 300, "max_change": 0.2}
    out, _ = _job(tmp_path, feed)
    f = pd.read_parquet(out / "tables" / "feeds").sort_values("pass_id")
    pred = f.peak_deflection_um.notna()
    assert pred.sum() >= 3 and f.overloaded[pred].all() and np.allclose(f.feed_new_mm_min[pred], 300)
    w = pd.read_parquet(out / "tables" / "warnings")
    assert set(w.query("reason == 'overloaded'").pass_id) == set(f.pass_id[pred]) and np.allclose(w.limit, 1e-3), w
    assert not (w.reason == "overloaded_as_programmed").any()      # none is brought within the limit
    moving = f[f.limited_by != "rapid"]
    assert moving.feed_new_mm_min.between(300 * (1 - 1e-12), 6000).all()
    ratio = moving.feed_new_mm_min.to_numpy()
    assert (np.maximum(ratio[1:] / ratio[:-1], ratio[:-1] / ratio[1:]) <= 1.2 + 1e-9).all()
    assert (f.limited_by[~f.peak_deflection_um.notna() & (f.limited_by != "rapid")]).isin(
        ["air", "as_programmed", "smoothing", "max_feed", "min_feed"]).all()


def test_no_feed_section_writes_no_feeds(tmp_path):
    out, _ = _job(tmp_path, None)
    assert pq.read_table(out / "tables" / "feeds").num_rows == 0


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(1.0, 1e4), min_size=1, max_size=40), st.floats(0.01, 2.0))
def test_smoothing_is_the_largest_feed_below_within_the_ratio(feed, c):
    f = np.array(feed)
    s = smooth_down(f, c)
    assert (s <= f * (1 + 1e-12)).all()
    assert (np.maximum(s[1:] / s[:-1], s[:-1] / s[1:]) <= (1 + c) * (1 + 1e-9)).all()
    # brute force: the largest sequence under f with the ratio bound is min_j f_j (1+c)^|i-j|
    i = np.arange(len(f))
    brute = (f[None, :] * (1 + c) ** np.abs(i[:, None] - i[None, :])).min(1)
    np.testing.assert_allclose(s, brute, rtol=1e-9)


def _without_f_words(text: bytes) -> bytes:
    import re
    return re.sub(rb" ?F[0-9.]+", b"", text)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2 ** 31 - 1), st.floats(0.05, 1.0), st.sampled_from([b"", b"G20\n"]))
def test_feed_words_give_the_scheduled_feed_on_every_cutting_block_and_change_nothing_else(seed, share, units):
    from stages.nc.feed_words import write_feeds
    from stages.nc.reader import parse_program
    from tests.ncprograms import raster_program
    src = raster_program(300, seed=seed % 1000, per_row=40)
    if units:                                   # the same program in inch: F in inch/min
        src = src.replace(b"G90 G17 G21", b"G90 G17 G20")
    blocks, _ = parse_program(src, "p.nc", "p")
    m = blocks.column("motion").to_numpy()
    old = blocks.column("feed_mm_min").to_numpy()
    rng = np.random.default_rng(seed)
    cut = (m >= 1) & (m <= 3)
    scale = 25.4 if units else 1.0
    new = np.where(cut & (rng.random(len(m)) < share), np.round(rng.uniform(100, 3000, len(m)) / scale) * scale, old)
    new = np.where(cut, new, np.nan)
    text, n = write_feeds(src, blocks, new)
    back, _ = parse_program(text, "p.nc", "p")
    np.testing.assert_allclose(back.column("feed_mm_min").to_numpy()[cut], new[cut], atol=1e-6)
    assert _without_f_words(text) == _without_f_words(src)                 # only F words differ
    assert n == text.count(b"F") - src.count(b"F") + sum(1 for a, b in zip(text.split(b"\n"), src.split(b"\n"))
                                                         if b"F" in a and b"F" in b and a != b)
    # the feeds as programmed: the program comes back byte for byte
    same, n0 = write_feeds(src, blocks, np.where(cut, old, np.nan))
    assert same == src and n0 == 0


def test_warnings_list_what_a_correction_cannot_help(tmp_path):
    feed = {"max_deflection_um": 1e-3, "max_chip_mm": 0.5, "max_mm_min": 6000, "min_mm_min": 300}
    out, wf = _job(tmp_path, feed)
    a = pd.read_parquet(out / "tables" / "allowance")
    e = pd.read_parquet(out / "tables" / "errors")
    assert len(a) == len(e) >= 3
    w = pd.read_parquet(out / "tables" / "warnings")
    f = pd.read_parquet(out / "tables" / "feeds")
    limit = wf["correct"]["max_move_um"]
    assert set(w.pass_id[w.reason == "beyond_move_limit"]) == set(e.pass_id[e.err_um.abs() > limit])
    assert set(w.pass_id[w.reason == "overloaded"]) == set(f.pass_id[f.overloaded]) and f.overloaded.sum() >= 3
    assert not (w.reason == "rest_material").any()                  # an even allowance: no rest material
    lines = pd.read_parquet(out / "tables" / "passes").set_index("pass_id").line_no
    assert (w.line_no.to_numpy() == lines[w.pass_id].to_numpy()).all()


def test_rest_material_is_stock_over_the_stated_allowance(tmp_path):
    (tmp_path / "a").mkdir()
    out, wf = _job(tmp_path / "a", None)
    path = sorted((tmp_path / "a").glob("wf_*.yaml"))[0]
    wf["warnings"] = {"allowance_mm": 0.03, "rest_factor": 3.0}        # 0.09 mm < the 0.13–0.3 mm met
    path.write_text(yaml.safe_dump(wf))
    _run(path)
    w = pd.read_parquet(out / "tables" / "warnings")
    a = pd.read_parquet(out / "tables" / "allowance")
    rest = w[w.reason == "rest_material"]
    assert set(rest.pass_id) == set(a.pass_id) and np.allclose(rest.limit, 0.09)
    np.testing.assert_allclose(rest.sort_values("pass_id").value, a.sort_values("pass_id").stock_mm)


def test_stock_along_the_normal_against_a_brute_force_of_the_material_before_each_pass(tmp_path):
    # a Ø10 ball finishing a floor (tip at z = 0) under a box stock whose top is 0.3 mm higher, rows
    # 1 mm apart. Brute force, sharing nothing with the scan: the material before a pass at its
    # prediction point is the box less the capsules swept by the ball centres of the earlier passes
    # and of its own path up to that point; the stock met is the largest (p − G)·n over the tool's
    # envelope points in it (G, n: the generating table). Over a floor it is the stock height.
    rows = [f"G1 X{18 if k % 2 == 0 else 2}.0 Y{4 + k}.0" for k in range(10)]
    zig = []
    for k, r in enumerate(rows):
        zig += [f"G1 Y{4 + k}.0", r]
    text = "\n".join(["%", "O1 (FLOOR)", "G90 G17 G21", "T1 M6", "S8000 M3", "G0 X2.0 Y4.0 Z5.0", "G1 Z0.0 F1500",
                      *zig, "G0 Z5.0", "M30", "%", ""])
    (tmp_path / "nc").mkdir()
    (tmp_path / "nc" / "floor.nc").write_text(text)
    top = 0.3
    trimesh.creation.box(bounds=[[0, 0, -5], [20, 20, top]]).export(tmp_path / "stock.stl")
    path = _workflow(tmp_path, max_iter=1, until="warn")
    wf = yaml.safe_load(path.read_text())
    wf["tool"]["diameter_mm"] = 10
    path.write_text(yaml.safe_dump(wf))
    _run(path)
    t = tmp_path / "out" / "tables"
    a = pd.read_parquet(t / "allowance").dropna().set_index("pass_id").stock_mm
    gen = pd.read_parquet(t / "generating").set_index("pass_id")
    cf = pd.read_parquet(t / "cut_filter").set_index("pass_id")
    p = pd.read_parquet(t / "passes").set_index("pass_id")
    assert len(a) >= 8
    R = 5.0
    z = (np.arange(360) + 0.5) * R / 180
    z = z[z < R]
    r = np.sqrt(R ** 2 - (R - z) ** 2)
    ang = np.radians(np.arange(0, 360, 2.0))
    c0 = p[["x0_mm", "y0_mm", "z0_mm"]].to_numpy() + [0, 0, R]
    c1 = p[["x1_mm", "y1_mm", "z1_mm"]].to_numpy() + [0, 0, R]
    ids = p.index.to_numpy()

    def in_capsule(x, a0, a1):
        d = a1 - a0
        s = np.clip(((x - a0) @ d) / max(d @ d, 1e-12), 0, 1)
        return np.linalg.norm(x - (a0 + s[:, None] * d), axis=1) < R - 1e-3
    for pid, got in a.items():
        tip = cf.loc[pid, ["pred_x_mm", "pred_y_mm", "pred_z_mm"]].to_numpy(float)
        pts = np.stack([tip[0] + r[:, None] * np.cos(ang), tip[1] + r[:, None] * np.sin(ang),
                        np.broadcast_to(tip[2] + z[:, None], (len(z), len(ang)))], -1).reshape(-1, 3)
        mat = (pts[:, 2] < top) & (pts[:, :2] > 0).all(1) & (pts[:, :2] < 20).all(1)
        k = int(np.flatnonzero(ids == pid)[0])
        for j in range(k):
            mat &= ~in_capsule(pts, c0[j], c1[j])
        mat &= ~in_capsule(pts, c0[k], tip + [0, 0, R] - 1e-3 * (c1[k] - c0[k]))
        G = gen.loc[pid, ["gen_x_mm", "gen_y_mm", "gen_z_mm"]].to_numpy(float)
        n = gen.loc[pid, ["nx", "ny", "nz"]].to_numpy(float)
        brute = ((pts[mat] - G) @ n).max()
        assert abs(got - brute) <= R / 180 + 1.0 / wf["render"]["px_per_mm"], (pid, got, brute)
        if abs(n[2]) > 0.999:                                   # the floor's own normal: the stock height
            assert abs(got - top) <= R / 180 + 1.0 / wf["render"]["px_per_mm"], (pid, got)


def test_a_program_without_a_kept_correction_still_gets_its_scheduled_feeds(tmp_path):
    from stages.nc.output import corrected_programs
    from stages.nc.reader import parse_program
    feed = {"max_deflection_um": LIMIT_UM, "max_chip_mm": 0.5, "max_mm_min": 20000, "min_mm_min": 10}
    out, _ = _job(tmp_path, feed)
    t = {n: pq.read_table(out / "tables" / n / "cyl.parquet") for n in ("blocks", "errors", "passes", "feeds")}
    src = tmp_path / "nc" / "cyl.nc"
    files = corrected_programs({"program_file": {"path": str(src), "sha256": "ab", "program_id": "cyl"},
                                "corrected": None, **t}, {"correct": {}})
    text = files["cyl.nc"]
    assert b"(FEEDS SCHEDULED" in text and b"COORDINATES AS PROGRAMMED" in text
    new, _ = parse_program(text, "cyl.nc", "cyl")
    old, _ = parse_program(src.read_bytes(), "cyl.nc", "cyl")
    for c in ("x1_mm", "y1_mm", "z1_mm"):
        assert np.array_equal(new.column(c).to_numpy(), old.column(c).to_numpy())
    assert (new.column("feed_mm_min").to_numpy() != old.column("feed_mm_min").to_numpy()).any()
    # without feeds nothing is written
    assert corrected_programs({"program_file": {"path": str(src), "sha256": "ab", "program_id": "cyl"},
                               "corrected": None, **dict(t, feeds=t["feeds"].slice(0, 0))}, {"correct": {}}) == {}


def test_with_scheduled_feeds_every_cutting_pass_is_predicted(tmp_path):
    # the passes claim 8 leaves out (their surface's contact angle under prune.min_contact_deg) load
    # the tool all the same: with a feed section each cutting pass gets its deflection and feed
    feed = {"max_deflection_um": LIMIT_UM, "max_chip_mm": 0.5, "max_mm_min": 20000, "min_mm_min": 10, "max_change": 10.0}
    predicted = {}
    for name, fd in (("without", None), ("with", feed)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "nc").mkdir()
        (tmp_path / name / "nc" / "cyl.nc").write_bytes(_program())
        stock = trimesh.creation.cylinder(radius=RC + DEPTH, height=4.0, sections=720)
        stock.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
        stock.export(tmp_path / name / "stock.stl")
        path = _workflow(tmp_path / name, max_iter=1, until="feed")
        wf = yaml.safe_load(path.read_text())
        wf["prune"] = {"min_contact_deg": 89.9}
        wf["feed"] = fd
        path.write_text(yaml.safe_dump(wf))
        _run(path)
        t = tmp_path / name / "out" / "tables"
        cf = pd.read_parquet(t / "cut_filter")
        predicted[name] = set(pd.read_parquet(t / "angle_prune").query("predict").pass_id)
        cutting = set(cf.pass_id[cf.is_cutting])
    assert predicted["without"] < cutting and predicted["with"] == cutting      # every level is under 89.9°
    f = pd.read_parquet(tmp_path / "with" / "out" / "tables" / "feeds")
    assert f.set_index("pass_id").peak_deflection_um[sorted(cutting)].notna().all()


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_the_rounds_predict_the_program_at_its_scheduled_feeds(seed):
    """``correct_blocks`` gives the next round the scheduled feeds: split again, every pass runs at
    the slowest scheduled feed of the passes over its blocks in the first round (found here by a
    loop over passes and blocks), and blocks no pass schedules keep the programmed feed."""
    from stages import correct_blocks
    from stages.nc.moves import split_blocks
    from stages.nc.reader import parse_program
    from tests.correct_cases import SPLIT
    blocks, _ = parse_program(_program(), "cyl.nc", "cyl")
    passes = split_blocks(blocks, SPLIT)
    rng = np.random.default_rng(seed)
    pick = np.flatnonzero(rng.random(passes.num_rows) < 0.5)
    new = rng.uniform(100.0, 900.0, pick.size)
    feeds = pa.table({"pass_id": passes.column("pass_id").take(pick), "feed_new_mm_min": new})
    empty = pa.table({"block_no": pa.array([], pa.int64())})
    out = correct_blocks.run({"blocks@first": blocks, "corrected@previous": empty, "passes@first": passes,
                              "feeds@first": feeds}, {})["blocks"].to_pandas().set_index("block_no")
    want = blocks.to_pandas().set_index("block_no").feed_mm_min.copy()
    slowest = {}
    p = passes.to_pandas()
    for k, f in zip(pick, new):
        for b in range(p.block_no[k], p.block_end[k] + 1):
            slowest[b] = min(slowest.get(b, np.inf), f)
    for b, f in slowest.items():
        want[b] = f
    np.testing.assert_allclose(out.feed_mm_min.to_numpy(), want.to_numpy())
    again = split_blocks(pa.Table.from_pandas(out.reset_index(), preserve_index=False), SPLIT).to_pandas()
    for _, r in again[again.motion.isin([1, 2, 3])].iterrows():
        assert r.feed_mm_min == pytest.approx(want[r.block_end])
