"""The cutting region (claim 5): the envelope points in the material before the pass, as an
engagement grid of axial levels × rotation angles, from the ordered scan's snapshots and, on steep
walls, along the surface normal.
"""
from __future__ import annotations


import numpy as np

from stages.geometry.passes import PassGeometry, overlaps, window_xy_bounds
from stages.geometry.sweeps import ordered_sweep_scene
from stages.geometry.workpiece import workpiece_scene
from stages.render import Snapshot, View
from stages.scan.layers import N_LAYERS, PASSES_PER_BATCH, layer_scene
from stages.scan.tiles import PASSES_PER_DRAW, scan_tiles


# Engagement grid: 2° bins and R/45 levels left the predicted error jumping by ±2 µm from pass to
# pass on the seed's cylinder (a finishing crescent is a few levels thick); 1° and R/180 are within
# 0.5 µm of a 4× finer grid (analytic engagement, bench/closed_loop_vm.py's set-up).
N_PHI = 360


DZ_PER_RADIUS = 1.0 / 180


# the own path's trailing passes left out of a prediction point's material snapshot: within a tool
# radius behind it, contiguous, turning by at most this in all (see :func:`snapshot_from`)
TRAIL_TURN_DEG = 15.0


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


def feed_per_tooth(pg: PassGeometry, flutes: int, fallback_mm: float):
    rpm = np.where(np.isfinite(pg.spindle_rpm), pg.spindle_rpm, 0.0)
    f = np.where(rpm > 0, pg.feed_mm_min / np.maximum(rpm, 1e-9) / max(int(flutes), 1), 0.0)
    return np.where((f > 0) & np.isfinite(f), f, fallback_mm)


def snapshot_from(pg, predict_idx, s_tip, reach_mm, turn_deg=TRAIL_TURN_DEG):
    """First pass of each prediction point's own trailing path that its material snapshot leaves out.

    The engagement is the envelope in the material before the cut (claim 5): the stock less the
    sweeps of the earlier passes. The tool's own path straight behind it never reaches into its
    front half (a ball δ behind lies √(R² + δ²) or more from every front point), but in the height
    field its end cap lies only about δ·tanθ·cosφ above the front near the tip: a point δ into a
    short chord (CAM's chords at fillets and corners are a few µm to a few tenths of a mm; the
    sample boss foot has 25 µm ones) lost its engagement there within the render tolerance, and a
    pass the virtual machine cuts at 68 N was predicted without force. So the passes of the own path
    that end within ``reach_mm`` behind the point, while the path is contiguous (no rapid, no gap)
    and turns by at most ``turn_deg`` in all from them to the point's pass, are drawn after the
    snapshot: the front half meets the material as the cut does, whatever the chord length. A
    sharper turn keeps them (a corner's sweep does reach into the front half).

    Parameters
    ----------
    pg : PassGeometry
    predict_idx : (m,) int
        Pass index of each prediction point, ascending.
    s_tip : (m,) float
        Path position of each prediction point (mm).
    reach_mm : float
        How far behind the point the own path is left out (a tool radius: a ball that far behind
        lies outside the footprint of the front half).

    Returns
    -------
    (m,) int
        Pass index j ≤ predict_idx: passes j … predict_idx − 1 are not in the snapshot.
        Non-decreasing with ``predict_idx`` (the scan draws passes in order).
    """
    predict_idx = np.asarray(predict_idx, np.int64)
    n = len(pg.pass_id)
    if n == 0 or len(predict_idx) == 0:
        return predict_idx.copy()
    d = pg.p1 - pg.p0
    L = np.linalg.norm(d, axis=1)
    u = d / np.maximum(L, 1e-12)[:, None]
    turn = np.zeros(n)
    brk = np.zeros(n, bool)
    brk[0] = True
    if n > 1:
        ang = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", u[:-1], u[1:]), -1.0, 1.0)))
        turn[1:] = np.where((L[:-1] > 1e-9) & (L[1:] > 1e-9), ang, 0.0)
        brk[1:] = ((pg.motion[:-1] == 0) | (pg.motion[1:] == 0)
                   | (np.linalg.norm(pg.p0[1:] - pg.p1[:-1], axis=1) > 1e-6))
    chain_start = np.maximum.accumulate(np.where(brk, np.arange(n), 0))
    C = np.cumsum(turn)                          # turning from pass j to pass i: C[i] - C[j]
    j_turn = np.searchsorted(C, C[predict_idx] - turn_deg - 1e-9, side="left")
    j_reach = np.searchsorted(pg.s0 + L, np.asarray(s_tip, float) - reach_mm, side="right")
    j = np.maximum(np.maximum(chain_start[predict_idx], j_turn), j_reach)
    return np.minimum(j, predict_idx)


def scan_program(pg, shape, wp, renderer, px_per_mm, mesh, predict_idx, tips, f, u, zlo, zhi, half,
                  eng, dz, n_phi, tol, fd, tops, snap):
    """One ordered scan of the program per tile: the final surface (which pass leaves which
    pixel) and, at each prediction point, a snapshot of the material left before its pass (stock
    and every earlier pass but the own path's trailing passes from ``snap``, see
    :func:`snapshot_from`): the claim-5 cutting region's top.

    Each snapshot becomes the prediction's engagement map (``eng[k]``) as soon as it is taken.
    Returns (final images per tile, tile index per prediction).
    """
    cand = np.nonzero(pg.motion != 0)[0]
    bounds = pg.sweep_bounds(shape)
    views, cores = scan_tiles(pg, shape, wp, px_per_mm, cand, zlo, zhi, halo_mm=half + 2.0 / px_per_mm)
    m = len(predict_idx)
    tile_of = np.zeros(m, np.int64)
    for t, (lo, hi) in enumerate(cores):                       # tiles are few; cores partition
        inside = np.all((tips[:, :2] >= lo) & (tips[:, :2] <= hi), axis=1)
        tile_of[inside] = t
    n_side = int(np.ceil(2 * half * px_per_mm))
    final = []
    for t, view in enumerate(views):
        mine = np.nonzero(tile_of == t)[0]
        if not len(mine):                                      # no prediction point in this tile
            final.append(None)
            continue
        lo_w, hi_w = window_xy_bounds([view])
        inside = cand[overlaps(lo_w, hi_w, bounds[cand, 0], bounds[cand, 1])[0]]
        mine = mine[np.argsort(predict_idx[mine], kind="stable")]
        rects = []
        for k in mine:
            c, r, _ = view.project(tips[k][None])
            r0 = int(np.clip(np.floor(r[0]) - n_side // 2, 0, view.shape[0] - n_side))
            c0 = int(np.clip(np.floor(c[0]) - n_side // 2, 0, view.shape[1] - n_side))
            rects.append(Snapshot(r0, c0, n_side, n_side))

        def batches(inside=inside, mine=mine, rects=rects):
            done = 0                                           # passes of `inside` drawn so far
            for k, rect in zip(mine, rects):
                upto = int(np.searchsorted(inside, snap[k]))
                for a in range(done, upto, PASSES_PER_DRAW):
                    j = inside[a:min(upto, a + PASSES_PER_DRAW)]
                    yield ordered_sweep_scene(mesh, pg.p0[j], pg.p1[j], j)
                done = max(done, upto)
                yield rect                                     # the material before the pass
            for a in range(done, len(inside), PASSES_PER_DRAW):
                j = inside[a:a + PASSES_PER_DRAW]
                yield ordered_sweep_scene(mesh, pg.p0[j], pg.p1[j], j)

        taken = iter(zip(mine, rects))

        def on_snapshot(depth, view=view, taken=taken):
            k, rect = next(taken)
            right, up, _ = view.basis()
            cx = (rect.col0 + rect.cols / 2 - view.shape[1] / 2) / px_per_mm
            cy = (rect.row0 + rect.rows / 2 - view.shape[0] / 2) / px_per_mm
            ctr = np.asarray(view.center, float) + cx * right + cy * up
            sv = View(tuple(ctr), view.view_dir, view.up, rect.cols / px_per_mm, rect.rows / px_per_mm,
                      px_per_mm, view.near_mm, view.far_mm)
            tops[k] = np.max(depth) - tips[k][2] if depth.size else 0.0
            eng[k] = (engagement(shape, sv, depth, tips[k], fd[k], dz, n_phi, tol), dz,
                      (np.cos(np.radians(fd[k])), np.sin(np.radians(fd[k]))))

        res = renderer.scan(view, workpiece_scene(wp, [view], -2.0), batches(), len(pg.pass_id), 1,
                            on_snapshot=on_snapshot)
        final.append(res.final)
    return final, tile_of


def ramp_deg(d):
    """Angle (deg) of each feed vector d (P, 3) above the horizontal; ±90 for a plunge."""
    d = np.asarray(d, float).reshape(-1, 3)
    return np.degrees(np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1])))


def bilinear(img, cols, rows):
    """``img`` at continuous pixel coordinates (pixel i covers [i, i+1)), bilinear between pixel
    centres and clamped at the border: the engagement boundary then moves continuously with the
    surface instead of in whole pixels."""
    hh, ww = img.shape
    x = np.clip(np.asarray(cols, float) - 0.5, 0.0, ww - 1.0)
    y = np.clip(np.asarray(rows, float) - 0.5, 0.0, hh - 1.0)
    i0 = np.minimum(np.floor(x).astype(np.int64), max(ww - 2, 0))
    j0 = np.minimum(np.floor(y).astype(np.int64), max(hh - 2, 0))
    i1, j1 = np.minimum(i0 + 1, ww - 1), np.minimum(j0 + 1, hh - 1)
    tx, ty = x - i0, y - j0
    return ((1 - ty) * ((1 - tx) * img[j0, i0] + tx * img[j0, i1])
            + ty * ((1 - tx) * img[j1, i0] + tx * img[j1, i1]))


def envelope_grid(shape, tip, feed, dz, n_phi, top):
    """Envelope points (n_z, n_phi, 3) at heights (k+.5)dz up to ``top`` above the tip (at most
    the stick-out) and angles (j+.5)360/n_phi from the feed direction ``feed`` (deg)."""
    n_z = int(np.clip(np.ceil(min(top, shape.stickout_mm) / dz), 1, None))
    z = (np.arange(n_z) + 0.5) * dz
    phi = (np.arange(n_phi) + 0.5) * 360.0 / n_phi
    r = shape.profile_radius(z)
    th = np.radians(phi + feed)
    return np.stack(np.broadcast_arrays(tip[0] + r[:, None] * np.cos(th)[None],
                                        tip[1] + r[:, None] * np.sin(th)[None],
                                        tip[2] + z[:, None]), axis=-1)


def trim(E):
    """``E`` without the levels above its highest engaged one (at least one level)."""
    lev = np.nonzero(E.any(1))[0]
    return E[:int(lev[-1]) + 1 if len(lev) else 1]


def engagement(shape, view, h, tip, feed, dz, n_phi, tol):
    """E[k, j]: envelope point at height (k+.5)dz, angle (j+.5)360/n_phi inside the material.

    ``h`` is the top of the material left before the cut (absolute z per pixel of ``view``, a
    from-below window; the view's near plane where there is none).
    """
    P = envelope_grid(shape, tip, feed, dz, n_phi, np.max(h) - tip[2] if h.size else 0.0)
    cols, rows, _ = view.project(P)
    return trim(P[..., 2] < bilinear(h, cols, rows) - tol)


def engagement_along_normal(eng, ks, gen, pg, shape, wp, renderer, px_per_mm, cutting, bounds, mesh,
                             tips, s_start, fd, tops, dz, n_phi, tol):
    """Claim 5 seen along the surface normal (claim 6) for the passes ``ks`` found in that view.

    On a steep wall the material a finishing pass removes is a layer tens of µm thick measured
    horizontally: from below it is one pixel wide, and the height field smears it over that
    pixel, so most of the side engagement is lost or invented. Along the normal that layer is a
    depth. Looking from inside the material along the normal, the material before the pass ends,
    on each ray, where the ray leaves the stock (W) or enters the sweep of an earlier pass (the
    T1 layers, cut where its snapshot starts: :func:`snapshot_from`), whichever is nearer; an envelope point is engaged when
    it lies before that depth.
    The window covers every envelope point up to the stock top that lies within the view's
    depth range around the surface; a ray that never leaves the stock within it (above the
    stock, or beyond the far plane) holds no material.
    """
    R = shape.radius_mm
    near, far = -0.5 * R, 0.5 * R
    for b0 in range(0, len(ks), PASSES_PER_BATCH):
        kb = np.asarray(ks[b0:b0 + PASSES_PER_BATCH])
        views, grids = [], []
        for k in kb:
            nrm, c = gen["eng_n"][k], gen["eng_c"][k]
            P = envelope_grid(shape, tips[k], fd[k], dz, n_phi, tops[k])
            probe = View(tuple(c), tuple(nrm), (0.0, 0.0, 1.0), 1.0, 1.0, px_per_mm, near, far)
            right, up, d = probe.basis()
            rel = P - c
            x, y, depth = rel @ right, rel @ up, rel @ d
            sel = (depth > near) & (depth < far)
            if not sel.any():
                sel = np.ones_like(depth, bool)
            pad = 2.0 / px_per_mm
            x0, x1, y0, y1 = x[sel].min() - pad, x[sel].max() + pad, y[sel].min() - pad, y[sel].max() + pad
            ctr = c + 0.5 * (x0 + x1) * right + 0.5 * (y0 + y1) * up
            views.append(View(tuple(ctr), tuple(nrm), tuple(up), x1 - x0, y1 - y0, px_per_mm, near, far))
            grids.append(P)
        n = len(views)
        zero = np.zeros(len(kb))                      # T1 = everything before s_start (snapshot_from)
        scene = layer_scene(views, pg, cutting, s_start[kb], zero, bounds, wp, mesh, tips[kb], fd[kb],
                             None, zero, material_only=True)
        imgs = renderer.render(views * N_LAYERS, scene)
        for i, k in enumerate(kb):
            W, T1, T1n = imgs[i], imgs[n + i], imgs[4 * n + i]
            end = np.where(W.id >= 0, np.minimum(np.minimum(W.depth, T1.depth), T1n.depth), near)
            cols, rows, depth = views[i].project(grids[i])
            hh, ww = end.shape
            ci = np.clip(np.floor(cols).astype(np.int64), 0, ww - 1)
            ri = np.clip(np.floor(rows).astype(np.int64), 0, hh - 1)
            # what this view decides: points within its depth range on rays where it found the
            # end of the stock
            seen = ((cols >= 0) & (cols <= ww) & (rows >= 0) & (rows <= hh) & (depth > near) & (depth < far)
                    & (W.id[ri, ci] >= 0))
            E = seen & (depth < bilinear(end, cols, rows) - tol)
            # the rest is read from below, as for every other pass: in a pocket corner the rest
            # material on the wall across lies beyond the depth range (sample pass 4822, down the
            # x wall with the y wall's rest material at 20° of its side: 25 % less force, the
            # deflection read 90 µm off the virtual machine's)
            below = eng[k][0]
            n_z = min(below.shape[0], E.shape[0])
            E[:n_z] |= below[:n_z] & ~seen[:n_z]
            eng[k] = (trim(E), dz, eng[k][2])
