"""The tool's cutting-edge envelope as a triangle mesh (seed 000 paras 0042, 0101).

The envelope of a rotating end mill is a surface of revolution about the tool axis (+Z) with the
profile r(z) of :class:`stages.geometry.cutter.Cutter`, closed by a cap at the stick-out so that
every tool is a closed convex solid.

Polygonisation tolerance. The profile polyline's arcs are split so that each chord's sagitta is at
most ``tol/2``; the columns are chosen the same way for the largest radius. Every vertex lies on
the true surface and every face is a planar trapezoid inscribed in it, so the mesh lies *inside*
the true envelope by at most ``tol_mm`` (tests/test_geometry.py samples faces against the profile).

Per-corner attributes (claim 4): ``q`` = angle of the envelope's outward normal from the downward
tool axis (the contact angle: 0° at the tip, 90° on the cylinder, 180° on the cap) and ``theta``
= angle about the tool axis from the column seam. Copies at a prediction point are rotated so that
the seam lies on the feed direction; ``theta`` is then the rotation angle φ, and the seam makes
sure no triangle interpolates across 0°/360°.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from stages.geometry.cutter import Cutter


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
    edge_theta_deg : (ne, 2) angle about the axis at the edge ends (from the seam, as ``theta_deg``).
    edge_faces : (ne, 2) the two faces adjacent to each edge.
    tol_mm : the tolerance the mesh was built for (mesh inside the true surface by <= tol_mm).
    """

    shape: Cutter
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
    edge_theta_deg: np.ndarray


def _profile_rows(shape: Cutter, tol_mm: float):
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
def envelope_mesh(shape: Cutter, tol_mm: float) -> EnvelopeMesh:
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
    mer_th = np.stack([thA, thD], axis=-1)
    rng_th = np.stack([thA[1:], thB[1:]], axis=-1)
    edge_th = np.concatenate([mer_th.reshape(-1, 2), rng_th[ring_ok].reshape(-1, 2)])
    return EnvelopeMesh(shape, float(tol_mm), n_theta, tris, qd, thd, fot,
                        normals.reshape(-1, 3), edges, edge_q, edge_f, edge_th)


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
