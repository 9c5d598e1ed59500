"""Geometry shared by the render back ends: tool envelopes, swept volumes, workpieces.

Everything here produces plain triangle lists (``(n, 3, 3)`` float64 corner positions plus
``(n, 3)`` per-corner attributes), so the moderngl and the numpy back end rasterise exactly the
same triangles (DESIGN §2).

Tool envelope (seed 000 paras 0042, 0101). The cutting-edge envelope of a rotating end mill is a
surface of revolution about the tool axis (+Z), given by a profile ``r(z)`` above the tip:

- ball: hemisphere of radius R centred at ``tip + (0, 0, R)``, then a cylinder of radius R;
- bull: flat bottom disc of radius ``R - rc``, torus corner of radius ``rc``, cylinder;
- flat: bottom disc of radius R, cylinder.

The cylinder is closed by a cap at ``stickout_mm`` so that every tool is a closed convex solid.

Polygonisation tolerance. The mesh is a surface of revolution with ``n_theta`` columns and a
profile polyline whose arcs are split so that each chord's sagitta is at most ``tol/2``; the
columns are chosen the same way for the largest radius. Every vertex lies on the true surface and
every face is a planar isosceles trapezoid inscribed in it, so the mesh lies *inside* the true
envelope by at most ``tol_mm`` (tested in tests/test_geometry.py by sampling faces against the
analytic profile).

Swept volume of a linear pass. All three tools are convex, so the volume swept by a translation
along a segment is the convex hull of the tool at both ends; for the polyhedral tool its boundary
is made of faces of the two end copies plus the faces swept by the *silhouette edges* (edges whose
two adjacent faces face opposite ways with respect to the motion). Rendering the two copies and
the swept silhouette edges with a depth test gives the exact first hit on the hull of the
polyhedral tool from any viewpoint outside it (the rest of both copies lies inside the hull).

Per-corner attributes (claim 4): ``q`` = angle of the envelope's outward normal from the downward
tool axis (the contact angle: 0° at the tip, 90° on the cylinder, 180° on the cap) and ``theta``
= angle about the tool axis, measured from the column seam. Copies of the envelope at a
prediction point are rotated so that the seam lies on the feed direction; ``theta`` is then the
rotation angle φ (counter-clockwise from the feed direction, seen from above), and the seam makes
sure no triangle interpolates across 0°/360°.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from stages import InputError


# ------------------------------------------------------------------------------------ tool shape

@dataclass(frozen=True)
class ToolShape:
    """Axisymmetric cutting-edge envelope. Lengths in mm, tip at the origin, axis +Z."""

    kind: str            # "ball" | "bull" | "flat"
    radius_mm: float     # R = diameter / 2
    corner_mm: float     # rc: R for ball, 0 for flat
    stickout_mm: float   # height of the cap that closes the envelope

    def profile_radius(self, z_mm):
        """Radius of the envelope at height ``z_mm`` above the tip (NaN below the tip)."""
        z = np.asarray(z_mm, dtype=float)
        R, rc = self.radius_mm, self.corner_mm
        with np.errstate(invalid="ignore"):
            corner = (R - rc) + np.sqrt(np.clip(rc * rc - (rc - z) ** 2, 0.0, None))
        r = np.where(z >= rc, R, corner)
        return np.where(z < 0, np.nan, r)

    def point(self, q_deg, phi_deg, feed_deg=0.0):
        """Envelope point (tip frame) at contact angle ``q`` and rotation angle ``phi``.

        ``phi`` is counted counter-clockwise from the feed direction ``feed_deg`` (seen from above).
        Returns an array (..., 3).
        """
        q = np.radians(np.asarray(q_deg, dtype=float))
        th = np.radians(np.asarray(phi_deg, dtype=float) + feed_deg)
        R, rc = self.radius_mm, self.corner_mm
        r = (R - rc) + rc * np.sin(q)
        z = rc * (1.0 - np.cos(q))
        return np.stack(np.broadcast_arrays(r * np.cos(th), r * np.sin(th), z), axis=-1)

    def clearance(self, points):
        """Distance of ``points`` (tip frame, (..., 3) mm) from the tool body, and its direction.

        The body is the envelope continued upward as the shank cylinder: the disk of radius
        R − rc at height rc swept by a ball of radius rc (a torus; a ball for rc = R, the flat
        end's sharp rim for rc = 0), closed above by the cylinder of radius R. Negative inside.

        Returns
        -------
        (d, u): (...,) mm and (..., 3) unit vectors from the nearest body point towards the point
        (the direction in which a move of the tool reduces the clearance by u·move); u is NaN
        where the point lies on the axis inside the body (no direction).
        """
        p = np.asarray(points, dtype=float)
        R, rc = self.radius_mm, self.corner_mm
        rho = np.hypot(p[..., 0], p[..., 1])
        radial = np.stack([p[..., 0], p[..., 1]], -1) / np.where(rho > 1e-12, rho, np.inf)[..., None]
        above = p[..., 2] >= rc
        # below the corner's centre height: the nearest point of the core disk, then out by rc
        vr = np.where(above, rho - R, rho - np.minimum(rho, R - rc))
        vz = np.where(above, 0.0, p[..., 2] - rc)
        length = np.hypot(vr, vz)
        d = np.where(above, rho - R, length - rc)
        sign = np.where(above, 1.0, 1.0 / np.where(length > 1e-12, length, np.nan))
        ur, uz = np.where(above, 1.0, vr * sign), np.where(above, 0.0, vz * sign)
        u = np.concatenate([radial * ur[..., None], uz[..., None]], -1)
        u[(rho <= 1e-12) & above] = np.nan
        return d, u


def tool_from_params(tool) -> ToolShape:
    """ToolShape from the ``tool`` workflow dict (pydantic dump of pipeline.config.Tool).

    A list of tools (one per T number) must have been resolved to one dict by the engine; a list
    with one entry is accepted.
    """
    if isinstance(tool, (list, tuple)):
        if len(tool) != 1:
            raise InputError("tool: one tool per program expected, got a list of "
                             f"{len(tool)} (select the entry for the program's T number)")
        tool = tool[0]
    try:
        kind = tool["type"]
        R = float(tool["diameter_mm"]) / 2.0
        stickout = float(tool.get("stickout_mm") or 40.0)
        rc = tool.get("corner_radius_mm")
    except (KeyError, TypeError) as e:
        raise InputError(f"tool: missing key {e}") from None
    if kind == "ball":
        rc = R
    elif kind == "flat":
        rc = 0.0
    elif kind == "bull":
        if rc is None or not (0 < float(rc) < R):
            raise InputError(f"tool.corner_radius_mm: bull-nose needs 0 < rc < {R}, got {rc}")
        rc = float(rc)
    else:
        raise InputError(f"tool.type: unknown tool type {kind!r} (ball, bull, flat)")
    if R <= 0:
        raise InputError("tool.diameter_mm: must be > 0")
    return ToolShape(kind, R, rc, max(stickout, R + 1e-3))


# ------------------------------------------------------------------------------------ envelope mesh

def segments_for_tolerance(radius_mm: float, sweep_rad: float, sagitta_mm: float) -> int:
    """Number of chords for an arc of ``radius_mm`` over ``sweep_rad`` with sagitta <= tolerance."""
    if radius_mm <= 0 or sweep_rad <= 0:
        return 1
    ratio = min(sagitta_mm / radius_mm, 1.0)
    step = 2.0 * math.acos(1.0 - ratio)
    return max(1, math.ceil(sweep_rad / max(step, 1e-9) - 1e-9))


@dataclass(frozen=True)
class EnvelopeMesh:
    """Polyhedral envelope of one tool (tip frame), with the structure needed for sweeps.

    Attributes
    ----------
    tris : (nt, 3, 3) triangle corners.
    q_deg, theta_deg : (nt, 3) per-corner contact angle and angle about the axis from the seam.
    face_of_tri : (nt,) index of the planar quad face each triangle belongs to.
    face_normals : (nf, 3) outward unit normals of the quad faces.
    edges : (ne, 2, 3) silhouette-candidate edges (meridians and rings).
    edge_q_deg : (ne, 2) contact angle at the edge ends.
    edge_faces : (ne, 2) the two faces adjacent to each edge.
    tol_mm : the tolerance the mesh was built for (mesh inside the true surface by <= tol_mm).
    """

    shape: ToolShape
    tol_mm: float
    n_theta: int
    tris: np.ndarray
    q_deg: np.ndarray
    theta_deg: np.ndarray
    face_of_tri: np.ndarray
    face_normals: np.ndarray
    edges: np.ndarray
    edge_q_deg: np.ndarray
    edge_faces: np.ndarray


def _profile_rows(shape: ToolShape, tol_mm: float):
    """Profile rows (r_lo, z_lo, q_lo, r_hi, z_hi, q_hi), from the tip up to the closing cap."""
    R, rc, H = shape.radius_mm, shape.corner_mm, shape.stickout_mm
    rows = []
    if R - rc > 1e-12:                               # flat bottom disc (bull, flat)
        rows.append((0.0, 0.0, 0.0, R - rc, 0.0, 0.0))
    if rc > 1e-12:                                   # corner arc (ball, bull)
        n = segments_for_tolerance(rc, math.pi / 2, tol_mm / 2)
        q = np.linspace(0.0, math.pi / 2, n + 1)
        r = (R - rc) + rc * np.sin(q)
        z = rc * (1.0 - np.cos(q))
        for k in range(n):
            rows.append((r[k], z[k], math.degrees(q[k]), r[k + 1], z[k + 1], math.degrees(q[k + 1])))
    rows.append((R, rc, 90.0, R, H, 90.0))           # cylinder
    rows.append((R, H, 180.0, 0.0, H, 180.0))        # cap
    return np.array(rows, dtype=float)


@lru_cache(maxsize=32)
def envelope_mesh(shape: ToolShape, tol_mm: float) -> EnvelopeMesh:
    """Polyhedral cutting-edge envelope of ``shape`` inside the true surface by <= ``tol_mm``."""
    if not tol_mm > 0:
        raise ValueError("tol_mm must be > 0")
    rows = _profile_rows(shape, tol_mm)
    n_theta = max(8, segments_for_tolerance(shape.radius_mm, 2 * math.pi, tol_mm / 2))
    nr = len(rows)
    th = np.linspace(0.0, 2 * math.pi, n_theta + 1)
    c, s = np.cos(th), np.sin(th)
    r_lo, z_lo, q_lo, r_hi, z_hi, q_hi = rows.T

    def ring(r, z, cols):                             # (nr, ncols, 3)
        return np.stack([r[:, None] * c[cols][None], r[:, None] * s[cols][None],
                         np.broadcast_to(z[:, None], (len(r), len(cols)))], axis=-1)

    j0, j1 = np.arange(n_theta), np.arange(1, n_theta + 1)
    A, B = ring(r_lo, z_lo, j0), ring(r_lo, z_lo, j1)
    C, D = ring(r_hi, z_hi, j1), ring(r_hi, z_hi, j0)
    normals = np.cross(C - A, D - B)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)

    th_deg = np.degrees(th)
    mid = 0.5 * (th_deg[j0] + th_deg[j1])
    # theta of a corner on the axis is undefined; give it the column's mid angle
    thA = np.where(r_lo[:, None] < 1e-12, mid[None], th_deg[j0][None])
    thB = np.where(r_lo[:, None] < 1e-12, mid[None], th_deg[j1][None])
    thC = np.where(r_hi[:, None] < 1e-12, mid[None], th_deg[j1][None])
    thD = np.where(r_hi[:, None] < 1e-12, mid[None], th_deg[j0][None])
    qlo = np.broadcast_to(q_lo[:, None], (nr, n_theta))
    qhi = np.broadcast_to(q_hi[:, None], (nr, n_theta))

    t1 = np.stack([A, B, C], axis=2).reshape(-1, 3, 3)
    t2 = np.stack([A, C, D], axis=2).reshape(-1, 3, 3)
    q1 = np.stack([qlo, qlo, qhi], axis=2).reshape(-1, 3)
    q2 = np.stack([qlo, qhi, qhi], axis=2).reshape(-1, 3)
    h1 = np.stack([thA, thB, thC], axis=2).reshape(-1, 3)
    h2 = np.stack([thA, thC, thD], axis=2).reshape(-1, 3)
    face = np.arange(nr * n_theta)
    tris = np.concatenate([t1, t2])
    area = np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
    keep = area > 1e-12 * max(shape.radius_mm, 1.0) ** 2
    tris = tris[keep]
    qd = np.concatenate([q1, q2])[keep]
    thd = np.concatenate([h1, h2])[keep]
    fot = np.concatenate([face, face])[keep]

    # silhouette-candidate edges: meridians (between columns j-1 and j of a row) ...
    mer = np.stack([A, D], axis=2)                                 # (nr, nt, 2, 3) at column j
    mer_q = np.stack([qlo, qhi], axis=-1)
    fr = np.arange(nr)[:, None] * n_theta
    mer_f = np.stack([fr + (j0[None] - 1) % n_theta, fr + j0[None]], axis=-1)
    # ... and rings (between row i-1 and row i), skipped where the ring has zero radius
    rng = np.stack([A[1:], B[1:]], axis=2)                         # (nr-1, nt, 2, 3)
    rq = 0.5 * (q_hi[:-1] + q_lo[1:])
    rng_q = np.broadcast_to(rq[:, None, None], (nr - 1, n_theta, 2))
    rng_f = np.stack([fr[:-1] + j0[None], fr[1:] + j0[None]], axis=-1)
    ring_ok = np.broadcast_to((r_lo[1:] > 1e-12)[:, None], (nr - 1, n_theta))
    edges = np.concatenate([mer.reshape(-1, 2, 3), rng[ring_ok].reshape(-1, 2, 3)])
    edge_q = np.concatenate([mer_q.reshape(-1, 2), rng_q[ring_ok].reshape(-1, 2)])
    edge_f = np.concatenate([mer_f.reshape(-1, 2), rng_f[ring_ok].reshape(-1, 2)])
    return EnvelopeMesh(shape, float(tol_mm), n_theta, tris, qd, thd, fot,
                        normals.reshape(-1, 3), edges, edge_q, edge_f)


def envelope_copies(mesh: EnvelopeMesh, tips, feed_deg=None, view_dir=None):
    """Envelope triangles translated to each tip position.

    Parameters
    ----------
    tips : (k, 3) tool tip positions.
    feed_deg : (k,) optional feed direction angles; the copy is rotated so that the seam lies on
        the feed direction, and the returned theta is then the rotation angle φ.
    view_dir : (3,) optional; triangles facing away from a viewer looking along it are dropped.

    Returns
    -------
    tris (k*m, 3, 3), q_deg (k*m, 3), phi_deg (k*m, 3), owner (k*m,) index into ``tips``.
    """
    tips = np.atleast_2d(np.asarray(tips, dtype=float))
    k = len(tips)
    nrm = mesh.face_normals[mesh.face_of_tri]                          # (m, 3)
    if feed_deg is None:
        front = (np.ones((k, len(nrm)), bool) if view_dir is None
                 else np.broadcast_to(nrm @ np.asarray(view_dir, float) < -1e-9, (k, len(nrm))))
        owner, sel = np.nonzero(front)
        tris = mesh.tris[sel] + tips[owner, None, :]
    else:
        a = np.radians(np.broadcast_to(np.asarray(feed_deg, dtype=float), (k,)))
        ca, sa = np.cos(a), np.sin(a)
        if view_dir is None:
            front = np.ones((k, len(nrm)), bool)
        else:
            # cull in the mesh frame: the view direction rotated back by each copy's feed angle
            v = np.asarray(view_dir, float)
            vx = ca * v[0] + sa * v[1]
            vy = -sa * v[0] + ca * v[1]
            front = (np.outer(vx, nrm[:, 0]) + np.outer(vy, nrm[:, 1]) + v[2] * nrm[None, :, 2]) < -1e-9
        owner, sel = np.nonzero(front)
        base = mesh.tris[sel]
        c, s_ = ca[owner, None], sa[owner, None]
        x, y = base[..., 0], base[..., 1]
        tris = np.stack([c * x - s_ * y, s_ * x + c * y, base[..., 2]], -1) + tips[owner, None, :]
    return tris, mesh.q_deg[sel], mesh.theta_deg[sel], owner


# Faces whose normal is within this (radians) of perpendicular to a pass count as parallel to it,
# in the silhouette (sweep_bands) and in the joint lunes (joint_lunes). Why: the faces of a copy
# that lie along the motion are covered by neither band of an exact pass but by the lunes at its
# joints. With a tolerance of 1e-9 a chain of passes turned by 2e-9 rad (a corrected program's via
# points: float noise of the moves) had a silhouette one face over and lunes without those faces,
# and its sweeps lost their cut pixels to the next pass (the cylinder's 0.5 mm passes: 105 of 727
# passes "not cutting" in round 2). 1e-6 rad is far below the mesh's facets (~1e-2 rad).
PARALLEL_TOL = 1e-6
# a move joined end to start to the next that turns less than this from it carries the same cut
# on: the split stage's pieces of one line, a corrected line's via pieces, a curve's CAM chords
# (see cut_filter.line_interior and errors._deepest_passage)
CONTINUE_DEG = 10.0


def sweep_bands(mesh: EnvelopeMesh, p0, p1, view_dir=None):
    """Faces swept by the silhouette edges of the envelope moving from ``p0`` to ``p1``.

    Together with :func:`envelope_copies` at ``p0`` and ``p1`` this renders the exact swept volume
    of the polyhedral tool. Vectorised over passes.

    Returns tris (n, 3, 3), q_deg (n, 3), owner (n,) index into ``p0``.
    """
    p0 = np.atleast_2d(np.asarray(p0, float))
    p1 = np.atleast_2d(np.asarray(p1, float))
    u = p1 - p0
    s = mesh.face_normals @ u.T                                     # (nf, k)
    # a face within PARALLEL_TOL of parallel to the motion counts as parallel (s = 0), so that a
    # pass turned by a few nanoradians has the silhouette of the exact one (see PARALLEL_TOL)
    eps = PARALLEL_TOL * np.maximum(np.linalg.norm(u, axis=1), 1e-30)[None]
    s = np.where(np.abs(s) <= eps, 0.0, s)
    sa, sb = s[mesh.edge_faces[:, 0]], s[mesh.edge_faces[:, 1]]     # (ne, k)
    sil = (sa * sb <= 0) & ~((sa == 0) & (sb == 0))
    sil &= (np.linalg.norm(u, axis=1) > 1e-12)[None]
    e, k = np.nonzero(sil)
    if view_dir is not None:
        # keep the bands a viewer looking along view_dir sees from outside: the band's outward
        # normal is (nearly) the mean of the two faces that meet at the silhouette edge
        nb = mesh.face_normals[mesh.edge_faces[e, 0]] + mesh.face_normals[mesh.edge_faces[e, 1]]
        front = nb @ np.asarray(view_dir, float) < -1e-9
        e, k = e[front], k[front]
    a0 = mesh.edges[e, 0] + p0[k]
    b0 = mesh.edges[e, 1] + p0[k]
    a1 = mesh.edges[e, 0] + p1[k]
    b1 = mesh.edges[e, 1] + p1[k]
    qa, qb = mesh.edge_q_deg[e, 0], mesh.edge_q_deg[e, 1]
    tris = np.concatenate([np.stack([a0, b0, b1], 1), np.stack([a0, b1, a1], 1)])
    q = np.concatenate([np.stack([qa, qb, qb], 1), np.stack([qa, qb, qa], 1)])
    owner = np.concatenate([k, k])
    return tris, q, owner


def sweep_triangles(mesh: EnvelopeMesh, p0, p1, view_dir=None):
    """Triangles of the swept volumes of linear passes ``p0[i] -> p1[i]`` (tool tips).

    Returns tris (n, 3, 3), q_deg (n, 3), owner (n,) pass index into ``p0``.
    """
    p0 = np.atleast_2d(np.asarray(p0, float))
    p1 = np.atleast_2d(np.asarray(p1, float))
    k = len(p0)
    t0, q0, _, o0 = envelope_copies(mesh, p0, view_dir=view_dir)
    t1, q1, _, o1 = envelope_copies(mesh, p1, view_dir=view_dir)
    tb, qb, ob = sweep_bands(mesh, p0, p1)
    tris = np.concatenate([t0, t1, tb])
    q = np.concatenate([q0, q1, qb])
    owner = np.concatenate([o0, o1, ob])
    del k
    return tris, q, owner


def chain_joints(seg0, seg1, window):
    """Joints of chains whose two envelope copies can be replaced by :func:`joint_lunes`.

    Where segment i ends exactly where segment i+1 (same window) starts, the copy at the joint is
    the end of one sweep and the start of the next: only its lune lies outside both, whatever the
    turn, so both full copies are left out and the lune is drawn instead (a few % of a copy on a
    smooth chain, a quarter of it at a right-angle corner). Envelope copies are the bulk of a
    sweep's triangles, and CAM output is mostly chains of short chords. Returns boolean masks
    (drop_start, drop_end) over the segments; ``drop_end[i]`` implies segment i+1 starts there.
    """
    seg0 = np.asarray(seg0, float).reshape(-1, 3)
    seg1 = np.asarray(seg1, float).reshape(-1, 3)
    k = len(seg0)
    drop_start = np.zeros(k, bool)
    drop_end = np.zeros(k, bool)
    if k < 2:
        return drop_start, drop_end
    window = np.asarray(window).reshape(-1)
    L = np.linalg.norm(seg1 - seg0, axis=1)
    joint = ((window[:-1] == window[1:]) & np.all(seg1[:-1] == seg0[1:], axis=1)
             & (L[:-1] > 1e-9) & (L[1:] > 1e-9))
    drop_end[:-1] = joint
    drop_start[1:] = joint
    return drop_start, drop_end


def _unit_directions(seg0, seg1):
    d = seg1 - seg0
    L = np.linalg.norm(d, axis=1)
    return d / np.where(L > 1e-12, L, 1.0)[:, None]


def joint_lunes(mesh: EnvelopeMesh, seg0, seg1, drop_end, view_dir=None, chunk: int = 1024):
    """The part of each left-out joint copy (:func:`chain_joints`) that no sweep draws.

    At a joint where the path turns from u (segment i) to v (segment i+1), the boundary of the
    two sweeps' union is their bands plus the copy's faces that face forward along u (the front
    of sweep i's end: N·u >= 0) and backward along v (the back of sweep i+1's start: N·v <= 0).
    Faces behind along u lie inside sweep i, faces ahead along v inside sweep i+1, at any turn.
    What remains is a lune between the two silhouettes, R·Δ wide for a turn Δ: without it a ray
    through the lune meets no front face and sees through the sweep. The polyhedral silhouettes
    are the same edges the bands are built on, so the lune closes against them exactly.

    Returns tris (n, 3, 3), q_deg (n, 3), owner (n,) index of segment i (its end copy).
    """
    seg0 = np.asarray(seg0, float).reshape(-1, 3)
    seg1 = np.asarray(seg1, float).reshape(-1, 3)
    idx = np.nonzero(np.asarray(drop_end, bool))[0]
    if len(idx) == 0:
        return np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0, np.int64)
    u = _unit_directions(seg0, seg1)
    nrm = mesh.face_normals[mesh.face_of_tri]                          # (m, 3)
    tri_ok = (np.ones(len(nrm), bool) if view_dir is None
              else nrm @ np.asarray(view_dir, float) < -1e-9)
    cand = np.nonzero(tri_ok)[0]
    nrm = nrm[cand]
    owners, sels = [], []
    for a in range(0, len(idx), chunk):                                # bounded (chunk × m) masks
        j = idx[a:a + chunk]
        lune = (u[j] @ nrm.T >= -PARALLEL_TOL) & (u[j + 1] @ nrm.T <= PARALLEL_TOL)
        o, t = np.nonzero(lune)
        owners.append(j[o])
        sels.append(cand[t])
    owner, sel = np.concatenate(owners), np.concatenate(sels)
    return mesh.tris[sel] + seg1[owner, None, :], mesh.q_deg[sel], owner


def ordered_sweep_scene(mesh: EnvelopeMesh, p0, p1, ident, view_dir=(0.0, 0.0, 1.0), bias=0.0):
    """Sweeps of passes ``p0[k] -> p1[k]`` in the given (execution) order, for ``Renderer.scan``.

    Only the faces a viewer looking along ``view_dir`` sees from outside are kept, and per pass
    the silhouette bands come before the end copies: within one convex sweep each pixel then
    passes the depth test once, so fragment counts are pixel counts. Attributes: id
    ``ident[k]``, a = position along the pass (0 at p0, 1 at p1; beyond on the end copies),
    b = contact angle q.
    """
    from stages.render import Scene
    p0 = np.asarray(p0, float).reshape(-1, 3)
    p1 = np.asarray(p1, float).reshape(-1, 3)
    tb, qb, ob = sweep_bands(mesh, p0, p1, view_dir=view_dir)
    drop0, drop1 = chain_joints(p0, p1, np.zeros(len(p0)))
    t0, q0, _, o0 = envelope_copies(mesh, p0[~drop0], view_dir=view_dir)
    o0 = np.nonzero(~drop0)[0][o0]
    t1, q1, _, o1 = envelope_copies(mesh, p1[~drop1], view_dir=view_dir)
    o1 = np.nonzero(~drop1)[0][o1]
    tl, ql, ol = joint_lunes(mesh, p0, p1, drop1, view_dir=view_dir)
    tris = np.concatenate([tb, t0, t1, tl])
    q = np.concatenate([qb, q0, q1, ql])
    key = np.concatenate([ob * 3, o0 * 3 + 1, o1 * 3 + 2, ol * 3 + 2])
    order = np.argsort(key, kind="stable")
    owner = key[order] // 3
    tris, q = tris[order], q[order]
    # a: position along the pass of the point itself, projected in 3-D on the line of corner
    # centres (linear in space, so exact under interpolation; the facets of a polyhedral
    # silhouette would misplace a per-end 0/1 label by up to half a facet)
    d = p1 - p0
    dd = np.einsum("ij,ij->i", d, d)
    c0 = p0 + (0.0, 0.0, mesh.shape.corner_mm)
    a = np.einsum("tkj,tj->tk", tris - c0[owner, None, :], d[owner]) / np.where(dd > 1e-12, dd, 1.0)[owner, None]
    a = np.where((dd > 1e-12)[owner, None], a, 0.5)
    attrs = np.empty((len(order), 3, 3), np.float32)
    attrs[:, :, 0] = np.asarray(ident, float)[owner, None]
    attrs[:, :, 1] = a
    attrs[:, :, 2] = q
    return Scene(tris, attrs, np.full(len(order), float(bias)), np.zeros(len(order), np.int64))


def sweep_lowest_z(shape: ToolShape, p0, p1, xy, n_t: int = 2001):
    """Brute-force reference: lowest point of the swept envelope above each ``xy`` (NaN if none).

    Samples the motion densely and takes the lower envelope; independent of the meshes (used by
    tests).
    """
    xy = np.atleast_2d(np.asarray(xy, float))
    t = np.linspace(0.0, 1.0, n_t)
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    tips = p0[None] + t[:, None] * (p1 - p0)[None]
    d = np.hypot(xy[:, None, 0] - tips[None, :, 0], xy[:, None, 1] - tips[None, :, 1])
    z = _lower_profile_z(shape, d) + tips[None, :, 2]
    return np.nanmin(np.where(np.isnan(z), np.inf, z), axis=1)


def _lower_profile_z(shape: ToolShape, r):
    """Height above the tip of the lowest envelope point at radius ``r`` (NaN outside)."""
    R, rc = shape.radius_mm, shape.corner_mm
    r = np.asarray(r, float)
    flat = r <= R - rc
    with np.errstate(invalid="ignore"):
        corner = rc - np.sqrt(np.clip(rc * rc - (r - (R - rc)) ** 2, 0.0, None))
    z = np.where(flat, 0.0, corner)
    return np.where(r <= R, z, np.nan)


# ------------------------------------------------------------------------------------ workpiece

@dataclass(frozen=True)
class Workpiece:
    """Closed triangle mesh of the stock. ``normals`` point out of the material."""

    tris: np.ndarray      # (n, 3, 3)
    normals: np.ndarray   # (n, 3)
    bounds: np.ndarray    # (2, 3)


def box_workpiece(box) -> Workpiece:
    import trimesh
    b = np.asarray(box, float).reshape(2, 3)
    if not np.all(b[1] > b[0]):
        raise InputError(f"stock.box: need x0<x1, y0<y1, z0<z1, got {list(box)}")
    m = trimesh.creation.box(bounds=b)
    return _from_trimesh(m)


def _from_trimesh(m) -> Workpiece:
    tris = np.asarray(m.triangles, dtype=float)
    n = np.asarray(m.face_normals, dtype=float)
    return Workpiece(tris, n, np.asarray(m.bounds, float))


class DesignSurface:
    """Distance of points to the nominal (design) model (no spatial-index extra needed).

    Candidate faces are those of the ``k`` nearest random surface samples (about ``spacing_mm``
    apart); the distance to each candidate is exact (closest point on the triangle), so the result
    is never under the true distance. Where the random samples miss the nearest face, a neighbour
    gives it: within a sample spacing of a 1 mm-faceted sphere at most 10 µm over (the test),
    against the 80 µm the generating stage asks of it. :meth:`signed_distance` signs it by the
    nearest face's normal (the file's winding; a closed model wound inside out is turned).
    """

    def __init__(self, mesh, spacing_mm: float = 0.2, k: int = 16):
        import trimesh
        from scipy.spatial import cKDTree
        count = int(min(max(mesh.area / spacing_mm ** 2, 1000), 2_000_000))
        pts, face = trimesh.sample.sample_surface(mesh, count, seed=0)
        self._tree = cKDTree(pts)
        self._face = np.asarray(face, np.int64)
        self._tris = np.asarray(mesh.triangles, float)
        normals = np.asarray(mesh.face_normals, float)
        if mesh.is_watertight and mesh.volume < 0:
            normals = -normals
        self._normals = normals
        self._k = min(k, count)

    def _closest(self, points):
        """Per point: distance to the model, the nearest face and the closest point on it."""
        import trimesh
        points = np.asarray(points, float).reshape(-1, 3)
        if len(points) == 0:
            return np.zeros(0), np.zeros(0, np.int64), np.zeros((0, 3))
        _, nb = self._tree.query(points, k=self._k)
        faces = self._face[nb]                                          # (n, k), with repeats
        rep = np.repeat(points, faces.shape[1], axis=0)
        cp = trimesh.triangles.closest_point(self._tris[faces.reshape(-1)], rep)
        d = np.linalg.norm(cp - rep, axis=1).reshape(faces.shape)
        best = d.argmin(axis=1)
        rows = np.arange(len(points))
        return d[rows, best], faces[rows, best], cp.reshape(*faces.shape, 3)[rows, best]

    def distance(self, points) -> np.ndarray:
        return self._closest(points)[0]

    def signed_distance(self, points) -> np.ndarray:
        """:meth:`distance`, negative inside the material (behind the nearest face's normal)."""
        points = np.asarray(points, float).reshape(-1, 3)
        d, face, cp = self._closest(points)
        side = np.einsum("ij,ij->i", points - cp, self._normals[face])
        return np.where(side < 0, -d, d)


def _read_mesh(path, what: str):
    """A mesh file as a trimesh, with an InputError naming the file and ``what`` it is for."""
    import trimesh
    path = os.fspath(path)
    if not os.path.exists(path):
        raise InputError(f"{path}: {what} not found")
    try:
        m = trimesh.load(path, force="mesh")
    except Exception as e:  # trimesh raises many types for bad files
        raise InputError(f"{path}: cannot read {what}: {e}") from None
    if len(m.faces) == 0:
        raise InputError(f"{path}: {what} has no faces")
    return m


@lru_cache(maxsize=4)
def _design_surface_cached(path: str, mtime: float) -> DesignSurface:
    return DesignSurface(_read_mesh(path, "nominal model"))


def load_design_surface(nominal) -> DesignSurface | None:
    """The workflow's ``nominal`` model (a mesh path) as a :class:`DesignSurface`; None without one."""
    if nominal is None or isinstance(nominal, DesignSurface):
        return nominal
    path = os.fspath(nominal)
    if not os.path.exists(path):
        raise InputError(f"{path}: nominal model not found")
    return _design_surface_cached(os.path.abspath(path), os.path.getmtime(path))


def load_workpiece(stock) -> Workpiece:
    """Stock from the engine's ``inputs['stock']``: a mesh path (STL/OBJ/PLY) or ``{'box': [...]}``."""
    if stock is None:
        raise InputError("stock: a stock model (mesh path or {box: [...]}) is required")
    if isinstance(stock, Workpiece):
        return stock
    if isinstance(stock, dict):
        if "box" not in stock:
            raise InputError(f"stock: dict must have key 'box', got {sorted(stock)}")
        return box_workpiece(stock["box"])
    m = _read_mesh(stock, "stock model")
    if not m.is_watertight:
        # from-below rendering needs the material side of every face; warn via message only
        pass
    if m.is_volume and m.volume < 0:
        m.invert()
    return _from_trimesh(m)


# ------------------------------------------------------------------------------------ passes

@dataclass
class PassGeometry:
    """Passes of one program as arrays (tool tip coordinates)."""

    program_id: str
    pass_id: np.ndarray      # (n,) int
    motion: np.ndarray       # (n,) int8, 0 = rapid
    p0: np.ndarray           # (n, 3) tip at start
    p1: np.ndarray           # (n, 3) tip at end
    feed_mm_min: np.ndarray
    spindle_rpm: np.ndarray

    @property
    def length(self):
        return np.linalg.norm(self.p1 - self.p0, axis=1)

    @property
    def s0(self):
        """Path length at the start of each pass (cumulative over the program)."""
        return np.concatenate([[0.0], np.cumsum(self.length)[:-1]])

    @property
    def feed_deg(self):
        """Direction of the xy feed, degrees CCW from +X (0 for pure plunges)."""
        d = self.p1 - self.p0
        return np.degrees(np.arctan2(d[:, 1], d[:, 0]))

    def sweep_bounds(self, shape: ToolShape):
        """(n, 2, 3) axis-aligned bounds of each pass's swept volume."""
        lo = np.minimum(self.p0, self.p1) - [shape.radius_mm, shape.radius_mm, 0.0]
        hi = np.maximum(self.p0, self.p1) + [shape.radius_mm, shape.radius_mm, shape.stickout_mm]
        return np.stack([lo, hi], axis=1)


def pass_geometry(passes, tool) -> PassGeometry:
    """Arrays of a ``passes`` table (one program). Converts ``control_point: center`` to tips."""
    shape = tool_from_params(tool)
    t = tool[0] if isinstance(tool, (list, tuple)) else tool
    cols = passes.column_names
    need = ["program_id", "pass_id", "motion", "x0_mm", "y0_mm", "z0_mm", "x1_mm", "y1_mm", "z1_mm"]
    missing = [c for c in need if c not in cols]
    if missing:
        raise InputError(f"passes: missing columns {missing}")
    col = {c: passes.column(c).to_numpy(zero_copy_only=False) for c in cols}
    p0 = np.stack([col["x0_mm"], col["y0_mm"], col["z0_mm"]], 1).astype(float)
    p1 = np.stack([col["x1_mm"], col["y1_mm"], col["z1_mm"]], 1).astype(float)
    if (t or {}).get("control_point", "tip") == "center":
        p0 = p0 - [0, 0, shape.corner_mm]
        p1 = p1 - [0, 0, shape.corner_mm]
    if not (np.all(np.isfinite(p0)) and np.all(np.isfinite(p1))):
        bad = int(np.nonzero(~np.all(np.isfinite(p0) & np.isfinite(p1), axis=1))[0][0])
        raise InputError(f"passes: pass_id {col['pass_id'][bad]}: non-finite coordinates")
    pid = col["program_id"][0] if len(passes) else ""
    n = len(passes)
    return PassGeometry(str(pid), col["pass_id"].astype(np.int64), col["motion"].astype(np.int8),
                        p0, p1, col.get("feed_mm_min", np.zeros(n)).astype(float),
                        col.get("spindle_rpm", np.zeros(n)).astype(float))


def overlaps(lo_a, hi_a, lo_b, hi_b):
    """(na, nb) boolean: axis-aligned xy boxes a and b overlap."""
    return ((lo_a[:, None, 0] <= hi_b[None, :, 0]) & (hi_a[:, None, 0] >= lo_b[None, :, 0])
            & (lo_a[:, None, 1] <= hi_b[None, :, 1]) & (hi_a[:, None, 1] >= lo_b[None, :, 1]))


def window_xy_bounds(views):
    """(n, 2) lo, hi xy bounds of the footprint of each view (conservative for oblique views)."""
    lo, hi = [], []
    for v in views:
        right, up, d = v.basis()
        c = np.asarray(v.center, float)
        corners = []
        for sx in (-0.5, 0.5):
            for sy in (-0.5, 0.5):
                for s in (v.near_mm, v.far_mm):
                    corners.append(c + sx * v.width_mm * right + sy * v.height_mm * up + s * d)
        corners = np.array(corners)
        lo.append(corners.min(0))
        hi.append(corners.max(0))
    return np.array(lo), np.array(hi)


def segment_scene(mesh: EnvelopeMesh, seg0, seg1, window, tri_id, view_dir, bias=0.0,
                  window_bounds=None, coarse_mesh=None, fine_ends=None):
    """Scene of the swept volumes of segments ``seg0[k] -> seg1[k]`` drawn into ``window[k]``.

    Identical segments (the same pass seen by several windows of a batch) are meshed once. Each
    sweep has three parts (end copies and silhouette bands); with ``window_bounds`` = (lo, hi)
    xy bounds per window, parts that miss their window are not copied at all.
    ``tri_id`` (k,) is the id stored in the pixels; attribute ``b`` is the contact angle q.
    Level of detail: with ``coarse_mesh`` and ``fine_ends`` (k, 2) bool, segment ends flagged
    False are drawn with the coarse mesh (far from where precision matters).
    """
    from stages.render import Scene
    seg0 = np.asarray(seg0, float).reshape(-1, 3)
    seg1 = np.asarray(seg1, float).reshape(-1, 3)
    window = np.asarray(window, np.int64).reshape(-1)
    k = len(seg0)
    if k == 0:
        return Scene.concat([])
    if fine_ends is None or coarse_mesh is None:
        fine_ends = np.ones((k, 2), bool)
        coarse_mesh = mesh
    fine_ends = np.asarray(fine_ends, bool).reshape(k, 2)
    key = np.concatenate([seg0, seg1, fine_ends], 1)
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    nu = len(uniq)
    f0, f1 = uniq[:, 6] > 0.5, uniq[:, 7] > 0.5
    # which (window, part) pairs are drawn, decided before any triangle is built: part 0/1 = the
    # copy at the start/end, 2 = the silhouette bands; a copy lies within the mesh's box moved to
    # its point, the bands within the union of the two copies' boxes (conservative bounds)
    pair = np.repeat(np.arange(k), 3)
    grp = (inv[:, None] * 3 + np.arange(3)[None]).reshape(-1)
    ok = np.ones(3 * k, bool)
    drop0, drop1 = chain_joints(seg0, seg1, window)
    ok &= ~np.stack([drop0, drop1, np.zeros(k, bool)], 1).reshape(-1)
    lune_t, lune_q, lune_o = [], [], []
    if window_bounds is not None:
        flat = mesh.tris.reshape(-1, 3)
        mlo, mhi = flat.min(0) - mesh.tol_mm, flat.max(0) + mesh.tol_mm     # the true envelope's box
        lo = np.empty((nu, 3, 3))
        hi = np.empty((nu, 3, 3))
        lo[:, 0], hi[:, 0] = uniq[:, 0:3] + mlo, uniq[:, 0:3] + mhi
        lo[:, 1], hi[:, 1] = uniq[:, 3:6] + mlo, uniq[:, 3:6] + mhi
        lo[:, 2], hi[:, 2] = np.minimum(lo[:, 0], lo[:, 1]), np.maximum(hi[:, 0], hi[:, 1])
        lo, hi = lo.reshape(-1, 3), hi.reshape(-1, 3)
        wlo, whi = (np.asarray(a_, float) for a_ in window_bounds)
        w = window[pair]
        ok &= ((lo[grp, 0] <= whi[w, 0]) & (hi[grp, 0] >= wlo[w, 0])
               & (lo[grp, 1] <= whi[w, 1]) & (hi[grp, 1] >= wlo[w, 1]))
    need = np.zeros(3 * nu, bool)
    need[grp[ok]] = True
    need = need.reshape(nu, 3)
    parts_t, parts_q, parts_g = [], [], []
    for end, flags in ((0, f0), (1, f1)):
        pts = uniq[:, 3 * end:3 * end + 3]
        for m_, sel in ((mesh, np.nonzero(flags & need[:, end])[0]), (coarse_mesh, np.nonzero(~flags & need[:, end])[0])):
            if len(sel):
                t_, q_, _, o_ = envelope_copies(m_, pts[sel], view_dir=view_dir)
                parts_t.append(t_), parts_q.append(q_), parts_g.append(sel[o_] * 3 + end)
    # the bands use the finer mesh of the two ends (cracks, if any, stay below that tolerance)
    for m_, sel in ((mesh, np.nonzero((f0 | f1) & need[:, 2])[0]), (coarse_mesh, np.nonzero(~(f0 | f1) & need[:, 2])[0])):
        if len(sel):
            t_, q_, o_ = sweep_bands(m_, uniq[sel, :3], uniq[sel, 3:6])
            parts_t.append(t_), parts_q.append(q_), parts_g.append(sel[o_] * 3 + 2)
    # the lunes of the left-out joint copies, per segment (they depend on the next segment too)
    lune_end = drop1.copy()
    if window_bounds is not None:
        lune_end &= ((seg1[:, 0] + mlo[0] <= whi[window, 0]) & (seg1[:, 0] + mhi[0] >= wlo[window, 0])
                     & (seg1[:, 1] + mlo[1] <= whi[window, 1]) & (seg1[:, 1] + mhi[1] >= wlo[window, 1]))
    fine_lune = fine_ends[:, 1]
    for m_, sel in ((mesh, lune_end & fine_lune), (coarse_mesh, lune_end & ~fine_lune)):
        if sel.any():
            t_, q_, o_ = joint_lunes(m_, seg0, seg1, sel, view_dir=view_dir)
            lune_t.append(t_), lune_q.append(q_), lune_o.append(o_)
    if not parts_t and not lune_t:
        return Scene.concat([])
    tris = np.concatenate(parts_t) if parts_t else np.zeros((0, 3, 3))
    q = np.concatenate(parts_q) if parts_q else np.zeros((0, 3))
    group = np.concatenate(parts_g) if parts_g else np.zeros(0, np.int64)
    order = np.argsort(group, kind="stable")
    tris, q, group = tris[order], q[order], group[order]
    starts = np.searchsorted(group, np.arange(3 * nu + 1))
    counts = np.diff(starts)
    ok &= counts[grp] > 0
    pair, grp = pair[ok], grp[ok]
    cnt = counts[grp]
    idx = ragged_ranges(starts[:-1][grp], cnt)
    rep = np.concatenate([np.repeat(pair, cnt)] + lune_o)
    tris = np.concatenate([tris[idx]] + lune_t)
    q = np.concatenate([q[idx]] + lune_q)
    attrs = np.zeros((len(rep), 3, 3), np.float32)
    attrs[:, :, 0] = np.broadcast_to(np.asarray(tri_id, float), (k,))[rep, None]
    attrs[:, :, 2] = q
    return Scene(tris, attrs, np.broadcast_to(np.asarray(bias, float), (k,))[rep].copy(),
                 window[rep])


def ragged_ranges(starts, counts):
    """Concatenation of ``arange(s, s + c)`` for each pair, without a Python loop."""
    counts = np.asarray(counts, np.int64)
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    ends = np.cumsum(counts)
    offs = np.repeat(ends - counts, counts)
    return np.repeat(np.asarray(starts, np.int64), counts) + (np.arange(total) - offs)


def workpiece_scene(wp: Workpiece, views, tri_id=0.0):
    """Workpiece faces a viewer inside the material leaves through (normal . view_dir > 0).

    Seen from below this is the top surface of the stock (the seed draws W without its lower
    face, para 0044); seen along a surface normal it is the face the ray exits through.
    """
    from stages.render import Scene
    lo_w, hi_w = window_xy_bounds(views)
    tlo, thi = wp.tris.min(1), wp.tris.max(1)
    d = np.array([np.asarray(v.view_dir, float) / np.linalg.norm(v.view_dir) for v in views])
    win, tri = np.nonzero(overlaps(lo_w, hi_w, tlo, thi) & ((d @ wp.normals.T) > 1e-9))
    attrs = np.zeros((len(tri), 3, 3), np.float32)
    attrs[:, :, 0] = tri_id
    attrs[:, :, 2] = -1.0
    return Scene(wp.tris[tri], attrs, np.zeros(len(tri)), win.astype(np.int64))
