"""Generating points, φ, q and the engagement of the predicted passes (seed 000 claims 1, 4, 5, 6).

For each predicted pass, at its prediction point p (from ``cut_filter``):

- M: the tool envelope at p, its pixels carrying the rotation angle φ and the contact angle q
  (claim 4: read back from the pixels, never recomputed from geometry);
- T1: everything the program sweeps before p - f (f = feed per tooth), along the path;
- T2: everything it sweeps after p + f;
- W: the stock.

From below (the seed's view, para 0045) the layers W, T1 and T2 of every window together are the
final surface of the program, which one ordered scan per tile renders once with the pass that left
each pixel (``Renderer.scan``; see ``cut_filter``). M is rendered alone, many windows per atlas, and
a pixel of M survives (M "stays in front after T2 is drawn") where the final surface there was left
by the own path within f + gap of p: no other sweep and no stock lies in front of M. The own path
within ±(f + gap) is replaced by the closed-form strip of tool positions one tooth feed apart
(:func:`own_path_strip`). The surviving pixels are the surface this pass leaves; their mean is
the generating point C, the mean of their φ (circular) and q values are its rotation and contact
angle, and the surface normal (out of the material) at C follows from φ and q. With the design
model (workflow ``nominal``), a pass that leaves both the design surface and rest material (the
semi-finishing's, on the far wall of a pocket corner) has C on the design surface, where the pass
touches it: the pixels within :data:`CONTACT_BAND_MM` of the deepest into the model (signed
distance: a correction round's path moved into the material lies under it), when that one lies
within :data:`DESIGN_TOL_MM` of the model. The band a pass leaves is symmetric about its contact only
between two rows; the last row before a wall or an edge leaves a band reaching much farther up one
side, whose mean read the rotation angle 4-9° off the surface normal (sample row y 61.2: up to
120 µm of the error, the deflection there swinging 20 µm per degree of spindle angle).

Second contact (with the design model): a ball in a pocket's vertical corner finishes both walls,
one on a floor beside a wall its foot too, and one generating point stands for one of them only (on
the sample's corner climbs, which one changed from piece to piece). Where the engaged strip around
the tool touches the design surface a second time, more than :data:`SECOND_DEG` off the first
contact's normal and separated from it (:func:`second_estimate`), the surface found along that
normal (claim 6's view) is the pass's second contact: columns ``gen2_*``, ``rotation2_deg``,
``contact2_deg``, ``nx2``…, ``n2_px`` (NaN and 0 where there is none).

View correction (claim 6, paras 0075-0078): seen from below, a surface with contact angle q is
foreshortened by cos q, so steep walls shrink below a pixel (the seed loses everything above
87.6°). When the from-below estimate says q > 60°, or no pixel survives although the pass cuts,
the window is rendered again looking along the estimated surface normal (the viewer inside the
material, looking out), zoomed 2× on the estimated generating point, with W, T1, T2, M and the
near own path in layers of the same window and the depth test completed in numpy. The ``view``
column says which render gave the row: ``below``, ``normal`` or ``none`` (no surface left by the
pass).

Engagement (claim 5): the envelope points, on a grid of axial levels and rotation angles, that lie
in the material left by the stock and every earlier pass. In 3-axis machining that material is a
height field: the depth buffer of the ordered scan just before the pass, read as a snapshot around
p. The own pass is not drawn: a straight move only removes, at p, material behind the tool (a
convex body translated along v never covers the boundary points whose outward normal u has
u·v > 0), and the chip h = fz·(v·u) of the force model already selects the front. Drawing the
own path up to p - f instead would leave, in front, only the layer one tooth removes, which on a
wall the tool climbs is fz·sin 2° ≈ 4 µm: under the mesh tolerance, so the side would be lost. On a
steep wall that height field cannot hold the layer a finishing pass removes (tens of µm wide seen
from below, less than a pixel), so for the passes whose generating point came from the normal view
the engagement is read in that direction too (:func:`engagement_along_normal`). Table
``engagement``; decode a row with :func:`unpack_engagement`.
"""
from __future__ import annotations


import numpy as np

from stages.geometry.envelope import envelope_copies, envelope_mesh
from stages.render import View, make_scene
from stages.scan.contacts import (SECOND_COLUMNS, SECOND_DEG, angles, material_normal, on_design, second_estimate,
                                   store, store_second, strip_estimate)
from stages.scan.engagement import (DZ_PER_RADIUS, N_PHI, engagement_along_normal, feed_per_tooth, scan_program,
                                     snapshot_from)
from stages.scan.layers import ID_M, N_LAYERS, PASSES_PER_BATCH, composite, layer_scene, own_path_gap, own_path_strip
from stages.scan.tiles import coarse_tolerance, fine_tolerance, z_range


STEEP_DEG = 60.0          # claim 6: re-render along the normal above this contact angle




M_WINDOWS_PER_BATCH = 256     # from-below windows of M per render (bounds the images in memory)


# view correction steps: (window side in tool radii, zoom over px_per_mm)
VIEW_STEPS = ((1.0, 2.0), (0.25, 8.0))




def generating(pg, shape, wp, renderer, px_per_mm, predict_idx, pred_tips, flutes,
               n_phi=N_PHI, dz_mm=None, tol_mm=None, design=None, steep_deg=STEEP_DEG):
    """Generating points and engagement for passes ``predict_idx`` at tips ``pred_tips``.

    ``steep_deg``: passes whose surface from below is steeper than this, or lost from below, are
    seen along their normal (claim 6); None switches claim 6 off.

    ``design``: the nominal model (:class:`DesignSurface`) or None; with it, the
    generating point of a pass that leaves both design surface and rest material is taken on the
    design surface (:data:`DESIGN_TOL_MM`).

    Returns (gen: dict of numpy columns, eng: list of (E, dz_mm, feed_dir_xy)).
    """
    predict_idx = np.asarray(predict_idx, np.int64)
    m = len(predict_idx)
    R = shape.radius_mm
    tol = fine_tolerance(px_per_mm) if tol_mm is None else tol_mm
    dz = R * DZ_PER_RADIUS if dz_mm is None else dz_mm
    mesh = envelope_mesh(shape, tol)
    coarse = envelope_mesh(shape, max(tol, coarse_tolerance(px_per_mm)))
    zlo, zhi = z_range(pg, wp, shape)
    cutting = pg.motion != 0
    bounds = pg.sweep_bounds(shape)
    f_all = feed_per_tooth(pg, flutes, 1.0 / px_per_mm)
    pred_tips = np.asarray(pred_tips, float).reshape(-1, 3)
    gen = {k: np.full(m, np.nan) for k in
           ("gen_x_mm", "gen_y_mm", "gen_z_mm", "rotation_deg", "contact_deg", "nx", "ny", "nz")}
    gen["n_px"] = np.zeros(m, np.int64)
    gen["view"] = np.array(["none"] * m, dtype=object)
    gen.update({k: np.full(m, np.nan) for k in SECOND_COLUMNS})    # the second contact, if any
    gen["n2_px"] = np.zeros(m, np.int64)
    gen["eng_c"] = np.full((m, 3), np.nan)      # engagement view (not in the table, see store)
    gen["eng_n"] = np.full((m, 3), np.nan)
    eng = [None] * m
    if m == 0:
        return gen, eng
    feed_deg = pg.feed_deg
    plunge = np.hypot(*(pg.p1 - pg.p0)[:, :2].T) < 1e-9
    feed_deg = np.where(plunge, 0.0, feed_deg)
    margin = 2.0 / px_per_mm
    s_p = pg.s0[predict_idx] + np.linalg.norm(pred_tips - pg.p0[predict_idx], axis=1)
    f = f_all[predict_idx]
    fd = feed_deg[predict_idx]
    gap = own_path_gap(shape, f, tol)
    dirs = pg.p1[predict_idx] - pg.p0[predict_idx]
    u = dirs / np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-12)
    half = R + margin
    tops = np.zeros(m)                            # highest material above each tip, from below
    snap = snapshot_from(pg, predict_idx, s_p, R)
    final, tile_of = scan_program(pg, shape, wp, renderer, px_per_mm, mesh, predict_idx, pred_tips,
                                   f, u, zlo, zhi, half, eng, dz, n_phi, tol, fd, tops, snap)
    path_lo, path_hi = pg.s0, pg.s0 + pg.length
    redo = []                                     # (slot, estimated q, phi)
    for b0 in range(0, m, M_WINDOWS_PER_BATCH):
        ks = np.arange(b0, min(m, b0 + M_WINDOWS_PER_BATCH))
        # M at the prediction points, from below, many windows per atlas
        views = [View((t[0], t[1], 0.0), (0, 0, 1.0), (np.cos(np.radians(a)), np.sin(np.radians(a)), 0.0),
                      2 * half, 2 * half, px_per_mm, zlo, zhi) for t, a in zip(pred_tips[ks], fd[ks])]
        tris, q, phi, owner = envelope_copies(mesh, pred_tips[ks], feed_deg=fd[ks], view_dir=(0, 0, 1.0))
        mimgs = renderer.render(views, make_scene(tris, owner, ID_M, a=phi, b=q))
        del tris, q, phi, owner
        for v, M, k in zip(views, mimgs, ks):
            from_below(gen, redo, k, v, M, final[tile_of[k]], shape, eng[k][0], dz, n_phi,
                       s_p[k], f[k], gap[k], u[k], fd[k], path_lo, path_hi, design, pred_tips[k], steep_deg)
    view_correction(gen, redo, pg, shape, wp, renderer, px_per_mm, cutting, bounds, mesh, coarse,
                     pred_tips, s_p, f, fd, gap, u, design)
    steep = [k for k, _, _ in redo if gen["view"][k] == "normal"]
    engagement_along_normal(eng, steep, gen, pg, shape, wp, renderer, px_per_mm, cutting, bounds, mesh,
                             pred_tips, pg.s0[snap], fd, tops, dz, n_phi, tol)
    if design is not None:
        # the second contact: aimed by the engaged strip, found along its normal as claim 6 finds
        # a steep wall (what the view sees there is the surface this pass leaves, or nothing)
        second = []
        for k in np.nonzero(gen["view"] != "none")[0]:
            n1 = np.array([gen["nx"][k], gen["ny"][k], gen["nz"][k]])
            c1 = np.array([gen["gen_x_mm"][k], gen["gen_y_mm"][k], gen["gen_z_mm"][k]])
            est = second_estimate(shape, eng[k][0], dz, n_phi, u[k], fd[k], pred_tips[k], design, n1, c1)
            if est is not None:
                second.append((int(k), est[0], est[1]))
        view_correction(gen, second, pg, shape, wp, renderer, px_per_mm, cutting, bounds, mesh, coarse,
                         pred_tips, s_p, f, fd, gap, u, design, second=True)
    return gen, eng


def from_below(gen, redo, k, view, M, fin, shape, E, dz, n_phi, s_p, f, gap, u, fd, path_lo, path_hi,
               design=None, tip=None, steep_deg=STEEP_DEG):
    """Generating point of prediction ``k`` from its from-below window of M and the final surface."""
    on = M.id >= 0
    rows, cols = np.nonzero(on)
    pts = view.pixel_points(rows, cols, M.depth[on])
    c, r, _ = fin.view.project(pts)
    hh, ww = fin.id.shape
    ri = np.clip(np.floor(r).astype(np.int64), 0, hh - 1)
    ci = np.clip(np.floor(c).astype(np.int64), 0, ww - 1)
    who = fin.id[ri, ci]
    # surviving: the final surface there was left by the own path within f + gap of p (the
    # closed-form strip narrows that to +-f): no other sweep and no stock is in front of M
    whoc = np.clip(who, 0, None)
    near = (who >= 0) & (path_lo[whoc] < s_p + f + gap) & (path_hi[whoc] > s_p - f - gap)
    strip = own_path_strip(M, shape, u, fd, f)
    surv = np.zeros_like(on)
    surv[on] = near
    surv &= strip
    if surv.any():
        on = on_design(design, view, M, surv)
        qk, phik = angles(M, on)
        store(gen, k, view, M, on, qk, phik, fd, "below", all_mask=surv)
        if steep_deg is not None and qk > steep_deg:
            redo.append((k, qk, phik))
    elif steep_deg is not None:
        # nothing survives from below (steep walls shrink below a pixel, or the pass rolls over
        # an edge): the surface it leaves lies on its own-path strip (the envelope circle
        # perpendicular to the motion) where that strip is in the material before the cut;
        # the mean direction of those engaged points is where to look from (claim 6)
        est = strip_estimate(shape, E, dz, n_phi, u, fd, tip=tip, design=design)
        if est is not None:
            redo.append((k, max(est[0], steep_deg), est[1]))


def view_correction(gen, redo, pg, shape, wp, renderer, px_per_mm, cutting, bounds, mesh, coarse,
                     tips, s_p, f, fd, gap, u, design=None, second=False):
    """Claim 6: look along the estimated normal, zoomed; zoom further where still nothing.

    With ``second`` the estimates are second contacts (:func:`second_estimate`): of what the view
    sees, the pixels nearer in normal to the estimate than to the generating point's and within
    :data:`SECOND_DEG` of the estimate are the second contact (the first wall, seen obliquely, is
    not), stored in the ``*2`` columns (:func:`store_second`).
    """
    R = shape.radius_mm
    for b0 in range(0, len(redo), PASSES_PER_BATCH):
        todo = redo[b0:b0 + PASSES_PER_BATCH]
        for size, zoom in VIEW_STEPS:
            if not todo:
                break
            ks = np.array([r[0] for r in todo])
            ovs = []
            for k, q, phi in todo:
                nrm = material_normal(q, phi, fd[k])
                c = tips[k] + shape.point(q, phi, fd[k])
                upv = (np.cos(np.radians(fd[k])), np.sin(np.radians(fd[k])), 0.0)
                if abs(np.dot(upv, nrm)) > 0.99:
                    upv = (0.0, 0.0, 1.0)
                ovs.append(View(tuple(c), tuple(nrm), upv, size * R, size * R, zoom * px_per_mm,
                                -R / 2, 2 * R))
            n2 = len(ovs)
            scene = layer_scene(ovs, pg, cutting, s_p[ks], f[ks], bounds, wp, mesh, tips[ks], fd[ks],
                                 coarse, gap[ks])
            imgs = renderer.render(ovs * N_LAYERS, scene)
            still = []
            for r, k in enumerate(ks):
                layers = [imgs[L * n2 + r] for L in range(N_LAYERS)]
                surv, _ = composite(layers, own_path_strip(layers[3], shape, u[k], fd[k], f[k]))
                if second and surv.any():
                    pn = material_normal(layers[3].b.astype(float), layers[3].a.astype(float), fd[k])
                    cos2 = np.einsum("i...,i->...", pn, np.asarray(ovs[r].view_dir, float))
                    cos1 = np.einsum("i...,i->...", pn, np.array([gen["nx"][k], gen["ny"][k], gen["nz"][k]]))
                    surv &= (cos2 > cos1) & (cos2 > np.cos(np.radians(SECOND_DEG)))
                    if surv.any():
                        on = on_design(design, ovs[r], layers[3], surv)
                        q, phi = angles(layers[3], on)
                        store_second(gen, k, ovs[r], layers[3], on, q, phi, fd[k])
                    else:
                        still.append(todo[r])
                elif surv.any():
                    on = on_design(design, ovs[r], layers[3], surv)
                    q, phi = angles(layers[3], on)
                    # the engagement is read along the direction of every pixel the pass leaves,
                    # rest material included: from below where anything survived there (this view
                    # may be aimed at the design surface alone; along a pocket wall the rest
                    # material on the wall across is then edge-on, and its engagement lost)
                    keep = np.isfinite(gen["eng_n"][k]).all()
                    ec, en = gen["eng_c"][k].copy(), gen["eng_n"][k].copy()
                    store(gen, k, ovs[r], layers[3], on, q, phi, fd[k], "normal", all_mask=surv)
                    if keep:
                        gen["eng_c"][k], gen["eng_n"][k] = ec, en
                elif second or gen["view"][k] == "none":
                    still.append(todo[r])
            todo = still
