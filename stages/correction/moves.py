"""Vertex moves against predicted errors (seed 000 claim 9, para 0084), and the gouge limit.

Every NC vertex is where two passes meet: the pass that ends there (i) and the pass that starts there
(j). With the predicted errors e (µm, positive = material left) and surface normals n (out of
material) of those passes, para 0084 forms the correction reference vectors E'i = −e_i·n_i and
E'j = −e_j·n_j, points the vertex move along E'i + E'j and chooses its magnitude s by least squares
so that the move best realises both. A pass moved by m moves the surface it generates by m·n (an
axisymmetric tool touching the surface at the point with normal n: the tangential part of m slides
along the surface), so with the unit direction d

    s = argmin Σ_k (s·(d·n_k) + e_k)²  =  −Σ e_k (d·n_k) / Σ (d·n_k)².

Two passes with the same normal and error give m = −e·n exactly; perpendicular normals give
m = −(e_i n_i + e_j n_j). :func:`vertex_moves` completes it by least squares where the normals
differ at an oblique angle; :func:`gouge_limit` keeps the moved tool off the surfaces other passes
generate.
"""
from __future__ import annotations

import numpy as np

EPS_UM = 1e-9


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
    ok = size > EPS_UM
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
    the tool body in direction u_k (:meth:`Cutter.clearance`) is reached by a
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
    shape : :class:`Cutter`

    Returns
    -------
    ((v, 3) limited moves in µm, (v,) µm taken off each vertex's move)
    """
    out = np.array(total_um, dtype=float, copy=True)
    size = np.linalg.norm(out, axis=1)
    moving = np.flatnonzero(size > EPS_UM)
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
    clearance of :meth:`Cutter.clearance`).

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
        side = np.flatnonzero(reach_xy > EPS_UM / 1000.0)
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


def node_turn_cos(pstart, pend):
    """(P + 1,) cosine of the path's turn at every node (start of pass k, end of the last; 0 at
    the ends) and the (P + 1, 3) sum of the unit directions in and out."""
    d = pend - pstart
    length = np.linalg.norm(d, axis=1)
    d = d / np.where(length > 1e-12, length, np.inf)[:, None]
    d_in = np.vstack([np.zeros((1, 3)), d])            # the pass ending at the node
    d_out = np.vstack([d, np.zeros((1, 3))])           # the pass starting there
    return np.einsum("ij,ij->i", d_in, d_out), d_in + d_out


def straight_through(pstart, pend):
    """(P + 1, 3) unit path direction at every node (start of pass k, end of the last) where the
    path turns there by less than :data:`PATH_TURN_DEG`; zero rows at corners and at the ends."""
    cos_turn, t = node_turn_cos(pstart, pend)
    straight = cos_turn > np.cos(np.radians(PATH_TURN_DEG))
    t = t / np.maximum(np.linalg.norm(t, axis=1), 1e-12)[:, None]
    return np.where(straight[:, None], t, 0.0)
