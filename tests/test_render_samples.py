"""Issue 3 on the bundled samples: gl and cpu back ends agree on the sample mould.

Same cutting passes over the whole finishing program (one ordered scan), and on a window of it the
same predicted passes with generating points whose contact angle q agrees within 0.2° (the issue's
figure) and which are found for (almost) every predicted pass, walls included (view correction).
"""
from pathlib import Path

import numpy as np
import pytest

from stages import cut_filter, parse, split
from stages.scan import generating as scan_generating
from stages.geometry.cutter import Cutter
from stages.geometry.passes import pass_geometry
from stages.geometry.workpiece import load_design_surface, load_workpiece
from stages.render import make_renderer

SAMPLES = Path(__file__).resolve().parents[1] / "data_samples"
TOOL = dict(type="ball", diameter_mm=10, flutes=2, helix_deg=30, stickout_mm=40)
SPLIT = {"split": {"chord_tol_mm": 0.001, "max_pass_mm": 5.0, "merge_max_mm": 0.5},
         "machine": {"rapid_mm_min": 30000}, "tool": TOOL}


def _gl():
    try:
        return make_renderer("gl")
    except Exception:
        pytest.skip("gl back end unavailable (no EGL context)")


@pytest.fixture(scope="module")
def sample():
    path = SAMPLES / "nc" / "mould_finish_t1.nc"
    p = parse.run({"program_file": {"path": str(path), "program_id": "finish", "sha256": ""}}, {})
    passes = split.run(p, SPLIT)["passes"]
    return passes, load_workpiece(str(SAMPLES / "models" / "semi.stl"))


def test_gl_and_cpu_find_the_same_cutting_passes_on_the_sample_program(sample):
    passes, wp = sample
    shape, pg = Cutter.from_params(TOOL), pass_geometry(passes, TOOL)
    res = {b: cut_filter.cut_filter(pg, shape, wp, r, 20.0) for b, r in
           (("gl", _gl()), ("cpu", make_renderer("cpu")))}
    g, c = res["gl"], res["cpu"]
    assert g["is_cutting"].sum() > 0.8 * len(pg.pass_id)            # a finishing raster mostly cuts
    assert np.array_equal(g["is_cutting"], c["is_cutting"])
    both = g["is_cutting"]
    # prediction points: the same position along the pass up to a pixel's worth of cut pixels
    assert np.nanpercentile(np.abs(g["pred_t"] - c["pred_t"])[both], 99) < 0.05


def test_gl_and_cpu_generating_points_agree_on_a_sample_window(sample):
    passes, wp = sample
    win = passes.slice(1500, 150)                 # a raster row over the pocket rim and wall
    shape, pg = Cutter.from_params(TOOL), pass_geometry(win, TOOL)
    out = {}
    for b, r in (("gl", _gl()), ("cpu", make_renderer("cpu"))):
        cf = cut_filter.cut_filter(pg, shape, wp, r, 20.0)
        q = np.where(cf["surface_px"] > 0, cf["surface_max_contact_deg"], cf["cut_max_contact_deg"])
        idx = np.nonzero(cf["is_cutting"] & (np.nan_to_num(q, nan=-1.0) >= 45.0))[0]
        tips = np.stack([cf["pred_x_mm"], cf["pred_y_mm"], cf["pred_z_mm"]], 1)[idx]
        out[b] = (idx, scan_generating.generating(pg, shape, wp, r, 20.0, idx, tips, 2)[0])
    (ig, g), (ic, c) = out["gl"], out["cpu"]
    assert len(ig) >= 10 and np.array_equal(ig, ic)
    assert list(g["view"]) == list(c["view"])
    found = g["view"] != "none"
    assert found.mean() >= 0.9                    # steep walls are found through the normal view
    assert (g["view"] == "normal").any()
    assert np.max(np.abs(g["contact_deg"] - c["contact_deg"])[found]) <= 0.2
    dphi = np.abs((g["rotation_deg"] - c["rotation_deg"] + 180.0) % 360.0 - 180.0)[found]
    assert np.max(dphi) <= 1.0


def _nearest_face(mesh, points):
    """Closest point and face normal on ``mesh`` for each point, by brute force over every face."""
    import trimesh
    tris = mesh.triangles
    out = []
    for x in np.asarray(points, float):
        cp = trimesh.triangles.closest_point(tris, np.repeat(x[None], len(tris), 0))
        d = np.linalg.norm(cp - x, axis=1)
        out.append((float(d.min()), mesh.face_normals[int(np.argmin(d))]))
    return out


def test_generating_point_on_the_design_surface_in_a_pocket_corner(sample):
    """Passes down the pocket walls next to a corner ride over the rest material the
    semi-finishing left on the wall parallel to X (data_samples/README.md). Without the design
    model their generating points lay on that rest material, 1.6-1.7 mm off the model and 45° off
    the wall each pass finishes (the virtual machine's probe points on those walls face ±X); with
    it, they lie on the model, along its face normal there."""
    import trimesh
    passes, wp = sample
    shape, pg = Cutter.from_params(TOOL), pass_geometry(passes, TOOL)
    r = _gl()
    cf = cut_filter.cut_filter(pg, shape, wp, r, 20.0)
    want = [4650, 4675, 4821, 4834]
    idx = np.array([int(np.flatnonzero(pg.pass_id == w)[0]) for w in want])
    assert cf["is_cutting"][idx].all()
    tips = np.stack([cf["pred_x_mm"], cf["pred_y_mm"], cf["pred_z_mm"]], 1)[idx]
    nominal = SAMPLES / "models" / "mould.stl"
    mesh = trimesh.load(str(nominal), force="mesh")
    engaged = {}
    for design, on_model in ((None, False), (load_design_surface(str(nominal)), True)):
        g, eng = scan_generating.generating(pg, shape, wp, r, 20.0, idx, tips, 2, design=design)
        engaged[on_model] = [e[0] for e in eng]
        c = np.stack([g["gen_x_mm"], g["gen_y_mm"], g["gen_z_mm"]], 1)
        n = np.stack([g["nx"], g["ny"], g["nz"]], 1)
        assert np.isfinite(c).all()
        for (dist, fn), nk in zip(_nearest_face(mesh, c), n):
            ang = np.degrees(np.arccos(np.clip(fn @ nk, -1, 1)))
            if on_model:
                assert dist < 0.1 and ang < 10.0, (dist, ang)
            else:
                assert dist > 0.3, dist
    # the engagement stays that of everything the pass cuts: read along the design wall's normal,
    # the rest material on the wall across lay edge-on and most of it was lost (4821: -89 µm
    # predicted where the virtual machine leaves +73 µm)
    for a, b in zip(engaged[False], engaged[True]):
        n_z = max(len(a), len(b))
        pad = lambda E: np.vstack([E, np.zeros((n_z - len(E), E.shape[1]), bool)])  # noqa: E731
        assert a.sum() > 1000 and np.sum(pad(a) ^ pad(b)) < 0.05 * a.sum()
