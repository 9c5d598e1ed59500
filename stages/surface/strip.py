"""The generating point of a pass (seed 000 claims 1 and 4, with claim 6 for steep walls).

A tool moving along u leaves the surface with the points of its envelope whose normal N is
perpendicular to u: the strip (for a level pass, the meridians at ±90° from the feed and the tip).
Seed 000 renders the tool M at the prediction point p between the sweeps before (T1) and after
(T2) it over the stock W, and keeps M's pixels that stay in front: here the same test is made on
M's strip itself. A strip point survives where it lies inside the stock and inside no other sweep;
the survivors are the surface the pass leaves at p, their mean the generating point C, the mean of
their normals its contact angle q and rotation angle φ (claim 4).

Inside the other sweeps: in 3-axis machining every sweep removes everything above its lower
surface, so the final surface of the ordered scan answers it where the strip is seen well from
below: a point survives where nothing of the final surface lies below it. Where the strip is steep
(contact angle over :data:`STEEP_DEG`, claim 6: from below a wall shrinks below a pixel and the
seed loses it above 87.6°) it is tested against the sweeps of the passes that reach it, in closed
form (:func:`stages.geometry.clearance.inside_sweep`). With the design model, of a strip that
leaves both the design surface and rest material (a pass into a pocket corner rides over the
semi-finished stock there), the points deepest into the model are the contact.
"""
from __future__ import annotations

import numpy as np

from stages.geometry.clearance import inside_sweep
from stages.geometry.cutter import Cutter
from stages.geometry.passes import PassGeometry, straight_run
from stages.surface.ordered import TileScan

STEEP_DEG = 60.0          # strip points steeper than this are tested against the sweeps themselves
STRIP_STEP_DEG = 0.5      # spacing of the strip's samples on the corner
SHANK_MM = 2.0            # the side of the tool sampled above the corner (a wall's step-down)
DESIGN_TOL_MM = 0.35      # a strip deeper than this above the design model is rest material
CONTACT_BAND_MM = 0.01    # the points within this of the deepest into the model are the contact
SECOND_DEG = 30.0         # two runs of surviving strip points whose normals differ by more are two contacts
RUN_GAP_DEG = 5.0         # a gap in a run of survivors up to this long does not split it
TIE_MM = 1e-4            # surfaces within this of each other are a tie, won by the earlier pass
GRID_MM = 1.0             # cells of the index of sweeps for the steep points
CHUNK = 1024              # predictions at a time (bounds the arrays)
OFF_STOCK_Z = -1e9        # the stock's top where there is no stock
GEN_COLUMNS = ("gen_x_mm", "gen_y_mm", "gen_z_mm", "rotation_deg", "contact_deg", "nx", "ny", "nz",
               "gen2_x_mm", "gen2_y_mm", "gen2_z_mm", "rotation2_deg", "contact2_deg", "nx2", "ny2", "nz2")


def strip_normals(u: np.ndarray, step_deg: float = STRIP_STEP_DEG):
    """Outward tool normals N ⟂ u on the lower half of the envelope, for each move direction.

    Returns (m, S, 3) unit normals: the half great circle from the left horizontal (ψ = 180°)
    through the lowest point to the right horizontal (360°), seen along u. A plunge has the whole
    equator as its strip.
    """
    u = np.asarray(u, float).reshape(-1, 3)
    m = len(u)
    h = np.hypot(u[:, 0], u[:, 1])
    level = h > 1e-9
    e1 = np.where(level[:, None], np.stack([-u[:, 1], u[:, 0], np.zeros(m)], 1) / np.where(level, h, 1.0)[:, None],
                  [1.0, 0.0, 0.0])
    e2 = np.cross(u, e1)
    e2 /= np.maximum(np.linalg.norm(e2, axis=1, keepdims=True), 1e-12)
    psi = np.radians(np.arange(180.0, 360.0 + 1e-9, step_deg))
    n = np.cos(psi)[None, :, None] * e1[:, None] + np.sin(psi)[None, :, None] * e2[:, None]
    if (~level).any():                                   # plunge: the equator all round
        ring = np.radians(np.arange(0.0, 360.0, 360.0 / len(psi)))
        n[~level] = np.stack([np.cos(ring), np.sin(ring), np.zeros_like(ring)], 1)[None]
    return n


def strip_points(cutter: Cutter, tips: np.ndarray, u: np.ndarray):
    """Points (m, S, 3) of each tool's strip on the corner, and their outward normals."""
    n = strip_normals(u)
    q = np.degrees(np.arccos(np.clip(-n[..., 2], -1.0, 1.0)))
    th = np.degrees(np.arctan2(n[..., 1], n[..., 0]))
    return tips[:, None, :] + cutter.point(q, th), n


def flank_points(cutter: Cutter, tips: np.ndarray, side_n: np.ndarray):
    """Points (m, F, 3) on the tool's side (contact angle 90°) above the corner, along the outward
    horizontal normals ``side_n`` (m, 2, 3) of the strip's two ends, every tenth of :data:`SHANK_MM`."""
    heights = cutter.corner_mm + np.linspace(0.0, SHANK_MM, 21)[1:]
    side = (tips[:, None, None, :] + cutter.radius_mm * side_n[:, :, None, :] * [1.0, 1.0, 0.0]
            + heights[None, None, :, None] * [0.0, 0.0, 1.0])
    return side.reshape(len(tips), -1, 3), np.repeat(side_n, len(heights), axis=1)


def bilinear_z(image_z: np.ndarray, view, xy: np.ndarray) -> np.ndarray:
    """A from-below depth image (absolute z) at points ``xy`` (..., 2), bilinear between pixel
    centres; +inf where any of the four pixels is off the stock or the surface."""
    h, w = image_z.shape
    x0 = view.center[0] - view.shape[1] / (2 * view.px_per_mm)
    y0 = view.center[1] - view.shape[0] / (2 * view.px_per_mm)
    cx = (xy[..., 0] - x0) * view.px_per_mm - 0.5
    cy = (xy[..., 1] - y0) * view.px_per_mm - 0.5
    i0 = np.clip(np.floor(cx).astype(np.int64), 0, w - 2)
    j0 = np.clip(np.floor(cy).astype(np.int64), 0, h - 2)
    tx, ty = np.clip(cx - i0, 0.0, 1.0), np.clip(cy - j0, 0.0, 1.0)
    z = image_z
    return ((1 - ty) * ((1 - tx) * z[j0, i0] + tx * z[j0, i0 + 1])
            + ty * ((1 - tx) * z[j0 + 1, i0] + tx * z[j0 + 1, i0 + 1]))


def _xy_segment_distance(p, a, b):
    d = b - a
    dd = np.einsum("ij,ij->i", d, d)
    t = np.clip(np.einsum("ij,ij->i", p - a, d) / np.where(dd > 0, dd, 1.0), 0.0, 1.0)
    return np.hypot(*(p - a - t[:, None] * d).T)


class SweepIndex:
    """Which passes' sweeps reach into each cell of a grid over a tile (CSR lists)."""

    def __init__(self, pg: PassGeometry, cutter: Cutter, passes: np.ndarray, lo: np.ndarray, cell: float = GRID_MM):
        b = pg.sweep_bounds(cutter)[passes]
        self.lo, self.cell = np.asarray(lo, float), cell
        c0 = np.floor((b[:, 0, :2] - self.lo) / cell).astype(np.int64)
        c1 = np.floor((b[:, 1, :2] - self.lo) / cell).astype(np.int64)
        self.shape = (int(c1[:, 0].max()) + 2, int(c1[:, 1].max()) + 2)
        c0 = np.maximum(c0, 0)
        nx, ny = c1[:, 0] - c0[:, 0] + 1, c1[:, 1] - c0[:, 1] + 1
        k = np.repeat(np.arange(len(passes)), nx * ny)
        off = np.arange(k.size) - np.repeat(np.cumsum(nx * ny) - nx * ny, nx * ny)
        cx, cy = c0[k, 0] + off % nx[k], c0[k, 1] + off // nx[k]
        cells = cx * self.shape[1] + cy
        order = np.argsort(cells, kind="stable")
        self.cells, self.passes = cells[order], passes[k[order]]

    def pairs(self, xy: np.ndarray):
        """(point index, pass index) of every pass whose sweep may hold each point."""
        c = np.floor((xy - self.lo) / self.cell).astype(np.int64)
        ok = (c >= 0).all(1) & (c[:, 0] < self.shape[0]) & (c[:, 1] < self.shape[1])
        key = np.where(ok, c[:, 0] * self.shape[1] + c[:, 1], -1)
        a = np.searchsorted(self.cells, key, side="left")
        b = np.searchsorted(self.cells, key, side="right")
        n = np.where(ok, b - a, 0)
        rows = np.repeat(np.arange(len(xy)), n)
        idx = np.repeat(a - np.cumsum(n) + n, n) + np.arange(rows.size)
        return rows, self.passes[idx]


def generating_points(ts: TileScan, pg: PassGeometry, cutter: Cutter, pred: np.ndarray, tips: np.ndarray,
                      tol_mm: float, design=None, steep_deg: float = STEEP_DEG) -> dict:
    """Generating point, φ, q and normal of passes ``pred`` (indices) at prediction tips ``tips``.

    A strip point is tested against the other passes by the order the machine cuts them: a pass
    before this one that leaves the same surface (a tie within :data:`TIE_MM`: the next level's
    flank on a vertical wall) has cut it already, one after it cuts nothing there. The own path
    is not another pass: within :func:`own_path_reach` of p its neighbouring chords leave the same
    surface, each at its own position, and a line split into pieces (its straight run,
    :func:`stages.geometry.passes.straight_run`) is one move of the tool whose flank, on a climb,
    runs ahead of it over the wall.

    Returns a dict of (m,) columns: gen_x_mm, gen_y_mm, gen_z_mm, rotation_deg, contact_deg,
    nx, ny, nz, n_px (the strip points that survive), view ("strip" or "none": the pass leaves no
    surface at p), and the same with ``2`` of a second contact (:func:`contact_labels`; NaN and
    ``n2_px`` 0 where there is none). ``steep_deg``: strip points steeper than this are tested against the sweeps
    (claim 6); 90 reads every point from below.
    """
    m = len(pred)
    out = {k: np.full(m, np.nan) for k in GEN_COLUMNS}
    out["n_px"], out["n2_px"] = np.zeros(m, np.int64), np.zeros(m, np.int64)
    out["view"] = np.array(["none"] * m, dtype=object)
    if m == 0:
        return out
    view = ts.tile.view
    index = SweepIndex(pg, cutter, ts.tile.drawn, np.array(view.center[:2]) - [view.width_mm / 2, view.height_mm / 2])
    final_z = np.where(np.isfinite(ts.final.depth), ts.final.depth, ts.stock_z)
    stock_z = np.where(np.isfinite(ts.stock_z), ts.stock_z, OFF_STOCK_Z)      # no material off the stock
    d = pg.p1 - pg.p0
    u_all = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)

    s_tip = pg.s0[pred] + np.linalg.norm(tips - pg.p0[pred], axis=1)
    reach = own_path_reach(pg, cutter, pred, tol_mm)
    run_lo, run_hi = straight_run(pg, pred)
    s_end = pg.s0 + pg.length

    def inside_others(pts, row, i, j):
        """Kill flags for points ``pts`` (of predictions ``row``) from pairs (point i, pass j)."""
        r = row[i]
        own = ((s_end[j] >= s_tip[r] - reach[r]) & (pg.s0[j] <= s_tip[r] + reach[r])) \
            | ((j >= run_lo[r]) & (j <= run_hi[r]))
        i, j = i[~own], j[~own]
        who = pred[row]
        eps = np.where(j < who[i], -TIE_MM, TIE_MM)
        hit = inside_sweep(pts[i], pg.p0[j], pg.p1[j], cutter, eps=eps)
        killed = np.zeros(len(pts), bool)
        killed[i[hit]] = True
        return killed

    for a in range(0, m, CHUNK):
        k = pred[a:a + CHUNK]
        P, N = strip_points(cutter, tips[a:a + CHUNK], u_all[k])
        q = np.degrees(np.arccos(np.clip(-N[..., 2], -1.0, 1.0)))
        alive = P[..., 2] < bilinear_z(stock_z, view, P[..., :2]) - tol_mm
        steep = q > steep_deg
        # seen from below: nothing of the final surface below the point
        shallow = alive & ~steep
        alive[shallow] = bilinear_z(final_z, view, P[shallow][:, :2]) >= P[shallow][:, 2] - 2.0 * tol_mm
        # steep: inside none of the sweeps that left the final surface around it
        r, s = np.nonzero(alive & steep)
        if len(r):
            i, j = owners_around(ts.final.id, view, P[r, s][:, :2])
            killed = inside_others(P[r, s], a + r, i, j)
            alive[r[killed], s[killed]] = False
        # the side above the corner, where the strip's end (the equator) survives: a flat or a
        # bull-nose flank on a vertical wall, a ball's between two levels. A plunge's strip is
        # the whole ring: its contacts are read on the ring alone, alike all round
        plunge = np.hypot(u_all[k, 0], u_all[k, 1]) <= 1e-9
        ends = alive[:, [0, -1]] & ~plunge[:, None]
        F, FN = flank_points(cutter, tips[a:a + CHUNK], N[:, [0, -1]])
        f_alive = np.repeat(ends, F.shape[1] // 2, axis=1)
        f_alive &= F[..., 2] < bilinear_z(stock_z, view, F[..., :2]) - tol_mm
        r, s = np.nonzero(f_alive)
        if len(r):
            pts = F[r, s]
            i, j = index.pairs(pts[:, :2])
            near = np.minimum(pg.p0[j, 2], pg.p1[j, 2]) < pts[i, 2]      # the tool lies above its tip
            i, j = i[near], j[near]
            near = _xy_segment_distance(pts[i, :2], pg.p0[j, :2], pg.p1[j, :2]) < cutter.radius_mm + tol_mm
            killed = inside_others(pts, a + r, i[near], j[near])
            f_alive[r[killed], s[killed]] = False
        P, N = np.concatenate([P, F], 1), np.concatenate([N, FN], 1)
        alive = np.concatenate([alive, f_alive], 1)
        if design is not None:
            alive = _on_design(design, P, alive)
        label = contact_labels(alive, N, S=N.shape[1] - F.shape[1], cyclic=plunge)
        _store(out, slice(a, a + len(k)), P, N, label == 1, pg.feed_deg[k], "")
        _store(out, slice(a, a + len(k)), P, N, label == 2, pg.feed_deg[k], "2")
    return out


def own_path_reach(pg: PassGeometry, cutter: Cutter, pred: np.ndarray, tol_mm: float) -> np.ndarray:
    """Path distance around each prediction point over which the own path is the pass itself.

    A tooth feed f each way (the tool one tooth on touches the strip only by f²/2rc), and beyond it
    as far as the neighbouring tool positions stay within ten mesh tolerances of the strip,
    √(20 rc tol) (the seed's own-path strip, para 0066).
    """
    rpm = np.where(np.isfinite(pg.spindle_rpm[pred]), pg.spindle_rpm[pred], 0.0)
    f = np.where(rpm > 0, pg.feed_mm_min[pred] / np.maximum(rpm, 1e-9) / cutter.flutes, 0.0)
    rc = max(cutter.corner_mm, 0.25 * cutter.radius_mm)
    return np.maximum(np.nan_to_num(f), np.sqrt(20.0 * rc * tol_mm))


def owners_around(ids: np.ndarray, view, xy: np.ndarray, half: int = 2):
    """(point index, pass index) of the distinct passes that left the final surface within ``half``
    pixels of each point (the suspects of having cut below it)."""
    h, w = ids.shape
    x0 = view.center[0] - view.shape[1] / (2 * view.px_per_mm)
    y0 = view.center[1] - view.shape[0] / (2 * view.px_per_mm)
    ci = np.floor((xy[:, 0] - x0) * view.px_per_mm).astype(np.int64)
    cj = np.floor((xy[:, 1] - y0) * view.px_per_mm).astype(np.int64)
    d = np.arange(-half, half + 1)
    ii = np.clip(ci[:, None, None] + d[None, None, :], 0, w - 1)
    jj = np.clip(cj[:, None, None] + d[None, :, None], 0, h - 1)
    own = ids[jj, ii].reshape(len(xy), -1).astype(np.int64)
    point = np.repeat(np.arange(len(xy)), own.shape[1])
    own = own.reshape(-1)
    ok = own >= 0
    n = int(own.max(initial=0)) + 1
    pair = np.unique(point[ok] * n + own[ok])
    return pair // n, pair % n


def _on_design(design, P, alive):
    """Of each strip's survivors, those deepest into the design model (within CONTACT_BAND_MM),
    when the deepest lies within DESIGN_TOL_MM of it; else all of them."""
    r, s = np.nonzero(alive)
    if not len(r):
        return alive
    sd = design.signed_distance(P[r, s])
    deepest = np.full(alive.shape[0], np.inf)
    np.minimum.at(deepest, r, sd)
    use = deepest[r] <= DESIGN_TOL_MM
    keep = ~use | (sd <= deepest[r] + CONTACT_BAND_MM)
    out = np.zeros_like(alive)
    out[r[keep], s[keep]] = True
    return out


def contact_labels(alive: np.ndarray, N: np.ndarray, S: int, cyclic: np.ndarray) -> np.ndarray:
    """Which contact each surviving point belongs to: 1, 2, or 0 (none).

    The survivors on the strip (its first ``S`` points; a plunge's ring is ``cyclic``) fall into
    runs; the flank points above each end belong to that end's run. When the two largest runs'
    mean normals differ by more than :data:`SECOND_DEG` the pass touches the surface twice (a ball
    in a vertical corner, in a V groove): the largest run is the first contact and the next the
    second. Otherwise every survivor is the one contact (a continuous contact, as in a fillet of
    the tool's own radius, is one run however far its normals turn).
    """
    m, K = alive.shape
    a = alive[:, :S] | short_gaps(alive[:, :S], int(RUN_GAP_DEG / STRIP_STEP_DEG), cyclic)
    start = a & ~np.concatenate([np.zeros((m, 1), bool), a[:, :-1]], 1)
    run = np.cumsum(start, 1) * a
    wrap = cyclic & a[:, 0] & a[:, -1]                    # the ring's last run is its first
    run = np.where(wrap[:, None] & a & (run == run[:, -1:]), 1, run)
    nf = (K - S) // 2
    flank = np.concatenate([np.repeat(run[:, :1], nf, 1), np.repeat(run[:, -1:], K - S - nf, 1)], 1)
    full = np.concatenate([run, flank * alive[:, S:]], 1)
    r, c = np.nonzero(alive)
    n_runs = int(full.max()) + 1
    size = np.zeros((m, n_runs))
    np.add.at(size, (r, full[r, c]), 1.0)
    size[:, 0] = 0.0
    nsum = np.zeros((m, n_runs, 3))
    np.add.at(nsum, (r, full[r, c]), N[r, c])
    rows = np.arange(m)
    first = np.argmax(size, 1)
    rest = size.copy()
    rest[rows, first] = 0.0
    second = np.argmax(rest, 1)
    n1, n2 = nsum[rows, first], nsum[rows, second]
    cos = np.einsum("ij,ij->i", n1, n2) / np.maximum(np.linalg.norm(n1, axis=1) * np.linalg.norm(n2, axis=1), 1e-12)
    split = (rest[rows, second] > 0) & (cos < np.cos(np.radians(SECOND_DEG)))
    full = full * alive
    label = np.where(alive, 1, 0)
    label = np.where(split[:, None], np.where(full == first[:, None], 1, np.where(full == second[:, None], 2, 0)), label)
    return label * alive


def short_gaps(a: np.ndarray, most: int, cyclic: np.ndarray) -> np.ndarray:
    """Points of each row of ``a`` in a gap of at most ``most`` between two True points (a sparse
    design model's distances leave single holes in a continuous contact)."""
    m, S = a.shape
    if cyclic.any():                                   # a ring: look round the end
        b = np.concatenate([a, a, a], 1)
        g = short_gaps(b, most, np.zeros(m, bool))[:, S:2 * S]
        return np.where(cyclic[:, None], g, short_gaps(a, most, np.zeros(m, bool)))
    i = np.arange(S)
    prev = np.maximum.accumulate(np.where(a, i, -1), axis=1)
    nxt = np.minimum.accumulate(np.where(a, i, S)[:, ::-1], axis=1)[:, ::-1]
    return ~a & (prev >= 0) & (nxt < S) & (nxt - prev - 1 <= most)


def _store(out, rows, P, N, alive, feed_deg, sfx=""):
    n = alive.sum(1)
    w = alive[..., None].astype(float)
    c = (P * w).sum(1) / np.maximum(n, 1)[:, None]
    nm = -(N * w).sum(1)                                 # the material's normal is minus the tool's
    nm /= np.maximum(np.linalg.norm(nm, axis=1, keepdims=True), 1e-12)
    q = np.degrees(np.arccos(np.clip(nm[:, 2], -1.0, 1.0)))
    phi = np.mod(np.degrees(np.arctan2(-nm[:, 1], -nm[:, 0])) - feed_deg, 360.0)
    has = n > 0
    for key, v in (("gen_x_mm", c[:, 0]), ("gen_y_mm", c[:, 1]), ("gen_z_mm", c[:, 2]), ("rotation_deg", phi),
                   ("contact_deg", q), ("nx", nm[:, 0]), ("ny", nm[:, 1]), ("nz", nm[:, 2])):
        out[key.replace("_", sfx + "_", 1) if "_" in key else key + sfx][rows] = np.where(has, v, np.nan)
    out["n" + sfx + "_px"][rows] = n
    if not sfx:
        out["view"][rows] = np.where(has, "strip", "none")
