"""Swept volumes of linear passes as triangles, for the depth-test renders.

All tools are convex, so the volume swept by a translation along a segment is the convex hull of
the tool at both ends; for the polyhedral tool its boundary is made of faces of the two end copies
plus the faces swept by the *silhouette edges* (edges whose two adjacent faces face opposite ways
with respect to the motion). Rendering the two copies and the swept silhouette edges with a depth
test gives the exact first hit on the hull of the polyhedral tool from any viewpoint outside it.
Chains of passes leave out the copies at their joints and draw only the lune no sweep covers
(:func:`joint_lunes`): CAM output is mostly chains of short chords.
"""
from __future__ import annotations

import numpy as np

from stages.geometry.cutter import Cutter
from stages.geometry.envelope import EnvelopeMesh, envelope_copies
from stages.render import Scene
from stages.render.base import N_ATTR

# Faces whose normal is within this (radians) of perpendicular to a pass count as parallel to it,
# in the silhouette (sweep_bands) and in the joint lunes (joint_lunes). Why: the faces of a copy
# that lie along the motion are covered by neither band of an exact pass but by the lunes at its
# joints. With a tolerance of 1e-9 a chain of passes turned by 2e-9 rad (a corrected program's via
# points: float noise of the moves) had a silhouette one face over and lunes without those faces,
# and its sweeps lost their cut pixels to the next pass (the cylinder's 0.5 mm passes: 105 of 727
# passes "not cutting" in round 2). 1e-6 rad is far below the mesh's facets (~1e-2 rad).
PARALLEL_TOL = 1e-6


def sweep_bands(mesh: EnvelopeMesh, p0, p1, view_dir=None):
    """Faces swept by the silhouette edges of the envelope moving from ``p0`` to ``p1``.

    Together with :func:`envelope_copies` at ``p0`` and ``p1`` this renders the exact swept volume
    of the polyhedral tool. Vectorised over passes.

    Returns tris (n, 3, 3), q_deg (n, 3), owner (n,) index into ``p0``, theta_deg (n, 3) (the
    angle about the axis from the seam).
    """
    p0 = np.atleast_2d(np.asarray(p0, float))
    p1 = np.atleast_2d(np.asarray(p1, float))
    u = p1 - p0
    s = mesh.face_normals @ u.T                                     # (nf, k)
    # a face within PARALLEL_TOL of parallel to the motion counts as parallel (sign 0), so that a
    # pass turned by a few nanoradians has the silhouette of the exact one (see PARALLEL_TOL)
    eps = PARALLEL_TOL * np.maximum(np.linalg.norm(u, axis=1), 1e-30)[None]
    sign = (s > eps).view(np.int8) - (s < -eps).view(np.int8)      # one byte per face and pass
    edges = np.arange(len(mesh.edges))
    if view_dir is not None:
        # keep the bands a viewer looking along view_dir sees from outside: the band's outward
        # normal is (nearly) the mean of the two faces that meet at the silhouette edge, whatever
        # the pass, so the edges are chosen before the passes' silhouettes are
        nb = mesh.face_normals[mesh.edge_faces[:, 0]] + mesh.face_normals[mesh.edge_faces[:, 1]]
        edges = np.flatnonzero(nb @ np.asarray(view_dir, float) < -1e-9)
    # a silhouette edge: its faces face opposite ways, or one is parallel and the other not (two
    # parallel faces, or a pass of no length, make none)
    e, k = np.nonzero(sign[mesh.edge_faces[edges, 0]] != sign[mesh.edge_faces[edges, 1]])
    e = edges[e]
    a0 = mesh.edges[e, 0] + p0[k]
    b0 = mesh.edges[e, 1] + p0[k]
    a1 = mesh.edges[e, 0] + p1[k]
    b1 = mesh.edges[e, 1] + p1[k]
    qa, qb = mesh.edge_q_deg[e, 0], mesh.edge_q_deg[e, 1]
    ha, hb = mesh.edge_theta_deg[e, 0], mesh.edge_theta_deg[e, 1]
    tris = np.concatenate([np.stack([a0, b0, b1], 1), np.stack([a0, b1, a1], 1)])
    q = np.concatenate([np.stack([qa, qb, qb], 1), np.stack([qa, qb, qa], 1)])
    theta = np.concatenate([np.stack([ha, hb, hb], 1), np.stack([ha, hb, ha], 1)])
    owner = np.concatenate([k, k])
    return tris, q, owner, theta


def sweep_triangles(mesh: EnvelopeMesh, p0, p1, view_dir=None):
    """Triangles of the swept volumes of linear passes ``p0[i] -> p1[i]`` (tool tips).

    Returns tris (n, 3, 3), q_deg (n, 3), owner (n,) pass index into ``p0``.
    """
    p0 = np.atleast_2d(np.asarray(p0, float))
    p1 = np.atleast_2d(np.asarray(p1, float))
    t0, q0, _, o0 = envelope_copies(mesh, p0, view_dir=view_dir)
    t1, q1, _, o1 = envelope_copies(mesh, p1, view_dir=view_dir)
    tb, qb, ob, _ = sweep_bands(mesh, p0, p1, view_dir=view_dir)
    return np.concatenate([t0, t1, tb]), np.concatenate([q0, q1, qb]), np.concatenate([o0, o1, ob])


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

    Returns tris (n, 3, 3), q_deg (n, 3), owner (n,) index of segment i (its end copy), theta_deg (n, 3).
    """
    seg0 = np.asarray(seg0, float).reshape(-1, 3)
    seg1 = np.asarray(seg1, float).reshape(-1, 3)
    idx = np.nonzero(np.asarray(drop_end, bool))[0]
    if len(idx) == 0:
        return np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros((0, 3))
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
    return mesh.tris[sel] + seg1[owner, None, :], mesh.q_deg[sel], owner, mesh.theta_deg[sel]


def ordered_sweep_scene(mesh: EnvelopeMesh, p0, p1, ident, view_dir=(0.0, 0.0, 1.0), bias=0.0):
    """Sweeps of passes ``p0[k] -> p1[k]`` in the given (execution) order, for ``Renderer.scan``.

    Only the faces a viewer looking along ``view_dir`` sees from outside are kept, and per pass
    the silhouette bands come before the end copies: within one convex sweep each pixel then
    passes the depth test once, so fragment counts are pixel counts. Attributes: id
    ``ident[k]``, a = position along the pass (0 at p0, 1 at p1; beyond on the end copies),
    b = contact angle q, c = the angle θ of the envelope point about the tool axis, counter-
    clockwise from +X (the copies are not turned to the feed: the rotation angle φ is θ minus the
    pass's feed direction).
    """
    p0 = np.asarray(p0, float).reshape(-1, 3)
    p1 = np.asarray(p1, float).reshape(-1, 3)
    tb, qb, ob, hb = sweep_bands(mesh, p0, p1, view_dir=view_dir)
    drop0, drop1 = chain_joints(p0, p1, np.zeros(len(p0)))
    t0, q0, h0, o0 = envelope_copies(mesh, p0[~drop0], view_dir=view_dir)
    o0 = np.nonzero(~drop0)[0][o0]
    t1, q1, h1, o1 = envelope_copies(mesh, p1[~drop1], view_dir=view_dir)
    o1 = np.nonzero(~drop1)[0][o1]
    tl, ql, ol, hl = joint_lunes(mesh, p0, p1, drop1, view_dir=view_dir)
    tris = np.concatenate([tb, t0, t1, tl])
    q = np.concatenate([qb, q0, q1, ql])
    theta = np.concatenate([hb, h0, h1, hl])
    key = np.concatenate([ob * 3, o0 * 3 + 1, o1 * 3 + 2, ol * 3 + 2])
    order = np.argsort(key, kind="stable")
    owner = key[order] // 3
    tris, q, theta = tris[order], q[order], theta[order]
    # a: position along the pass of the point itself, projected in 3-D on the line of corner
    # centres (linear in space, so exact under interpolation; the facets of a polyhedral
    # silhouette would misplace a per-end 0/1 label by up to half a facet)
    d = p1 - p0
    dd = np.einsum("ij,ij->i", d, d)
    c0 = p0 + (0.0, 0.0, mesh.shape.corner_mm)
    a = np.einsum("tkj,tj->tk", tris - c0[owner, None, :], d[owner]) / np.where(dd > 1e-12, dd, 1.0)[owner, None]
    a = np.where((dd > 1e-12)[owner, None], a, 0.5)
    attrs = np.empty((len(order), 3, N_ATTR), np.float32)
    attrs[:, :, 0] = np.asarray(ident, float)[owner, None]
    attrs[:, :, 1] = a
    attrs[:, :, 2] = q
    attrs[:, :, 3] = theta
    return Scene(tris, attrs, np.full(len(order), float(bias)), np.zeros(len(order), np.int64))


def sweep_lowest_z(shape: Cutter, p0, p1, xy, n_t: int = 2001):
    """Brute-force reference: lowest point of the swept envelope above each ``xy`` (NaN if none).

    Samples the motion densely and takes the lower envelope; independent of the meshes (used by
    tests).
    """
    xy = np.atleast_2d(np.asarray(xy, float))
    t = np.linspace(0.0, 1.0, n_t)
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    tips = p0[None] + t[:, None] * (p1 - p0)[None]
    d = np.hypot(xy[:, None, 0] - tips[None, :, 0], xy[:, None, 1] - tips[None, :, 1])
    z = shape.lowest_z(d) + tips[None, :, 2]
    return np.nanmin(np.where(np.isnan(z), np.inf, z), axis=1)


def ragged_ranges(starts, counts):
    """Concatenation of ``arange(s, s + c)`` for each pair, without a Python loop."""
    counts = np.asarray(counts, np.int64)
    total = int(counts.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    ends = np.cumsum(counts)
    offs = np.repeat(ends - counts, counts)
    return np.repeat(np.asarray(starts, np.int64), counts) + (np.arange(total) - offs)
