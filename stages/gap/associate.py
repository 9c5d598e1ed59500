"""Association (DESIGN §8 step 1): every measured point → the pass that left the surface there.

The pass is the one whose ball centre segment is nearest to the point's ideal ball centre p + R·n.
Features per point: contact angle q, rotation angle φ, normal, machining time t, cut length so far
L, tool-tip position, distance to the nearest path corner with its angle and inside bisector,
feed, and the predicted error: the deepest tooth passage of its own and the neighbouring passes
(``predicted_at_points``). Points farther than ``off_part_mm`` from every tool envelope, or whose
normal disagrees with the envelope's by more than ``MAX_NORMAL_DEG``, are rejected and listed.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import pyarrow as pa

from stages import InputError
from stages.cutting import passages
from stages.cutting.surface_error import machining_error, read_profile
from stages.geometry.cutter import Cutter
from stages.geometry.paths import corner_features, nearest_pass, program_paths
from stages.tables import list_values

MAX_NORMAL_DEG = 30.0


def associate(meas: pa.Table, passes: pa.Table, errors: Optional[pa.Table], tool,
              off_part_mm: float = 0.05, deflection: Optional[pa.Table] = None) -> tuple[dict, list]:
    """Features of every measured point (dict of arrays) and the rejected points [(id, reason)].

    The predicted error at a point is the prediction model's (``stages.cutting.surface_error.machining_error``)
    evaluated at the point's own normal, contact and rotation angle with the deflection of its pass
    (``deflection`` table; the nearest predicted pass when its own was not predicted), plus the tool
    shape error at the point's q; where the tooth passages of neighbouring passes sweep the point
    (within ``stages.cutting.passages.PASSAGE_REVS`` revolutions of feed along the path: across a corner,
    beyond a short pass), the deepest of them (``predicted_at_points``). Without a deflection table
    the pass's ``errors`` row is used.

    Parameters
    ----------
    meas : pa.Table
        ``measurements`` table of N points (``point_id``, ``x_mm, y_mm, z_mm`` mm, ``nx, ny, nz``,
        ``err_um`` µm).
    passes : pa.Table
        The run's ``passes`` table.
    errors : pa.Table or None
        The run's ``errors`` table (used without a deflection table).
    tool : dict or Cutter
        The workflow's tool entry (a ball).
    off_part_mm : float
        Points farther than this from every tool envelope are rejected (mm).
    deflection : pa.Table, optional
        The run's ``deflection`` table: the prediction evaluated at each point.

    Returns
    -------
    F : dict
        Per kept point (n,), sorted by program, pass and position along it: ``point_id``,
        ``program_id``, ``pass_id``, ``x_mm, y_mm, z_mm``, ``nx, ny, nz``, ``q_deg``, ``phi_deg``,
        ``t_s`` (s), ``cut_len_mm`` and ``s_mm`` (mm of cut so far), ``tip_x_mm, tip_y_mm,
        tip_z_mm``, ``corner_dist_mm`` (inf without a corner), ``corner_deg``, ``bx, by, bz``,
        ``feed_mm_min``, ``feed_deg``, ``rpm``, ``u``, ``dist_mm``, ``normal_dev_deg``, and
        ``measured_um``, ``predicted_um``, ``pred_deflection_um``, ``pred_shape_um``,
        ``residual_um`` (µm); ``F["_geometry"]``: the paths, R, flutes and the passage geometry.
    rejected : list of (int, str)
        Rejected point ids with the reason.
    """
    cutter = Cutter.from_params(tool)
    if cutter.kind != "ball":
        raise InputError(f"tool.type {cutter.kind!r}: the gap diagnosis associates points for ball tools only")
    R = cutter.radius_mm
    pts = np.stack([meas.column(c).to_numpy() for c in ("x_mm", "y_mm", "z_mm")], 1)
    nrm = np.stack([meas.column(c).to_numpy() for c in ("nx", "ny", "nz")], 1)
    ids = meas.column("point_id").to_numpy()
    n = len(pts)
    paths = program_paths(passes, R, cutter.control_point)
    if not paths:
        raise InputError("gap: the run has no cutting passes")
    best = np.full(n, np.inf)
    which = np.zeros(n, np.int64)
    row = np.zeros(n, np.int64)
    uu = np.zeros(n)
    cstar = pts + R * nrm
    for k, p in enumerate(paths):
        if len(p.pass_id) == 0:
            continue
        r, u, d = nearest_pass(p, cstar)
        better = d < best
        best[better], which[better], row[better], uu[better] = d[better], k, r[better], u[better]
    F = {k: np.zeros(n) for k in ("u", "s_mm", "rpm", "t_s", "cut_len_mm", "tip_x_mm", "tip_y_mm", "tip_z_mm", "corner_dist_mm",
                                  "corner_deg", "bx", "by", "bz", "feed_mm_min", "feed_deg", "dist_mm", "normal_dev_deg",
                                  "predicted_um", "pred_deflection_um", "pred_shape_um")}
    prog = np.empty(n, dtype=object)
    pass_id = np.zeros(n, np.int64)
    for k, p in enumerate(paths):
        m = which == k
        if not m.any():
            continue
        r, u = row[m], uu[m]
        prog[m] = p.program_id
        pass_id[m] = p.pass_id[r]
        c = p.c0[r] + u[:, None] * (p.c1 - p.c0)[r]
        v = pts[m] - c
        dist = np.linalg.norm(v, axis=1)
        F["dist_mm"][m] = dist - R
        cosn = -np.einsum("ij,ij->i", v, nrm[m]) / np.maximum(dist, 1e-12)
        F["normal_dev_deg"][m] = np.degrees(np.arccos(np.clip(cosn, -1, 1)))
        F["u"][m] = u
        F["t_s"][m] = p.t0[r] + u * (p.t1[r] - p.t0[r])
        F["cut_len_mm"][m] = p.L0[r] + u * p.length[r]
        F["s_mm"][m] = p.s0[r] + u * p.length[r]
        F["rpm"][m] = p.rpm[r]
        F["tip_x_mm"][m], F["tip_y_mm"][m], F["tip_z_mm"][m] = c[:, 0], c[:, 1], c[:, 2] - R
        cd, ca, b = corner_features(p, r, u)
        F["corner_dist_mm"][m], F["corner_deg"][m] = cd, ca
        F["bx"][m], F["by"][m], F["bz"][m] = b[:, 0], b[:, 1], b[:, 2]
        F["feed_mm_min"][m] = p.feed[r]
        dd = p.c1[r] - p.c0[r]
        F["feed_deg"][m] = np.degrees(np.arctan2(dd[:, 1], dd[:, 0]))
        if deflection is None or not deflection.num_rows:
            pe, pdf, psh = _predicted(errors, p.program_id, p.pass_id, r)
            F["predicted_um"][m], F["pred_deflection_um"][m], F["pred_shape_um"][m] = pe, pdf, psh
    F["point_id"] = ids
    F["program_id"] = prog
    F["pass_id"] = pass_id
    F["x_mm"], F["y_mm"], F["z_mm"] = pts[:, 0], pts[:, 1], pts[:, 2]
    F["nx"], F["ny"], F["nz"] = nrm[:, 0], nrm[:, 1], nrm[:, 2]
    F["q_deg"] = np.degrees(np.arccos(np.clip(nrm[:, 2], -1, 1)))
    F["phi_deg"] = (np.degrees(np.arctan2(-nrm[:, 1], -nrm[:, 0])) - F["feed_deg"]) % 360.0
    F["measured_um"] = meas.column("err_um").to_numpy().astype(float)
    F["residual_um"] = F["measured_um"] - F["predicted_um"]
    off = np.abs(F["dist_mm"]) > off_part_mm
    badn = ~off & (F["normal_dev_deg"] > MAX_NORMAL_DEG)
    rejected = [(int(i), f"off the part: {abs(d) * 1e3:.0f} µm from every tool envelope (limit {off_part_mm * 1e3:.0f} µm)")
                for i, d in zip(ids[off], F["dist_mm"][off])]
    rejected += [(int(i), f"normal {a:.0f}° from the machined surface's (limit {MAX_NORMAL_DEG:.0f}°)")
                 for i, a in zip(ids[badn], F["normal_dev_deg"][badn])]
    keep = ~(off | badn)
    if keep.sum() < max(10, 0.5 * n):
        raise InputError(f"gap: {n - keep.sum()} of {n} measured points are not on the machined surface "
                         f"(first: point {rejected[0][0]}: {rejected[0][1]}); wrong file, frame or units?")
    order = np.lexsort((F["u"][keep], F["pass_id"][keep], F["program_id"][keep].astype(str)))
    F = {k: v[keep][order] for k, v in F.items()}
    # the paths themselves, for the servo lag's tooth-passage envelope (``servo_signature``)
    F["_geometry"] = {"paths": {p.program_id: p for p in paths}, "R": R, "flutes": cutter.flutes, "cache": []}
    if deflection is not None and deflection.num_rows:
        # the neighbouring passes' tooth passages that sweep each point (``passage_geometry``)
        F["_geometry"]["passages"] = passage_geometry(F, passes, cutter)
        pe, pdf, psh = predicted_at_points(F, lambda prog: deflection, cutter)
        F["predicted_um"], F["pred_deflection_um"], F["pred_shape_um"] = pe, pdf, psh
        F["residual_um"] = F["measured_um"] - F["predicted_um"]
    return F, rejected


# ---------------------------------------------------------------- the deepest tooth passage at a point


def passage_geometry(F: dict, passes: pa.Table, tool) -> dict:
    """The tooth passages of the neighbouring passes that sweep each measured point.

    A surface point is cut by discrete tooth passages within about a revolution of the tool passing
    it; near the ends of passes those passages belong to the neighbouring passes of the path
    (``stages.cutting.passages``: across a corner, or beyond a pass shorter than the feed per
    revolution), each with its own deflection. Per program, the moves of the path in execution
    order (tips; the ``control_point: center`` programs lowered by the corner radius, as the errors
    stage does), and per (point, move) pair within ``stages.cutting.passages.PASSAGE_REVS`` revolutions of
    feed of the point along the path: the move's nominal stand-off from the point (µm along the
    tool normal; the point first moved onto its own pass's nominal envelope, so that pass's own
    stand-off is 0), the contact angle q, height above the tip and position angle φ (from that
    move's feed direction) of the tool point nearest it. Depends on the geometry only: computed
    once per set of points, reused by every prediction re-run (``predicted_at_points``).

    Parameters
    ----------
    F : dict
        Features of n points (``associate``).
    passes : pa.Table
        The run's ``passes`` table.
    tool : dict or Cutter
        The tool.

    Returns
    -------
    dict
        {program_id: dict(pass_id (k,), feed_move (k,) bool, row (m,), move (m,), standoff_um (m,)
        µm, q (m,) deg, height (m,) mm, phi (m,) deg)} over the m (point, move) pairs; ``row``
        indexes F, ``move`` the program's moves (``pass_id[move]``).
    """
    cutter = Cutter.from_params(tool)
    pid_col = np.asarray(passes.column("program_id").to_pylist(), dtype=object)
    pts = np.stack([F["x_mm"], F["y_mm"], F["z_mm"]], 1)
    out = {}
    for prog in dict.fromkeys(F["program_id"].tolist()):
        sub = passes.filter(pa.array(pid_col == prog))
        col = lambda c: sub.column(c).to_numpy(zero_copy_only=False).astype(float)  # noqa: E731
        order = np.argsort(sub.column("pass_id").to_numpy(), kind="stable")      # execution order
        pid = sub.column("pass_id").to_numpy().astype(np.int64)[order]
        tip0 = np.stack([col("x0_mm"), col("y0_mm"), col("z0_mm")], 1)[order]
        tip1 = np.stack([col("x1_mm"), col("y1_mm"), col("z1_mm")], 1)[order]
        tip0[:, 2] -= cutter.control_offset_mm        # centre programs: lowered to the tip
        tip1[:, 2] -= cutter.control_offset_mm
        feed_move = (sub.column("motion").to_numpy(zero_copy_only=False)[order] != 0) \
            & np.all(np.isfinite(tip0), 1) & np.all(np.isfinite(tip1), 1)
        tip0, tip1 = np.nan_to_num(tip0), np.nan_to_num(tip1)
        f_rev = (col("feed_mm_min") / np.maximum(col("spindle_rpm"), 1e-9))[order]
        s0, chain = passages.path_chains(tip0, tip1, feed_move)
        length = np.linalg.norm(tip1 - tip0, axis=1) * feed_move
        m = np.flatnonzero(F["program_id"] == prog)
        owner = np.clip(np.searchsorted(pid, F["pass_id"][m]), 0, len(pid) - 1)
        ok = (pid[owner] == F["pass_id"][m]) & feed_move[owner]
        geo = {"pass_id": pid, "feed_move": feed_move, "row": np.zeros(0, np.int64), "move": np.zeros(0, np.int64)}
        geo.update({k: np.zeros(0) for k in ("standoff_um", "q", "height", "phi")})
        out[prog] = geo
        if not ok.any():
            continue
        m, owner = m[ok], owner[ok]
        d_own, t_own, _, _, n_own = passages.sweep_distance(pts[m], tip0[owner], tip1[owner], cutter)
        s_c = s0[owner] + t_own * length[owner]
        c_on = pts[m] - d_own[:, None] * n_own
        r, j, ta, tb = passages.passage_pairs(owner, s_c, passages.PASSAGE_REVS * f_rev[owner], s0, length, chain, feed_move)
        if r.size == 0:
            continue
        seg = tip1[j] - tip0[j]
        a, b = tip0[j] + ta[:, None] * seg, tip0[j] + tb[:, None] * seg
        dist, t, q, height, _ = passages.sweep_distance(c_on[r], a, b, cutter)
        # a move reaches the point only from inside its extent: the deflection cannot change at a
        # vertex (measured on the gap reference part: counting pass ends, 0.122 → 0.139 µm RMS)
        inside = passages.reaches_inside(t, ta, tb)
        r, j, a, b, t = r[inside], j[inside], a[inside], b[inside], t[inside]
        dist, q, height, seg = dist[inside], q[inside], height[inside], seg[inside]
        rel = c_on[r] - (a + t[:, None] * (b - a))
        phi = np.degrees(np.arctan2(rel[:, 1], rel[:, 0]) - np.arctan2(seg[:, 1], seg[:, 0]))
        geo.update(row=m[r], move=j, standoff_um=dist * 1e3, q=q, height=height, phi=phi)
    return out


def predicted_at_points(F: dict, deflection_of, tool, rows: Optional[np.ndarray] = None,
                        runout_part: bool = False):
    """The prediction model at the measured points ``rows`` (bool mask of F; all when None).

    Per point the error its own pass leaves (``_predicted_at_points``: the deflection of its pass at
    the point's φ, projected on its normal, + runout and shape at its q), then, where the neighbouring
    passes' tooth passages sweep it (``passage_geometry``), the deepest of them: the minimum over
    them and its own pass of

        s_j + e_j          (µm along the point's normal)

    with s_j the nominal stand-off of pass j's tool from the point and e_j its error there
    (``stages.cutting.surface_error.machining_error`` with pass j's deflection at the contact of its tool, the
    errors stage's ``_deepest_passage`` at a measured point). Only passes with a deflection row
    take part. ``deflection_of(program_id)`` gives the deflection table to use.

    Returns (error, deflection + runout part, shape part) of the passage that leaves each point; the
    stand-off is in the error only (it does not scale with the force model). With ``runout_part``
    the first item is that passage's runout part alone.

    Parameters
    ----------
    F : dict
        Features of n points (``associate``), with their passage geometry.
    deflection_of : callable
        ``deflection_of(program_id)`` → the ``deflection`` table to use for that program.
    tool : dict or Cutter
        The tool (its runout and profile table enter the error).
    rows : (n,) bool ndarray, optional
        The points to predict (all when None).
    runout_part : bool
        Return the runout part alone as the first item.

    Returns
    -------
    error, deflection_part, shape_part : (m,) ndarray
        µm along each normal at the m selected points.
    """
    cutter = Cutter.from_params(tool)
    rows = np.ones(len(F["q_deg"]), bool) if rows is None else np.asarray(rows, bool)
    idx = np.flatnonzero(rows)
    pos = np.full(len(rows), -1, np.int64)
    pos[idx] = np.arange(len(idx))
    out = [np.zeros(len(idx)) for _ in range(3)]
    nrm = np.stack([F["nx"], F["ny"], F["nz"]], 1)
    geos = F.get("_geometry", {}).get("passages", {})
    profile = read_profile(cutter.profile) if cutter.profile else None
    progs = F["program_id"][idx]
    for prog in dict.fromkeys(progs.tolist()):
        k = idx[progs == prog]
        d = deflection_of(prog)
        e, dfl, sh = _predicted_at_points(d, prog, F["pass_id"][k], F["q_deg"][k], F["phi_deg"][k], nrm[k], cutter,
                                          profile, runout_part, full=True)
        geo = geos.get(prog)
        if geo is not None and geo["row"].size and d is not None and d.num_rows:
            sel = rows[geo["row"]]
            r, j = pos[geo["row"][sel]], geo["move"][sel]
            pid = np.asarray(d.column("program_id").to_pylist(), dtype=object)
            dm = np.flatnonzero(pid == prog)
            d_pass = d.column("pass_id").to_numpy().astype(np.int64)[dm]
            at = np.searchsorted(geo["pass_id"], d_pass)
            at_ok = at < len(geo["pass_id"])
            at_ok[at_ok] = geo["pass_id"][at[at_ok]] == d_pass[at_ok]
            n_rot = list_values(d.column("dx_um"), "deflection.dx_um").shape[1]
            dx_all, dy_all = np.zeros((len(geo["pass_id"]), n_rot)), np.zeros((len(geo["pass_id"]), n_rot))
            has = np.zeros(len(geo["pass_id"]), bool)
            dx_all[at[at_ok]] = list_values(d.column("dx_um"), "deflection.dx_um")[dm[at_ok]]
            dy_all[at[at_ok]] = list_values(d.column("dy_um"), "deflection.dy_um")[dm[at_ok]]
            has[at[at_ok]] = True
            keep = has[j]
            r, j = r[keep], j[keep]
            g = {kk: geo[kk][sel][keep] for kk in ("standoff_um", "q", "height", "phi")}
            if r.size:
                ej = machining_error(dx_all[j], dy_all[j], g["phi"], g["q"], nrm[idx[r]], g["height"], cutter, profile)
                total = g["standoff_um"] + ej["err_um"]
                total = np.where(np.isnan(total), np.inf, total)
                # the deepest passage per point (pairs sorted by total, the first of each point)
                o = np.lexsort((total, r))
                first = np.concatenate([[True], r[o][1:] != r[o][:-1]])
                best = o[first]
                own = e["total"]
                li = np.searchsorted(k, idx[r[best]])           # the point's place among this program's
                win = total[best] < own[li]
                li, w = li[win], best[win]
                e["total"][li] = total[w]
                e["runout"][li] = ej["err_runout_um"][w]
                dfl[li] = ej["err_deflection_um"][w] + ej["err_runout_um"][w]
                sh[li] = ej["err_shape_um"][w]
        where = pos[k]
        out[0][where] = np.nan_to_num(e["runout"] if runout_part else e["total"])
        out[1][where], out[2][where] = np.nan_to_num(dfl), np.nan_to_num(sh)
    return out[0], out[1], out[2]


def _predicted_at_points(deflection, program_id, pass_ids, q, phi, normal, cutter: Cutter, profile,
                         runout_part: bool = False, full: bool = False):
    """Prediction model at each point from its own pass alone: the deflection of its pass read at the
    point's φ, projected on its n (``predicted_at_points`` adds the neighbouring passes' passages).

    Returns (error, deflection + runout part, shape part); with ``runout_part`` the first item is
    the runout part alone (−ρ·sin q of the flute that leaves the surface). With ``full``: ({"total":
    error, "runout": runout part}, deflection + runout part, shape part), NaN kept. ``profile``: the
    cutter's profile table, read once by the caller."""
    z = np.zeros(len(q))
    pid = np.asarray(deflection.column("program_id").to_pylist(), dtype=object) if deflection is not None else []
    m = np.flatnonzero(pid == program_id) if len(pid) else np.zeros(0, np.int64)
    if not m.size:
        return ({"total": z, "runout": z.copy()}, z.copy(), z.copy()) if full else (z, z.copy(), z.copy())
    d_pass = deflection.column("pass_id").to_numpy()[m]
    order = np.argsort(d_pass)
    d_pass = d_pass[order]
    i = np.clip(np.searchsorted(d_pass, pass_ids), 0, len(d_pass) - 1)
    j = np.clip(i - 1, 0, len(d_pass) - 1)
    pick = m[order[np.where(np.abs(d_pass[j] - pass_ids) < np.abs(d_pass[i] - pass_ids), j, i)]]
    dx = list_values(deflection.column("dx_um"), "deflection.dx_um")[pick]
    dy = list_values(deflection.column("dy_um"), "deflection.dy_um")[pick]
    res = machining_error(dx, dy, phi, q, normal, cutter.corner_height(q), cutter, profile)
    if full:
        return ({"total": res["err_um"], "runout": res["err_runout_um"]},
                res["err_deflection_um"] + res["err_runout_um"], res["err_shape_um"])
    return (np.nan_to_num(res["err_runout_um" if runout_part else "err_um"]),
            np.nan_to_num(res["err_deflection_um"] + res["err_runout_um"]),
            np.nan_to_num(res["err_shape_um"]))


def _predicted(errors, program_id, pass_ids, rows):
    """Prediction of the pass at each row; passes without one take the nearest predicted pass."""
    z = np.zeros(len(rows))
    if errors is None or errors.num_rows == 0:
        return z, z.copy(), z.copy()
    pid = np.asarray(errors.column("program_id").to_pylist(), dtype=object)
    m = pid == program_id
    if not m.any():
        return z, z.copy(), z.copy()
    e_pass = errors.column("pass_id").to_numpy()[m]
    vals = [errors.column(c).to_numpy()[m].astype(float) for c in ("err_um", "err_deflection_um", "err_shape_um")]
    order = np.argsort(e_pass)
    e_pass = e_pass[order]
    vals = [v[order] for v in vals]
    want = pass_ids[rows]
    i = np.clip(np.searchsorted(e_pass, want), 0, len(e_pass) - 1)
    j = np.clip(i - 1, 0, len(e_pass) - 1)
    pick = np.where(np.abs(e_pass[j] - want) < np.abs(e_pass[i] - want), j, i)
    out = [np.nan_to_num(v[pick]) for v in vals]
    return out[0], out[1], out[2]
