"""Stage ``correct``: move NC vertices against the predicted error (seed 000 claim 9, para 0083–0084).

Every NC vertex (the end point of a motion block) is where two passes meet: the pass that ends
there (i) and the pass that starts there (j). With the predicted errors e (µm, positive = material
left) and surface normals n (out of material) of those passes, para 0084 forms the correction
reference vectors E'i = −e_i·n_i and E'j = −e_j·n_j, points the vertex move along E'i + E'j and
chooses its magnitude s by least squares so that the move best realises both. A pass moved by m
moves the surface it generates by m·n (a ball, or any axisymmetric tool, touching the surface at
the point with normal n: the tangential part of m slides along the surface), so with the unit
direction d the least-squares magnitude is

    s = argmin Σ_k (s·(d·n_k) + e_k)²  =  −Σ e_k (d·n_k) / Σ (d·n_k)².

Two passes with the same normal and error give m = −e·n exactly; perpendicular normals give
m = −(e_i n_i + e_j n_j), which realises both errors exactly.

- Vertices inside a pass that merges several short blocks get the error of that pass alone.
- A pass without an error row (pruned, non-cutting, rapid) contributes nothing: a vertex between it
  and a predicted pass follows the predicted pass; a vertex with no predicted pass on either side
  does not move.
- Moves are clipped at ``max_move_um`` (the total move over all iterations); clipped vertices are
  flagged in the ``clipped`` column.
- Gouge limit (``correct.gouge_limit``, on by default; needs the ``generating`` table and the
  tool): a vertex is not moved so far that the tool cuts past the generating point of another
  surface it passes beside (:func:`gouge_limit`); ``gouge_limit_um`` lists what was taken off: a
  heavy pass in a pocket corner asks to move sideways into the wall beside it, which the wall's
  own passes leave at the design.
- Arcs (G2/G3): the chord points of the arc are moved like vertices, then the arc is refitted by
  least squares: the centre lies on the perpendicular bisector of the moved end points (so the
  program stays consistent) at the position that best fits the moved chord points (algebraic
  circle fit, linear in the one unknown). Full circles keep their end on their start and fit the
  centre freely; arcs over 180° with a short chord (whose bisector would swing with every
  micrometre) fit the centre freely through the start and put the end back on the circle; an arc
  whose sweep would still jump by more than 90° is translated with its start instead.

Iteration (seed 003, DESIGN §7): :func:`correct_once` takes blocks, their passes and errors plus the
previous ``corrected`` table; it adds its move to the blocks' own offset from the original
coordinates (kept from the previous table), clips the total, counts iterations and reports the
change against the previous table's coordinates. Two kinds of errors drive it:

- residuals against the ORIGINAL surface (a measurement, or a closed-loop simulation): pass the
  current (corrected) blocks; the moves accumulate. :func:`correct_iteratively` runs this loop
  around any callable that machines/measures a program (the closed-loop tests).
- predictions, which are relative to the path they were made for (the surface of path P is
  P + e(P)·n): the command that leaves the original surface is the fixed point P = P0 − e(P)·n, so
  the move for the errors predicted on the corrected path is applied to the ORIGINAL blocks
  (:func:`run` with ``round_passes``; the engine repeats the chain, see the stage graph).

:func:`apply_corrected` turns a ``corrected`` table back into ``blocks`` (new coordinates and arc
centres) for the next prediction.
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa

from stages import InputError

NAME = "correct"
VERSION = "15"
INPUTS = ("blocks", "passes", "errors", "generating")
OUTPUTS = ("corrected",)
# only the clip limit and the relaxation of rounds 2… change the table; tol_um and max_iter steer
# the engine's rounds and the LN / compensation-table options the writer, so changing them re-uses
# every cached round
PARAMS = ("correct.max_move_um", "correct.relax", "correct.gouge_limit", "correct.normal_tol_deg", "tool")

DEFAULTS = {"max_move_um": 50.0, "tol_um": 0.1, "max_iter": 5, "relax": 1.0, "ln_normals": False,
            "comp_table": False, "gouge_limit": True, "normal_tol_deg": None}
_PLANE_AXES = {17: (0, 1, 2), 18: (2, 0, 1), 19: (1, 2, 0)}  # as stages.parse: (first, second, normal)
_EPS_UM = 1e-9
# normals of the two passes at a vertex closer than this are one normal for the least-squares
# refinement of the vertex move (see vertex_moves); about 4× the contact-angle accuracy of the
# generating stage (≤ 0.5° RMS, issue 3). correct.normal_tol_deg overrides it
NORMAL_TOL_DEG = 2.0
# the refinement moves a vertex at most this many times the larger of its two errors: realising two
# different errors along normals θ apart takes Δe / sin θ along the weak direction, and on the
# sample's pocket wall (normals 2.5° apart where the wall's slope changes) a 4 µm difference asked
# for ~100 µm, hit the move limit and lifted the top of the wall line instead of moving it in
REFINE_MAX_RATIO = 2.0
# the least-squares refinement does not slide a vertex along a path that turns there by less than
# this (vertex_moves): on the sample's row y 61.2, down a convex profile, passes 0.025–0.7 mm long
# have normals 4–6° apart in the plane of the path (−155 and −130 µm); realising both took
# Δe / sin θ ≈ 300 µm along the path against ~100 µm along the normals, alternating from vertex to
# vertex (a pass's surface follows both its ends, the per-vertex solve assumes it follows one),
# and the rounds folded the row (the virtual machine: −175 → −700 µm after three). A corner of the
# path (a ball rounding a wall foot: 2–3 vertices over 90°, a floor pass turning up a wall) turns
# by far more and keeps the refinement that realises both errors there.
PATH_TURN_DEG = 10.0
# where the path runs on through a vertex within this angle (a via point, or the vertex between
# two pieces of one line), the vertex takes the para 0084 move alone, without the refinement: its
# two passes finish one surface there, so the difference of their predicted normals is the
# prediction's scatter (the seed's cylinder: 0.4–0.9° between the 0.5 mm pieces of one level), and
# realising their two errors (the deflection changing along the line, as where the stock runs out
# in front of the ball) by the refinement turned that scatter into slides across the line (14–27 µm
# on the cylinder's levels at the stock's end, another each round) where each piece's error is
# realised by the moves of its own two ends anyway
LINE_TURN_DEG = 3.0
# smallest step fraction of a vertex whose rounds do not contract (see correct_once)
MIN_RELAX = 1.0 / 16
# gouge limit (see gouge_limit): generating points of other passes whose normal lies within this
# angle of a vertex's own pass normals are the same surface (the neighbouring rows of a floor or a
# slope, corrected by their own moves) and do not limit the vertex
SAME_SURFACE_DEG = 30.0
# a generating point deeper than this inside the tool at the ORIGINAL vertex is not one the vertex
# can gouge (the program already cuts there: a point taken off the design within the generating
# stage's tolerance, a crossing pass), so it sets no limit
GOUGE_INSIDE_MM = 0.02
# candidate search (see _NearTool): a vertex whose own normals are within _FLOOR_DEG of +z stands
# on a floor, and every point within _FLOOR_DEG + _FLAT_DEG ≤ SAME_SURFACE_DEG of +z is its surface
_FLOOR_DEG = 10.0
_FLAT_DEG = 20.0
# vertices checked at once (candidate pairs: ~10 per vertex on the sample mould)
_GOUGE_CHUNK = 8192
_PLANE_AXES_LUT = np.zeros((20, 3), np.int64)
for _pl, _ax in _PLANE_AXES.items():
    _PLANE_AXES_LUT[_pl] = _ax


def _col(table: pa.Table, name: str, dtype=float) -> np.ndarray:
    return table.column(name).to_numpy(zero_copy_only=False).astype(dtype)


def _xyz(table: pa.Table, names) -> np.ndarray:
    if table.num_rows == 0:
        return np.zeros((0, 3))
    return np.stack([_col(table, c) for c in names], axis=1)


def vertex_moves(err_a, n_a, has_a, err_b, n_b, has_b, refine=True, along_path=None,
                 normal_tol_deg=NORMAL_TOL_DEG):
    """Move of vertices shared by passes a and b (para 0084, refined by least squares), vectorised.

    The para 0084 move points along E'a + E'b with the least-squares magnitude. That realises both
    errors only when the normals are equal (with equal errors) or perpendicular; where the normals
    of the two passes differ at an oblique angle (a floor pass meeting a wall pass, the fan of
    normals at a concave corner), one magnitude cannot satisfy m·n_a = −e_a and m·n_b = −e_b, and
    the part left over came back round after round of the iteration (the sample mould's pocket
    corner). With ``refine`` the para 0084 move is completed by the damped least-squares move in
    the plane of the two normals that realises the remaining part of both errors:

        m = m_0084 + Nᵀ F(N Nᵀ) r,   N = [n_a; n_b],   r_k = −e_k − m_0084·n_k,

    F(G) = Σ_modes v (μ / (μ² + μ_tol²)) vᵀ over the eigen pairs (μ, v) of G, μ_tol =
    1 − cos(``normal_tol_deg``): a mode of clearly different normals is solved exactly (F → G⁻¹),
    normals closer than the tolerance are treated as one (the difference of two nearly parallel
    normals is within the accuracy of the predicted normals and would amplify error noise by
    1/sin(angle)); there the para 0084 move (the mean) stays. The refinement is limited to
    :data:`REFINE_MAX_RATIO` times the larger error (a vertex is not moved far along the direction
    both passes barely see). Where the path runs on nearly straight through the vertex
    (``along_path``: its unit direction there, zero where it turns by :data:`PATH_TURN_DEG` or
    more), the solved move's part along the path is taken off. Normals that differ only along the path
    are a profile's own curvature, and realising their different errors by sliding the vertex
    along its passes changes their lengths, not their surfaces (see :data:`PATH_TURN_DEG`).

    Parameters
    ----------
    err_a, err_b : (v,) float, errors of the two passes, µm (positive = material left)
    n_a, n_b : (v, 3) float, unit surface normals (out of material)
    has_a, has_b : (v,) bool, whether the pass has a prediction (else it does not count)
    refine : bool or (v,) bool, add the least-squares refinement (False: the para 0084 move alone;
        per vertex with an array)
    along_path : (v, 3) float or None, unit path direction the refinement must not move along
        (zero rows: no restriction)
    normal_tol_deg : float, normals closer than this are one normal for the refinement
        (default :data:`NORMAL_TOL_DEG`; ``correct.normal_tol_deg``)

    Returns
    -------
    (v, 3) float, vertex moves in µm.
    """
    err_a = np.where(has_a, np.nan_to_num(err_a), 0.0)
    err_b = np.where(has_b, np.nan_to_num(err_b), 0.0)
    n_a = np.nan_to_num(n_a)
    n_b = np.nan_to_num(n_b)
    wa, wb = has_a.astype(float), has_b.astype(float)
    ref = -(err_a * wa)[:, None] * n_a - (err_b * wb)[:, None] * n_b   # E'a + E'b
    size = np.linalg.norm(ref, axis=1)
    ok = size > _EPS_UM
    d = ref / np.where(ok, size, 1.0)[:, None]
    ca = np.einsum("ij,ij->i", d, n_a)
    cb = np.einsum("ij,ij->i", d, n_b)
    num = -(wa * err_a * ca + wb * err_b * cb)
    den = wa * ca ** 2 + wb * cb ** 2
    ok &= den > 1e-12
    s = np.where(ok, num / np.where(ok, den, 1.0), 0.0)
    m = s[:, None] * d
    refine = np.broadcast_to(np.asarray(refine, bool), err_a.shape)
    if not refine.any():
        return m
    # residual of both errors after the para 0084 move, solved in the plane of the two normals:
    # G = N Nᵀ (2×2) in its eigenbasis, each mode μ taken with the filter μ²/(μ² + μ_tol²), so
    # modes of well-separated normals are solved exactly and those of normals closer than
    # NORMAL_TOL_DEG (μ = 1 − cos angle) fade out instead of being amplified by 1/sin(angle)
    na, nb = n_a * wa[:, None], n_b * wb[:, None]
    r = np.stack([-wa * err_a - np.einsum("ij,ij->i", m, na),
                  -wb * err_b - np.einsum("ij,ij->i", m, nb)], 1)
    g = np.empty((m.shape[0], 2, 2))
    g[:, 0, 0] = np.einsum("ij,ij->i", na, na)
    g[:, 1, 1] = np.einsum("ij,ij->i", nb, nb)
    g[:, 0, 1] = g[:, 1, 0] = np.einsum("ij,ij->i", na, nb)
    mu, vec = np.linalg.eigh(g)
    mu_tol = 1.0 - np.cos(np.radians(normal_tol_deg))
    gain = np.where(mu > 1e-12, mu / (mu ** 2 + mu_tol ** 2), 0.0)        # f(μ)/μ
    coef = np.einsum("vki,vk->vi", vec, r) * gain                           # per mode
    ab = np.einsum("vki,vi->vk", vec, coef)                                 # (α, β)
    extra = ab[:, :1] * na + ab[:, 1:] * nb
    if along_path is not None:
        extra -= np.einsum("ij,ij->i", extra, along_path)[:, None] * along_path
    cap = REFINE_MAX_RATIO * np.maximum(np.abs(wa * err_a), np.abs(wb * err_b))
    size = np.linalg.norm(extra, axis=1)
    extra *= (np.minimum(1.0, cap / np.maximum(size, 1e-30)) * refine)[:, None]
    return m + extra


def gouge_limit(total_um, tips, own, own_normals, gen_xyz, gen_normals, gen_pass, shape, sweeps=3):
    """Limit vertex moves so the tool does not cut into the surface other passes generate.

    A vertex is moved for the errors of its own two passes; the tool at the moved vertex must not
    reach past the design surface that OTHER passes finish (a heavy cut in a pocket corner asks to
    move sideways into the wall beside it, which the wall's own passes leave at the design). With
    the tool at the original vertex (tip ``tips``), a generating point C_k at clearance d_k ≥ 0 from
    the tool body in direction u_k (:meth:`stages.geometry.ToolShape.clearance`) is reached by a
    move m when u_k·m > d_k (first order, the tool body locally a plane at its nearest point). The
    excess of the most violated limit is taken off along u_k, ``sweeps`` times. Points on the same
    surface (normal within :data:`SAME_SURFACE_DEG` of the vertex's own pass normals: the next row
    of a floor, which moves with its own errors) and points already inside the tool
    (:data:`GOUGE_INSIDE_MM`) set no limit. The tool's deflection is ignored: a correction is not
    allowed to rely on it to stay off another surface.

    Parameters
    ----------
    total_um : (v, 3) float, vertex moves from the original program, µm (a limited copy is returned)
    tips : (v, 3) float, tool tip at the original vertices, mm
    own : (v, 2) int, index of the vertex's own passes into ``gen_pass``'s numbering (−1: none)
    own_normals : (v, 2, 3) float, unit normals of their surfaces (zeros: none)
    gen_xyz, gen_normals : (g, 3) float, generating points (mm) and their unit normals
    gen_pass : (g,) int, pass index of each generating point
    shape : :class:`stages.geometry.ToolShape`

    Returns
    -------
    ((v, 3) limited moves in µm, (v,) µm taken off each vertex's move)
    """
    out = np.array(total_um, dtype=float, copy=True)
    size = np.linalg.norm(out, axis=1)
    moving = np.flatnonzero(size > _EPS_UM)
    if moving.size == 0 or len(gen_xyz) == 0:
        return out, np.zeros(len(out))
    gen_xyz = np.asarray(gen_xyz, dtype=float)
    near = _NearTool(gen_xyz, np.asarray(gen_normals, dtype=float), shape)
    cos_same = np.cos(np.radians(SAME_SURFACE_DEG))
    for lo in range(0, moving.size, _GOUGE_CHUNK):
        v = moving[lo:lo + _GOUGE_CHUNK]
        i, j = near.pairs(tips[v], size[v] / 1000.0, own_normals[v],
                          np.hypot(out[v, 0], out[v, 1]) / 1000.0)
        i = v[i]
        # the exact clearance first (few pairs are within reach), then the pass filters
        d0, u = shape.clearance(gen_xyz[j] - tips[i])
        keep = (d0 < size[i] / 1000.0) & (d0 >= -GOUGE_INSIDE_MM) & np.isfinite(u).all(axis=1)
        keep &= (gen_pass[j] != own[i, 0]) & (gen_pass[j] != own[i, 1])
        i, j, d0, u = i[keep], j[keep], d0[keep], u[keep]
        same = np.einsum("pj,pkj->pk", gen_normals[j], own_normals[i]).max(axis=1) > cos_same
        i, u, limit = i[~same], u[~same], np.maximum(d0[~same], 0.0) * 1000.0
        for _ in range(sweeps):
            excess = np.einsum("pj,pj->p", u, out[i]) - limit
            bad = excess > 1e-6
            if not bad.any():
                break
            ib, eb, ub = i[bad], excess[bad], u[bad]
            order = np.lexsort((-eb, ib))                  # per vertex, the most violated first
            first = order[np.r_[True, ib[order][1:] != ib[order][:-1]]]
            out[ib[first]] -= eb[first, None] * ub[first]
    return out, np.linalg.norm(out - total_um, axis=1)


class _NearTool:
    """Candidate generating points within reach of a tool at given tips (a superset, for the exact
    clearance of :meth:`stages.geometry.ToolShape.clearance`).

    Two k-d tree queries instead of one disk around the axis (which on a floor returns every point
    under the tool, hundreds per vertex): the sphere of radius R + reach about the corner's centre
    (it holds the whole body below the centre and all points within reach of it) and, for the
    shank, the box |dx|, |dy| ≤ R + reach, z from the corner's centre up to the stickout (a
    Chebyshev ball of the tree with z scaled so that its half height is the shank's). The shank
    box holds only steep points (normal over :data:`_FLAT_DEG` from +z: walls; the shank reaches a
    floor only at a wall's top edge, which the wall's own points guard). A vertex whose own
    normals are within :data:`_FLOOR_DEG` of +z queries the steep points alone: every flatter point
    is within SAME_SURFACE_DEG of its normals. Most vertices of a mould are on floors; without this
    the sphere touching the floor it stands on made each query ~4 µs.
    """

    def __init__(self, points, normals, shape):
        from scipy.spatial import cKDTree
        self.shape = shape
        self.half = max(shape.stickout_mm - shape.corner_mm, 1e-3) / 2.0
        self.scale = shape.radius_mm / self.half
        self.steep = np.flatnonzero(normals[:, 2] < np.cos(np.radians(_FLAT_DEG)))
        self.ball_all = cKDTree(points)
        self.ball_steep = cKDTree(points[self.steep])
        self.box_steep = cKDTree(points[self.steep] * [1.0, 1.0, self.scale])

    @staticmethod
    def _flat(hits, rows, index=None):
        counts = np.fromiter((len(h) for h in hits), np.int64, len(hits))
        j = np.fromiter((k for h in hits for k in h), np.int64, int(counts.sum()))
        return np.repeat(rows, counts), (j if index is None else index[j])

    def pairs(self, tips, reach, own_normals, reach_xy):
        """(i, j): tip index, point index of every candidate pair. ``reach`` (mm) is the size of the
        move, ``reach_xy`` its horizontal part: the shank's side (direction to a point horizontal)
        is reached only by that."""
        R, rc = self.shape.radius_mm, self.shape.corner_mm
        present = np.abs(own_normals).sum(axis=2) > 0
        on_floor = present.any(axis=1) & (np.where(present, own_normals[:, :, 2], 1.0).min(axis=1)
                                          >= np.cos(np.radians(_FLOOR_DEG)))
        out = []
        side = np.flatnonzero(reach_xy > _EPS_UM / 1000.0)
        if self.steep.size and side.size:
            mid = (tips[side] + [0.0, 0.0, rc + self.half]) * [1.0, 1.0, self.scale]
            hits = self.box_steep.query_ball_point(mid, R + reach_xy[side], p=np.inf, return_sorted=False)
            out.append(self._flat(hits, side, self.steep))
        for rows, tree, index in ((np.flatnonzero(on_floor), self.ball_steep, self.steep),
                                  (np.flatnonzero(~on_floor), self.ball_all, None)):
            if rows.size and tree.n:
                hits = tree.query_ball_point(tips[rows] + [0.0, 0.0, rc], R + reach[rows], return_sorted=False)
                out.append(self._flat(hits, rows, index))
        if not out:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        return np.concatenate([o[0] for o in out]), np.concatenate([o[1] for o in out])


def _errors_per_pass(passes: pa.Table, errors: pa.Table):
    """Error, unit normal and has-flag per pass row (passes in pass_id order)."""
    pid = _col(passes, "pass_id", np.int64)
    n = pid.size
    err = np.zeros(n)
    nrm = np.zeros((n, 3))
    has = np.zeros(n, bool)
    if errors is None or errors.num_rows == 0 or n == 0:
        return err, nrm, has
    eid = _col(errors, "pass_id", np.int64)
    order = np.argsort(pid, kind="stable")
    pos = np.searchsorted(pid[order], eid)
    pos_c = np.minimum(pos, n - 1)
    found = pid[order][pos_c] == eid
    if not found.all():
        bad = int(eid[~found][0])
        raise InputError(f"errors.pass_id {bad}: no such pass in the program")
    rows = order[pos_c]
    e = _col(errors, "err_um")
    nn = _xyz(errors, ("nx", "ny", "nz"))
    length = np.linalg.norm(nn, axis=1)
    good = np.isfinite(e) & np.isfinite(length) & (length > 1e-12)
    err[rows[good]] = e[good]
    nrm[rows[good]] = nn[good] / length[good, None]
    has[rows[good]] = True
    return err, nrm, has


def _node_turn_cos(pstart, pend):
    """(P + 1,) cosine of the path's turn at every node (start of pass k, end of the last; 0 at
    the ends) and the (P + 1, 3) sum of the unit directions in and out."""
    d = pend - pstart
    length = np.linalg.norm(d, axis=1)
    d = d / np.where(length > 1e-12, length, np.inf)[:, None]
    d_in = np.vstack([np.zeros((1, 3)), d])            # the pass ending at the node
    d_out = np.vstack([d, np.zeros((1, 3))])           # the pass starting there
    return np.einsum("ij,ij->i", d_in, d_out), d_in + d_out


def _straight_through(pstart, pend):
    """(P + 1, 3) unit path direction at every node (start of pass k, end of the last) where the
    path turns there by less than :data:`PATH_TURN_DEG`; zero rows at corners and at the ends."""
    cos_turn, t = _node_turn_cos(pstart, pend)
    straight = cos_turn > np.cos(np.radians(PATH_TURN_DEG))
    t = t / np.maximum(np.linalg.norm(t, axis=1), 1e-12)[:, None]
    return np.where(straight[:, None], t, 0.0)


def _generating_points(generating: pa.Table, passes: pa.Table):
    """Generating points (mm), unit normals and pass index (into ``passes`` sorted by pass id)."""
    if generating.num_rows == 0 or passes.num_rows == 0:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64)
    xyz = _xyz(generating, ("gen_x_mm", "gen_y_mm", "gen_z_mm"))
    n = _xyz(generating, ("nx", "ny", "nz"))
    ids = _col(passes, "pass_id", np.int64)
    gid = _col(generating, "pass_id", np.int64)
    k = np.minimum(np.searchsorted(ids, gid), ids.size - 1)
    ok = (ids[k] == gid) & np.isfinite(xyz).all(axis=1) & np.isfinite(n).all(axis=1)
    n = n[ok] / np.maximum(np.linalg.norm(n[ok], axis=1), 1e-12)[:, None]
    xyz, k = xyz[ok], k[ok]
    return xyz, n, k


def _params(params: dict) -> dict:
    p = dict(DEFAULTS)
    p.update((params or {}).get("correct") or {})
    return p


def _normal_tol(p: dict) -> float:
    """The refinement's normal tolerance, degrees (``correct.normal_tol_deg``, None: the default)."""
    return NORMAL_TOL_DEG if p.get("normal_tol_deg") is None else float(p["normal_tol_deg"])


def correct_once(blocks: pa.Table, passes: pa.Table, errors: pa.Table, params: dict,
                 previous: pa.Table | None = None, relax: float | None = None,
                 generating: pa.Table | None = None, tool_shape=None) -> pa.Table:
    """One correction round: move every NC vertex of ``blocks`` against ``errors``.

    Parameters
    ----------
    blocks : ``blocks`` table of the program as it is now (the original, or the corrected program
        of the previous round, see :func:`apply_corrected`)
    passes : ``passes`` table split from ``blocks``
    errors : ``errors`` table predicted for ``passes`` (rows may be missing: pruned passes)
    params : dict with ``params["correct"]`` = {max_move_um, ...}
    previous : the ``corrected`` table of the previous round, or None on the first
    relax : None (moves accumulate: residual errors) or, for errors predicted on the corrected path
        (rounds of the fixed point P = P0 − e(P)·n), the largest fraction of the way a vertex goes
        from its previous total move to the one this round computes. A vertex whose change does not
        shrink from one round to the next (the iteration is not contracting there: an error that
        falls faster than the path moves in, or a generating point that jumps between rounds) has
        its fraction halved (down to :data:`MIN_RELAX`) and keeps it; elsewhere it takes the full
        step, so a smooth prediction converges as fast as the plain fixed point
    generating, tool_shape : the ``generating`` table of the ORIGINAL program's passes and the
        tool (:class:`stages.geometry.ToolShape`): with both, moves are limited so that the tool
        does not cut into the surface other passes generate (:func:`gouge_limit`); else unlimited

    Returns
    -------
    ``corrected`` table: one row per motion block (G0–G3), original and new coordinates (mm),
    new arc centres, total move and this round's change (µm), clipped flag, iteration count.
    """
    from schemas.corrected import SCHEMA
    p = _params(params)
    max_move = float(p["max_move_um"])
    motion_all = _col(blocks, "motion", np.int64) if blocks.num_rows else np.zeros(0, np.int64)
    keep = motion_all <= 3
    blk = blocks.filter(pa.array(keep)) if not keep.all() else blocks
    nb = blk.num_rows
    if nb == 0:
        return SCHEMA.empty_table()
    program_id = blk.column("program_id")
    block_no = _col(blk, "block_no", np.int64)
    motion = motion_all[keep]
    end = _xyz(blk, ("x1_mm", "y1_mm", "z1_mm"))

    passes = passes.sort_by("pass_id") if passes.num_rows else passes
    err, nrm, has = _errors_per_pass(passes, errors)
    n_pass = passes.num_rows
    if n_pass:
        pb0 = _col(passes, "block_no", np.int64)
        pb1 = _col(passes, "block_end", np.int64)
        pend = _xyz(passes, ("x1_mm", "y1_mm", "z1_mm"))
        pstart = _xyz(passes, ("x0_mm", "y0_mm", "z0_mm"))
        # node k: start of pass k (k < P) / end of pass P−1 (k = P); between passes k−1 and k
        has_b = np.concatenate(([False], has))
        has_a = np.concatenate((has, [False]))
        eb, ea = np.concatenate(([0.0], err)), np.concatenate((err, [0.0]))
        nb_, na_ = np.vstack([np.zeros((1, 3)), nrm]), np.vstack([nrm, np.zeros((1, 3))])
        node_move = vertex_moves(eb, nb_, has_b, ea, na_, has_a,
                                 refine=_node_turn_cos(pstart, pend)[0] <= np.cos(np.radians(LINE_TURN_DEG)),
                                 along_path=_straight_through(pstart, pend), normal_tol_deg=_normal_tol(p))
        node_xyz = np.vstack([pstart, pend[-1:]])
        node_normal = nb_ * has_b[:, None] + na_ * has_a[:, None]
        # vertex → node: the last pass starting at or before the block
        q = np.searchsorted(pb0, block_no, side="right") - 1
        qc = np.maximum(q, 0)
        inside = (q >= 0) & (pb1[qc] > block_no)          # interior vertex of a merged pass
        node = np.where(q < 0, 0, qc + 1)
        move = node_move[node]
        k_in = qc[inside]
        move[inside] = vertex_moves(err[k_in], nrm[k_in], has[k_in], err[k_in], nrm[k_in], has[k_in])
        vnormal = node_normal[node]
        vnormal[inside] = nrm[qc[inside]] * has[qc[inside], None]
        # the vertex's own passes (they set its move; the gouge limit checks the others)
        own = np.stack([node - 1, np.where(node < n_pass, node, -1)], 1)
        own[inside] = qc[inside, None]
        n_own = np.where(has[:, None], nrm, 0.0)
        own_normals = np.where((own >= 0)[..., None], n_own[np.maximum(own, 0)], 0.0)
        # pass coordinates are the tool tip; blocks may be the ball centre (control_point: center)
        frame = np.median(end[~inside] - node_xyz[node[~inside]], axis=0) if (~inside).any() else np.zeros(3)
    else:
        move = np.zeros((nb, 3))
        vnormal = np.zeros((nb, 3))
        node_move = node_xyz = None

    # accumulate over rounds, clip the total move
    if previous is not None and previous.num_rows:
        prev_bn = _col(previous, "block_no", np.int64)
        if prev_bn.size != nb or np.any(prev_bn != block_no):
            raise InputError("corrected: previous round has a different block structure than blocks")
        orig = _xyz(previous, ("x_mm", "y_mm", "z_mm"))
        iteration = int(_col(previous, "iteration", np.int64).max()) + 1
        prev_n = _xyz(previous, ("nx", "ny", "nz"))
        last = _xyz(previous, ("x_new_mm", "y_new_mm", "z_new_mm"))   # the change is against these
    else:
        orig = end.copy()
        iteration = 1
        prev_n = np.full((nb, 3), np.nan)
        last = end
    total_um = (end - orig) * 1000.0 + move
    last_um = (last - orig) * 1000.0
    step = total_um - last_um                   # what this round's errors ask of each vertex
    step_frac = np.ones(nb)
    if previous is not None and previous.num_rows and relax is not None:
        prev_frac = (_col(previous, "relax") if "relax" in previous.column_names else np.ones(nb))
        prev_frac = np.where(np.isfinite(prev_frac), prev_frac, 1.0)
        # the step it asked for last round: its change over the fraction it took
        asked = _col(previous, "change_um") / prev_frac
        contracting = np.linalg.norm(step, axis=1) <= asked * (1 + 1e-9) + _EPS_UM
        step_frac = np.minimum(float(relax), np.where(contracting, prev_frac, np.maximum(prev_frac / 2, MIN_RELAX)))
        total_um = last_um + step_frac[:, None] * step
    if previous is not None and previous.num_rows:
        # a vertex no pass of this round predicts (a render lost its pass on the corrected path)
        # keeps the last round's move instead of snapping back to the original program
        stale = np.linalg.norm(vnormal, axis=1) <= 1e-12
        total_um[stale] = (last[stale] - orig[stale]) * 1000.0
    gouge_um = np.zeros(nb)
    if n_pass and generating is not None and tool_shape is not None:
        gen_xyz, gen_n, gen_pass = _generating_points(generating, passes)
        total_um, gouge_um = gouge_limit(total_um, orig - frame, own, own_normals, gen_xyz, gen_n,
                                         gen_pass, tool_shape)
    size = np.linalg.norm(total_um, axis=1)
    clipped = size > max_move * (1 + 1e-12)
    total_um[clipped] *= (max_move / size[clipped])[:, None]
    new = orig + total_um / 1000.0
    # a full circle (I J K with the end on the start) stays full: its end follows its start, else
    # a tiny difference would turn it into a sliver arc
    arc = (motion == 2) | (motion == 3)
    start_now = _xyz(blk, ("x0_mm", "y0_mm", "z0_mm"))
    full = arc & (np.linalg.norm(end - start_now, axis=1) < 1e-9)
    full[0] = False
    if full.any():
        src = np.maximum.accumulate(np.where(~full, np.arange(nb), 0))
        new[full] = new[src[full]]
        total_um[full] = (new[full] - orig[full]) * 1000.0
        clipped[full] = clipped[src[full]]
    change_um = np.linalg.norm((new - last) * 1000.0, axis=1)

    vlen = np.linalg.norm(vnormal, axis=1)
    vn = np.where(vlen[:, None] > 1e-12, vnormal / np.where(vlen > 1e-12, vlen, 1.0)[:, None], np.nan)
    vn = np.where(np.isnan(vn) & ~np.isnan(prev_n), prev_n, vn)   # keep last round's normal

    centre = np.full((nb, 3), np.nan)
    if arc.any():
        rows = np.flatnonzero(arc)
        plane = _col(blk, "plane", np.int64)[rows]
        ax = _PLANE_AXES_LUT[np.clip(plane, 0, 19)]

        def refit():
            c, free = _refit_arcs(blk, arc, end, new, max_move, passes, node_move, node_xyz,
                                  frame if n_pass else np.zeros(3))
            centre[arc] = c
            return free

        for _ in range(2):
            free = refit()
            if not free.any():
                break
            # long arcs fitted freely: their end goes back onto the circle (radially, in the plane);
            # the arcs after them are refitted to that end on the next pass
            f, fa = rows[free], ax[free]
            k = np.arange(f.size)
            prev_f = np.vstack([new[:1], new[:-1]])[f]
            c0, c1 = centre[f, fa[:, 0]], centre[f, fa[:, 1]]
            rs = np.hypot(prev_f[k, fa[:, 0]] - c0, prev_f[k, fa[:, 1]] - c1)
            da, db = new[f, fa[:, 0]] - c0, new[f, fa[:, 1]] - c1
            re = np.maximum(np.hypot(da, db), 1e-12)
            new[f, fa[:, 0]] = c0 + da * rs / re
            new[f, fa[:, 1]] = c1 + db * rs / re
        else:
            refit()
        # an arc whose sweep would still jump (a near-180° arc turning to the other side, ...) is
        # translated with its start instead of refitted, and the arc after it refitted
        ccw = motion[rows] == 3
        old_c = _xyz(blk, ("cx_mm", "cy_mm", "cz_mm"))[rows]
        prev_new = np.vstack([new[:1], new[:-1]])[rows]
        s_old = _arc_sweep(start_now[rows], end[rows], old_c, plane, ccw)
        s_new = _arc_sweep(prev_new, new[rows], centre[rows], plane, ccw)
        jump = np.abs(s_new - s_old) > np.pi / 2
        if jump.any():
            j = rows[jump]
            shift = prev_new[jump] - start_now[j]
            new[j] = end[j] + shift
            centre[j] = old_c[jump] + shift
            follow = np.zeros(nb, bool)
            follow[np.minimum(j + 1, nb - 1)] = True
            follow &= arc
            follow[j] = False
            if follow.any():
                keep_c = centre.copy()
                refit()
                centre[~follow] = keep_c[~follow]
        total_um = (new - orig) * 1000.0
        clipped |= np.linalg.norm(total_um, axis=1) > max_move * (1 + 1e-9)
        change_um = np.linalg.norm((new - last) * 1000.0, axis=1)

    return pa.table({
        "program_id": program_id,
        "block_no": block_no.astype(np.int32),
        "line_no": _col(blk, "line_no", np.int32),
        "motion": motion.astype(np.int8),
        "x_mm": orig[:, 0], "y_mm": orig[:, 1], "z_mm": orig[:, 2],
        "x_new_mm": new[:, 0], "y_new_mm": new[:, 1], "z_new_mm": new[:, 2],
        "cx_new_mm": pa.array(centre[:, 0], mask=~arc), "cy_new_mm": pa.array(centre[:, 1], mask=~arc),
        "cz_new_mm": pa.array(centre[:, 2], mask=~arc),
        "move_um": np.linalg.norm(total_um, axis=1),
        "change_um": change_um,
        "clipped": clipped,
        "gouge_limit_um": gouge_um,
        "iteration": np.full(nb, iteration, np.int32),
        "relax": step_frac,
        "step_x_um": step[:, 0], "step_y_um": step[:, 1], "step_z_um": step[:, 2],
        "nx": vn[:, 0], "ny": vn[:, 1], "nz": vn[:, 2],
    }, schema=SCHEMA)


def _arc_sweep(start, end, centre, plane, ccw):
    """Signed sweep (rad) of arcs as the splitter reads them: CCW positive, same start/end = full."""
    lut = np.zeros((20, 3), np.int64)
    for pl, ax in _PLANE_AXES.items():
        lut[pl] = ax
    axes = lut[np.clip(plane, 0, 19)]
    r = np.arange(start.shape[0])
    a0, a1 = axes[:, 0], axes[:, 1]
    th0 = np.arctan2(start[r, a1] - centre[r, a1], start[r, a0] - centre[r, a0])
    th1 = np.arctan2(end[r, a1] - centre[r, a1], end[r, a0] - centre[r, a0])
    sweep = np.where(ccw, np.mod(th1 - th0, 2 * np.pi), -np.mod(th0 - th1, 2 * np.pi))
    return np.where(np.abs(sweep) < 1e-12, np.where(ccw, 2 * np.pi, -2 * np.pi), sweep)


def _refit_arcs(blk, arc, end, new, max_move, passes, node_move, node_xyz, frame):
    """New centres (absolute mm) of the arc rows, fitted through their moved chord points."""
    rows = np.flatnonzero(arc)
    na = rows.size
    # start of an arc = new end of the previous motion block (the first block starts where it ends)
    new_start = np.vstack([new[:1], new[:-1]])[rows]
    old_start = _xyz(blk, ("x0_mm", "y0_mm", "z0_mm"))[rows]
    old_end, new_end = end[rows], new[rows]
    old_centre = _xyz(blk, ("cx_mm", "cy_mm", "cz_mm"))[rows]
    plane = _col(blk, "plane", np.int64)[rows]
    bno = _col(blk, "block_no", np.int64)[rows]
    lut = np.zeros((20, 3), np.int64)
    for pl, ax in _PLANE_AXES.items():
        lut[pl] = ax
    axes = lut[np.clip(plane, 0, 19)]
    r = np.arange(na)

    # interior chord points of each arc: nodes between two passes that both belong to the arc block
    owner = np.zeros(0, np.int64)
    pts = np.zeros((0, 3))
    if node_move is not None and passes.num_rows > 1:
        pb0 = _col(passes, "block_no", np.int64)
        pb1 = _col(passes, "block_end", np.int64)
        k = np.arange(1, pb0.size)                       # node k joins pass k−1 and pass k
        inner = (pb1[k - 1] == pb0[k])
        cand = k[inner]
        cand_block = pb0[cand]
        pos = np.searchsorted(bno, cand_block)
        posc = np.minimum(pos, na - 1)
        hit = bno[posc] == cand_block
        cand, owner = cand[hit], posc[hit]
        mv = node_move[cand].copy()
        size = np.linalg.norm(mv, axis=1)
        big = size > max_move
        mv[big] *= (max_move / size[big])[:, None]
        pts = node_xyz[cand] + frame + mv / 1000.0

    a0, a1, an = axes[:, 0], axes[:, 1], axes[:, 2]
    sa, sb = new_start[r, a0], new_start[r, a1]
    ba, bb = new_end[r, a0] - sa, new_end[r, a1] - sb
    chord = np.hypot(ba, bb)
    full = chord < 1e-9
    # arcs of more than 180° whose chord is short against the radius: the bisector of the moved
    # end points turns with every micrometre of move, so the centre is fitted freely (through the
    # start, like a full circle) and the end is put back on the circle afterwards
    r_old = np.hypot(old_start[r, a0] - old_centre[r, a0], old_start[r, a1] - old_centre[r, a1])
    sweep_old = _arc_sweep(old_start, old_end, old_centre, plane, _col(blk, "motion", np.int64)[rows] == 3)
    free = full | ((np.abs(sweep_old) > np.pi) & (chord < 0.5 * r_old))
    # fallback centre: the old centre carried by the mean in-plane move of the end points
    shift = (new_start - old_start + new_end - old_end) / 2
    fa = old_centre[r, a0] + shift[r, a0] - sa
    fb = old_centre[r, a1] + shift[r, a1] - sb
    with np.errstate(invalid="ignore", divide="ignore"):
        ua, ub = -bb / chord, ba / chord
    t0 = (fa - ba / 2) * ua + (fb - bb / 2) * ub
    # chord points relative to the new start, in the plane
    pa_ = pts[np.arange(owner.size), a0[owner]] - sa[owner] if owner.size else np.zeros(0)
    pb_ = pts[np.arange(owner.size), a1[owner]] - sb[owner] if owner.size else np.zeros(0)
    sq = pa_ ** 2 + pb_ ** 2
    g = 2 * (ua[owner] * pa_ + ub[owner] * pb_)
    r0 = sq - (ba[owner] * pa_ + bb[owner] * pb_)
    sgg = np.bincount(owner, g * g, na)
    sgr = np.bincount(owner, np.nan_to_num(g * r0), na)
    use_fit = ~free & (sgg > 1e-18 * np.maximum(chord, 1e-9) ** 2)
    t = np.where(use_fit, sgr / np.where(use_fit, sgg, 1.0), t0)
    ca = np.where(free, fa, ba / 2 + t * np.nan_to_num(ua))
    cb = np.where(free, fb, bb / 2 + t * np.nan_to_num(ub))
    if free.any():
        # free centre c through the start: |p|² − 2 c·p = 0 in least squares over the chord points
        # and the end point (2×2 normal equations per arc)
        qa = np.concatenate([pa_, ba[free]])
        qb = np.concatenate([pb_, bb[free]])
        qo = np.concatenate([owner, np.flatnonzero(free)])
        qq = qa ** 2 + qb ** 2
        sxx = np.bincount(qo, qa * qa, na)
        sxy = np.bincount(qo, qa * qb, na)
        syy = np.bincount(qo, qb * qb, na)
        rx = np.bincount(qo, qa * qq, na) / 2
        ry = np.bincount(qo, qb * qq, na) / 2
        det = sxx * syy - sxy ** 2
        ok = free & (det > 1e-12 * np.maximum(sxx + syy, 1e-30) ** 2)
        ca = np.where(ok, (syy * rx - sxy * ry) / np.where(ok, det, 1.0), ca)
        cb = np.where(ok, (sxx * ry - sxy * rx) / np.where(ok, det, 1.0), cb)
    out = np.empty((na, 3))
    out[r, a0] = sa + ca
    out[r, a1] = sb + cb
    out[r, an] = new_start[r, an]          # the parser's convention: centre at the start's height
    return out, free & ~full


def apply_corrected(blocks: pa.Table, corrected: pa.Table) -> pa.Table:
    """The ``blocks`` table with the new coordinates and arc centres of ``corrected``.

    Start points follow the new end points of the preceding motion block; dwell rows keep their
    place (at the new position of the move before them).
    """
    nb = blocks.num_rows
    if nb == 0 or corrected.num_rows == 0:
        return blocks
    bno = _col(blocks, "block_no", np.int64)
    cbn = _col(corrected, "block_no", np.int64)
    pos = np.searchsorted(cbn, bno)
    posc = np.minimum(pos, cbn.size - 1)
    hit = cbn[posc] == bno
    end = _xyz(blocks, ("x1_mm", "y1_mm", "z1_mm"))
    new = _xyz(corrected, ("x_new_mm", "y_new_mm", "z_new_mm"))
    end[hit] = new[posc[hit]]
    # rows without a corrected row (dwells) stay at the position reached before them
    last = np.maximum.accumulate(np.where(hit, np.arange(nb), -1))
    has_last = last >= 0
    end[~hit & has_last] = end[last[~hit & has_last]]
    start = np.vstack([end[:1], end[:-1]])
    start[0] = end[0]
    cen = _xyz(blocks, ("cx_mm", "cy_mm", "cz_mm"))
    ncen = np.stack([corrected.column(c).to_numpy(zero_copy_only=False).astype(float)
                     for c in ("cx_new_mm", "cy_new_mm", "cz_new_mm")], 1)
    motion = _col(blocks, "motion", np.int64)
    is_arc = (motion == 2) | (motion == 3)
    take = hit & is_arc
    cen[take] = ncen[posc[take]]
    out = blocks
    for i, (c0, c1, cc) in enumerate(zip(("x0_mm", "y0_mm", "z0_mm"), ("x1_mm", "y1_mm", "z1_mm"),
                                         ("cx_mm", "cy_mm", "cz_mm"))):
        out = out.set_column(out.schema.get_field_index(c0), c0, pa.array(start[:, i]))
        out = out.set_column(out.schema.get_field_index(c1), c1, pa.array(end[:, i]))
        out = out.set_column(out.schema.get_field_index(cc), out.schema.field(cc),
                             pa.array(cen[:, i], mask=~is_arc))
    return out


def correct_iteratively(blocks: pa.Table, predict, params: dict, on_round=None) -> pa.Table:
    """Predict → correct → predict again until the largest change is below ``tol_um``.

    Parameters
    ----------
    blocks : the original ``blocks`` table
    predict : callable(blocks) -> (passes, errors): the whole prediction chain on a (corrected)
        program; the caller owns it (split, render, forces, deflection, errors)
    params : dict with ``params["correct"]``
    on_round : optional callable(round, corrected, passes, errors) for reporting

    Returns
    -------
    the last ``corrected`` table (its ``iteration`` column is the number of rounds run).
    """
    p = _params(params)
    corrected = None
    current = blocks
    for k in range(int(p["max_iter"])):
        passes, errors = predict(current)
        corrected = correct_once(current, passes, errors, params, previous=corrected)
        if on_round is not None:
            on_round(k + 1, corrected, passes, errors)
        current = apply_corrected(blocks, corrected)
        change = _col(corrected, "change_um")
        if change.size == 0 or float(change.max()) < float(p["tol_um"]):
            break
    return corrected


def errors_on_passes(errors: pa.Table, passes_from: pa.Table, passes_to: pa.Table) -> pa.Table:
    """Re-key an ``errors`` table from one split of a program to another split of the same blocks.

    A corrected program is split again for its prediction; its passes usually match the original's
    one to one (same ``block_no``/``block_end``), and then the table is returned as it is. Where
    the splitter merged or split differently, each error row goes to the pass of ``passes_to`` in
    the same block whose midpoint is nearest to the midpoint of its own pass; rows without such a
    pass are dropped.
    """
    if errors.num_rows == 0:
        return errors
    def sig(p):
        return (_col(p, "pass_id", np.int64), _col(p, "block_no", np.int64), _col(p, "block_end", np.int64))
    a, b = sig(passes_from.sort_by("pass_id")), sig(passes_to.sort_by("pass_id"))
    if a[0].size == b[0].size and all(np.array_equal(x, y) for x, y in zip(a, b)):
        return errors
    from scipy.spatial import cKDTree
    mid = lambda p: (_xyz(p, ("x0_mm", "y0_mm", "z0_mm")) + _xyz(p, ("x1_mm", "y1_mm", "z1_mm"))) / 2  # noqa: E731
    pf, pt = passes_from.sort_by("pass_id"), passes_to.sort_by("pass_id")
    eid = _col(errors, "pass_id", np.int64)
    row = np.searchsorted(a[0], eid)
    row = np.minimum(row, a[0].size - 1)
    ok = a[0][row] == eid
    k = min(8, pt.num_rows)
    dist, idx = cKDTree(mid(pt)).query(mid(pf)[row], k=k)
    idx = idx.reshape(row.size, k)
    same = b[1][idx] == a[1][row][:, None]
    first = np.argmax(same, axis=1)
    ok &= same[np.arange(row.size), first]
    target = b[0][idx[np.arange(row.size), first]]
    out = errors.filter(pa.array(ok))
    return out.set_column(out.schema.get_field_index("pass_id"), "pass_id",
                          pa.array(target[ok], out.schema.field("pass_id").type))


def with_missing_from(errors: pa.Table, fallback: pa.Table | None) -> pa.Table:
    """``errors`` plus the rows of ``fallback`` (same passes) for passes ``errors`` has no finite error for."""
    if fallback is None or fallback.num_rows == 0:
        return errors
    have = _col(errors, "pass_id", np.int64)[np.isfinite(_col(errors, "err_um"))] if errors.num_rows else np.zeros(0, np.int64)
    add = fallback.filter(pa.array(~np.isin(_col(fallback, "pass_id", np.int64), have)
                                   & np.isfinite(_col(fallback, "err_um"))))
    if add.num_rows == 0:
        return errors
    return pa.concat_tables([errors, add.select(errors.column_names).cast(errors.schema)])


def run(inputs: dict, params: dict) -> dict[str, pa.Table]:
    """One correction round on the predicted errors (the engine iterates, ``pipeline/iterate.py``).

    Round 1: ``blocks``, ``passes`` and ``errors`` of the program. Later rounds (seed 003, DESIGN §7)
    also get ``corrected`` (the previous round's table) and ``round_passes``: the passes of the
    corrected program the chain predicted ``errors`` on. Those errors are, like every prediction,
    relative to the path they were predicted for; the machined surface of path P is P + e(P)·n, so
    the command that leaves the original surface is the fixed point P = P0 − e(P)·n: each round
    applies the move for the newly predicted errors to the ORIGINAL program (``blocks`` and
    ``passes`` stay the original ones) instead of adding it to the previous moves. A pass the
    round's render did not predict (a moved pass whose cut the neighbours now cover in the pixel
    grid, a generating view that found nothing) keeps its round-1 error (``first_errors``, the
    prediction on the original program): without it the vertex it shares with a predicted pass
    followed that pass alone, and a pocket corner's 140 µm error came back uncorrected. With
    ``correct.keep_surface_deg`` a pass whose new normal lies further than that from its round-1
    normal (the moved ball touches the surface elsewhere, or another surface) keeps its round-1
    error too (:func:`on_first_surface`).
    From round 2 a vertex whose change does not shrink from round to round takes half its step
    (again halved while it does not contract; ``correct.relax`` caps the fraction): on the sample's
    boss foot, where generating points jump between rounds and heavy cuts' errors change with the
    move, the full step flipped vertices by up to 83 µm from round to round.
    (:func:`correct_iteratively` is the other case: its errors are measured against the original
    surface, residuals, and its moves accumulate.)
    ``generating`` (of the original program: the moves are from it) and the ``tool`` parameter
    drive the gouge limit (``correct.gouge_limit``).
    """
    errors = inputs["errors"]
    relax = None
    if inputs.get("round_passes") is not None:
        errors = errors_on_passes(errors, inputs["round_passes"], inputs["passes"])
        errors = with_missing_from(errors, inputs.get("first_errors"))
        relax = float(_params(params)["relax"])
    shape = None
    if (_params(params)["gouge_limit"] and params.get("tool") is not None
            and inputs.get("generating") is not None):
        from stages.forces import pick_entry, program_tool_number
        from stages.geometry import tool_from_params
        shape = tool_from_params(pick_entry(params["tool"], program_tool_number(inputs["passes"]), "tool"))
    return {"corrected": correct_once(inputs["blocks"], inputs["passes"], errors, params,
                                      previous=inputs.get("corrected"), relax=relax,
                                      generating=inputs.get("generating"), tool_shape=shape)}
