"""Cylinder benchmark of seed 000 Fig. 16 (paras 0091-0092): contour machining of a cylinder.

Ball end mill Ø20 mm, 2 flutes, 6000 min⁻¹, 0.4 mm/tooth, 0.2 mm depth along the normal, 0.63 mm
pitch along the surface. The cylinder (radius ``rc_mm``) lies along Y; z-level passes run along
its axis in a zigzag from the top (contact angle 0°) down the +X side to ``q_max_deg``. The
generating point is analytic: the line from the ball centre to the cylinder axis meets the
surface, at contact angle q_k of the level, and rotation angle 90° (feed +Y) or 270° (feed -Y).
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import trimesh

TOOL = {"type": "ball", "diameter_mm": 20.0, "flutes": 2, "helix_deg": 30.0, "stickout_mm": 40.0,
        "corner_radius_mm": None, "runout_um": 0.0, "profile": None, "control_point": "tip",
        "t": None}
RPM, FZ, PITCH, DEPTH = 6000.0, 0.4, 0.63, 0.2


def cylinder_case(n_levels=50, q_max_deg=89.0, length_mm=6.0, program_id="cyl"):
    """Returns passes table, stock trimesh, and per-pass analytic (q, phi) (NaN elsewhere).

    Levels q_k = k * q_max / n_levels for k = 0..n_levels (so 0° and q_max are both levels) at
    0.63 mm pitch, which sets the cylinder radius; one more level on each side so every reference
    level has a neighbour on both sides (the analytic point assumes it). Those two padding levels
    get NaN references.
    """
    dq = np.radians(q_max_deg / n_levels)
    rc_mm = PITCH / dq
    R = TOOL["diameter_mm"] / 2
    qs = np.arange(-1, n_levels + 2) * dq
    Y = length_mm / 2 + R + 2.0
    feed = FZ * TOOL["flutes"] * RPM
    rows, q_ref, phi_ref = [], [], []
    cen = lambda q: np.array([(rc_mm + R) * np.sin(q), 0.0, (rc_mm + R) * np.cos(q) - R])
    prev = None
    for k, q in enumerate(qs):
        sgn = 1 if k % 2 == 0 else -1
        a, b = cen(q) + [0, -sgn * Y, 0], cen(q) + [0, sgn * Y, 0]
        if prev is None:
            rows.append((0, a + [0, 0, 30.0], a, 30000.0))     # rapid approach from above
        else:
            rows.append((1, prev, a, feed))                     # link in the air beyond the stock
        q_ref.append(np.nan), phi_ref.append(np.nan)
        rows.append((1, a, b, feed))
        pad = k == 0 or k == len(qs) - 1
        q_ref.append(np.nan if pad else np.degrees(q))
        phi_ref.append(np.nan if pad else (90.0 if sgn > 0 else 270.0))
        prev = b
    n = len(rows)
    p0 = np.array([r[1] for r in rows]); p1 = np.array([r[2] for r in rows])
    f = np.array([r[3] for r in rows])
    dt = np.linalg.norm(p1 - p0, axis=1) / f * 60
    t1 = np.cumsum(dt)
    passes = pa.table({
        "program_id": [program_id] * n, "pass_id": pa.array(np.arange(n), pa.int32()),
        "block_no": pa.array(np.arange(n), pa.int32()), "line_no": pa.array(np.arange(n) + 1, pa.int32()),
        "motion": pa.array([r[0] for r in rows], pa.int8()),
        "x0_mm": p0[:, 0], "y0_mm": p0[:, 1], "z0_mm": p0[:, 2],
        "x1_mm": p1[:, 0], "y1_mm": p1[:, 1], "z1_mm": p1[:, 2],
        "feed_mm_min": f, "spindle_rpm": np.full(n, RPM), "tool": pa.array([1] * n, pa.int32()),
        "t_start_s": t1 - dt, "t_end_s": t1})
    stock = trimesh.creation.cylinder(radius=rc_mm + DEPTH, height=length_mm, sections=720)
    stock.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    return passes, stock, np.array(q_ref), np.array(phi_ref), rc_mm
