"""The corrected path as Heidenhain-style ``LN`` blocks with surface normals, and a contact-angle
compensation table (radius deviation per angle, like a 3D-ToolComp ``.3DTC`` file).
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa

from stages.tables import col


def write_ln_program(blocks: pa.Table, corrected: pa.Table, name: str = "CORRECTED", use_new: bool = True,
                     chord_tol_mm: float = 0.001, decimals: int = 4) -> str:
    """Heidenhain-style program: ``LN`` blocks with the surface normals of the corrected path.

    One block per NC vertex: ``LN X.. Y.. Z.. NX.. NY.. NZ..`` where a predicted pass meets the
    vertex (its unit normal, out of material), plain ``L`` elsewhere, ``FMAX`` for rapids, ``F`` when
    the feed changes. LN blocks are straight, so arcs are written as chords within
    ``chord_tol_mm`` of the (refitted) arc, each with the arc's end normal turned about the arc axis
    to the chord point. ``use_new=False`` writes the original path with normals, for controls that
    apply the compensation themselves (3D-ToolComp with :func:`write_comp_table`); do not use the
    corrected path and the table together, that corrects twice. Coordinates are in the frame of the
    source program (tool tip unless ``tool.control_point`` says centre).
    """
    from stages.nc.moves import arc_chords
    cols = ("x_new_mm", "y_new_mm", "z_new_mm") if use_new else ("x_mm", "y_mm", "z_mm")
    p = np.stack([col(corrected, c) for c in cols], 1)
    nrm = np.stack([col(corrected, c) for c in ("nx", "ny", "nz")], 1)
    motion = col(corrected, "motion", np.int64)
    bno = col(blocks, "block_no", np.int64)
    rows = np.searchsorted(bno, col(corrected, "block_no", np.int64))
    feed = np.nan_to_num(col(blocks, "feed_mm_min")[rows])
    plane = col(blocks, "plane", np.int64)[rows]
    if use_new:
        centre = np.stack([col(corrected, c) for c in ("cx_new_mm", "cy_new_mm", "cz_new_mm")], 1)
    else:
        centre = np.stack([col(blocks, c) for c in ("cx_mm", "cy_mm", "cz_mm")], 1)[rows]
    start = np.vstack([p[:1], p[:-1]])
    # expand arcs into chord end points; lines keep their vertex
    arc = np.flatnonzero(((motion == 2) | (motion == 3)) & ~np.isnan(centre).any(1))
    pts, nn, src = p, nrm, np.arange(p.shape[0])
    if arc.size:
        owner, _, q1 = arc_chords(start[arc], p[arc], centre[arc], plane[arc], motion[arc] == 3, chord_tol_mm)
        axis = np.zeros((arc.size, 3))
        axis[np.arange(arc.size), np.array([{17: 2, 18: 1, 19: 0}[int(v)] for v in plane[arc]])] = 1.0
        # turn the end normal about the arc axis by the angle from the end to the chord point
        c, e = centre[arc][owner], p[arc][owner]
        ax = axis[owner]
        u, v = e - c, q1 - c
        u -= np.einsum("ij,ij->i", u, ax)[:, None] * ax
        v -= np.einsum("ij,ij->i", v, ax)[:, None] * ax
        ang = np.arctan2(np.einsum("ij,ij->i", np.cross(u, v), ax), np.einsum("ij,ij->i", u, v))
        n0 = nrm[arc][owner]
        cos, sin = np.cos(ang)[:, None], np.sin(ang)[:, None]
        n1 = n0 * cos + np.cross(ax, n0) * sin + ax * np.einsum("ij,ij->i", ax, n0)[:, None] * (1 - cos)
        keep = np.ones(p.shape[0], bool)
        keep[arc] = False
        line_rows = np.flatnonzero(keep)
        order_key = np.concatenate([line_rows.astype(float), arc[owner] + (np.arange(owner.size) + 1.0) / (owner.size + 2)])
        o = np.argsort(order_key, kind="stable")
        pts = np.concatenate([p[line_rows], q1])[o]
        nn = np.concatenate([nrm[line_rows], n1])[o]
        src = np.concatenate([line_rows, arc[owner]])[o]
    out = [f"0 BEGIN PGM {name} MM"]
    prev = np.full(3, np.nan)
    prev_f = None
    k = 1
    res = 0.5 * 10.0 ** -decimals
    for i in range(pts.shape[0]):
        words = [f"{letter}{pts[i, a]:+.{decimals}f}" for a, letter in enumerate("XYZ")
                 if not abs(pts[i, a] - prev[a]) <= res]
        if not words:
            continue
        prev = pts[i]
        r = src[i]
        has_n = motion[r] != 0 and np.all(np.isfinite(nn[i]))
        line = f"{k} {'LN' if has_n else 'L'} " + " ".join(words)
        if has_n:
            line += " " + " ".join(f"N{letter}{v:+.7f}" for letter, v in zip("XYZ", nn[i]))
        if motion[r] == 0:
            line += " FMAX"
        elif feed[r] != prev_f:
            line += f" F{feed[r]:g}"
            prev_f = feed[r]
        out.append(line)
        k += 1
    out.append(f"{k} END PGM {name} MM")
    return "\n".join(out) + "\n"


def write_comp_table(errors: pa.Table, step_deg: float = 1.0, max_deg: float = 90.0) -> str:
    """Contact-angle compensation table (like a Heidenhain ``.3DTC`` file) as CSV.

    Radius deviation per contact angle: the predicted error turned into an equivalent tool-contour
    error (seed 002: 2 µm left at a 45° contact → a tool 2 µm smaller there), i.e. ``−err_um`` as mm,
    averaged per angle bin, linearly interpolated over empty bins (held at the ends).
    """
    q = col(errors, "contact_deg") if errors.num_rows else np.zeros(0)
    e = col(errors, "err_um") if errors.num_rows else np.zeros(0)
    ok = np.isfinite(q) & np.isfinite(e)
    q, e = q[ok], e[ok]
    angles = np.arange(0.0, max_deg + step_deg / 2, step_deg)
    b = np.clip(np.rint(q / step_deg).astype(np.int64), 0, angles.size - 1)
    s = np.bincount(b, e, angles.size)
    c = np.bincount(b, None, angles.size)
    have = c > 0
    dev = np.zeros(angles.size)
    if have.any():
        dev = np.interp(angles, angles[have], -(s[have] / c[have]))
    lines = ["# contact-angle compensation table (3DTC-like): radius deviation of the ball per contact angle",
             "# angle 0 = tip, 90 = equator; deviation in mm, negative = the tool cuts as if smaller",
             "angle_deg,radius_deviation_mm,n_passes"]
    lines += [f"{a:.1f},{d / 1000.0:+.5f},{int(cnt)}" for a, d, cnt in zip(angles, dev, c)]
    return "\n".join(lines) + "\n"
