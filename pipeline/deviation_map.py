"""The predicted error as a colour deviation map on the part, as metrology software shows CMM
deviations: the nominal mesh, refined, each vertex coloured by the error interpolated from the
predicted passes (a symmetric diverging scale, grey where nothing was predicted).

- :func:`surface_samples`: each predicted pass's error along its contact line (its generating
  point swept along the pass), so the map follows the passes rather than isolated points.
- :func:`vertex_errors`: inverse-distance mean of the samples near each vertex whose normal agrees.
- :func:`write_ply`: the coloured mesh (binary PLY, ``red green blue alpha`` and ``err_um`` per
  vertex) for MeshLab or ParaView.
- :func:`draw_views`: top and oblique orthographic pictures (painter's algorithm, Lambert shading).
"""
from __future__ import annotations

import numpy as np
import pandas as pd

from stages.geometry.sweeps import ragged_ranges

# refined mesh edge (mm): fine enough for the pass spacing of a finish, coarse enough to draw
EDGE_MM = 1.0
# most faces of a refined mesh (a picture of ~2 s, a PLY of a few MB)
MAX_FACES = 300_000
# samples along a pass's contact line (mm apart)
SAMPLE_MM = 0.5
# a sample colours a vertex whose normal is within ~72° of its own (not the far side of a thin wall)
NORMAL_DOT = 0.3
GREY = np.array([0.78, 0.78, 0.78])


def surface_samples(points: pd.DataFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points (mm), unit normals and errors (µm) along every predicted pass's contact line.

    ``points`` has per predicted pass its generating point ``gen_*_mm``, normal ``n*``, error
    ``err_um`` and the pass's ends ``x0_mm`` … ``z1_mm``: the contact line is the generating point
    moved along the pass by ±half its length.
    """
    ok = np.isfinite(points[["gen_x_mm", "gen_y_mm", "gen_z_mm", "nx", "ny", "nz", "err_um"]].to_numpy()).all(1)
    p = points[ok]
    g = p[["gen_x_mm", "gen_y_mm", "gen_z_mm"]].to_numpy()
    n = p[["nx", "ny", "nz"]].to_numpy()
    n = n / np.maximum(np.linalg.norm(n, axis=1), 1e-12)[:, None]
    d = (p[["x1_mm", "y1_mm", "z1_mm"]].to_numpy() - p[["x0_mm", "y0_mm", "z0_mm"]].to_numpy())
    d = np.nan_to_num(d)
    k = np.maximum(1, np.ceil(np.linalg.norm(d, axis=1) / SAMPLE_MM).astype(int) + 1)
    row = np.repeat(np.arange(len(p)), k)
    kk = np.repeat(k, k)
    s = np.where(kk > 1, ragged_ranges(np.zeros(len(p)), k) / np.maximum(kk - 1, 1) - 0.5, 0.0)
    return g[row] + s[:, None] * d[row], n[row], p.err_um.to_numpy()[row]


def vertex_errors(vertices: np.ndarray, normals: np.ndarray, xyz: np.ndarray, nrm: np.ndarray,
                  err: np.ndarray, radius_mm: float, k: int = 12) -> np.ndarray:
    """Error at each vertex: inverse-distance mean of the ``k`` nearest samples within ``radius_mm``
    whose normal agrees with the vertex's; NaN where there is none."""
    from scipy.spatial import cKDTree
    out = np.full(len(vertices), np.nan)
    if len(xyz) == 0 or len(vertices) == 0:
        return out
    k = min(k, len(xyz))
    dist, idx = cKDTree(xyz).query(vertices, k=k, distance_upper_bound=radius_mm)
    dist, idx = dist.reshape(len(vertices), k), idx.reshape(len(vertices), k)
    found = idx < len(xyz)
    safe = np.where(found, idx, 0)
    agree = found & (np.einsum("vkj,vj->vk", nrm[safe], normals) > NORMAL_DOT)
    w = np.where(agree, 1.0 / np.maximum(dist, 0.05 * radius_mm), 0.0)
    total = w.sum(1)
    has = total > 0
    out[has] = (w[has] * err[safe][has]).sum(1) / total[has]
    return out


def refined_mesh(mesh, near: np.ndarray, radius_mm: float, edge_mm: float = EDGE_MM,
                 max_faces: int = MAX_FACES):
    """The mesh with no edge longer than ``edge_mm`` on the faces within ``radius_mm`` of the points
    ``near`` (and the faces around them); the rest as it is, to be drawn grey (the seams between
    the two do not matter to a picture). The edge grows where that would make more than
    ``max_faces`` faces (a picture of a whole large mould)."""
    import trimesh
    faces = np.asarray(mesh.faces)
    hit = _faces_near(mesh, near, radius_mm)
    touch = np.zeros(len(mesh.vertices), bool)
    touch[faces[hit].ravel()] = True
    fine = touch[faces].any(1)
    if not fine.any():
        return mesh
    # midpoint subdivision splits a face in 4 until its longest edge fits: 4^k faces for k rounds
    longest = mesh.edges_unique_length[mesh.faces_unique_edges[fine]].max(1)
    count = lambda e: int((4.0 ** np.ceil(np.log2(np.maximum(longest / e, 1.0)))).sum())  # noqa: E731
    while count(edge_mm) > max_faces:
        edge_mm *= 1.25
    v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, faces[fine], max_edge=edge_mm, max_iter=20)
    coarse = faces[~fine]
    return trimesh.Trimesh(np.vstack([v, mesh.vertices]), np.vstack([f, coarse + len(v)]), process=True)


def _faces_near(mesh, points: np.ndarray, radius_mm: float) -> np.ndarray:
    """Faces with a point within ``radius_mm`` of their plane inside their bounding sphere grown by it."""
    from scipy.spatial import cKDTree
    if len(points) == 0:
        return np.zeros(0, np.int64)
    tri = mesh.triangles
    centre = tri.mean(1)
    reach = np.linalg.norm(tri - centre[:, None], axis=2).max(1) + radius_mm
    n, d = mesh.face_normals, np.einsum("ij,ij->i", mesh.face_normals, tri[:, 0])
    cand = cKDTree(points).query_ball_point(centre, reach)
    face = np.repeat(np.arange(len(tri)), [len(c) for c in cand])
    if face.size == 0:
        return np.zeros(0, np.int64)
    pt = np.concatenate([np.asarray(c, np.int64) for c in cand])
    close = np.abs(np.einsum("ij,ij->i", points[pt], n[face]) - d[face]) <= radius_mm
    return np.unique(face[close])


def interpolation_radius(xyz: np.ndarray) -> float:
    """Search radius (mm): twice the median distance from a sample to its nearest other sample, plus
    the sampling step, at least 0.5 mm."""
    from scipy.spatial import cKDTree
    if len(xyz) < 2:
        return 1.0
    d, _ = cKDTree(xyz).query(xyz, k=2)
    return float(max(0.5, 2.0 * np.median(d[:, 1]) + SAMPLE_MM))


def colours(err: np.ndarray, limit_um: float) -> np.ndarray:
    """RGB in [0, 1] per value on the symmetric scale ±``limit_um`` (coolwarm); grey for NaN."""
    from matplotlib import colormaps
    rgb = colormaps["coolwarm"](np.clip(0.5 + 0.5 * np.nan_to_num(err) / limit_um, 0, 1))[:, :3]
    rgb[~np.isfinite(err)] = GREY
    return rgb


def write_ply(path, mesh, err: np.ndarray, limit_um: float) -> None:
    """Binary PLY of ``mesh`` with one colour (``red green blue alpha``) and ``err_um`` per vertex."""
    import trimesh
    rgba = np.hstack([np.round(colours(err, limit_um) * 255), np.full((len(err), 1), 255)]).astype(np.uint8)
    m = trimesh.Trimesh(mesh.vertices, mesh.faces, vertex_colors=rgba, process=False)
    m.vertex_attributes["err_um"] = np.nan_to_num(err, nan=0.0).astype(np.float32)
    data = trimesh.exchange.ply.export_ply(m, encoding="binary", include_attributes=True)
    with open(path, "wb") as fh:
        fh.write(data)


# view directions (towards the viewer) and up vectors: top, and oblique from the front left
VIEWS = {"top": (np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0])),
         "oblique": (np.array([-0.55, -0.75, 0.85]), np.array([0.0, 0.0, 1.0]))}


def draw_views(ax_by_view: dict, mesh, err: np.ndarray, limit_um: float):
    """Draw the coloured mesh in each axes of ``ax_by_view`` (view name → matplotlib axes)."""
    from matplotlib.collections import PolyCollection
    light = np.array([-0.3, -0.5, 1.0])
    light /= np.linalg.norm(light)
    rgb_v = colours(err, limit_um)
    face_rgb = rgb_v[mesh.faces].mean(1)
    face_err = err[mesh.faces]
    no_data = ~np.isfinite(face_err).any(1)
    face_rgb[no_data] = GREY
    shade = 0.55 + 0.45 * np.abs(mesh.face_normals @ light)
    for name, ax in ax_by_view.items():
        view, up = VIEWS[name]
        view = view / np.linalg.norm(view)
        right = np.cross(up, view)
        right /= np.linalg.norm(right)
        up2 = np.cross(view, right)
        facing = mesh.face_normals @ view > 0
        tri = mesh.vertices[mesh.faces[facing]]
        depth = (tri @ view).mean(1)
        order = np.argsort(depth)                   # far first: nearer faces are drawn over them
        uv = np.stack([tri @ right, tri @ up2], -1)[order]
        pc = PolyCollection(uv, facecolors=(face_rgb[facing] * shade[facing, None])[order],
                            edgecolors="face", linewidths=0.1, antialiaseds=False)
        ax.add_collection(pc, autolim=False)
        allv = np.stack([mesh.vertices @ right, mesh.vertices @ up2], -1)
        lo, hi = allv.min(0), allv.max(0)
        pad = 0.03 * max(hi - lo)
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
        ax.set_aspect("equal")
        if name == "top":
            ax.set(xlabel="X mm", ylabel="Y mm", title="Top view")
        else:
            ax.set_axis_off()
            ax.set_title("Oblique view")
