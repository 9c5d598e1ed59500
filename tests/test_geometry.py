"""Tool envelopes, swept volumes and workpieces against closed forms and brute force."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

from stages import InputError
from stages.geometry.cutter import Cutter
from stages.geometry.envelope import envelope_mesh
from stages.geometry.sweeps import chain_joints, ordered_sweep_scene, sweep_bands, sweep_lowest_z, sweep_triangles
from stages.geometry.workpiece import DesignSurface, load_design_surface, load_workpiece
from stages.render import View, make_scene
from stages.render.cpu import CPURenderer

TOOLS = {
    "ball": {"type": "ball", "diameter_mm": 10.0, "stickout_mm": 20.0},
    "bull": {"type": "bull", "diameter_mm": 10.0, "corner_radius_mm": 2.0, "stickout_mm": 20.0},
    "flat": {"type": "flat", "diameter_mm": 10.0, "stickout_mm": 20.0},
}


def _profile_boundary(shape, n=200_000):
    """Dense samples of the closed (r, z) profile outline, written independently of the mesh."""
    R, rc, H = shape.radius_mm, shape.corner_mm, shape.stickout_mm
    t = np.linspace(0, 1, n)
    parts = [np.stack([t * (R - rc), 0 * t], 1)]                          # bottom
    a = t * np.pi / 2
    parts.append(np.stack([R - rc + rc * np.sin(a), rc - rc * np.cos(a)], 1))  # corner arc
    parts.append(np.stack([R + 0 * t, rc + t * (H - rc)], 1))             # side
    parts.append(np.stack([t * R, H + 0 * t], 1))                          # cap
    return np.concatenate(parts)


@pytest.mark.parametrize("kind", sorted(TOOLS))
@pytest.mark.parametrize("tol", [0.05, 0.005])
def test_envelope_within_tolerance_and_inside(kind, tol):
    shape = Cutter.from_params(TOOLS[kind])
    mesh = envelope_mesh(shape, tol)
    rng = np.random.default_rng(0)
    u = rng.random((len(mesh.tris), 4, 2))
    flip = u.sum(-1) > 1
    u[flip] = 1 - u[flip]
    pts = (mesh.tris[:, None, 0] * (1 - u.sum(-1))[..., None] + mesh.tris[:, None, 1] * u[..., :1]
           + mesh.tris[:, None, 2] * u[..., 1:]).reshape(-1, 3)
    rz = np.stack([np.hypot(pts[:, 0], pts[:, 1]), pts[:, 2]], 1)
    dist, _ = cKDTree(_profile_boundary(shape)).query(rz)
    assert dist.max() <= tol, f"{kind}: mesh deviates {dist.max():.4g} mm > tol {tol}"
    # inscribed: never outside the true envelope (the radius at that height)
    assert np.all(rz[:, 0] <= shape.profile_radius(np.clip(rz[:, 1], 0, None)) + 1e-9)
    # normals point outward
    c = mesh.tris.mean(1)
    n = mesh.face_normals[mesh.face_of_tri]
    axis_pt = np.stack([0 * c[:, 0], 0 * c[:, 0], np.clip(c[:, 2], shape.corner_mm, shape.stickout_mm - 1)], 1)
    assert np.all(np.einsum("ij,ij->i", n, c - axis_pt) > -1e-9)


@pytest.mark.parametrize("kind", sorted(TOOLS))
def test_sweep_from_below_matches_brute_force(kind):
    """Rendered lowest surface of a sweep = lower envelope of densely sampled tool positions."""
    shape = Cutter.from_params(TOOLS[kind])
    tol = 0.01
    mesh = envelope_mesh(shape, tol)
    p0, p1 = np.array([-3.0, -2.0, 0.0]), np.array([4.0, 3.0, -1.5])   # inclined, diagonal
    tris, q, _ = sweep_triangles(mesh, p0[None], p1[None], view_dir=(0, 0, 1))
    view = View((0.5, 0.5, 0.0), (0, 0, 1.0), (0, 1.0, 0), 22, 22, 10, -10, 30)
    im = CPURenderer().render([view], make_scene(tris, 0, 1, b=q))[0]
    rows, cols = np.nonzero(im.id >= 0)
    xy = view.pixel_points(rows, cols, 0 * rows)[:, :2]
    ref = sweep_lowest_z(shape, p0, p1, xy, n_t=4001)
    # compare where the true surface is at most 60° steep (vertical error <= tol / cos 60°)
    zr = np.full(im.id.shape, np.nan)
    zr[rows, cols] = ref
    gy, gx = np.gradient(zr, 1 / view.px_per_mm)
    gentle = (np.hypot(gx, gy) <= np.tan(np.radians(60)))[rows, cols]
    err = im.depth[rows, cols] - ref
    assert gentle.sum() > 10000
    assert err[gentle].max() <= 2 * tol + 1e-3      # the mesh is inside: never lower ...
    assert err[gentle].min() >= -1e-3               # ... than the true sweep
    # the footprint is right: every pixel whose centre the brute force covers is drawn
    allpix = view.pixel_points(*np.indices(im.id.shape).reshape(2, -1), 0)[:, :2]
    ref_all = sweep_lowest_z(shape, p0, p1, allpix, n_t=801).reshape(im.id.shape)
    inside = np.isfinite(ref_all)
    assert np.mean((im.id >= 0) == inside) > 0.995


def _turning_chain(n=14, chord=0.7, turn_deg=4.0, climb=0.05):
    """Chords turning by ``turn_deg`` each and climbing."""
    pts = [np.zeros(3)]
    for a in np.radians(turn_deg * np.arange(n)):
        pts.append(pts[-1] + [chord * np.cos(a), chord * np.sin(a), climb])
    pts = np.array(pts)
    return pts[:-1], pts[1:]


@pytest.mark.parametrize("turn_deg", [4.0, 40.0])
def test_turning_chain_from_below_matches_brute_force(turn_deg):
    """A chain whose joint copies are left out (all but the lune) renders the lower envelope of the
    whole motion: no hole at any joint (a ray through a missing lune sees through the sweep) and
    never above the true surface, on a smooth chain (CAM chords at 4°) and at sharp corners.
    Reference: densely sampled tool positions, segment by segment."""
    shape = Cutter.from_params(TOOLS["ball"])
    tol = 0.005
    mesh = envelope_mesh(shape, tol)
    p0, p1 = _turning_chain(n=14 if turn_deg < 10 else 6, chord=0.7 if turn_deg < 10 else 2.0, turn_deg=turn_deg)
    k = len(p0)
    drop0, drop1 = chain_joints(p0, p1, np.zeros(k))
    assert drop1[:-1].all() and drop0[1:].all()                     # every joint is drawn as its lune
    sc = ordered_sweep_scene(mesh, p0, p1, np.arange(k) + 1.0)
    view = View((4.5, 2.0, 0.0), (0, 0, 1.0), (0, 1.0, 0), 22, 18, 10, -10, 30)
    im = CPURenderer().render([view], sc)[0]
    allpix = view.pixel_points(*np.indices(im.id.shape).reshape(2, -1), 0)[:, :2]
    ref = np.min([sweep_lowest_z(shape, a, b, allpix, n_t=301) for a, b in zip(p0, p1)], axis=0)
    ref = ref.reshape(im.id.shape)
    inside = np.isfinite(ref)
    drawn = im.id >= 0
    # the footprint: no pixel inside the swept area is left empty (each hole would be a lune)
    assert inside.sum() > 12000 and np.mean(drawn[inside]) > 0.999
    gy, gx = np.gradient(np.where(inside, ref, np.nan), 1 / view.px_per_mm)
    gentle = inside & drawn & (np.hypot(gx, gy) <= np.tan(np.radians(60)))
    err = im.depth[gentle] - ref[gentle]
    assert gentle.sum() > 10000
    assert err.max() <= 2 * tol + 2e-3 and err.min() >= -2e-3
    # and the point of leaving the copies out: far fewer triangles than a full copy per joint
    full, _, _ = sweep_triangles(mesh, p0, p1, view_dir=(0, 0, 1.0))
    assert len(sc.tris) < 0.6 * len(full)


def test_bands_vertical_plunge_and_zero_length():
    mesh = envelope_mesh(Cutter.from_params(TOOLS["ball"]), 0.05)
    t, q, o, _ = sweep_bands(mesh, [[0, 0, 5.0], [1, 1, 1.0]], [[0, 0, 0.0], [1, 1, 1.0]])
    assert len(t) > 0 and set(np.unique(o)) == {0}            # zero-length pass: no band
    # plunge: bands lie on the cylinder r = R (silhouette = equator)
    r = np.hypot(t[..., 0], t[..., 1])
    assert np.allclose(r, 5.0, atol=1e-9)


def test_tool_params_and_workpieces(tmp_path):
    with pytest.raises(InputError, match="corner_radius_mm"):
        Cutter.from_params({"type": "bull", "diameter_mm": 10, "corner_radius_mm": 6})
    with pytest.raises(InputError, match="tool.type"):
        Cutter.from_params({"type": "drill", "diameter_mm": 10})
    box = load_workpiece({"box": [0, 0, -5, 10, 20, 0]})
    assert np.allclose(box.bounds, [[0, 0, -5], [10, 20, 0]])
    # outward normals: the top face points up
    top = box.tris[:, :, 2].min(1) > -1e-9
    assert np.all(box.normals[top, 2] > 0.99)
    import trimesh
    path = tmp_path / "s.stl"
    trimesh.creation.box(bounds=[[0, 0, -5], [10, 20, 0]]).export(path)
    assert np.allclose(load_workpiece(str(path)).bounds, box.bounds)
    with pytest.raises(InputError, match="not found"):
        load_workpiece(str(tmp_path / "missing.stl"))
    with pytest.raises(InputError, match="stock"):
        load_workpiece(None)


def test_design_surface_distance_matches_brute_force():
    import trimesh
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=5.0)
    mesh.apply_translation([1.0, -2.0, 0.5])
    ds = DesignSurface(mesh, spacing_mm=0.2)
    rng = np.random.default_rng(3)
    p, f = trimesh.sample.sample_surface(mesh, 400, seed=4)
    q = p + rng.uniform(-0.5, 1.0, len(p))[:, None] * mesh.face_normals[f]
    tris = mesh.triangles
    ref = np.array([np.linalg.norm(trimesh.triangles.closest_point(tris, np.repeat(x[None], len(tris), 0)) - x,
                                   axis=1).min() for x in q])
    d = ds.distance(q)
    assert np.all(d >= ref - 1e-9)                       # never under the true distance
    near = ref < 0.2                                      # within a sample spacing
    assert near.sum() > 50 and np.max((d - ref)[near]) < 0.01
    assert np.median((d - ref)[near]) < 1e-9              # mostly the exact face
    assert np.max(d - ref) < 0.05
    offset = rng.uniform(-0.5, 1.0, len(p))                        # signed: inside the sphere < 0
    q = p + offset[:, None] * mesh.face_normals[f]
    sd = ds.signed_distance(q)
    clear = np.abs(offset) > 0.02
    assert np.array_equal(np.sign(sd[clear]), np.sign(offset[clear]))
    assert np.allclose(np.abs(sd), ds.distance(q))


def test_design_surface_load_errors(tmp_path):
    assert load_design_surface(None) is None
    with pytest.raises(InputError, match="not found"):
        load_design_surface(tmp_path / "missing.stl")
    bad = tmp_path / "bad.stl"
    bad.write_text("solid x\nthis is not an stl\n")
    with pytest.raises(InputError, match="bad.stl"):
        load_design_surface(bad)


@pytest.mark.parametrize("kind,rc", [("ball", 3.0), ("bull", 1.0), ("flat", 0.0)])
def test_tool_clearance_matches_a_dense_sample_of_the_body(kind, rc):
    """Distance and direction from the tool body against the nearest of ~200,000 points sampled on
    the body's surface (profile swept round the axis, flat end disk, shank to 20 mm)."""
    shape = Cutter(kind, 3.0, rc, 40.0)
    q = np.linspace(0, np.pi / 2, 200)
    prof = [np.stack([(3.0 - rc) + rc * np.sin(q), rc * (1 - np.cos(q))], 1)]
    prof.append(np.stack([np.full(200, 3.0), np.linspace(rc, 20.0, 200)], 1))
    prof.append(np.stack([np.linspace(0, 3.0 - rc, 100), np.zeros(100)], 1))
    prof = np.vstack(prof)
    th = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    body = np.stack([np.outer(prof[:, 0], np.cos(th)).ravel(), np.outer(prof[:, 0], np.sin(th)).ravel(),
                     np.repeat(prof[:, 1], th.size)], 1)
    rng = np.random.default_rng(3)
    pts = rng.uniform([-6, -6, -3], [6, 6, 15], (400, 3))
    d, u = shape.clearance(pts)
    dist, idx = cKDTree(body).query(pts)
    outside = d > 0.05
    np.testing.assert_allclose(d[outside], dist[outside], atol=0.03)
    # the direction points from the nearest body point to the point (a millimetre away, where the
    # sample's spacing blurs it by less than a few degrees)
    far = d > 1.0
    ref = (pts[far] - body[idx[far]]) / dist[far, None]
    assert np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", ref, u[far]), -1, 1))).max() < 4.0
    # inside the body: negative
    inside = (np.hypot(pts[:, 0], pts[:, 1]) < shape.profile_radius(np.clip(pts[:, 2], 0, None)) - 0.05) & (pts[:, 2] > 0.05)
    assert (d[inside] < 0).all() and inside.sum() > 20
