"""The layered windows of the per-pass views: stock W, earlier sweeps T1, later sweeps T2, the tool M
at the prediction point (seed 000 claim 1), and the closed-form strip of the pass's own path.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from stages.geometry.envelope import envelope_copies
from stages.geometry.passes import overlaps, window_xy_bounds
from stages.geometry.sweeps import segment_scene
from stages.geometry.workpiece import workpiece_scene
from stages.render import Scene, make_scene


ID_W, ID_T1, ID_T2, ID_M = 0, 1, 2, 3


N_LAYERS = 5
PASSES_PER_BATCH = 8          # view-correction windows per render


def segments_around(pg, cutting, s_p, f, win_lo, win_hi, bounds, gap):
    """Path pieces around path positions ``s_p`` (one per window), split at s_p - f and s_p + f.

    Returns three (window, a, b) segment lists: T1 far (path up to s_p - f - gap), T1 near
    (s_p - f - gap to s_p - f) and T2 far (from s_p + f + gap on).
    """
    ov = overlaps(win_lo, win_hi, bounds[:, 0], bounds[:, 1]) & cutting[None, :]
    w, j = np.nonzero(ov)
    L = pg.length[j]
    S = pg.s0[j]
    d = pg.p1[j] - pg.p0[j]
    Ls = np.where(L > 1e-12, L, 1.0)
    point = L <= 1e-12

    def piece(lo, hi):                      # part of each pass inside path interval [lo, hi]
        has = ((S < hi) & (S + L > lo)) | (point & (S >= lo) & (S <= hi))
        ta = np.clip((lo - S) / Ls, 0, 1)
        tb = np.clip((hi - S) / Ls, 0, 1)
        return (w[has], pg.p0[j][has] + ta[has, None] * d[has], pg.p0[j][has] + tb[has, None] * d[has])

    e1 = s_p[w] - f[w]
    e2 = s_p[w] + f[w]
    g = gap[w]
    return piece(-np.inf, e1 - g), piece(e1 - g, e1), piece(e2 + g, np.inf)


def layer_scene(views, pg, cutting, s_p, f, bounds, wp, mesh, m_tips, m_feed, coarse, gap,
                 material_only=False):
    """Scene of the layers (W, T1 far, T2 far, M, T1 near) for ``views``: layer k of view i is
    window k*n+i. With ``material_only`` only W, T1 far and T1 near (the material before path
    position s_p - f) are drawn; windows of the other layers stay empty.

    Sweep ends within one tool radius of the window's prediction point use the fine mesh: only
    their copies can cross M near the surface it leaves (bands take the finer of their two
    ends); the others use the coarse mesh.
    """
    n = len(views)
    R = mesh.shape.radius_mm

    def fine(w, a, b):
        return np.stack([np.linalg.norm(a - m_tips[w], axis=1) < R,
                         np.linalg.norm(b - m_tips[w], axis=1) < R], axis=1)

    d = np.asarray(views[0].view_dir, float)
    # a sweep can only hide M where it is nearer than M: M lies within R/4 behind the window
    # centre over an R-wide window, so sweeps are gathered over that depth only (the stock,
    # farther away by its allowance, keeps the whole range)
    lo, hi = window_xy_bounds([replace(v, far_mm=min(v.far_mm, 0.25 * R)) for v in views])
    segs = segments_around(pg, cutting, s_p, f, lo, hi, bounds, gap)
    (w1, a1, b1), (w4, a4, b4), (w2, a2, b2) = segs
    wb = (np.tile(lo, (N_LAYERS, 1)), np.tile(hi, (N_LAYERS, 1)))
    parts = [workpiece_scene(wp, views, ID_W)]
    # all views of a batch share the view direction only when seen from below; oblique views
    # are grouped one per scene part (culling depends on the direction)
    per_view = not all(np.allclose(v.view_dir, d) for v in views)
    drawn = ((1, (w1, a1, b1, ID_T1)), (4, (w4, a4, b4, ID_T1)))
    if not material_only:
        drawn += ((2, (w2, a2, b2, ID_T2)),)
    for layer, (w, a, b, ident) in drawn:
        if per_view:
            for i, v in enumerate(views):
                s = w == i
                parts.append(segment_scene(mesh, a[s], b[s], w[s] + layer * n, np.full(s.sum(), ident),
                                               v.view_dir, window_bounds=wb, coarse_mesh=coarse,
                                               fine_ends=fine(w[s], a[s], b[s])))
        else:
            parts.append(segment_scene(mesh, a, b, w + layer * n, np.full(len(w), ident), d,
                                           window_bounds=wb, coarse_mesh=coarse,
                                           fine_ends=fine(w, a, b)))
    for i, v in enumerate(views if not material_only else ()):
        tris, q, phi, _ = envelope_copies(mesh, m_tips[i:i + 1], feed_deg=m_feed[i:i + 1],
                                              view_dir=v.view_dir)
        parts.append(scene(tris, 3 * n + i, ID_M, phi, q))
    return Scene.concat(parts)


def scene(tris, window, ident, a, b):
    return make_scene(tris, window, ident, a=a, b=b)


def composite(layers, strip):
    """Surviving and cutting masks from the (W, T1 far, T2 far, M, T1 near) layers of a window.

    ``strip`` marks the pixels of M between the bisectors with its own path at p - f and p + f
    (see :func:`own_path_strip`), which stands in for the own path within ``gap`` of p.
    """
    W, T1, T2, M, T1n = layers
    over_stock = (W.id >= 0) & (M.id >= 0) & (M.depth < W.depth)
    cut = over_stock & (M.depth < T1.depth) & (M.depth < T1n.depth)
    surv = over_stock & (M.depth < T1.depth) & (M.depth < T2.depth) & strip
    return surv, cut


def own_path_strip(M, shape, u, feed_deg, f):
    """Pixels of M in front of the envelope copies at p - f·u and p + f·u, from the pixel values.

    Neighbouring tool positions one tooth feed apart differ in depth by only ~(f/2)²/(2 rc)
    around the surface they leave (0.4 µm for f = 0.125 mm, rc = 5 mm): far below any
    polygonisation tolerance, so this comparison is done in closed form. For the ball (and the
    torus corner, locally) a point of M with envelope normal N lies in front of both copies iff
    ``|rc N·u| < f/2`` (bisector planes of the corner centres); N comes from the pixel's (q, φ).
    """
    q = np.radians(M.b.astype(float))
    th = np.radians(M.a.astype(float) + feed_deg)
    nu = np.sin(q) * np.cos(th) * u[0] + np.sin(q) * np.sin(th) * u[1] - np.cos(q) * u[2]
    return (M.id >= 0) & (np.abs(shape.corner_mm * nu) < f / 2)


def own_path_gap(shape, f, tol):
    """Path distance beyond ±f over which the own path is replaced by the closed form.

    Beyond f + gap the depth difference to M near the surface it leaves, (f + gap)²/(2 rc),
    exceeds the polygonisation tolerance ~10×, so rendering decides reliably.
    """
    rc = max(shape.corner_mm, 0.25 * shape.radius_mm)
    return np.maximum(0.0, np.sqrt(20.0 * rc * tol) - f)
