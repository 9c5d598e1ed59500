"""Issue 4 on the seed's cylinder benchmark through the real chain: render → forces → deflection → errors.

Seed 000 Fig. 19: the predicted error is small near the tool tip and grows toward the wall. And a
tool profile table with a known dent moves the prediction by exactly that dent at that angle (claim 2).
"""
from __future__ import annotations

import numpy as np
import pytest

from stages import deflection, errors, forces, scan
from tests.cylinder_case import TOOL, cylinder_case

MATERIAL = {"name": "FCD550", "ktc": 2000.0, "krc": 700.0, "kac": 300.0, "kte": 20.0, "kre": 15.0, "kae": 5.0}
MACHINE = {"rapid_mm_min": 30000.0, "frf": {"x": [{"fn_hz": 900.0, "zeta": 0.03, "k_n_per_um": 2.0}],
                                             "y": [{"fn_hz": 900.0, "zeta": 0.03, "k_n_per_um": 2.0}], "table": None}}


@pytest.fixture(scope="module")
def chain(tmp_path_factory):
    passes, stock, q_ref, _, _ = cylinder_case()  # the Fig. 16 set-up: 51 levels 0–89°
    path = str(tmp_path_factory.mktemp("cyl") / "stock.stl")
    stock.export(path)
    params = {"tool": TOOL, "render": {"backend": "auto", "px_per_mm": 20}, "prune": {"min_contact_deg": 0.0},
              "material": MATERIAL, "machine": MACHINE}
    g = scan.run({"passes": passes, "stock": path}, params)
    f = forces.run({"passes": passes, "generating": g["generating"], "engagement": g["engagement"]}, params)["forces"]
    d = deflection.run({"forces": f}, params)["deflection"]
    return passes, g["generating"], d, params, q_ref, tmp_path_factory.mktemp("prof")


def _errors(chain, profile=None):
    passes, gen, d, params, q_ref, _ = chain
    p = dict(params, tool=dict(TOOL, profile=profile))
    e = errors.run({"passes": passes, "generating": gen, "deflection": d}, p)["errors"].to_pandas()
    e["q_ref"] = q_ref[e.pass_id.to_numpy()]
    return e[np.isfinite(e.q_ref)].sort_values("q_ref")


def test_error_small_at_the_tip_growing_toward_the_wall(chain):
    e = _errors(chain)
    assert len(e) == 51  # every level 0–89° has a prediction
    tip = e[e.q_ref <= 5].err_um.abs()
    wall = e[e.q_ref >= 60].err_um.abs()
    print("\nq_deg  err_um\n" + "\n".join(f"{q:5.1f} {v:+7.2f}" for q, v in zip(e.q_ref, e.err_um)))
    assert abs(e.err_um.iloc[0]) < 0.5                       # at the tip the flank does not cut
    assert wall.mean() > 5 * max(tip.mean(), 0.1)           # Fig. 19: small at the tip, large at the wall
    # the zigzag alternates up and down milling: two branches, each rising from the tip to the wall
    for branch in (e.iloc[1::2], e.iloc[2::2]):
        b = branch.err_um.abs().to_numpy()
        assert b[:2].mean() < b[-10:].mean()
    # deflection pushes the tool away from the wall: material is left (positive, DESIGN §5)
    assert (e[e.q_ref >= 60].err_um > 0).all()


def test_profile_dent_moves_prediction_by_the_dent_at_that_angle(chain):
    base = _errors(chain)
    q0 = float(base.contact_deg.iloc[25])  # a mid-level's generating contact angle
    q = np.round(np.arange(0, 90.05, 0.1), 1)
    dent = np.where(np.abs(q - q0) <= 1.0, 3.0, np.where(np.abs(q - q0) <= 2.0, 3.0 * (2.0 - np.abs(q - q0)), 0.0))
    path = chain[5] / "dent.csv"
    np.savetxt(path, np.column_stack([q, dent]), delimiter=",", header="contact_deg,error_um", comments="", fmt="%.4f")
    moved = _errors(chain, str(path))
    diff = (moved.set_index("pass_id").err_um - base.set_index("pass_id").err_um)
    qq = base.set_index("pass_id").contact_deg
    np.testing.assert_allclose(diff[np.abs(qq - q0) <= 0.9], 3.0, atol=1e-9)
    np.testing.assert_allclose(diff[np.abs(qq - q0) > 2.1], 0.0, atol=1e-9)
