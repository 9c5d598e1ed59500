"""Measurement files (DESIGN §6 ``measurements``): the reader's mappings, units and errors naming
file, line and key; rejected rows listed; a file written and read back; points off the part
rejected by the association.
"""
from __future__ import annotations

import numpy as np
import pyarrow.parquet as pq
import pytest

from stages import InputError
from stages.gap.associate import associate
from stages.gap.measurements import measurement_table, points_and_normals, read_measurements, write_measurements
from tests.gap_helpers import TOOL, fresh_rng, sample


def _csv(tmp_path, text, name="m.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_reader_mapping_units_nan_and_bad_normal_listed(tmp_path):
    p = _csv(tmp_path, "PT;PX;PY;PZ;VI;VJ;VK;DEVI\n"
                       "1;1.0;2.0;3.0;0;0;1;0.002\n"
                       "2;1.0;2.0;nan;0;0;1;0.001\n"
                       "3;1.0;2.0;3.0;0;0;1.2;0.001\n"
                       "4;0.5;0.5;0.5;0.6;0;0.8;-0.003\n")
    cols = {"point_id": "PT", "x_mm": "PX", "y_mm": "PY", "z_mm": "PZ", "nx": "VI", "ny": "VJ", "nz": "VK",
            "err_um": "DEVI"}
    tab, rej, lines = read_measurements(p, cols, length_unit="inch", deviation_unit="mm")
    assert tab.column("point_id").to_pylist() == [1, 4]
    assert tab.column("x_mm").to_pylist() == pytest.approx([25.4, 12.7])
    assert tab.column("err_um").to_pylist() == pytest.approx([2.0, -3.0])
    reasons = {pid: (line, why) for pid, line, why in rej.rows}
    assert reasons[2][0] == 3 and "NaN" in reasons[2][1]
    assert reasons[3][0] == 4 and "normal length 1.2" in reasons[3][1]


@pytest.mark.parametrize("text, mapping, needle", [
    ("id,x,y,z,i,j,k,dev\n1,0,0,0,0,0,1,1.5\n1,1,0,0,0,0,1,2.0\n", {}, "duplicated point id 1"),
    ("id,x,y,z,i,j,k\n1,0,0,0,0,0,1\n", {}, "no column for ['err_um']"),
    ("id,x,y,z,i,j,k,dev\n1,0,0,0,0,0,1,0.002\n2,0,1,0,0,0,1,-0.001\n", {}, "looks like mm"),
    ("id,x,y,z,i,j,k,dev\n1,0,0,0,0,0,1,abc\n", {}, ":2: column 'dev'"),
    ("id,x,y,z,i,j,k,dev\n1,0,0,0,0,0,1,1\n", {"err_um": "Deviation"}, "measurements.columns.err_um"),
    ("id,x,y,z,i,j,k,dev [mm]\n1,0,0,0,0,0,1,0.001\n", {"deviation_unit": "um"}, "says mm"),
])
def test_reader_errors_name_file_line_and_key(tmp_path, text, mapping, needle):
    p = _csv(tmp_path, text)
    dev_unit = mapping.pop("deviation_unit", None)
    with pytest.raises(InputError) as e:
        read_measurements(p, mapping, deviation_unit=dev_unit)
    assert needle in str(e.value) and str(p) in str(e.value)


def test_reader_parquet_and_off_part_points_rejected(tmp_path):
    passes, pts, nrm = sample()
    n = 60
    err = np.zeros(n)
    moved = pts[:n].copy()
    moved[5] += 1.0 * nrm[5]                     # 1 mm off the surface along its normal
    moved[7] += [0.0, 0.0, -0.5]                 # inside the part
    pq.write_table(measurement_table(np.arange(n), moved, nrm[:n], err), tmp_path / "m.parquet")
    back, rej, _ = read_measurements(tmp_path / "m.parquet")
    assert back.num_rows == n and len(rej) == 0
    F, rejected = associate(back, passes, None, TOOL)
    assert sorted(i for i, _ in rejected) == [5, 7]
    assert all("off the part" in why for _, why in rejected)
    assert len(F["point_id"]) == n - 2


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_written_measurements_read_back(tmp_path, suffix):
    """Random points, unit normals, deviations (±50 µm) and times written and read back: equal, the
    CSV within its printed decimals (5 for mm, 6 for normals, 4 for µm and s)."""
    seed, rng = fresh_rng()
    n = int(rng.integers(5, 200))
    pts = rng.uniform(-100.0, 100.0, (n, 3))
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    err, t = rng.uniform(-50.0, 50.0, n), rng.uniform(0.0, 1e3, n)
    ids = rng.permutation(10 * n)[:n]
    write_measurements(measurement_table(ids, pts, nrm, err, t), tmp_path / f"m{suffix}")
    back, rej, _ = read_measurements(tmp_path / f"m{suffix}")
    csv = suffix == ".csv"
    p2, n2 = points_and_normals(back)
    assert len(rej) == 0 and back.column("point_id").to_pylist() == ids.tolist(), f"seed {seed}"
    np.testing.assert_allclose(p2, pts, atol=5e-6 if csv else 0, err_msg=f"seed {seed}")
    np.testing.assert_allclose(n2, nrm, atol=2e-6 if csv else 1e-15, err_msg=f"seed {seed}")
    np.testing.assert_allclose(back.column("err_um").to_numpy(), err, atol=5e-5 if csv else 0,
                               err_msg=f"seed {seed}")
    np.testing.assert_allclose(back.column("t_s").to_numpy(), t, atol=5e-5 if csv else 0, err_msg=f"seed {seed}")
