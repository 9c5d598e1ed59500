"""The prediction at measured points (``stages.gap.associate``): the deepest tooth passage of a
point's own pass and its neighbours', against the construction of a straight wall job whose passes
have known constant deflections.
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from stages.gap.associate import associate, predicted_at_points
from stages.gap.measurements import measurement_table
from tests.ncprograms import wall_program


@pytest.mark.parametrize("offset_um", [0.0, 3.0, 8.0])
def test_predicted_error_is_the_deepest_tooth_passage_of_the_neighbouring_passes(offset_um):
    """Deflection pushes A, B, C away from the wall by a constant 10, 30, 5 µm. A point swept by
    the tooth passages of neighbouring passes (within 1.5 revolutions = 0.15 mm of feed along the
    path) is left by the deepest of them: its own pass's error or a neighbour's error plus the
    neighbour's nominal stand-off from it, here the distance from the point to the ball at the
    neighbour's nearest end, hypot(δ, 5 mm + offset) − 5 mm (δ along the wall). Points farther than
    0.15 mm from another pass keep their own pass's error. Re-predicted with the deflection × 2 on
    a subset of the points, every error and stand-off term follows; the deflection part is the
    winning passage's error without its stand-off (the stand-off does not scale with the forces).

    Every neighbour here reaches the points only from one of its ends (the path is straight): the
    deflection cannot change at a vertex, so every point keeps its own pass's error."""
    R10 = 5.0
    off = offset_um * 1e-3
    passes = wall_program(offset_um)
    pid = passes.column("pass_id").to_numpy()
    x0, x1 = passes.column("x0_mm").to_numpy(), passes.column("x1_mm").to_numpy()
    cut = (passes.column("motion").to_numpy() == 1) & (passes.column("z0_mm").to_numpy() == 0) \
        & (passes.column("z1_mm").to_numpy() == 0)
    a = int(pid[cut & (x0 == 0) & (x1 == 10)][0])
    b = int(pid[cut & (x0 == 10) & (x1 == 10.05)][0])
    c = int(pid[cut & (x0 == 10.05) & (x1 == 20)][0])
    n_rot = 64

    def defl(k):
        return pa.table({"program_id": ["w"] * 3, "pass_id": pa.array([a, b, c], pa.int32()),
                         "rotation_deg": [list(np.arange(n_rot) * 360.0 / n_rot)] * 3,
                         "dx_um": [[0.0] * n_rot] * 3,
                         "dy_um": [[10.0 * k] * n_rot, [30.0 * k] * n_rot, [5.0 * k] * n_rot]})

    def want(k):
        """(error, deflection part) per point, from the construction."""
        ea, eb, ec = 10.0 * k, 30.0 * k, 5.0 * k
        return [(ea, ea)] * 7 + [(eb, eb)] + [(ec, ec)] * 6

    # on the wall at the ball's equator: six points mid A, one 0.01 mm before A's end, mid B, six mid C
    x = np.array([2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 9.99, 10.025, 13.0, 14.0, 15.0, 16.0, 17.0, 18.0])
    y = np.where(x > 10.05, -R10 + off, -R10)
    n = len(x)
    nrm = np.tile([0.0, 1.0, 0.0], (n, 1))
    meas = measurement_table(np.arange(n), np.stack([x, y, np.full(n, R10)], 1), nrm, np.zeros(n))
    tool = {"type": "ball", "diameter_mm": 10.0, "flutes": 2, "helix_deg": 0.0, "stickout_mm": 20.0,
            "runout_um": 0.0, "control_point": "tip"}
    F, rej = associate(meas, passes, None, tool, 0.05, defl(1.0))
    assert not rej
    got = dict(zip(F["point_id"].tolist(), F["predicted_um"].tolist()))
    got_d = dict(zip(F["point_id"].tolist(), F["pred_deflection_um"].tolist()))
    for i, (e, d) in enumerate(want(1.0)):
        assert got[i] == pytest.approx(e, abs=1e-6), i
        assert got_d[i] == pytest.approx(d, abs=1e-9), i
    np.testing.assert_allclose(F["residual_um"], -F["predicted_um"])
    # re-predicted with another deflection table on a subset of the points
    rows = np.zeros(n, bool)
    rows[np.isin(F["point_id"], [0, 6, 7, 13])] = True
    e2, d2, s2 = predicted_at_points(F, lambda prog: defl(2.0), tool, rows)
    w2 = want(2.0)
    np.testing.assert_allclose(e2, [w2[i][0] for i in F["point_id"][rows]], atol=1e-6)
    np.testing.assert_allclose(d2, [w2[i][1] for i in F["point_id"][rows]], atol=1e-9)
    np.testing.assert_allclose(s2, 0.0)
    # a runout e moves the largest flute out by e on every pass: every passage cuts e deeper (q = 90°)
    r3 = predicted_at_points(F, lambda prog: defl(1.0), dict(tool, runout_um=2.0), runout_part=True)[0]
    np.testing.assert_allclose(r3, -2.0, atol=1e-9)
