"""How much of the closed loop's remaining error sits at the model's sharp edges (issue 58).

A ball cannot follow a sharp convex or concave edge of the model, and near one the probe's normal
is the model's, not the cut surface's: the error there is the cutter's shape meeting the edge,
which a path offset hardly changes. This splits ``closed_loop_points.parquet`` of
``bench/closed_loop_job.py`` by the distance of each probe point to the nearest sharp edge of the
nominal model (dihedral angle over ``--edge-deg``) and prints the RMS before and after, and the
ratio, of the points farther than each distance.

    python bench/closed_loop_edges.py runs/closed_loop/closed_loop_points.parquet data_samples/models/mould.stl
"""
from __future__ import annotations

import argparse

import numpy as np
import pandas as pd
import trimesh
from scipy.spatial import cKDTree


def sharp_edge_points(mesh: trimesh.Trimesh, edge_deg: float, step_mm: float = 0.02) -> np.ndarray:
    """Points every ``step_mm`` along the edges whose faces meet at more than ``edge_deg``."""
    sharp = mesh.face_adjacency_angles > np.radians(edge_deg)
    seg = mesh.vertices[mesh.face_adjacency_edges[sharp]]                # (e, 2, 3)
    n = np.maximum(np.ceil(np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1) / step_mm).astype(int), 1) + 1
    e = np.repeat(np.arange(len(seg)), n)
    t = (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)) / np.repeat(n - 1, n)
    return seg[e, 0] + t[:, None] * (seg[e, 1] - seg[e, 0])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("points")
    ap.add_argument("nominal")
    ap.add_argument("--edge-deg", type=float, default=30.0)
    ap.add_argument("--within", type=float, nargs="+", default=[0.0, 0.25, 0.5, 1.0])
    a = ap.parse_args(argv)
    pts = pd.read_parquet(a.points)
    mesh = trimesh.load(a.nominal, force="mesh")
    d, _ = cKDTree(sharp_edge_points(mesh, a.edge_deg)).query(pts[["x_mm", "y_mm", "z_mm"]].to_numpy())
    print(f"{'away from edges':>18} {'points':>7} {'before um':>9} {'after um':>8} {'ratio %':>7}")
    for w in a.within:
        sel = pts[d > w]
        b, f = np.sqrt((sel.before_rms_um ** 2).mean()), np.sqrt((sel.after_rms_um ** 2).mean())
        print(f"{'> ' + format(w, 'g') + ' mm':>18} {len(sel):>7} {b:>9.2f} {f:>8.2f} {100 * f / b:>7.1f}")


if __name__ == "__main__":
    main()
