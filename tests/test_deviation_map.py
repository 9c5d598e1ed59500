"""The report's deviation map: errors carried from predicted passes onto the design model."""
from __future__ import annotations

import numpy as np
import pandas as pd
import trimesh
from hypothesis import given, settings, strategies as st

from pipeline import deviation_map as dm


def test_samples_follow_each_pass_through_its_generating_point():
    p = pd.DataFrame({"gen_x_mm": [1.0], "gen_y_mm": [0.0], "gen_z_mm": [-5.0], "nx": [0.0], "ny": [0.0], "nz": [2.0],
                      "err_um": [3.0], "x0_mm": [0.0], "y0_mm": [0.0], "z0_mm": [0.0],
                      "x1_mm": [2.0], "y1_mm": [0.0], "z1_mm": [0.0]})
    xyz, n, e = dm.surface_samples(p)
    assert np.allclose(xyz[[0, -1], 0], [0.0, 2.0]) and np.allclose(xyz[:, 1:], [0.0, -5.0])
    assert np.diff(xyz[:, 0]).max() <= dm.SAMPLE_MM + 1e-12 and np.allclose(n, [0, 0, 1]) and (e == 3.0).all()


@settings(max_examples=30, deadline=None)
@given(gx=st.floats(-20, 20), gy=st.floats(-20, 20), radius=st.floats(0.6, 2.0))
def test_a_linear_error_field_is_reproduced_within_its_gradient_times_the_radius(gx, gy, radius):
    # samples on a 0.25 mm grid of the plane z = 0 carry e = gx·x + gy·y; a vertex sees only
    # samples within the radius, so its inverse-distance mean is within |∇e|·radius of e(vertex)
    g = np.arange(-5, 5.001, 0.25)
    x, y = np.meshgrid(g, g)
    xyz = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)
    nrm = np.tile([0.0, 0.0, 1.0], (len(xyz), 1))
    err = gx * xyz[:, 0] + gy * xyz[:, 1]
    rng = np.random.default_rng(0)
    v = np.column_stack([rng.uniform(-3, 3, (200, 2)), np.zeros(200)])
    est = dm.vertex_errors(v, np.tile([0.0, 0.0, 1.0], (200, 1)), xyz, nrm, err, radius)
    assert np.all(np.abs(est - (gx * v[:, 0] + gy * v[:, 1])) <= np.hypot(gx, gy) * radius + 1e-9)


def test_no_error_beyond_the_radius_or_on_the_far_side_of_a_wall():
    xyz = np.array([[0.0, 0.0, 0.0]])
    nrm = np.array([[0.0, 0.0, 1.0]])
    v = np.array([[0.5, 0, 0], [3.0, 0, 0], [0.5, 0, 0]])
    vn = np.array([[0, 0, 1.0], [0, 0, 1.0], [0, 0, -1.0]])
    est = dm.vertex_errors(v, vn, xyz, nrm, np.array([7.0]), radius_mm=1.0)
    assert est[0] == 7.0 and np.isnan(est[1]) and np.isnan(est[2])


def test_refinement_keeps_the_surface_and_refines_only_near_the_samples():
    box = trimesh.creation.box(extents=(40.0, 20.0, 10.0))
    near = np.array([[0.0, 0.0, 5.0]])                   # on the top face
    fine = dm.refined_mesh(box, near, radius_mm=1.0)
    assert np.isclose(fine.area, box.area) and np.allclose(fine.bounds, box.bounds)
    top = fine.triangles_center[:, 2] > 4.999
    assert fine.edges_unique_length[np.isin(fine.edges_unique, fine.faces[top]).all(1)].max() <= dm.EDGE_MM + 1e-9
    bottom = fine.triangles_center[:, 2] < -4.999
    assert bottom.sum() == 2                                # far from the samples: as it was


def test_colour_scale_is_symmetric_and_grey_without_data():
    c = dm.colours(np.array([-10.0, 0.0, 10.0, np.nan, 50.0]), 10.0)
    assert c[0, 2] > c[0, 0] and c[2, 0] > c[2, 2]          # overcut blue, material left red
    assert np.allclose(c[1], c[1].mean(), atol=0.01)        # zero: neutral
    assert np.allclose(c[3], dm.GREY) and np.allclose(c[4], c[2])   # beyond the scale: clipped
