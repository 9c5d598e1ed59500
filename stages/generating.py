"""Stage ``generating`` (seed 000 claims 1, 4, 5, 6; paras 0042-0046, 0064-0078).

For each predicted pass, at its prediction point p (from ``cut_filter``):

- M: the tool envelope at p, its pixels carrying the rotation angle φ and the contact angle q
  (claim 4: read back from the pixels, never recomputed from geometry);
- T1: everything the program sweeps before p - f (f = feed per tooth), along the path;
- T2: everything it sweeps after p + f;
- W: the stock.

Each is rendered into its own layer of the same window (one atlas holds the layers of many
passes) and the depth test is completed in numpy: a pixel of M survives when M is nearer than
W, T1 and T2 there (M "stays in front after T2 is drawn"), and lies over the stock. The surviving
pixels are the surface this pass leaves; their mean is the generating point C, the mean of their
φ (circular) and q values are its rotation and contact angle, and the surface normal (out of the
material) at C follows from φ and q.

View correction (claim 6, paras 0075-0078): seen from below, a surface with contact angle q is
foreshortened by cos q, so steep walls shrink below a pixel (the seed loses everything above
87.6°). When the from-below estimate says q > 60°, or no pixel survives although the pass cuts,
the window is rendered again looking along the estimated surface normal (the viewer inside the
material, looking out), zoomed 2× on the estimated generating point, with the depth range
starting R/2 behind it so only the neighbourhood is seen. The ``view`` column says which
render gave the row: ``below``, ``normal`` or ``none`` (no surface left by the pass).

Engagement (claim 5): in 3-axis machining the material left after T1 and W is a height field,
which the from-below depth layers of W and T1 give. Points of the envelope on a grid of axial
levels and rotation angles are engaged where they lie below it. Table ``engagement``; decode a
row with :func:`unpack_engagement`.
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa

import schemas
from stages import InputError
from stages import geometry as geo
from stages.cut_filter import coarse_tolerance, fine_tolerance, render_settings, z_range
from stages.render import Scene, View

NAME = "generating"
VERSION = "1"
INPUTS = ("passes", "stock", "cut_filter", "angle_prune")
OUTPUTS = ("generating", "engagement")
PARAMS = ("tool", "render")

ID_W, ID_T1, ID_T2, ID_M = 0, 1, 2, 3
STEEP_DEG = 60.0          # claim 6: re-render along the normal above this contact angle
PASSES_PER_BATCH = 8
N_LAYERS = 5
# view correction steps: (window side in tool radii, zoom over px_per_mm)
VIEW_STEPS = ((1.0, 2.0), (0.25, 8.0))
_redo_when_lost = True     # claim 6 also when nothing survives from below (tests switch it off)
N_PHI = 180


def unpack_engagement(row):
    """Decode one ``engagement`` row.

    Parameters
    ----------
    row : mapping with keys dz_mm, n_z, n_phi, mask (e.g. ``table.slice(i, 1).to_pylist()[0]``).

    Returns
    -------
    E : (n_z, n_phi) bool, True where the envelope point is inside the material.
    z_levels_mm : (n_z,) heights above the tool tip, (k + 0.5) * dz_mm.
    phi_deg : (n_phi,) rotation angles, (j + 0.5) * 360 / n_phi, CCW from the feed direction.
    """
    n_z, n_phi = int(row["n_z"]), int(row["n_phi"])
    bits = np.unpackbits(np.frombuffer(row["mask"], np.uint8), count=n_z * n_phi)
    E = bits.astype(bool).reshape(n_z, n_phi)
    z = (np.arange(n_z) + 0.5) * float(row["dz_mm"])
    phi = (np.arange(n_phi) + 0.5) * 360.0 / n_phi
    return E, z, phi


def feed_per_tooth(pg: geo.PassGeometry, flutes: int, fallback_mm: float):
    rpm = np.where(np.isfinite(pg.spindle_rpm), pg.spindle_rpm, 0.0)
    f = np.where(rpm > 0, pg.feed_mm_min / np.maximum(rpm, 1e-9) / max(int(flutes), 1), 0.0)
    return np.where((f > 0) & np.isfinite(f), f, fallback_mm)


def _segments_around(pg, cutting, s_p, f, win_lo, win_hi, bounds, gap):
    """Path pieces around path positions ``s_p`` (one per window), split at s_p - f and s_p + f.

    Returns three (window, a, b) segment lists: T1 far (path up to s_p - f - gap), T1 near
    (s_p - f - gap to s_p - f) and T2 far (from s_p + f + gap on).
    """
    ov = geo.overlaps(win_lo, win_hi, bounds[:, 0], bounds[:, 1]) & cutting[None, :]
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


def _layer_scene(views, pg, cutting, s_p, f, bounds, wp, mesh, m_tips, m_feed, coarse, gap):
    """Scene of the layers (W, T1 far, T2 far, M, T1 near) for ``views``: layer k of view i is
    window k*n+i.

    Sweep ends within one tool radius (xy) of the window's prediction point use the fine mesh:
    only they can bound the surface M leaves; the others use the coarse mesh.
    """
    n = len(views)
    R = mesh.shape.radius_mm

    def fine(w, a, b):
        return np.stack([np.hypot(*(a - m_tips[w])[:, :2].T) < R,
                         np.hypot(*(b - m_tips[w])[:, :2].T) < R], axis=1)

    d = np.asarray(views[0].view_dir, float)
    lo, hi = geo.window_xy_bounds(views)
    segs = _segments_around(pg, cutting, s_p, f, lo, hi, bounds, gap)
    (w1, a1, b1), (w4, a4, b4), (w2, a2, b2) = segs
    wb = (np.tile(lo, (N_LAYERS, 1)), np.tile(hi, (N_LAYERS, 1)))
    parts = [geo.workpiece_scene(wp, views, ID_W)]
    # all views of a batch share the view direction only when seen from below; oblique views
    # are grouped one per scene part (culling depends on the direction)
    per_view = not all(np.allclose(v.view_dir, d) for v in views)
    for layer, (w, a, b, ident) in ((1, (w1, a1, b1, ID_T1)), (2, (w2, a2, b2, ID_T2)),
                                    (4, (w4, a4, b4, ID_T1))):
        if per_view:
            for i, v in enumerate(views):
                s = w == i
                parts.append(geo.segment_scene(mesh, a[s], b[s], w[s] + layer * n, np.full(s.sum(), ident),
                                               v.view_dir, window_bounds=wb, coarse_mesh=coarse,
                                               fine_ends=fine(w[s], a[s], b[s])))
        else:
            parts.append(geo.segment_scene(mesh, a, b, w + layer * n, np.full(len(w), ident), d,
                                           window_bounds=wb, coarse_mesh=coarse,
                                           fine_ends=fine(w, a, b)))
    for i, v in enumerate(views):
        tris, q, phi, _ = geo.envelope_copies(mesh, m_tips[i:i + 1], feed_deg=m_feed[i:i + 1],
                                              view_dir=v.view_dir)
        parts.append(_scene(tris, 3 * n + i, ID_M, phi, q))
    return Scene.concat(parts)


def _scene(tris, window, ident, a, b):
    from stages.render import make_scene
    return make_scene(tris, window, ident, a=a, b=b)


def _composite(layers, strip):
    """Surviving and cutting masks from the (W, T1 far, T2 far, M, T1 near) layers of a window.

    ``strip`` marks the pixels of M between the bisectors with its own path at p - f and p + f
    (see :func:`_own_path_strip`), which stands in for the own path within ``gap`` of p.
    """
    W, T1, T2, M, T1n = layers
    over_stock = (W.id >= 0) & (M.id >= 0) & (M.depth < W.depth)
    cut = over_stock & (M.depth < T1.depth) & (M.depth < T1n.depth)
    surv = over_stock & (M.depth < T1.depth) & (M.depth < T2.depth) & strip
    return surv, cut


def _own_path_strip(M, shape, u, feed_deg, f):
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


def _angles(M, mask):
    """Mean contact and rotation angle of the pixels ``mask`` of layer M, read from the pixels.

    The (q, φ) of each pixel is a direction on the unit sphere (the envelope normal); their mean
    direction gives the mean angles. Unlike averaging q and φ separately this has no bias near
    the tip (q = 0, where φ is undefined and q is never negative) and no wrap at φ = 0/360°.
    """
    q = np.radians(M.b[mask].astype(float))
    a = np.radians(M.a[mask].astype(float))
    v = np.array([np.mean(np.sin(q) * np.cos(a)), np.mean(np.sin(q) * np.sin(a)),
                  np.mean(np.cos(q))])
    qm = float(np.degrees(np.arctan2(np.hypot(v[0], v[1]), v[2])))
    phi = float(np.degrees(np.arctan2(v[1], v[0])) % 360.0)
    return qm, phi


def material_normal(q_deg, phi_deg, feed_deg):
    """Surface normal out of the material at the contact point (q, φ) of the envelope."""
    q, th = np.radians(q_deg), np.radians(phi_deg + feed_deg)
    return np.array([-np.sin(q) * np.cos(th), -np.sin(q) * np.sin(th), np.cos(q)])


def generating(pg, shape, wp, renderer, px_per_mm, predict_idx, pred_tips, flutes,
               n_phi=N_PHI, dz_mm=None, tol_mm=None):
    """Generating points and engagement for passes ``predict_idx`` at tips ``pred_tips``.

    Returns (gen: dict of numpy columns, eng: list of (E, dz_mm, feed_dir_xy)).
    """
    predict_idx = np.asarray(predict_idx, np.int64)
    m = len(predict_idx)
    R = shape.radius_mm
    tol = fine_tolerance(px_per_mm) if tol_mm is None else tol_mm
    dz = R / 45.0 if dz_mm is None else dz_mm
    mesh = geo.envelope_mesh(shape, tol)
    coarse = geo.envelope_mesh(shape, max(tol, coarse_tolerance(px_per_mm)))
    zlo, zhi = z_range(pg, wp, shape)
    cutting = pg.motion != 0
    bounds = pg.sweep_bounds(shape)
    f_all = feed_per_tooth(pg, flutes, 1.0 / px_per_mm)
    pred_tips = np.asarray(pred_tips, float).reshape(-1, 3)
    gen = {k: np.full(m, np.nan) for k in
           ("gen_x_mm", "gen_y_mm", "gen_z_mm", "rotation_deg", "contact_deg", "nx", "ny", "nz")}
    gen["n_px"] = np.zeros(m, np.int64)
    gen["view"] = np.array(["none"] * m, dtype=object)
    eng = [None] * m
    feed_deg = pg.feed_deg
    plunge = np.hypot(*(pg.p1 - pg.p0)[:, :2].T) < 1e-9
    feed_deg = np.where(plunge, 0.0, feed_deg)
    margin = 2.0 / px_per_mm
    for b0 in range(0, m, PASSES_PER_BATCH):
        sl = np.arange(b0, min(m, b0 + PASSES_PER_BATCH))
        ii = predict_idx[sl]
        tips = pred_tips[sl]
        s_p = pg.s0[ii] + np.linalg.norm(tips - pg.p0[ii], axis=1)
        f = f_all[ii]
        fd = feed_deg[ii]
        views = [View((t[0], t[1], 0.0), (0, 0, 1.0),
                      (np.cos(np.radians(a)), np.sin(np.radians(a)), 0.0),
                      2 * R + 2 * margin, 2 * R + 2 * margin, px_per_mm, zlo, zhi)
                 for t, a in zip(tips, fd)]
        n = len(views)
        gap = own_path_gap(shape, f, tol)
        dirs = pg.p1[ii] - pg.p0[ii]
        u = dirs / np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-12)
        scene = _layer_scene(views, pg, cutting, s_p, f, bounds, wp, mesh, tips, fd, coarse, gap)
        imgs = renderer.render(views * N_LAYERS, scene)
        redo = []                                     # (slot, estimated q, phi)
        for k in range(n):
            layers = [imgs[L * n + k] for L in range(N_LAYERS)]
            surv, cut = _composite(layers, _own_path_strip(layers[3], shape, u[k], fd[k], f[k]))
            slot = sl[k]
            eng[slot] = (_engagement(shape, views[k], layers, tips[k], fd[k], dz, n_phi, tol),
                         dz, (np.cos(np.radians(fd[k])), np.sin(np.radians(fd[k]))))
            M = layers[3]
            if surv.any():
                q, phi = _angles(M, surv)
                _store(gen, slot, views[k], M, surv, q, phi, fd[k], "below")
                if q > STEEP_DEG:
                    redo.append((k, q, phi))
            elif cut.any() and _redo_when_lost:
                # nothing survives from below: estimate the place from the cut pixels closest
                # to surviving (smallest depth margin behind T2)
                strip = _own_path_strip(M, shape, u[k], fd[k], f[k])
                cand = cut & strip if (cut & strip).any() else cut
                with np.errstate(invalid="ignore"):
                    margin_t2 = np.where(cand, M.depth - layers[2].depth, np.inf)
                near_px = cand & (margin_t2 <= np.quantile(margin_t2[cand], 0.02))
                q, phi = _angles(M, near_px)
                redo.append((k, max(q, STEEP_DEG), phi))
        # claim 6: look along the estimated normal, zoomed; zoom further where still nothing
        for size, zoom in VIEW_STEPS:
            if not redo:
                break
            ks = np.array([r[0] for r in redo])
            ovs = []
            for k, q, phi in redo:
                nrm = material_normal(q, phi, fd[k])
                c = tips[k] + shape.point(q, phi, fd[k])
                upv = (np.cos(np.radians(fd[k])), np.sin(np.radians(fd[k])), 0.0)
                if abs(np.dot(upv, nrm)) > 0.99:
                    upv = (0.0, 0.0, 1.0)
                ovs.append(View(tuple(c), tuple(nrm), upv, size * R, size * R, zoom * px_per_mm,
                                -R / 2, 2 * R))
            n2 = len(ovs)
            scene = _layer_scene(ovs, pg, cutting, s_p[ks], f[ks], bounds, wp, mesh, tips[ks], fd[ks],
                                 coarse, gap[ks])
            imgs = renderer.render(ovs * N_LAYERS, scene)
            still = []
            for r, k in enumerate(ks):
                layers = [imgs[L * n2 + r] for L in range(N_LAYERS)]
                surv, _ = _composite(layers, _own_path_strip(layers[3], shape, u[k], fd[k], f[k]))
                if surv.any():
                    q, phi = _angles(layers[3], surv)
                    _store(gen, sl[k], ovs[r], layers[3], surv, q, phi, fd[k], "normal")
                elif gen["view"][sl[k]] == "none":
                    still.append(redo[r])
            redo = still
    return gen, eng


def _store(gen, slot, view, M, mask, q, phi, feed, how):
    rows, cols = np.nonzero(mask)
    pts = view.pixel_points(rows, cols, M.depth[mask])
    c = pts.mean(0)
    nrm = material_normal(q, phi, feed)
    gen["gen_x_mm"][slot], gen["gen_y_mm"][slot], gen["gen_z_mm"][slot] = c
    gen["rotation_deg"][slot] = phi
    gen["contact_deg"][slot] = q
    gen["nx"][slot], gen["ny"][slot], gen["nz"][slot] = nrm
    gen["n_px"][slot] = int(mask.sum())
    gen["view"][slot] = how


def _engagement(shape, view, layers, tip, feed, dz, n_phi, tol):
    """E[k, j]: envelope point at height (k+.5)dz, angle (j+.5)360/n_phi inside the material."""
    W, T1, T1n = layers[0], layers[1], layers[4]
    h = np.where(W.id >= 0, np.minimum(np.minimum(W.depth, T1.depth), T1n.depth), -np.inf)  # top (z)
    top = np.max(h[np.isfinite(h)]) - tip[2] if np.isfinite(h).any() else 0.0
    n_z = int(np.clip(np.ceil(min(top, shape.stickout_mm) / dz), 1, None))
    z = (np.arange(n_z) + 0.5) * dz
    phi = (np.arange(n_phi) + 0.5) * 360.0 / n_phi
    r = shape.profile_radius(z)
    th = np.radians(phi + feed)
    P = np.stack(np.broadcast_arrays(tip[0] + r[:, None] * np.cos(th)[None],
                                     tip[1] + r[:, None] * np.sin(th)[None],
                                     tip[2] + z[:, None]), axis=-1)
    cols, rows, _ = view.project(P)
    hh, ww = h.shape
    ci = np.clip(np.floor(cols).astype(int), 0, ww - 1)
    ri = np.clip(np.floor(rows).astype(int), 0, hh - 1)
    E = P[..., 2] < h[ri, ci] - tol
    lev = np.nonzero(E.any(1))[0]
    n_keep = int(lev[-1]) + 1 if len(lev) else 1
    return E[:n_keep]


def run(inputs: dict, params: dict) -> dict:
    passes = inputs["passes"]
    tool = params["tool"]
    shape = geo.tool_from_params(tool)
    t = tool[0] if isinstance(tool, (list, tuple)) else tool
    pg = geo.pass_geometry(passes, tool)
    wp = geo.load_workpiece(inputs.get("stock"))
    renderer, ppm = render_settings(params)
    cf = inputs["cut_filter"]
    ap = inputs["angle_prune"]
    for name, tab, cols in (("cut_filter", cf, ("pass_id", "is_cutting", "pred_x_mm")),
                            ("angle_prune", ap, ("pass_id", "predict"))):
        miss = [c for c in cols if c not in tab.column_names]
        if miss:
            raise InputError(f"{name}: missing columns {miss}")
    pos = {int(p): k for k, p in enumerate(pg.pass_id)}
    cfp = cf.column("pass_id").to_numpy()
    ok = cf.column("is_cutting").to_numpy(zero_copy_only=False).astype(bool)
    pred = {int(p): (x, y, z) for p, c, x, y, z in zip(
        cfp, ok, cf.column("pred_x_mm").to_numpy(zero_copy_only=False),
        cf.column("pred_y_mm").to_numpy(zero_copy_only=False),
        cf.column("pred_z_mm").to_numpy(zero_copy_only=False)) if c}
    app = ap.column("pass_id").to_numpy()
    apf = ap.column("predict").to_numpy(zero_copy_only=False).astype(bool)
    chosen = sorted(int(p) for p, k in zip(app, apf) if k and int(p) in pred and int(p) in pos)
    idx = np.array([pos[p] for p in chosen], np.int64)
    tips = np.array([pred[p] for p in chosen], float).reshape(-1, 3)
    gen, eng = generating(pg, shape, wp, renderer, ppm, idx, tips, int(t.get("flutes") or 2))
    m = len(idx)
    pid = pa.array([pg.program_id] * m, pa.string())
    g = pa.table({"program_id": pid, "pass_id": pa.array(chosen, pa.int32()),
                  **{k: pa.array(gen[k]) for k in ("gen_x_mm", "gen_y_mm", "gen_z_mm",
                                                   "rotation_deg", "contact_deg", "nx", "ny", "nz")},
                  "n_px": pa.array(gen["n_px"], pa.int32()),
                  "view": pa.array(list(gen["view"]), pa.string())})
    e = pa.table({"program_id": pid, "pass_id": pa.array(chosen, pa.int32()),
                  "dz_mm": pa.array([x[1] for x in eng], pa.float64()),
                  "n_z": pa.array([x[0].shape[0] for x in eng], pa.int32()),
                  "n_phi": pa.array([x[0].shape[1] for x in eng], pa.int32()),
                  "mask": pa.array([np.packbits(x[0].reshape(-1)).tobytes() for x in eng], pa.binary()),
                  "feed_dir_x": pa.array([x[2][0] for x in eng], pa.float64()),
                  "feed_dir_y": pa.array([x[2][1] for x in eng], pa.float64())})
    return {"generating": schemas.check("generating", g), "engagement": schemas.check("engagement", e)}
