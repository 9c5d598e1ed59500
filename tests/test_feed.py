"""Stage ``feed``: scheduled feeds checked by predicting the forces and deflections again at them."""
from __future__ import annotations

import numpy as np
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
