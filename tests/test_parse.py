"""Parser and splitter: geometry against closed forms, modal state, timing, and clean errors."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import schemas
from stages import InputError
from stages.nc.reader import parse_program
from stages.nc.moves import split_blocks
from tests.ncprograms import raster_program

PARAMS = {"split": {"chord_tol_mm": 0.001, "max_pass_mm": 5.0, "merge_max_mm": 0.5},
          "machine": {"rapid_mm_min": 30000.0},
          "tool": {"type": "ball", "diameter_mm": 6.0, "control_point": "tip", "corner_radius_mm": None}}

HEADER = "%\nO1(T)\nG90 G17 G21\nT1 M6\nS10000 M3\n"


def passes_of(text: str, params=PARAMS):
    blocks, summary = parse_program(text.encode(), "t.nc", "t")
    schemas.check("blocks", blocks)
    p = split_blocks(blocks, params)
    schemas.check("passes", p)
    return p.to_pandas(), summary


def cut(df):
    return df[df.motion != 0]


def test_modal_coordinates_feed_and_line_numbers():
    df, s = passes_of(HEADER + "G0 X0 Y0 Z5\nG1 Z0 F600\nX3\nY4 F1200\n(done)\nM30\n")
    c = cut(df)
    assert s["tool"] == 1
    np.testing.assert_allclose(c[["x1_mm", "y1_mm", "z1_mm"]].to_numpy(), [[0, 0, 0], [3, 0, 0], [3, 4, 0]])
    assert list(c.line_no) == [7, 8, 9]
    # time from feed: 5 mm at 600, 3 mm at 600, 4 mm at 1200 mm/min (G0 Z5 from the first point is zero-length)
    np.testing.assert_allclose(c.t_end_s.to_numpy(), np.cumsum([0.5, 0.3, 0.2]))


def test_rapids_timed_at_rapid_rate_and_dwell_adds_time():
    df, _ = passes_of(HEADER + "G0 X0 Y0 Z0\nG1 X1 F60\nG4 P1500\nG0 X301\nG4 X2.\nG1 X302\nM30\n")
    np.testing.assert_allclose(df.t_start_s, [0.0, 2.5, 5.1])       # 1 s cut, 1.5 s dwell, 0.6 s rapid, 2 s dwell
    np.testing.assert_allclose(df.t_end_s, [1.0, 3.1, 6.1])         # 2 s dwell then 1 mm at 60 mm/min


def test_incremental_and_inch():
    params = dict(PARAMS, split=dict(PARAMS["split"], max_pass_mm=100.0))
    df, _ = passes_of(HEADER + "G0 X1 Y1 Z1\nG91 G1 X1 Y2 F100\nX-0.5\nG90 G20 X1.\nG21 Y0\nM30\n", params)
    c = cut(df)
    np.testing.assert_allclose(c[["x1_mm", "y1_mm"]].to_numpy(), [[2, 3], [1.5, 3], [25.4, 3], [25.4, 0]])


@pytest.mark.parametrize("plane,word", [(17, "G17"), (18, "G18"), (19, "G19")])
def test_arcs_lie_on_the_circle_within_chord_tolerance(plane, word):
    r, tol = 5.0, 0.001
    # a half circle in the plane's coordinates (a, b), CCW seen from +normal: (r,0) → (−r,0), centre 0
    axes = {17: "XYZ", 18: "ZXY", 19: "YZX"}[plane]
    a, b, n = axes
    ij = {"X": "I", "Y": "J", "Z": "K"}
    text = HEADER + f"G0 X0 Y0 Z0\nG1 {a}{r} F1000\n{word} G3 {a}{-r} {b}0 {ij[a]}{-r} {ij[b]}0\nM30\n"
    df, _ = passes_of(text)
    c = cut(df)
    arc = c[c.motion == 3]
    idx = {"X": 0, "Y": 1, "Z": 2}
    pts0 = arc[["x0_mm", "y0_mm", "z0_mm"]].to_numpy()
    pts1 = arc[["x1_mm", "y1_mm", "z1_mm"]].to_numpy()
    rad = np.hypot(pts1[:, idx[a]], pts1[:, idx[b]])
    np.testing.assert_allclose(rad, r, atol=1e-12)
    mid = (pts0 + pts1) / 2
    sag = r - np.hypot(mid[:, idx[a]], mid[:, idx[b]])
    assert sag.max() <= tol + 1e-12
    assert sag.max() > tol / 4  # not absurdly over-refined
    assert len(arc) == math.ceil(math.pi / (2 * math.acos(1 - tol / r)))
    # CCW seen from +normal: the b coordinate goes positive first
    assert pts1[0, idx[b]] > 0
    np.testing.assert_allclose(pts1[-1, [idx[a], idx[b]]], [-r, 0], atol=1e-12)


def test_cw_arc_with_r_and_helix():
    # G2 from (0,0) to (10,0) with R5: centre (5,0), CW seen from +Z passes through (5,5); Z rises 1 mm
    df, _ = passes_of(HEADER + "G0 X0 Y0 Z0\nG1 Z0 F500\nG2 X10 Y0 Z1 R5\nM30\n")
    arc = df[df.motion == 2]
    p = arc[["x1_mm", "y1_mm", "z1_mm"]].to_numpy()
    np.testing.assert_allclose(np.hypot(p[:, 0] - 5, p[:, 1]), 5, atol=1e-12)
    assert p[:, 1].max() == pytest.approx(5, abs=0.01)
    ang = np.arctan2(p[:, 1], p[:, 0] - 5)               # π → 0 going clockwise through π/2
    np.testing.assert_allclose(p[:, 2], (np.pi - ang) / np.pi, atol=1e-12)  # helix: z linear in angle
    # arc length of the helix over feed gives the time
    length = math.hypot(math.pi * 5, 1.0)
    assert arc.t_end_s.iloc[-1] - arc.t_start_s.iloc[0] == pytest.approx(length / 500 * 60, rel=1e-4)


def test_negative_r_takes_the_long_way():
    df, _ = passes_of(HEADER + "G0 X0 Y0 Z0\nG1 Z0 F500\nG3 X5 Y5 R-5\nM30\n")
    arc = df[df.motion == 3]
    # chord (0,0)→(5,5), |R| = 5: the 270° arc's centre is (5,0) for CCW with R<0
    p = arc[["x1_mm", "y1_mm"]].to_numpy()
    np.testing.assert_allclose(np.hypot(p[:, 0] - 5, p[:, 1]), 5, atol=1e-12)
    length = (arc.t_end_s.iloc[-1] - arc.t_start_s.iloc[0]) * 500 / 60
    assert length == pytest.approx(1.5 * math.pi * 5, rel=1e-4)


def test_full_circle_with_ijk():
    df, _ = passes_of(HEADER + "G0 X0 Y0 Z0\nG1 Z0 F500\nG2 I5 J0\nM30\n")
    arc = df[df.motion == 2]
    assert arc.t_end_s.iloc[-1] - arc.t_start_s.iloc[0] == pytest.approx(2 * math.pi * 5 / 500 * 60, rel=1e-4)


def test_long_moves_split_and_short_collinear_runs_merged():
    moves = "\n".join(f"X{0.1 * i:.1f}" for i in range(1, 21))  # 20 × 0.1 mm on a line
    df, _ = passes_of(HEADER + f"G0 X0 Y0 Z0\nG1 Y12 F1000\n{moves}\nM30\n")
    c = cut(df)
    # 12 mm move → 3 passes of 4 mm (max 5), 2 mm of collinear 0.1 mm moves → 4 passes of 0.5 mm
    lengths = np.hypot(c.x1_mm - c.x0_mm, c.y1_mm - c.y0_mm).to_numpy()
    np.testing.assert_allclose(lengths, [4, 4, 4, 0.5, 0.5, 0.5, 0.5], atol=1e-9)
    assert list(c.block_no.iloc[3:]) == [7, 12, 17, 22] and list(c.block_end.iloc[3:]) == [11, 16, 21, 26]


def test_merge_never_moves_the_path_beyond_tolerance():
    # a zig-zag of 0.1 mm moves with 0.01 mm amplitude: must not be merged at 0.001 mm tolerance
    moves = "\n".join(f"X{0.1 * i:.1f} Y{0.01 * (i % 2):.2f}" for i in range(1, 11))
    df, _ = passes_of(HEADER + f"G0 X0 Y0 Z0\nG1 Z0 F1000\n{moves}\nM30\n")
    assert len(cut(df)) == 10  # G1 Z0 from Z0 is zero-length: 10 moves, none merged


def test_raster_program_round_trip():
    text = raster_program(3000).decode()
    df, s = passes_of(text)
    code_lines = [ln for ln in text.splitlines() if ln.strip() and not ln.startswith(("%", "("))]
    assert s["n_blocks"] == len(code_lines)
    c = cut(df)
    # consecutive passes are connected and time is monotonic
    np.testing.assert_allclose(df[["x0_mm", "y0_mm", "z0_mm"]].to_numpy()[1:],
                               df[["x1_mm", "y1_mm", "z1_mm"]].to_numpy()[:-1], atol=1e-12)
    assert (np.diff(df.t_start_s) > 0).all()
    assert (c.feed_mm_min > 0).all() and (c.spindle_rpm == 12000).all()


BROKEN = {
    "unknown G": ("G0 X0 Y0 Z5\nG1 Z0 F100\nG7 X1\n", 8, "unknown or unsupported G code G7"),
    "canned cycle": ("G0 X0 Y0 Z5\nG81 Z-5 R1 F100\n", 7, "canned cycle G81"),
    "macro": ("#1=5\n", 6, "macro"),
    "5-axis": ("G0 X0 Y0 Z5\nG1 Z0 A30 F100\n", 7, "rotary axis"),
    "inconsistent arc": ("G0 X0 Y0 Z5\nG1 Z0 F100\nG2 X10 Y0 I4 J0\n", 8, "arc radius inconsistent"),
    "missing feed": ("G0 X0 Y0 Z5\nG1 Z0\n", 7, "without a feed"),
    "garbage line": ("G0 X0 Y0 Z5\n!!garbage??\n", 7, "unexpected character '!'"),
    "R too small": ("G0 X0 Y0 Z5\nG1 Z0 F100\nG3 X10 Y0 R2\n", 8, "too small"),
    "subprogram": ("M98 P100\n", 6, "M98"),
    "malformed number": ("G0 X1.2.3\n", 6, "malformed number '1.2.3'"),
    "unclosed comment": ("G0 X0 (oops\n", 6, "comment not closed"),
    "no value": ("G0 X\n", 6, "address X without a value"),
    "duplicate address": ("G0 X1 X2\n", 6, "address X appears twice"),
    "unknown position": ("G1 X1 F100\n", 6, "unknown position"),
    "cutter comp": ("G41 D1\n", 6, "G41"),
    "two motion codes": ("G0 G1 X1\n", 6, "two motion G codes"),
}


@pytest.mark.parametrize("name", sorted(BROKEN))
def test_broken_programs_give_file_line_errors(name):
    body, line, what = BROKEN[name]
    with pytest.raises(InputError) as e:
        parse_program((HEADER + body).encode(), "dir/prog.nc", "prog")
    msg = str(e.value)
    assert msg.startswith(f"dir/prog.nc:{line}: "), msg
    assert what in msg
    # every problem has its line; one with a column points at what it names
    text = (HEADER + body).splitlines()
    assert e.value.problems[0][0] == line and what in e.value.problems[0][2]
    for ln, col, _ in e.value.problems:
        assert 1 <= ln <= len(text) + 1
        if col is not None:
            assert text[ln - 1][col - 1] not in " \t(", (ln, col, text[ln - 1])


def test_every_problem_of_a_program_is_listed_with_line_and_column():
    body = "G0 X0 Y0 Z5\nNow cut the pocket\nG1 Z0 F100 A5\nG7 X1 G66 Y2\nG1 X1 X2\n"
    with pytest.raises(InputError) as e:
        parse_program((HEADER + body).encode(), "p.nc", "p")
    h = len(HEADER.splitlines())
    found = [(ln - h, col, msg.split(":")[0]) for ln, col, msg in e.value.problems]
    assert found == [(2, 1, "unrecognised word 'Now'"), (3, 12, "rotary axis words (A/B/C, 4/5-axis) are not supported"),
                     (4, 1, "unknown or unsupported G code G7"), (4, 7, "unknown or unsupported G code G66")], found
    assert str(e.value).startswith(f"p.nc:{h + 2}: unrecognised word 'Now' at column 1: ") and "(and 3 more problems)" in str(e.value)


def test_binary_and_truncated():
    with pytest.raises(InputError, match=r"^b.nc:1: binary data"):
        parse_program(bytes(range(256)), "b.nc", "b")
    text = raster_program(500)
    with pytest.raises(InputError, match=r"^t.nc:\d+: "):
        parse_program(text[: len(text) // 2] + b"G2 X", "t.nc", "t")


def test_lines_after_m30_are_not_executed():
    df, _ = passes_of(HEADER + "G0 X0 Y0 Z0\nG1 X1 F100\nM30\nG1 X99\n")
    assert df.x1_mm.max() == 1


_VALID = raster_program(120, per_row=20).decode().splitlines()


@settings(max_examples=600, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_fuzz_mutated_programs_only_clean_errors(data):
    """600 mutated programs a run (fresh draws each run): the parser returns tables or raises InputError, nothing else."""
    lines = list(_VALID)
    for _ in range(data.draw(st.integers(1, 4))):
        op = data.draw(st.sampled_from(["replace", "insert", "delete", "bytes", "truncate", "swap"]))
        i = data.draw(st.integers(0, len(lines) - 1))
        if op == "replace":
            lines[i] = data.draw(st.text(alphabet="GXYZIJKRFSTMNP0123456789.-+ ()#;%/=abcA", max_size=20))
        elif op == "insert":
            lines.insert(i, data.draw(st.text(max_size=15)))
        elif op == "delete" and len(lines) > 1:
            del lines[i]
        elif op == "bytes":
            j = data.draw(st.integers(0, max(0, len(lines[i]) - 1)))
            c = data.draw(st.characters(min_codepoint=0, max_codepoint=255))
            lines[i] = lines[i][:j] + c + lines[i][j + 1:]
        elif op == "truncate":
            lines = lines[: i + 1]
            lines[-1] = lines[-1][: data.draw(st.integers(0, len(lines[-1])))]
        elif op == "swap" and len(lines) > 2:
            j = data.draw(st.integers(0, len(lines) - 1))
            lines[i], lines[j] = lines[j], lines[i]
    blob = "\n".join(lines).encode("latin-1", errors="replace")
    try:
        blocks, _ = parse_program(blob, "f.nc", "f")
    except InputError as e:
        assert str(e).startswith("f.nc:")
        return
    schemas.check("blocks", blocks)
    passes = split_blocks(blocks, PARAMS)
    schemas.check("passes", passes)
    t = passes.column("t_end_s").to_numpy()
    assert np.isfinite(t).all() and (np.diff(t) >= 0).all()
