"""Render back ends: closed-form depth/attributes, atlas isolation, gl == cpu, auto fallback."""
import os
import subprocess
import sys

import numpy as np
import pytest

from stages import InputError, render
from stages.geometry.cutter import Cutter
from stages.geometry.envelope import envelope_mesh
from stages.geometry.sweeps import sweep_triangles
from stages.render import Scene, View, make_scene
from stages.render.cpu import CPURenderer


def gl_or_skip():
    try:
        return render.make_renderer("gl")
    except Exception as e:  # no EGL here
        pytest.skip(f"gl back end unavailable: {e}")


def backends():
    return [CPURenderer(), gl_or_skip()]


def _plane_scene(window=0):
    # plane z = 0.3 x - 0.2 y + 1 over a square, attribute a = x, b = y (linear: exact)
    c = np.array([[-4, -4], [4, -4], [4, 4], [-4, 4]], float)
    z = 0.3 * c[:, 0] - 0.2 * c[:, 1] + 1
    v = np.column_stack([c, z])
    tris = np.stack([v[[0, 1, 2]], v[[0, 2, 3]]])
    return make_scene(tris, window, 7, a=tris[..., 0], b=tris[..., 1])


@pytest.mark.parametrize("name", ["cpu", "gl"])
def test_plane_depth_and_attributes_exact(name):
    r = CPURenderer() if name == "cpu" else gl_or_skip()
    view = View((0, 0, 0), (0, 0, 1.0), (0, 1.0, 0), 6, 5, 10, -5, 5)
    im = r.render([view], _plane_scene())[0]
    rows, cols = np.indices(im.id.shape)
    p = view.pixel_points(rows, cols, 0 * rows)
    assert np.all(im.id == 7)
    assert np.allclose(im.depth, 0.3 * p[..., 0] - 0.2 * p[..., 1] + 1, atol=2e-5)
    assert np.allclose(im.a, p[..., 0], atol=1e-4) and np.allclose(im.b, p[..., 1], atol=1e-4)


@pytest.mark.parametrize("name", ["cpu", "gl"])
def test_atlas_windows_do_not_leak_and_batches_split(name, monkeypatch):
    r = CPURenderer() if name == "cpu" else gl_or_skip()
    views = [View((0, 0, 0), (0, 0, 1.0), (0, 1.0, 0), 6, 5, 10, -5, 5) for _ in range(5)]
    # only windows 1 and 3 get the plane (which extends far beyond the window)
    sc = Scene.concat([_plane_scene(1), _plane_scene(3)])
    for atlas_px in (2048, 128):               # 128 px: several atlas draws
        monkeypatch.setattr(r, "atlas_px", atlas_px)
        ims = r.render(views, sc)
        assert [bool((im.id >= 0).any()) for im in ims] == [False, True, False, True, False]
        assert np.all(ims[1].id == 7) and np.all(ims[3].id == 7)


def test_depth_test_nearest_wins_and_bias():
    view = View((0, 0, 0), (0, 0, 1.0), (0, 1.0, 0), 4, 4, 10, -5, 5)
    sq = np.array([[-3, -3], [3, -3], [3, 3], [-3, 3]], float)

    def quad(z, ident, bias=0.0):
        v = np.column_stack([sq, np.full(4, z)])
        return make_scene(np.stack([v[[0, 1, 2]], v[[0, 2, 3]]]), 0, ident, bias=bias)
    for r in backends():
        assert np.all(r.render([view], Scene.concat([quad(1.0, 1), quad(0.5, 2)]))[0].id == 2)
        # a bias pushes a triangle back: 0.5 + 0.6 is behind 1.0
        assert np.all(r.render([view], Scene.concat([quad(1.0, 1), quad(0.5, 2, 0.6)]))[0].id == 1)


def test_gl_and_cpu_agree_on_tool_sweeps():
    gl = gl_or_skip()
    shape = Cutter.from_params({"type": "ball", "diameter_mm": 10.0, "stickout_mm": 20})
    mesh = envelope_mesh(shape, 0.01)
    rng = np.random.default_rng(1)
    p0 = rng.uniform(-5, 5, (12, 3)) * [1, 1, 0.2]
    p1 = p0 + rng.uniform(-4, 4, (12, 3)) * [1, 1, 0.2]
    views = [View((0, 0, 0), (0, 0, 1.0), (0, 1.0, 0), 20, 20, 20, -10, 30),
             View((1, 0, 0), (0.6, 0, 0.8), (0, 1.0, 0), 20, 20, 20, -10, 30)]
    tris, q, owner = sweep_triangles(mesh, p0, p1)
    sc = Scene.concat([make_scene(tris, w, owner + 1, b=q) for w in range(2)])
    for a, b in zip(CPURenderer().render(views, sc), gl.render(views, sc)):
        both = (a.id >= 0) & (b.id >= 0)
        assert np.mean(a.id == b.id) > 0.995
        assert np.percentile(np.abs(a.depth[both] - b.depth[both]), 99.9) < 1e-3
        assert np.percentile(np.abs(a.b[both] - b.b[both]), 99) < 0.05


def test_make_renderer_choices_and_auto_fallback():
    assert render.make_renderer("cpu").name == "cpu"
    with pytest.raises(InputError, match="render.backend"):
        render.make_renderer("vulkan")
    # a machine whose EGL finds no driver (glvnd's vendor list points nowhere): auto falls back to
    # the cpu back end and says why, gl refuses
    code = ("import logging; logging.basicConfig()\n"
            "from stages.render import make_renderer\n"
            "print('auto', make_renderer('auto').name)\n"
            "try:\n    make_renderer('gl')\nexcept RuntimeError as e:\n    print('gl refused:', e)\n")
    env = dict(os.environ, __EGL_VENDOR_LIBRARY_FILENAMES="/nonexistent.json")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert "auto cpu" in out.stdout, out.stderr
    assert "gl refused: cannot open a headless EGL context" in out.stdout
    assert "using the cpu back end" in out.stderr
