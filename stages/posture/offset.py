"""The inverse offset of a ball end mill (seed §3, Kondo's inverse offset method).

The tool-tip centre C of a ball of radius r on a shank of the same radius along the tool axis θ
touches the surface and collides with nothing exactly when it lies on the upper envelope (seen
along θ) of the balls of radius r centred on every surface point. That envelope is the surface
offset by r along its normals (each face translated; smooth regions with their vertex normals),
closed by cylinders over sharp convex edges and open boundary edges and by spheres at corners.
This module builds it once as one triangle list; the first ``n_faces`` offset triangles are the
part's faces in order (the z-map's ids), the others (arcs and spheres) occlude but own nothing.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.posture.part import Part

OCCLUDER = -2           # id of offset triangles that belong to no face (arcs, spheres)
EMPTY = -1              # z-map cells where no offset lies


@dataclass
class OffsetMesh:
    """The inverse offset as triangles (mm).

    vertices : (m, 3); faces : (t, 3) int; ids : (t,) face of the part or ``OCCLUDER``;
    n_faces : the first n_faces triangles are the offset faces; plane_normals : (n_faces, 3) unit
    normals of those offset triangles; centres : (n_regions, 3) each micro-region's centroid carried
    onto its offset triangle (where the ball centre sits when the tool touches it).
    """

    vertices: np.ndarray
    faces: np.ndarray
    ids: np.ndarray
    n_faces: int
    plane_normals: np.ndarray
    centres: np.ndarray
    radius: float
    crease_deg: float = 0.0

    def triangles(self) -> np.ndarray:
        return self.vertices[self.faces]


def decode(code):
    """Ids from the rendered code (face + 1, 0 for an occluder, −1 for nothing)."""
    code = np.asarray(code)
    return np.where(code > 0, code - 1, np.where(code == 0, OCCLUDER, EMPTY)).astype(np.int64)


def crease_deg(radius: float, cell_mm: float) -> float:
    """Angle between neighbouring convex faces above which their edge gets an arc rather than shared
    vertex normals: a vertex normal then turns a face's offset by at most half a cell sideways
    (r sin(a/2) ≤ cell/2), so what it hides is right to the z-map's resolution."""
    return float(np.degrees(2 * np.arcsin(min(1.0, 0.5 * cell_mm / radius))).clip(0.5, 30.0))


def _smooth_vertices(part: Part, crease: float):
    """Split the vertices at sharp edges: a label per face corner (nf, 3) and a normal per label."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components
    import trimesh
    mesh = trimesh.Trimesh(part.vertices, part.faces, process=False)
    adj, edges = mesh.face_adjacency, mesh.face_adjacency_edges
    # joined: nearly coplanar edges, and convex ones below the crease angle (their vertex normals sag
    # at most the tolerance under the arc); concave edges keep each face's own translate, which
    # overlap there, so the z-buffer takes their upper envelope exactly
    ang = mesh.face_adjacency_angles
    smooth = (ang <= np.radians(0.01)) | ((ang <= np.radians(crease)) & mesh.face_adjacency_convex)
    F = part.faces
    rows, cols = [], []
    for k in range(2):
        u = edges[smooth, k]
        f1, f2 = adj[smooth, 0], adj[smooth, 1]
        rows.append(3 * f1 + np.argmax(F[f1] == u[:, None], 1))
        cols.append(3 * f2 + np.argmax(F[f2] == u[:, None], 1))
    n = 3 * len(F)
    g = sp.coo_matrix((np.ones(sum(len(r) for r in rows)), (np.concatenate(rows), np.concatenate(cols))), (n, n))
    n_lab, lab = connected_components(g, directed=False)
    # angle-weighted normal per label
    tri = part.vertices[F]
    e1 = tri[:, [1, 2, 0]] - tri
    e2 = tri[:, [2, 0, 1]] - tri
    cosang = np.sum(e1 * e2, -1) / (np.linalg.norm(e1, axis=-1) * np.linalg.norm(e2, axis=-1))
    w = np.arccos(np.clip(cosang, -1, 1)).ravel()
    nrm = np.zeros((n_lab, 3))
    np.add.at(nrm, lab, part.face_normals.repeat(3, 0) * w[:, None])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
    pos = np.zeros((n_lab, 3))
    pos[lab] = tri.reshape(-1, 3)
    vert = np.zeros(n_lab, np.int64)
    vert[lab] = F.ravel()
    return lab.reshape(-1, 3), nrm, pos, vert, mesh, adj, edges, smooth


def _rotate(n, axis, ang):
    """Rodrigues: unit vectors ``n`` (m, 3) turned by ``ang`` (m, k) about unit ``axis`` (m, 3) → (m, k, 3)."""
    c, s = np.cos(ang)[..., None], np.sin(ang)[..., None]
    n, axis = n[:, None], axis[:, None]
    return n * c + np.cross(axis, n) * s + axis * np.sum(axis * n, -1, keepdims=True) * (1 - c)


def _strips(a_pts, b_pts):
    """Triangles between two polylines of k+1 points each: (m, k+1, 3) × 2 → (m·2k, 3, 3)."""
    k = a_pts.shape[1] - 1
    t1 = np.stack([a_pts[:, :k], a_pts[:, 1:], b_pts[:, 1:]], 2)
    t2 = np.stack([a_pts[:, :k], b_pts[:, 1:], b_pts[:, :k]], 2)
    return np.concatenate([t1, t2], 1).reshape(-1, 3, 3)


def _arcs(base_u, base_v, start_u, start_v, axis, angle, r, step):
    """Cylinder strips over edges (u, v): the normals at u and v turned about ``axis`` by 0 … angle."""
    out = []
    k_all = np.maximum(1, np.ceil(angle / step)).astype(np.int64)
    for k in np.unique(k_all):
        s = k_all == k
        t = angle[s, None] * np.linspace(0, 1, k + 1)[None]
        pu = base_u[s, None] + r * _rotate(start_u[s], axis[s], t)
        pv = base_v[s, None] + r * _rotate(start_v[s], axis[s], t)
        out.append(_strips(pu, pv))
    return np.concatenate(out) if out else np.zeros((0, 3, 3))


def _slerp(a, b, t):
    """Great-circle points between unit vectors a and b (m, 3) at fractions t (k,) → (m, k, 3)."""
    om = np.arccos(np.clip(np.sum(a * b, -1), -1, 1))[:, None, None]
    so = np.sin(om)
    t = t[None, :, None]
    lin = so < 1e-9
    wa = np.where(lin, 1 - t, np.sin((1 - t) * om) / np.where(lin, 1, so))
    wb = np.where(lin, t, np.sin(t * om) / np.where(lin, 1, so))
    return wa * a[:, None] + wb * b[:, None]


def _slerp_arcs(pu, pv, nu1, nu2, nv1, nv2, r, step):
    """Cylinder strips over sharp edges (u, v): from each side's vertex normal to the other's."""
    ang = np.maximum(np.arccos(np.clip(np.sum(nu1 * nu2, 1), -1, 1)), np.arccos(np.clip(np.sum(nv1 * nv2, 1), -1, 1)))
    k_all = np.maximum(1, np.ceil(ang / step)).astype(np.int64)
    out = []
    for k in np.unique(k_all):
        s = k_all == k
        t = np.linspace(0, 1, k + 1)
        out.append(_strips(pu[s, None] + r * _slerp(nu1[s], nu2[s], t), pv[s, None] + r * _slerp(nv1[s], nv2[s], t)))
    return np.concatenate(out) if out else np.zeros((0, 3, 3))


def _sphere(r, sag):
    """Icosphere of radius r whose faces sag at most about ``sag`` (level ≤ 3)."""
    import trimesh
    level = 0
    while level < 3 and r * (1 - np.cos(np.radians(63.4 / 2 ** level) / 2)) > sag:
        level += 1
    s = trimesh.creation.icosphere(subdivisions=level, radius=r)
    return s.vertices[s.faces]


def inverse_offset(part: Part, radius: float, cell_mm: float) -> OffsetMesh:
    """The inverse offset of ``part`` for a ball of ``radius`` (mm), as fine as a z-map of ``cell_mm``
    needs: arcs and spheres whose chords sag at most a quarter of a cell."""
    r = float(radius)
    sag_mm = cell_mm / 4
    crease = crease_deg(r, cell_mm)
    step = 2 * np.arccos(max(-1.0, 1 - min(sag_mm / r, 2.0)))
    lab, nrm, pos, vert, mesh, adj, edges, smooth = _smooth_vertices(part, crease)
    W = pos + r * nrm
    F = part.faces
    nf = len(F)
    parts = []
    # sharp convex edges: from one side's normal to the other's, about the edge
    sharp = ~smooth & mesh.face_adjacency_convex
    if sharp.any():
        f1, f2, u, v = adj[sharp, 0], adj[sharp, 1], edges[sharp, 0], edges[sharp, 1]
        lu1, lu2 = lab[f1, np.argmax(F[f1] == u[:, None], 1)], lab[f2, np.argmax(F[f2] == u[:, None], 1)]
        lv1, lv2 = lab[f1, np.argmax(F[f1] == v[:, None], 1)], lab[f2, np.argmax(F[f2] == v[:, None], 1)]
        parts.append(_slerp_arcs(part.vertices[u], part.vertices[v], nrm[lu1], nrm[lu2], nrm[lv1], nrm[lv2], r, step))
        # at each end of the arc, a triangle to the vertex's mean normal closes the spherical polygon
        # the arcs around a convex vertex leave open (a fan from the mean, one triangle per arc)
        mean = np.zeros((len(part.vertices), 3))
        np.add.at(mean, vert, nrm)
        mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-300)
        for p, a, b in ((u, lu1, lu2), (v, lv1, lv2)):
            x = part.vertices[p]
            parts.append(np.stack([x + r * mean[p], x + r * nrm[a], x + r * nrm[b]], 1))
    # open boundary edges: half a cylinder from the face's normal over the edge to its back
    eu = mesh.edges_sorted
    from trimesh.grouping import group_rows
    single = group_rows(eu, require_count=1)
    corners = np.zeros(len(part.vertices), bool)
    if len(single):
        f = mesh.edges_face[single]
        u, v = mesh.edges[single, 0], mesh.edges[single, 1]
        axis = part.vertices[v] - part.vertices[u]
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        edir = axis.copy()
        third = part.vertices[F[f]].sum(1) - part.vertices[u] - part.vertices[v]
        out = part.vertices[u] - third            # away from the face, roughly
        sgn = np.sign(np.sum(np.cross(axis, part.face_normals[f]) * out, 1))
        axis = axis * np.where(sgn == 0, 1, sgn)[:, None]
        lu, lv = lab[f, np.argmax(F[f] == u[:, None], 1)], lab[f, np.argmax(F[f] == v[:, None], 1)]
        parts.append(_arcs(part.vertices[u], part.vertices[v], nrm[lu], nrm[lv], axis,
                           np.full(len(f), np.pi), r, step))
        # a boundary vertex where the boundary turns: the two half cylinders leave a wedge
        turn = np.zeros((len(part.vertices), 3))
        np.add.at(turn, u, edir)
        np.add.at(turn, v, -edir)
        corners = np.linalg.norm(turn, axis=1) > 2 * np.sin(np.radians(crease) / 2)
    # corners whose fan would sag (edges sharper than 45° meeting three or more groups), and turns of
    # the open boundary: a sphere
    groups = np.bincount(vert, minlength=len(part.vertices))
    big = sharp & (mesh.face_adjacency_angles > np.radians(45.0))
    n_big = np.bincount(edges[big].ravel(), minlength=len(part.vertices))
    corners |= (groups >= 3) & (n_big >= 2)
    idx = np.nonzero(corners)[0]
    if len(idx):
        sph = _sphere(r, sag_mm)
        parts.append((part.vertices[idx, None, None] + sph[None]).reshape(-1, 3, 3))
    extra = np.concatenate(parts) if parts else np.zeros((0, 3, 3))
    vertices = np.concatenate([W, extra.reshape(-1, 3)])
    faces = np.concatenate([lab, len(W) + np.arange(3 * len(extra)).reshape(-1, 3)]).astype(np.int64)
    ids = np.concatenate([np.arange(nf), np.full(len(extra), OCCLUDER)])
    ot = W[lab]
    pn = np.cross(ot[:, 1] - ot[:, 0], ot[:, 2] - ot[:, 0])
    ln = np.linalg.norm(pn, axis=1, keepdims=True)
    pn = np.where(ln > 1e-300, pn / np.maximum(ln, 1e-300), part.face_normals)
    pn *= np.where(np.sum(pn * part.face_normals, 1, keepdims=True) < 0, -1, 1)
    centres = np.einsum("nk,nkj->nj", part.bary, ot[part.parent])
    return OffsetMesh(vertices, faces, ids, nf, pn, centres, r, crease)
