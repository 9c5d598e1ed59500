"""``pipeline tool-wear`` (issue 6 deliver 2): wear per contact angle with the job's cut length,
as a Parquet table analysts query with DuckDB.

References are built here: a known wear land added to the shipped measured profile, and cut
lengths summed from the geometry of a program written in the test.
"""
from __future__ import annotations

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import duckdb
import yaml
from click.testing import CliRunner

import schemas
from pipeline.cli import main

PROFILE = "data_samples/tools/t1_profile_measured.csv"


def known_wear_um(q):
    """2.5 µm wear land centred at 60° plus 1 µm tip rounding fading out by 20°."""
    q = np.asarray(q, float)
    return 2.5 * np.exp(-0.5 * ((q - 60.0) / 8.0) ** 2) + np.clip(1.0 - q / 20.0, 0.0, None)


def _profiles(tmp_path):
    before = pd.read_csv(PROFILE)
    after = before.copy()
    after["error_um"] = before["error_um"] + known_wear_um(before["contact_deg"])
    b, a = tmp_path / "before.csv", tmp_path / "after.csv"
    before.to_csv(b, index=False, float_format="%.6f")
    after.to_csv(a, index=False, float_format="%.6f")
    return b, a


def cli(*args):
    r = CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)
    return r.exit_code, r.output


def test_wear_table_with_a_given_cut_length_queryable_with_duckdb(tmp_path):
    b, a = _profiles(tmp_path)
    out = tmp_path / "wear.parquet"
    code, text = cli("tool-wear", "--before", b, "--after", a, "--cut-length-m", 120.0, "--tool-id", "T1-D10",
                     "--out", out)
    assert code == 0, text
    assert "largest wear +2.5" in text and "120.000 m (given)" in text
    schemas.check("tool_wear", pq.read_table(out))
    rows = duckdb.sql(f"select contact_deg, wear_um, wear_rate_um_per_m, cut_length_m, tool_id "
                      f"from read_parquet('{out}') where contact_deg in (0, 10, 45, 60, 85) order by contact_deg").fetchall()
    assert [r[0] for r in rows] == [0.0, 10.0, 45.0, 60.0, 85.0]
    for q, w, rate, length, tool in rows:
        assert abs(w - known_wear_um(q)) < 2e-6          # CSVs written with 6 decimals
        assert abs(rate - known_wear_um(q) / 120.0) < 1e-7 and length == 120.0 and tool == "T1-D10"
    n = duckdb.sql(f"select count(*) from read_parquet('{out}')").fetchall()[0][0]
    assert n == 901                                      # 0–90° in 0.1° steps


PROGRAM = b"""%
O4001 (WEAR JOB)
G90 G17 G21
T1 M6
S8000 M3
G0 X0. Y0. Z5.
G1 Z-1. F300
G1 X30. F1500
G1 Y0.6
G1 X0.
G2 X0. Y10.6 I0. J5.
G0 Z5.
M30
%
"""
# feed moves: plunge 6 mm, 30, 0.6, 30, half circle of radius 5 (π·5) = 66.6 + 5π mm


def test_wear_rate_from_a_run_and_bad_inputs(tmp_path):
    b, a = _profiles(tmp_path)
    (tmp_path / "nc").mkdir()
    (tmp_path / "nc" / "job.nc").write_bytes(PROGRAM)
    wf = {"name": "wear", "programs": "nc/*.nc", "stock": {"box": [-5, -5, -5, 40, 20, 0]},
          "tool": {"type": "ball", "diameter_mm": 10, "flutes": 2},
          "material": {"name": "FCD550", "ktc": 2000, "krc": 700, "kac": 300}, "output": "run", "until": "split"}
    (tmp_path / "wf.yaml").write_text(yaml.safe_dump(wf))
    code, text = cli("run", tmp_path / "wf.yaml", "--workers", "1", "-q")
    assert code == 0, text
    run = tmp_path / "run"
    feed_mm = 6.0 + 30.0 + 0.6 + 30.0 + np.pi * 5.0
    out = tmp_path / "w.parquet"
    code, text = cli("tool-wear", "--before", b, "--after", a, "--run", run, "--out", out)
    assert code == 0, text
    t = pq.read_table(out).to_pandas()
    assert (t.cut_length_source == "feed_moves").all()
    assert abs(t.cut_length_m.iloc[0] - feed_mm / 1000.0) < 2e-6        # arc chords within 1 µm
    assert list(t.programs.iloc[0]) == ["job"] and t.run.iloc[0] == str(run.resolve())
    i60 = int(np.argmin(np.abs(t.contact_deg - 60.0)))
    assert abs(t.wear_rate_um_per_m.iloc[i60] - 2.5 / (feed_mm / 1000.0)) < 1e-3

    # with a cut_filter table (the render stages ran): only the cutting passes count
    passes = pq.read_table(run / "tables" / "passes").to_pandas()
    length = np.sqrt(sum((passes[f"{c}1_mm"] - passes[f"{c}0_mm"]) ** 2 for c in "xyz"))
    cutting = (passes.motion != 0) & (passes.y0_mm < 0.3) & (passes.y1_mm < 0.3) & (passes.z0_mm < -0.5)  # X0→X30
    cf = pa.table({"program_id": passes.program_id, "pass_id": passes.pass_id, "is_cutting": cutting.to_numpy()})
    for c in schemas.get("cut_filter").names:
        if c not in cf.column_names:
            cf = cf.append_column(c, pa.nulls(cf.num_rows, schemas.get("cut_filter").field(c).type))
    (run / "tables" / "cut_filter").mkdir()
    pq.write_table(schemas.check("cut_filter", cf), run / "tables" / "cut_filter" / "job.parquet")
    code, text = cli("tool-wear", "--before", b, "--after", a, "--run", run, "--out", out)
    assert code == 0, text
    t = pq.read_table(out).to_pandas()
    assert (t.cut_length_source == "cut_filter").all()
    assert abs(t.cut_length_m.iloc[0] - 0.030) < 1e-9 and abs(length[cutting].sum() - 30.0) < 1e-9

    # bad inputs: a clear error naming the file or option, exit 2, nothing written
    bad = tmp_path / "bad.csv"
    bad.write_text("contact_deg,err\n0,1\n90,2\n")
    ragged = tmp_path / "ragged.csv"
    ragged.write_text("contact_deg,error_um\n0,1\n45,abc\n90,2\n")
    short = tmp_path / "short.csv"
    short.write_text("contact_deg,error_um\n0,1\n45,2\n")
    cases = [(("--before", bad, "--after", a, "--cut-length-m", 1), "bad.csv: column error_um missing"),
             (("--before", ragged, "--after", a, "--cut-length-m", 1), "ragged.csv:3: error_um is not a finite number"),
             (("--before", short, "--after", a, "--cut-length-m", 1), "short.csv: contact_deg covers 0.0–45.0°"),
             (("--before", tmp_path / "none.csv", "--after", a, "--cut-length-m", 1), "none.csv: no such profile file"),
             (("--before", b, "--after", a, "--cut-length-m", -3), "--cut-length-m -3.0: must be a positive"),
             (("--before", b, "--after", a), "give --run RUN_DIR or --cut-length-m"),
             (("--before", b, "--after", a, "--run", run, "--cut-length-m", 1), "either --cut-length-m or --run"),
             (("--before", b, "--after", a, "--run", tmp_path), "no tables/passes"),
             (("--before", b, "--after", a, "--run", run, "--program", "nope"), "program(s) nope not in this run")]
    for args, msg in cases:
        target = tmp_path / "never.parquet"
        code, text = cli("tool-wear", *args, "--out", target)
        assert code == 2 and msg in text, (args, text)
        assert not target.exists() and not list(tmp_path.glob(".never.parquet*"))
