"""Stage ``generating`` (seed 000 claims 1, 4, 5, 6; paras 0042-0046, 0064-0078).

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
(:func:`_own_path_strip`). The surviving pixels are the surface this pass leaves; their mean is
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
contact's normal and separated from it (:func:`_second_estimate`), the surface found along that
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
the engagement is read in that direction too (:func:`_engagement_along_normal`). Table
``engagement``; decode a row with :func:`unpack_engagement`.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pyarrow as pa

import schemas
from stages import InputError
from stages.cut_filter import (
    PASSES_PER_DRAW,
    coarse_tolerance,
    fine_tolerance,
    render_settings,
    scan_tiles,
    z_range,
)
from stages.geometry.cutter import Cutter
from stages.geometry.envelope import envelope_copies, envelope_mesh
from stages.geometry.passes import (
    PassGeometry,
    overlaps,
    pass_geometry,
    window_xy_bounds,
)
from stages.geometry.sweeps import ordered_sweep_scene, segment_scene
from stages.geometry.workpiece import (
    load_design_surface,
    load_workpiece,
    workpiece_scene,
)
from stages.render import Scene, Snapshot, View

NAME = "generating"
VERSION = "17"
INPUTS = ("passes", "stock", "cut_filter", "angle_prune", "nominal")
OUTPUTS = ("generating", "engagement")
PARAMS = ("tool", "render")
# The engine runs a program's predictions as this many shards on separate workers (each shard
# every SHARDS-th predicted pass, so pocket walls and floors spread evenly; each shard repeats the
# ordered scan for its own snapshots, a few % of the work) and joins them with combine_shards.
SHARDS = 4

ID_W, ID_T1, ID_T2, ID_M = 0, 1, 2, 3
STEEP_DEG = 60.0          # claim 6: re-render along the normal above this contact angle
# with the design model given (workflow ``nominal``), surviving pixels farther than this from it are
# rest material the program leaves for another (a pass down a wall into a pocket corner rides over
# the stock the semi-finishing left there, 0.5-1.7 mm off the model on the sample), not the design
# surface the pass finishes; the generating point is taken on the design surface where the pass
# leaves any. Over cusps, CAM and render tolerance and the moves of a correction round (a corrected
# path's envelope lies up to correct.max_move_um off the model by construction; 0.3 mm on the
# sample), under the rest material.
DESIGN_TOL_MM = 0.35
# the pixels deepest into the design surface, within this of the deepest: the pass's contact (a ball
# lifts 10 µm off a plane 0.32 mm from its contact point; the sample's cusps are 9 µm high, so
# between two rows the band is the whole strip the pass leaves, as without the model)
CONTACT_BAND_MM = 0.01
# the strip estimate of a pass lost from below (_strip_estimate) with the design model: the strip
# points within this of the deepest into the model aim the view (wide enough to hold the contact's
# neighbourhood on a wall the tool climbs: the side departs from a 2° draft by 0.1 mm over 3 mm),
# from at most this many strip points
STRIP_BAND_MM = 0.1
STRIP_DESIGN_POINTS = 4000
# a second contact (_second_estimate): strip points more than SECOND_DEG off the generating point's
# normal, the deepest of them within SECOND_TOL_MM of the generating point's depth into the model
# (the rest material across a pocket corner the pass does not reach lies 0.5 mm and more off it;
# the sample's y wall at x 73.5, y 53, which the row y 48 does cut, 0.09-0.25 mm), the patch of those within
# CONTACT_BAND_MM of that deepest within SECOND_SPREAD_DEG of its mean direction (a ball in a
# plane's contact: ±5° for the band; a fillet of the ball's own radius: the whole arc, rejected)
SECOND_DEG = 30.0
SECOND_TOL_MM = DESIGN_TOL_MM
SECOND_SPREAD_DEG = 15.0
PASSES_PER_BATCH = 8          # view-correction windows per render
M_WINDOWS_PER_BATCH = 256     # from-below windows of M per render (bounds the images in memory)
N_LAYERS = 5
# view correction steps: (window side in tool radii, zoom over px_per_mm)
VIEW_STEPS = ((1.0, 2.0), (0.25, 8.0))
_redo_when_lost = True     # claim 6 also when nothing survives from below (tests switch it off)
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


def _segments_around(pg, cutting, s_p, f, win_lo, win_hi, bounds, gap):
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


def _layer_scene(views, pg, cutting, s_p, f, bounds, wp, mesh, m_tips, m_feed, coarse, gap,
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
    segs = _segments_around(pg, cutting, s_p, f, lo, hi, bounds, gap)
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


def _on_design(design, view, M, mask, tol_mm=DESIGN_TOL_MM):
    """The pixels of ``mask`` where the pass touches the design surface: the deepest into it
    (signed distance, within :data:`CONTACT_BAND_MM` of the lowest), when the lowest lies within
    ``tol_mm`` above it; all of ``mask`` when the design model is not given or none is that low.

    Deepest, not nearest: a path a correction round moved into the material leaves its envelope
    under the model, and its pixels nearest the model are where it meets the neighbouring row's
    surface, off its contact."""
    if design is None or not mask.any():
        return mask
    rows, cols = np.nonzero(mask)
    pts = view.pixel_points(rows, cols, M.depth[mask])
    dist = design.signed_distance(pts)
    if not dist.min() <= tol_mm:
        return mask
    near = dist <= dist.min() + CONTACT_BAND_MM
    out = np.zeros_like(mask)
    out[rows[near], cols[near]] = True
    return out


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
               n_phi=N_PHI, dz_mm=None, tol_mm=None, design=None):
    """Generating points and engagement for passes ``predict_idx`` at tips ``pred_tips``.

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
    gen["eng_c"] = np.full((m, 3), np.nan)      # engagement view (not in the table, see _store)
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
    final, tile_of = _scan_program(pg, shape, wp, renderer, px_per_mm, mesh, predict_idx, pred_tips,
                                   f, u, zlo, zhi, half, eng, dz, n_phi, tol, fd, tops, snap)
    path_lo, path_hi = pg.s0, pg.s0 + pg.length
    redo = []                                     # (slot, estimated q, phi)
    from stages.render import make_scene
    for b0 in range(0, m, M_WINDOWS_PER_BATCH):
        ks = np.arange(b0, min(m, b0 + M_WINDOWS_PER_BATCH))
        # M at the prediction points, from below, many windows per atlas
        views = [View((t[0], t[1], 0.0), (0, 0, 1.0), (np.cos(np.radians(a)), np.sin(np.radians(a)), 0.0),
                      2 * half, 2 * half, px_per_mm, zlo, zhi) for t, a in zip(pred_tips[ks], fd[ks])]
        tris, q, phi, owner = envelope_copies(mesh, pred_tips[ks], feed_deg=fd[ks], view_dir=(0, 0, 1.0))
        mimgs = renderer.render(views, make_scene(tris, owner, ID_M, a=phi, b=q))
        del tris, q, phi, owner
        for v, M, k in zip(views, mimgs, ks):
            _from_below(gen, redo, k, v, M, final[tile_of[k]], shape, eng[k][0], dz, n_phi,
                        s_p[k], f[k], gap[k], u[k], fd[k], path_lo, path_hi, design, pred_tips[k])
    _view_correction(gen, redo, pg, shape, wp, renderer, px_per_mm, cutting, bounds, mesh, coarse,
                     pred_tips, s_p, f, fd, gap, u, design)
    steep = [k for k, _, _ in redo if gen["view"][k] == "normal"]
    _engagement_along_normal(eng, steep, gen, pg, shape, wp, renderer, px_per_mm, cutting, bounds, mesh,
                             pred_tips, pg.s0[snap], fd, tops, dz, n_phi, tol)
    if design is not None:
        # the second contact: aimed by the engaged strip, found along its normal as claim 6 finds
        # a steep wall (what the view sees there is the surface this pass leaves, or nothing)
        second = []
        for k in np.nonzero(gen["view"] != "none")[0]:
            n1 = np.array([gen["nx"][k], gen["ny"][k], gen["nz"][k]])
            c1 = np.array([gen["gen_x_mm"][k], gen["gen_y_mm"][k], gen["gen_z_mm"][k]])
            est = _second_estimate(shape, eng[k][0], dz, n_phi, u[k], fd[k], pred_tips[k], design, n1, c1)
            if est is not None:
                second.append((int(k), est[0], est[1]))
        _view_correction(gen, second, pg, shape, wp, renderer, px_per_mm, cutting, bounds, mesh, coarse,
                         pred_tips, s_p, f, fd, gap, u, design, second=True)
    return gen, eng


def _from_below(gen, redo, k, view, M, fin, shape, E, dz, n_phi, s_p, f, gap, u, fd, path_lo, path_hi,
                design=None, tip=None):
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
    strip = _own_path_strip(M, shape, u, fd, f)
    surv = np.zeros_like(on)
    surv[on] = near
    surv &= strip
    if surv.any():
        on = _on_design(design, view, M, surv)
        qk, phik = _angles(M, on)
        _store(gen, k, view, M, on, qk, phik, fd, "below", all_mask=surv)
        if qk > STEEP_DEG:
            redo.append((k, qk, phik))
    elif _redo_when_lost:
        # nothing survives from below (steep walls shrink below a pixel, or the pass rolls over
        # an edge): the surface it leaves lies on its own-path strip (the envelope circle
        # perpendicular to the motion) where that strip is in the material before the cut;
        # the mean direction of those engaged points is where to look from (claim 6)
        est = _strip_estimate(shape, E, dz, n_phi, u, fd, tip=tip, design=design)
        if est is not None:
            redo.append((k, max(est[0], STEEP_DEG), est[1]))


def _strip_points(shape, E, dz, n_phi, u, feed_deg, width=0.1):
    """The engaged envelope points of the own-path strip (|N·u| < ``width``, N the envelope normal)
    of engagement grid ``E``: their grid indices (k, j), contact angles q and world azimuths θ (rad)
    and envelope normals N (world frame, out of the tool: minus the material's normal there)."""
    n_z = E.shape[0]
    z = (np.arange(n_z) + 0.5) * dz
    rc = max(shape.corner_mm, 1e-9)
    q = np.where(z < rc, np.arccos(np.clip((rc - z) / rc, -1.0, 1.0)), np.pi / 2)
    th = np.radians((np.arange(n_phi) + 0.5) * 360.0 / n_phi + feed_deg)
    u = np.asarray(u, float)
    # N·u = sin q (cos θ u_x + sin θ u_y) − cos q u_z, an outer product: the grid's normals are
    # formed only at the strip's points (a wall climb's grid holds 10⁵–10⁶ points)
    nu = np.sin(q)[:, None] * (np.cos(th) * u[0] + np.sin(th) * u[1])[None] - (np.cos(q) * u[2])[:, None]
    kk, jj = np.nonzero(E & (np.abs(nu) < width))
    qs, ts = q[kk], th[jj]
    return kk, jj, qs, ts, np.stack([np.sin(qs) * np.cos(ts), np.sin(qs) * np.sin(ts), -np.cos(qs)], axis=1)


def _strip_world(shape, tip, dz, kk, th):
    """World coordinates of strip points at levels ``kk`` and azimuths ``th`` of the tool at ``tip``."""
    z = (kk + 0.5) * dz
    r = shape.profile_radius(z)
    return np.asarray(tip, float)[:3] + np.stack([r * np.cos(th), r * np.sin(th), z], axis=1)


def _mean_angles(q, th, feed_deg):
    """(q, φ) in degrees, φ from the feed direction, of the mean of envelope directions (q, θ)."""
    v = np.array([np.mean(np.sin(q) * np.cos(th)), np.mean(np.sin(q) * np.sin(th)), np.mean(np.cos(q))])
    return (float(np.degrees(np.arctan2(np.hypot(v[0], v[1]), v[2]))),
            float((np.degrees(np.arctan2(v[1], v[0])) - feed_deg) % 360.0))


def _strip_estimate(shape, E, dz, n_phi, u, feed_deg, width=0.1, tip=None, design=None):
    """(q, φ) of the mean direction of the engaged envelope points with |N·u| < ``width``.

    ``E`` is the engagement grid (axial levels × rotation angles, see :func:`unpack_engagement`);
    N is the envelope normal at a grid point. With the design model and the ``tip`` (world
    coordinates of the grid's origin), only the strip points deepest into the design surface
    count (within :data:`STRIP_BAND_MM`, when the deepest lies within :data:`DESIGN_TOL_MM`): in
    a pocket corner the strip also runs through the rest material on the wall across, and the
    mean of all of it points between the walls (sample: the passes climbing the pocket's x wall
    0.9 mm from the y wall's rest material, φ 32–41° against the contact's 4°; the view aimed
    there saw nothing, or a few pixels of its edge, and the pass had no generating point or a
    wrong one). Returns None when no such point is engaged.
    """
    kk, jj, q, th, _ = _strip_points(shape, E, dz, n_phi, u, feed_deg, width)
    if not len(kk):
        return None
    if design is not None and tip is not None:
        take = np.linspace(0, len(kk) - 1, min(len(kk), STRIP_DESIGN_POINTS)).astype(np.int64)
        kk, q, th = kk[take], q[take], th[take]
        sd = design.signed_distance(_strip_world(shape, tip, dz, kk, th))
        if sd.min() <= DESIGN_TOL_MM:
            # the patch around the deepest point: in a vertical corner both walls lie within the
            # band, and their mean aims between them at neither (the second contact is found later)
            i = int(np.argmin(sd))
            near = (np.sin(q) * np.sin(q[i]) * np.cos(th - th[i]) + np.cos(q) * np.cos(q[i])
                    > np.cos(np.radians(SECOND_DEG)))
            deep = (sd <= sd.min() + STRIP_BAND_MM) & near
            q, th = q[deep], th[deep]
    return _mean_angles(q, th, feed_deg)


def _second_estimate(shape, E, dz, n_phi, u, feed_deg, tip, design, n1, c1, width=0.1):
    """(q, φ) where the pass touches the design surface a second time, or None.

    A ball in a pocket's vertical corner finishes both walls at once, and one on a floor beside a
    wall its foot too: two contacts whose normals lie far apart, with no contact between them.
    One generating point stands for one of them (from below a vertical wall is edge-on; along one
    wall's normal the other is), and on the sample's corner climbs (source lines 3996 and 3999)
    which one changed from piece to piece with the pixels each piece happened to cut. The second
    contact is sought on the engaged strip (as :func:`_strip_estimate`): its points more than
    :data:`SECOND_DEG` off the generating point's normal ``n1`` whose deepest lies within
    :data:`SECOND_TOL_MM` of the generating point ``c1``'s depth into the model (so not the rest
    material across a corner, 0.5–1.7 mm off it), separated from the first (no strip point between
    half that angle and it within 2 × :data:`CONTACT_BAND_MM` of that depth: a ball rolling in a
    fillet of its own radius touches along the whole arc, which is one contact), and whose points
    within :data:`CONTACT_BAND_MM` of that deepest form one tight patch (within
    :data:`SECOND_SPREAD_DEG` of their mean).
    """
    kk, jj, q, th, N = _strip_points(shape, E, dz, n_phi, u, feed_deg, width)
    cos_a = -(N @ np.asarray(n1, float))                  # cosine of each point's angle off n1
    if not (cos_a < np.cos(np.radians(SECOND_DEG))).any():
        return None
    take = np.linspace(0, len(kk) - 1, min(len(kk), STRIP_DESIGN_POINTS)).astype(np.int64)
    kk, q, th, cos_a = kk[take], q[take], th[take], cos_a[take]
    far = cos_a < np.cos(np.radians(SECOND_DEG))
    if not far.any():
        return None
    sd = design.signed_distance(_strip_world(shape, tip, dz, kk, th))
    sd1 = float(design.signed_distance(np.asarray(c1, float)[None])[0])
    sd2 = float(sd[far].min())
    if not sd2 <= sd1 + SECOND_TOL_MM:
        return None
    # a contact that runs on from the first to the second (a fillet) is one contact: none of the
    # strip between SECOND_DEG / 2 and SECOND_DEG off n1 lies that close to the model
    between = (cos_a < np.cos(np.radians(SECOND_DEG / 2))) & ~far
    if (between & (sd <= sd2 + 2 * CONTACT_BAND_MM)).any():
        return None
    deep = far & (sd <= sd2 + CONTACT_BAND_MM)
    q, th = q[deep], th[deep]
    q2, phi2 = _mean_angles(q, th, feed_deg)
    m2 = material_normal(q2, phi2, feed_deg)
    own = np.stack([-np.sin(q) * np.cos(th), -np.sin(q) * np.sin(th), np.cos(q)], axis=1)
    if np.min(own @ m2) < np.cos(np.radians(SECOND_SPREAD_DEG)):
        return None
    return q2, phi2


def _scan_program(pg, shape, wp, renderer, px_per_mm, mesh, predict_idx, tips, f, u, zlo, zhi, half,
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
            eng[k] = (_engagement(shape, sv, depth, tips[k], fd[k], dz, n_phi, tol), dz,
                      (np.cos(np.radians(fd[k])), np.sin(np.radians(fd[k]))))

        res = renderer.scan(view, workpiece_scene(wp, [view], -2.0), batches(), len(pg.pass_id), 1,
                            on_snapshot=on_snapshot)
        final.append(res.final)
    return final, tile_of


def _view_correction(gen, redo, pg, shape, wp, renderer, px_per_mm, cutting, bounds, mesh, coarse,
                     tips, s_p, f, fd, gap, u, design=None, second=False):
    """Claim 6: look along the estimated normal, zoomed; zoom further where still nothing.

    With ``second`` the estimates are second contacts (:func:`_second_estimate`): of what the view
    sees, the pixels nearer in normal to the estimate than to the generating point's and within
    :data:`SECOND_DEG` of the estimate are the second contact (the first wall, seen obliquely, is
    not), stored in the ``*2`` columns (:func:`_store_second`).
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
            scene = _layer_scene(ovs, pg, cutting, s_p[ks], f[ks], bounds, wp, mesh, tips[ks], fd[ks],
                                 coarse, gap[ks])
            imgs = renderer.render(ovs * N_LAYERS, scene)
            still = []
            for r, k in enumerate(ks):
                layers = [imgs[L * n2 + r] for L in range(N_LAYERS)]
                surv, _ = _composite(layers, _own_path_strip(layers[3], shape, u[k], fd[k], f[k]))
                if second and surv.any():
                    pn = material_normal(layers[3].b.astype(float), layers[3].a.astype(float), fd[k])
                    cos2 = np.einsum("i...,i->...", pn, np.asarray(ovs[r].view_dir, float))
                    cos1 = np.einsum("i...,i->...", pn, np.array([gen["nx"][k], gen["ny"][k], gen["nz"][k]]))
                    surv &= (cos2 > cos1) & (cos2 > np.cos(np.radians(SECOND_DEG)))
                    if surv.any():
                        on = _on_design(design, ovs[r], layers[3], surv)
                        q, phi = _angles(layers[3], on)
                        _store_second(gen, k, ovs[r], layers[3], on, q, phi, fd[k])
                    else:
                        still.append(todo[r])
                elif surv.any():
                    on = _on_design(design, ovs[r], layers[3], surv)
                    q, phi = _angles(layers[3], on)
                    # the engagement is read along the direction of every pixel the pass leaves,
                    # rest material included: from below where anything survived there (this view
                    # may be aimed at the design surface alone; along a pocket wall the rest
                    # material on the wall across is then edge-on, and its engagement lost)
                    keep = np.isfinite(gen["eng_n"][k]).all()
                    ec, en = gen["eng_c"][k].copy(), gen["eng_n"][k].copy()
                    _store(gen, k, ovs[r], layers[3], on, q, phi, fd[k], "normal", all_mask=surv)
                    if keep:
                        gen["eng_c"][k], gen["eng_n"][k] = ec, en
                elif second or gen["view"][k] == "none":
                    still.append(todo[r])
            todo = still


def _store(gen, slot, view, M, mask, q, phi, feed, how, all_mask=None):
    """Generating point of ``slot`` from the pixels ``mask``; the direction the engagement is read
    along (:func:`_engagement_along_normal`) from ``all_mask`` (default ``mask``): every pixel the
    pass leaves, rest material included, as before the design surface was told apart."""
    rows, cols = np.nonzero(mask)
    pts = view.pixel_points(rows, cols, M.depth[mask])
    c = pts.mean(0)
    nrm = material_normal(q, phi, feed)
    if all_mask is not None and not np.array_equal(all_mask, mask):
        ra, ca = np.nonzero(all_mask)
        qa, pa_ = _angles(M, all_mask)
        gen["eng_c"][slot] = view.pixel_points(ra, ca, M.depth[all_mask]).mean(0)
        gen["eng_n"][slot] = material_normal(qa, pa_, feed)
    else:
        gen["eng_c"][slot], gen["eng_n"][slot] = c, nrm
    gen["gen_x_mm"][slot], gen["gen_y_mm"][slot], gen["gen_z_mm"][slot] = c
    gen["rotation_deg"][slot] = phi
    gen["contact_deg"][slot] = q
    gen["nx"][slot], gen["ny"][slot], gen["nz"][slot] = nrm
    gen["n_px"][slot] = int(mask.sum())
    gen["view"][slot] = how


SECOND_COLUMNS = ("gen2_x_mm", "gen2_y_mm", "gen2_z_mm", "rotation2_deg", "contact2_deg", "nx2", "ny2", "nz2")


def _store_second(gen, slot, view, M, mask, q, phi, feed):
    """Second contact of ``slot`` from the pixels ``mask`` (the ``*2`` columns)."""
    rows, cols = np.nonzero(mask)
    c = view.pixel_points(rows, cols, M.depth[mask]).mean(0)
    values = (*c, phi, q, *material_normal(q, phi, feed))
    for key, v in zip(SECOND_COLUMNS, values):
        gen[key][slot] = v
    gen["n2_px"][slot] = int(mask.sum())


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


def _envelope_grid(shape, tip, feed, dz, n_phi, top):
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


def _trim(E):
    """``E`` without the levels above its highest engaged one (at least one level)."""
    lev = np.nonzero(E.any(1))[0]
    return E[:int(lev[-1]) + 1 if len(lev) else 1]


def _engagement(shape, view, h, tip, feed, dz, n_phi, tol):
    """E[k, j]: envelope point at height (k+.5)dz, angle (j+.5)360/n_phi inside the material.

    ``h`` is the top of the material left before the cut (absolute z per pixel of ``view``, a
    from-below window; the view's near plane where there is none).
    """
    P = _envelope_grid(shape, tip, feed, dz, n_phi, np.max(h) - tip[2] if h.size else 0.0)
    cols, rows, _ = view.project(P)
    return _trim(P[..., 2] < bilinear(h, cols, rows) - tol)


def _engagement_along_normal(eng, ks, gen, pg, shape, wp, renderer, px_per_mm, cutting, bounds, mesh,
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
            P = _envelope_grid(shape, tips[k], fd[k], dz, n_phi, tops[k])
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
        scene = _layer_scene(views, pg, cutting, s_start[kb], zero, bounds, wp, mesh, tips[kb], fd[kb],
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
            eng[k] = (_trim(E), dz, eng[k][2])


def run(inputs: dict, params: dict, shard: tuple[int, int] | None = None) -> dict:
    """Generating points and engagement of the predicted passes; with ``shard`` = (i, n) only
    every n-th of them from the i-th on (see ``SHARDS``)."""
    passes = inputs["passes"]
    tool = params["tool"]
    shape = Cutter.from_params(tool)
    t = tool[0] if isinstance(tool, (list, tuple)) else tool
    pg = pass_geometry(passes, tool)
    wp = load_workpiece(inputs.get("stock"))
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
    if shard is not None:
        i, n = shard
        chosen = chosen[i::n]
    idx = np.array([pos[p] for p in chosen], np.int64)
    tips = np.array([pred[p] for p in chosen], float).reshape(-1, 3)
    gen, eng = generating(pg, shape, wp, renderer, ppm, idx, tips, int(t.get("flutes") or 2),
                          design=load_design_surface(inputs.get("nominal")))
    m = len(idx)
    pid = pa.array([pg.program_id] * m, pa.string())
    g = pa.table({"program_id": pid, "pass_id": pa.array(chosen, pa.int32()),
                  **{k: pa.array(gen[k]) for k in ("gen_x_mm", "gen_y_mm", "gen_z_mm",
                                                   "rotation_deg", "contact_deg", "nx", "ny", "nz")},
                  "n_px": pa.array(gen["n_px"], pa.int32()),
                  "view": pa.array(list(gen["view"]), pa.string()),
                  **{k: pa.array(gen[k]) for k in SECOND_COLUMNS},
                  "n2_px": pa.array(gen["n2_px"], pa.int32())})
    e = pa.table({"program_id": pid, "pass_id": pa.array(chosen, pa.int32()),
                  "dz_mm": pa.array([x[1] for x in eng], pa.float64()),
                  "n_z": pa.array([x[0].shape[0] for x in eng], pa.int32()),
                  "n_phi": pa.array([x[0].shape[1] for x in eng], pa.int32()),
                  "mask": pa.array([np.packbits(x[0].reshape(-1)).tobytes() for x in eng], pa.binary()),
                  "feed_dir_x": pa.array([x[2][0] for x in eng], pa.float64()),
                  "feed_dir_y": pa.array([x[2][1] for x in eng], pa.float64()),
                  "ramp_deg": pa.array(ramp_deg(pg.p1[idx] - pg.p0[idx]), pa.float64())})
    return {"generating": schemas.check("generating", g), "engagement": schemas.check("engagement", e)}


def combine_shards(parts: list[dict]) -> dict:
    """The tables of one program from its shards' tables, in pass order."""
    out = {}
    for name in OUTPUTS:
        t = pa.concat_tables([p[name] for p in parts])
        out[name] = t.take(pa.array(np.argsort(t.column("pass_id").to_numpy(), kind="stable")))
    return out

