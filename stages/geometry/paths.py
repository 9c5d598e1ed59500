"""Path geometry shared by the gap diagnosis and the virtual machine (no prediction code).

Cutting passes as ball-centre segments with times and path lengths, the nearest pass to a point,
and path corners (direction changes between touching cutting moves).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyarrow as pa

CORNER_DEG = 20.0  # a direction change larger than this between cutting moves is a corner


@dataclass
class Path3:
    """Cutting passes of one program as ball-centre segments with times and path lengths."""

    program_id: str
    pass_id: np.ndarray
    c0: np.ndarray
    c1: np.ndarray
    t0: np.ndarray
    t1: np.ndarray
    feed: np.ndarray
    rpm: np.ndarray
    L0: np.ndarray          # cut length (mm) at the start of each pass
    s0: np.ndarray          # path length (mm) over cutting moves at the start of each pass
    corner_s: np.ndarray    # path length of each corner vertex
    corner_deg: np.ndarray
    corner_b: np.ndarray    # (k, 3) unit bisector towards the inside of the turn

    @property
    def length(self):
        return np.linalg.norm(self.c1 - self.c0, axis=1)


def program_paths(passes: pa.Table, radius_mm: float, control_point: str = "tip") -> list[Path3]:
    """Cutting moves (motion ≠ 0) of each program, as ball-centre segments."""
    out = []
    pid_col = np.asarray(passes.column("program_id").to_pylist(), dtype=object)
    for prog in dict.fromkeys(pid_col.tolist()):
        m = pid_col == prog
        sub = passes.filter(pa.array(m))
        g = {c: sub.column(c).to_numpy(zero_copy_only=False) for c in
             ("pass_id", "motion", "x0_mm", "y0_mm", "z0_mm", "x1_mm", "y1_mm", "z1_mm", "feed_mm_min",
              "spindle_rpm", "t_start_s", "t_end_s")}
        order = np.argsort(g["pass_id"], kind="stable")
        g = {k: v[order] for k, v in g.items()}
        cut = (g["motion"] != 0) & np.isfinite(g["x0_mm"])
        lift = 0.0 if control_point == "center" else radius_mm
        p0 = np.stack([g["x0_mm"], g["y0_mm"], g["z0_mm"] + lift], 1)[cut]
        p1 = np.stack([g["x1_mm"], g["y1_mm"], g["z1_mm"] + lift], 1)[cut]
        ln = np.linalg.norm(p1 - p0, axis=1)
        keep = ln > 1e-9
        p0, p1, ln = p0[keep], p1[keep], ln[keep]
        idx = np.flatnonzero(cut)[keep]
        s0 = np.concatenate([[0.0], np.cumsum(ln)[:-1]])
        # corners: consecutive cutting moves that touch (end = start) and turn by more than CORNER_DEG
        d = (p1 - p0) / ln[:, None]
        touch = np.linalg.norm(p1[:-1] - p0[1:], axis=1) < 1e-6
        cosang = np.clip(np.sum(d[:-1] * d[1:], axis=1), -1, 1)
        ang = np.degrees(np.arccos(cosang))
        k = np.flatnonzero(touch & (ang > CORNER_DEG))
        b = d[k + 1] - d[k]
        bn = np.linalg.norm(b, axis=1)
        b = b / np.where(bn > 0, bn, 1.0)[:, None]
        out.append(Path3(prog, g["pass_id"][idx].astype(np.int64), p0, p1, g["t_start_s"][idx], g["t_end_s"][idx],
                         g["feed_mm_min"][idx].astype(float), g["spindle_rpm"][idx].astype(float),
                         s0.copy(), s0, s0[k + 1], ang[k], b))
    return out


def nearest_pass(path: Path3, pts: np.ndarray, k: int = 16, sub_mm: float = 0.25):
    """For each point, the cutting pass whose centre segment is nearest: (row, u, distance).

    Candidates come from a KD-tree over sub-segment mid points; the exact point–segment distance
    decides. Ties within 1e-7 mm go to the later pass (it cut last).
    """
    from scipy.spatial import cKDTree
    ln = path.length
    nsub = np.maximum(1, np.ceil(ln / sub_mm).astype(np.int64))
    owner = np.repeat(np.arange(len(ln)), nsub)
    frac = (np.arange(nsub.sum()) - np.repeat(np.cumsum(nsub) - nsub, nsub) + 0.5) / np.repeat(nsub, nsub)
    mids = path.c0[owner] + frac[:, None] * (path.c1 - path.c0)[owner]
    tree = cKDTree(mids)
    kk = min(k, len(mids))
    _, cand = tree.query(pts, k=kk)
    cand = owner[np.atleast_2d(cand).reshape(len(pts), kk)]
    a, b = path.c0[cand], path.c1[cand]
    ab = b - a
    u = np.clip(np.einsum("pkj,pkj->pk", pts[:, None, :] - a, ab) / np.maximum(np.einsum("pkj,pkj->pk", ab, ab), 1e-30), 0, 1)
    dist = np.linalg.norm(a + u[..., None] * ab - pts[:, None, :], axis=2)
    score = dist - 1e-7 * cand / max(len(ln), 1)     # later pass wins ties
    j = np.argmin(score, axis=1)
    r = np.arange(len(pts))
    return cand[r, j], u[r, j], dist[r, j]


def corner_features(path: Path3, rows: np.ndarray, u: np.ndarray):
    """Distance along the path to the nearest corner, its angle and inside bisector (inf/0 if none)."""
    s = path.s0[rows] + u * path.length[rows]
    n = len(s)
    if len(path.corner_s) == 0:
        return np.full(n, np.inf), np.zeros(n), np.zeros((n, 3))
    i = np.searchsorted(path.corner_s, s)
    lo, hi = np.clip(i - 1, 0, len(path.corner_s) - 1), np.clip(i, 0, len(path.corner_s) - 1)
    dlo, dhi = np.abs(s - path.corner_s[lo]), np.abs(path.corner_s[hi] - s)
    c = np.where(dlo <= dhi, lo, hi)
    return np.minimum(dlo, dhi), path.corner_deg[c], path.corner_b[c]




def path_point(path: Path3, s: np.ndarray):
    """Nominal ball centre at path length ``s`` along the cutting moves and the pass (row) it lies on.

    Within the moves the centre follows them (across a pass end onto the next cutting move);
    before the first and after the last move the line of that move is extended.
    """
    s = np.asarray(s, float)
    i = np.clip(np.searchsorted(path.s0, s, side="right") - 1, 0, len(path.s0) - 1)
    f = (s - path.s0[i]) / path.length[i]
    inner = (i > 0) & (i < len(path.s0) - 1)
    f = np.where(inner, np.clip(f, 0.0, 1.0), f)
    f = np.where((i == 0) & (len(path.s0) > 1), np.minimum(f, 1.0), f)
    f = np.where((i == len(path.s0) - 1) & (len(path.s0) > 1), np.maximum(f, 0.0), f)
    return path.c0[i] + f[..., None] * (path.c1[i] - path.c0[i]), i
