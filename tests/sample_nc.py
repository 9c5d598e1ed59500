"""Independent readers of the sample files for tests/test_samples*.py: a tiny NC interpreter (not
``stages.parse``) and brute-force distances and ray crossings on meshes (no spatial index)."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import trimesh


def read_nc(path):
    """Interpret G0/G1/G2/G3 (G17 I J or R, G18 I K), absolute, modal. Returns a list of moves.

    Each move: dict(g, plane, feed, start (3,), end (3,), centre (3,) or None).
    """
    pos = np.full(3, np.nan)
    g, plane, feed = None, 17, np.nan
    moves = []
    for line in Path(path).read_text().splitlines():
        line = re.sub(r"\(.*?\)", "", line).split(";")[0].strip()
        if not line or line == "%" or line.startswith("O"):
            continue
        words = dict()
        gs = []
        for a, v in re.findall(r"([A-Z])\s*([-+]?\d*\.?\d+)", line):
            if a == "G":
                gs.append(int(float(v)))
            else:
                words[a] = float(v)
        for code in gs:
            if code in (0, 1, 2, 3):
                g = code
            elif code in (17, 18, 19):
                plane = code
        feed = words.get("F", feed)
        end = pos.copy()
        for i, a in enumerate("XYZ"):
            if a in words:
                end[i] = words[a]
        if not any(a in words for a in "XYZ"):
            continue
        centre = None
        if g in (2, 3):
            axes = {17: (0, 1, "IJ"), 18: (0, 2, "IK")}[plane]
            i0, i1, names = axes
            if "R" in words:
                # minor arc (R > 0) of radius R from start to end; centre on the side of the turn
                s2, e2 = pos[[i0, i1]], end[[i0, i1]]
                mid, chord = (s2 + e2) / 2, e2 - s2
                h = np.sqrt(words["R"] ** 2 - (chord @ chord) / 4)
                left = np.array([-chord[1], chord[0]]) / np.linalg.norm(chord)
                c2 = mid + (left if g == 3 else -left) * h
            else:
                c2 = pos[[i0, i1]] + [words.get(names[0], 0.0), words.get(names[1], 0.0)]
            centre = pos.copy()
            centre[[i0, i1]] = c2
        moves.append(dict(g=g, plane=plane, feed=feed, start=pos.copy(), end=end.copy(), centre=centre))
        pos = end
    return moves


def arc_points(m, n=16):
    """Points along an arc move (G17 or G18), direction per ISO (G2 clockwise seen from +axis)."""
    i0, i1 = (0, 1) if m["plane"] == 17 else (2, 0)  # G18: the ZX plane, Z first
    c, s, e = m["centre"], m["start"], m["end"]
    a0 = np.arctan2(s[i1] - c[i1], s[i0] - c[i0])
    a1 = np.arctan2(e[i1] - c[i1], e[i0] - c[i0])
    sweep = (a1 - a0) % (2 * np.pi) if m["g"] == 3 else -((a0 - a1) % (2 * np.pi))
    if abs(sweep) < 1e-9:
        sweep = 2 * np.pi if m["g"] == 3 else -2 * np.pi
    r = np.hypot(s[i1] - c[i1], s[i0] - c[i0])
    t = a0 + sweep * np.linspace(0, 1, n)
    p = np.repeat(s[None], n, 0)
    p[:, i0] = c[i0] + r * np.cos(t)
    p[:, i1] = c[i1] + r * np.sin(t)
    # the third axis moves linearly (helix); flat arcs here
    k = 3 - i0 - i1
    p[:, k] = s[k] + (e[k] - s[k]) * np.linspace(0, 1, n)
    return p


def closest(mesh, points):
    """Brute-force closest point on the mesh surface and distance, for each point."""
    cp, d, _ = trimesh.proximity.closest_point_naive(mesh, np.asarray(points, float))
    return cp, d


def distance_to(mesh, points):
    """Brute-force unsigned distance from points to the mesh surface."""
    return closest(mesh, points)[1]


def ray_exit(mesh, origins, dirs, reach=3.0):
    """Distance along each unit ray to its first crossing with a triangle of the mesh within ``reach``
    (inf where none): Möller–Trumbore against every triangle whose box meets the ray's segment."""
    tris = np.asarray(mesh.triangles, float)
    lo, hi = tris.min(1), tris.max(1)
    out = np.full(len(origins), np.inf)
    for k, (o, d) in enumerate(zip(np.asarray(origins, float), np.asarray(dirs, float))):
        e = o + reach * d
        sel = np.flatnonzero((hi >= np.minimum(o, e) - 1e-9).all(1) & (lo <= np.maximum(o, e) + 1e-9).all(1))
        v0, v1, v2 = tris[sel, 0], tris[sel, 1], tris[sel, 2]
        e1, e2 = v1 - v0, v2 - v0
        p = np.cross(d, e2)
        det = (e1 * p).sum(1)
        ok = np.abs(det) > 1e-15
        inv = 1.0 / np.where(ok, det, 1.0)
        tv = o - v0
        u = (tv * p).sum(1) * inv
        q = np.cross(tv, e1)
        v = (q @ d) * inv
        t = (e2 * q).sum(1) * inv
        hit = ok & (u >= -1e-12) & (v >= -1e-12) & (u + v <= 1 + 1e-12) & (t > 0) & (t <= reach)
        if hit.any():
            out[k] = t[hit].min()
    return out


def feature_edges(mesh, min_deg=20.0):
    """(n, 2, 3) edges of the mesh whose faces meet at more than ``min_deg``: its sharp edges."""
    sharp = np.degrees(mesh.face_adjacency_angles) > min_deg
    return mesh.vertices[mesh.face_adjacency_edges[sharp]]


def distance_to_segments(points, segs):
    """Distance from each point to the nearest of the segments (n, 2, 3)."""
    a, b = segs[:, 0], segs[:, 1]
    ab = b - a
    L2 = np.maximum((ab * ab).sum(1), 1e-18)
    out = np.empty(len(points))
    for k, p in enumerate(np.asarray(points, float)):
        t = np.clip(((p - a) * ab).sum(1) / L2, 0, 1)
        out[k] = np.linalg.norm(a + t[:, None] * ab - p, axis=1).min()
    return out
