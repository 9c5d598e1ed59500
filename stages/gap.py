"""Sim-to-real gap diagnosis (DESIGN §8, issue 7): where, which effect, how far.

1. ``associate``: every measured point → the pass whose ball centre segment is nearest to the
   point's ideal ball centre p + R·n (the pass that left the surface there), with features: contact
   angle q, rotation angle φ, normal, machining time t, cut length so far L, tool-tip position,
   distance to the nearest path corner with its angle and inside bisector, feed, predicted error
   (the deepest tooth passage of its own and the neighbouring passes: ``predicted_at_points``).
   Points farther than ``off_part_mm`` from every tool envelope, or whose normal disagrees with the
   envelope's by more than ``MAX_NORMAL_DEG``, are rejected and listed.
2. ``where``: residual r = measured − predicted; spatial blocks whose mean residual differs from
   zero by more than 3 standard errors and by more than σ/2, with bounding box, pass range,
   contact-angle band, time window, mean and 95 % interval (before, and after the effects).
3. ``diagnose``: the effect catalogue below, each a physical parametric model of r, fitted on
   training blocks and scored on held-out blocks (K-fold over spatial blocks). An effect is kept when
   its held-out sum of squares improvement, in units of the noise variance σ² (σ from differences of
   neighbouring points along the path, robust), exceeds the χ² quantile at ``ALPHA`` for its number of
   parameters, and where it acts the RMS it explains beyond the effects already chosen (or, when its
   signature is nearly collinear with theirs, its own fitted contribution) reaches half of hypot(σ,
   model floor) (the floor is 0 unless a reference part measured it). Greedy (at most
   ``MAX_EFFECTS``): the best significant effect is added — a simpler one when the richer one is
   not better by the χ² margin of its extra parameters — with the nonlinear parameters of those already chosen re-fitted; then a swap pass
   and a backward check (every kept effect must still pass both tests given the others), repeated
   while the check drops an effect (``settle``). An effect
   whose addition takes a fit beyond a real machine's limits (``LIMITS``: two effects cancelling
   each other) is not chosen, and listed (``beyond_limits``). The order
   of size is the RMS of each effect's fitted contribution. What it could not see: for every effect
   not chosen, ``detection_limits`` — the largest RMS of it that the two tests would not claim next
   to the chosen effects (large when its signature is nearly collinear with theirs on these points,
   e.g. tool wear ∝ L and a thermal drift along z on a raster whose cut length grows with time),
   and ``ambiguous_with``: per chosen effect, those it explains to a canonical correlation ≥
   ``AMBIGUOUS_RHO``. The reported parameters are the chosen effects fitted jointly on all points
   to the least-squares optimum (``final_fit``), each with a standard error from the model
   linearised there (``param_uncertainty``: probe noise only, not a systematic model error).
4. ``how far``: held-out predictions (each point predicted by the fit without its block, nonlinear
   parameters re-fitted: ``fold_fits``) with the chosen effects added; here as the effects' terms.
   The caller (``pipeline.gap.how_far``) re-runs the prediction itself for the model effects
   (force scale, runout, tool profile table) and adds the offset effects' terms: RMS, P95, max
   before and after, and the same on the points where the effects act.

Catalogue (signature on r, µm; features as in ``associate``):

- ``runout``: −e·sin q (e ≥ 0, µm); when the caller gives the prediction's own response to runout
  (``F["runout_resp_um"]``: forces → deflection → errors re-run with tool.runout_um + e on a grid of e),
  that response (it also holds the changed chip of each flute), interpolated at e
- ``tool_contour``: a·exp(−½((q − q0)/w)²) (a µm, q0 deg, w deg; + = tool smaller = material left)
- ``tool_wear``: rate·L (µm per m of cut, ≥ 0)
- ``thermal_drift``: n·A·(1 − exp(−t/τ)) (A µm per axis, τ s)
- ``force_scale``: (s − 1)·predicted deflection error (s ratio)
- ``servo_corner``: the tool lags by a·sin(θ/2)/sin 45°·exp(−d/λ) towards the inside of the turn (a µm,
  λ mm; b inside bisector, θ corner angle, d path distance to the corner). Chosen with the smooth
  form a·(b·n)·sin(θ/2)/sin 45°·exp(−d/λ) (the lag at the point's own path position); its parameters
  are then fitted with what the surface shows (``servo_signature``): the envelope of the tooth
  passages (one per feed per tooth, each with its own lag) around each point near a corner,
  averaged over the unknown spindle phase. The passage whose lag cuts deeper wins, so the smooth
  form read a too small for a lag that leaves material and too large for one that over-cuts
  (−30 µm, λ 0.3 mm: −34.5 µm, λ 0.29 mm on the sample plan, noise-free).
- ``machine_geometry``: n·(sx·x + exy·y + exz·z, sy·y + eyz·z, sz·z) at the tool tip (µm/mm)
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
import pyarrow as pa

from stages import InputError
from stages.geometry.paths import corner_features, nearest_pass, program_paths

ALPHA = 1e-3          # false-claim rate of the per-effect test (a priori, not tuned)
MAX_EFFECTS = 3
K_FOLDS = 5
MAX_NORMAL_DEG = 30.0
EFFECT_NAMES = ("runout", "tool_contour", "tool_wear", "thermal_drift", "force_scale", "servo_corner",
                "machine_geometry")


# ============================================================================ association
def associate(meas: pa.Table, passes: pa.Table, errors: Optional[pa.Table], tool: dict,
              off_part_mm: float = 0.05, deflection: Optional[pa.Table] = None) -> tuple[dict, list]:
    """Features of every measured point (dict of arrays) and the rejected points [(id, reason)].

    The predicted error at a point is the prediction model's (``stages.cutting.surface_error.machining_error``)
    evaluated at the point's own normal, contact and rotation angle with the deflection of its pass
    (``deflection`` table; the nearest predicted pass when its own was not predicted), plus the tool
    shape error at the point's q; where the tooth passages of neighbouring passes sweep the point
    (within ``stages.cutting.passages.PASSAGE_REVS`` revolutions of feed along the path: across a corner,
    beyond a short pass), the deepest of them (``predicted_at_points``). Without a deflection table
    the pass's ``errors`` row is used.
    """
    if tool["type"] != "ball":
        raise InputError(f"tool.type {tool['type']!r}: the gap diagnosis associates points for ball tools only")
    R = float(tool["diameter_mm"]) / 2
    pts = np.stack([meas.column(c).to_numpy() for c in ("x_mm", "y_mm", "z_mm")], 1)
    nrm = np.stack([meas.column(c).to_numpy() for c in ("nx", "ny", "nz")], 1)
    ids = meas.column("point_id").to_numpy()
    n = len(pts)
    paths = program_paths(passes, R, tool.get("control_point", "tip"))
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
    F["_geometry"] = {"paths": {p.program_id: p for p in paths}, "R": R, "flutes": int(tool.get("flutes") or 2),
                      "cache": []}
    if deflection is not None and deflection.num_rows:
        # the neighbouring passes' tooth passages that sweep each point (``passage_geometry``)
        F["_geometry"]["passages"] = passage_geometry(F, passes, tool)
        pe, pdf, psh = predicted_at_points(F, lambda prog: deflection, tool)
        F["predicted_um"], F["pred_deflection_um"], F["pred_shape_um"] = pe, pdf, psh
        F["residual_um"] = F["measured_um"] - F["predicted_um"]
    return F, rejected


# ---------------------------------------------------------------- the deepest tooth passage at a point


def passage_geometry(F: dict, passes: pa.Table, tool: dict) -> dict:
    """The tooth passages of the neighbouring passes that sweep each measured point.

    A surface point is cut by discrete tooth passages within about a revolution of the tool passing
    it; near the ends of passes those passages belong to the neighbouring passes of the path
    (``stages.passage_envelope``: across a corner, or beyond a pass shorter than the feed per
    revolution), each with its own deflection. Per program, the moves of the path in execution
    order (tips; the ``control_point: center`` programs lowered by the corner radius, as the errors
    stage does), and per (point, move) pair within ``stages.cutting.passages.PASSAGE_REVS`` revolutions of
    feed of the point along the path: the move's nominal stand-off from the point (µm along the
    tool normal; the point first moved onto its own pass's nominal envelope, so that pass's own
    stand-off is 0), the contact angle q, height above the tip and position angle φ (from that
    move's feed direction) of the tool point nearest it. Depends on the geometry only: computed
    once per set of points, reused by every prediction re-run (``predicted_at_points``).

    Returns {program_id: dict(pass_id, feed_move, row, move, standoff_um, q, height, phi)}; ``row``
    indexes F, ``move`` the program's moves (``pass_id[move]``).
    """
    from stages.cutting import passages as pe
    from stages.geometry.cutter import Cutter
    cutter = Cutter.from_params(tool)
    R, rc, stick = cutter.radius_mm, cutter.corner_mm, cutter.stickout_mm
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
        if tool.get("control_point") == "center":
            tip0[:, 2] -= rc
            tip1[:, 2] -= rc
        feed_move = (sub.column("motion").to_numpy(zero_copy_only=False)[order] != 0) \
            & np.all(np.isfinite(tip0), 1) & np.all(np.isfinite(tip1), 1)
        tip0, tip1 = np.nan_to_num(tip0), np.nan_to_num(tip1)
        f_rev = (col("feed_mm_min") / np.maximum(col("spindle_rpm"), 1e-9))[order]
        s0, chain = pe.path_chains(tip0, tip1, feed_move)
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
        d_own, t_own, _, _, n_own = pe.sweep_distance(pts[m], tip0[owner], tip1[owner], R, rc, stick)
        s_c = s0[owner] + t_own * length[owner]
        c_on = pts[m] - d_own[:, None] * n_own
        r, j, ta, tb = pe.passage_pairs(owner, s_c, pe.PASSAGE_REVS * f_rev[owner], s0, length, chain, feed_move)
        if r.size == 0:
            continue
        seg = tip1[j] - tip0[j]
        a, b = tip0[j] + ta[:, None] * seg, tip0[j] + tb[:, None] * seg
        dist, t, q, height, _ = pe.sweep_distance(c_on[r], a, b, R, rc, stick)
        # a move reaches the point only from inside its extent: the deflection cannot change at a
        # vertex (measured on the gap reference part: counting pass ends, 0.122 → 0.139 µm RMS)
        inside = pe.reaches_inside(t, ta, tb)
        r, j, a, b, t = r[inside], j[inside], a[inside], b[inside], t[inside]
        dist, q, height, seg = dist[inside], q[inside], height[inside], seg[inside]
        rel = c_on[r] - (a + t[:, None] * (b - a))
        phi = np.degrees(np.arctan2(rel[:, 1], rel[:, 0]) - np.arctan2(seg[:, 1], seg[:, 0]))
        geo.update(row=m[r], move=j, standoff_um=dist * 1e3, q=q, height=height, phi=phi)
    return out


def predicted_at_points(F: dict, deflection_of, tool: dict, rows: Optional[np.ndarray] = None,
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
    """
    from stages.cutting.surface_error import machining_error, read_profile
    from stages.geometry.cutter import Cutter
    from stages.tables import list_values
    rows = np.ones(len(F["q_deg"]), bool) if rows is None else np.asarray(rows, bool)
    idx = np.flatnonzero(rows)
    pos = np.full(len(rows), -1, np.int64)
    pos[idx] = np.arange(len(idx))
    out = [np.zeros(len(idx)) for _ in range(3)]
    nrm = np.stack([F["nx"], F["ny"], F["nz"]], 1)
    geos = F.get("_geometry", {}).get("passages", {})
    profile = read_profile(tool["profile"]) if tool.get("profile") else None
    progs = F["program_id"][idx]
    for prog in dict.fromkeys(progs.tolist()):
        k = idx[progs == prog]
        d = deflection_of(prog)
        e, dfl, sh = _predicted_at_points(d, prog, F["pass_id"][k], F["q_deg"][k], F["phi_deg"][k], nrm[k], tool,
                                          runout_part, full=True)
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
                ej = machining_error(dx_all[j], dy_all[j], g["phi"], g["q"], nrm[idx[r]], g["height"], Cutter.from_params(tool), profile)
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


def _predicted_at_points(deflection, program_id, pass_ids, q, phi, normal, tool, runout_part: bool = False,
                         full: bool = False):
    """Prediction model at each point from its own pass alone: the deflection of its pass read at the
    point's φ, projected on its n (``predicted_at_points`` adds the neighbouring passes' passages).

    Returns (error, deflection + runout part, shape part); with ``runout_part`` the first item is
    the runout part alone (−ρ·sin q of the flute that leaves the surface). With ``full``: ({"total":
    error, "runout": runout part}, deflection + runout part, shape part), NaN kept."""
    from stages.cutting.surface_error import machining_error, read_profile
    from stages.geometry.cutter import Cutter
    from stages.tables import list_values
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
    R = float(tool["diameter_mm"]) / 2
    z_c = R * (1 - np.cos(np.radians(q)))
    profile = read_profile(tool["profile"]) if tool.get("profile") else None
    res = machining_error(dx, dy, phi, q, normal, z_c, Cutter.from_params(tool), profile)
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


# ============================================================================ effects
@dataclass
class Effect:
    name: str
    grid: list                     # nonlinear parameter values (tuples), [()] when none
    n_lin: int

    def basis(self, F, th) -> np.ndarray:          # (n, n_lin)
        return _BASIS[self.name](F, th)

    def params(self, beta, th) -> dict:
        return _PARAMS[self.name](beta, th)

    @property
    def n_params(self):
        return self.n_lin + (len(self.grid[0]) if self.grid and self.grid[0] else 0)


def _q(F):
    return np.radians(F["q_deg"])


def runout_response(F, e_um: float) -> np.ndarray:
    """The prediction's own change per µm of runout at ``e_um`` (tool.runout_um + e re-predicted
    through forces → deflection → errors), linear between the computed values
    ``F["runout_grid_um"]`` (0 → no change): (n, 2) = the flute's −ρ·sin q and the rest (the
    deflection changed by the flutes' unequal chips). (n, 1) = −sin q when none was computed."""
    if "runout_resp_um" not in F:
        return -np.sin(_q(F))[:, None]
    grid = np.concatenate([[0.0], F["runout_grid_um"]])
    resp = np.concatenate([np.zeros((len(F["q_deg"]), 1, 2)), F["runout_resp_um"]], axis=1)
    e = float(np.clip(e_um, grid[1], grid[-1]))
    i = int(np.clip(np.searchsorted(grid, e) - 1, 0, len(grid) - 2))
    w = (e - grid[i]) / (grid[i + 1] - grid[i])
    return ((1 - w) * resp[:, i] + w * resp[:, i + 1]) / e


# ------------------------------------------------------------------ servo lag: tooth-passage envelope
ENV_PHASES = 8      # spindle phases averaged: the diagnosis does not know the phase a point was cut at
ENV_TOL_UM = 1e-3   # the envelope is computed where it may differ from the smooth form by more than this


def servo_smooth(F, lam_mm: float) -> np.ndarray:
    """(b·n)·sin(θ/2)/sin 45°·exp(−d/λ): the lag of the tool at the point's own path position, per µm of a."""
    return ((F["bx"] * F["nx"] + F["by"] * F["ny"] + F["bz"] * F["nz"])
            * np.sin(np.radians(F["corner_deg"]) / 2) / math.sin(math.pi / 4)
            * np.exp(-np.where(np.isfinite(F["corner_dist_mm"]), F["corner_dist_mm"], 1e9) / lam_mm))


def _env_geometry(F, a_max_um: float, lam_max_mm: float) -> dict:
    """The tooth passages around every point near a corner, for lags up to ``a_max_um`` and decay
    lengths up to ``lam_max_mm`` (cached on ``F``).

    The surface at a point is left by discrete tooth passages, one per feed per tooth fz = feed /
    (rpm·flutes) along the path, each a ball (radius R) centred on the path at its own position plus
    the servo lag there. Which passage cuts deepest at a point depends on the spindle phase, which
    the diagnosis does not know: ``ENV_PHASES`` phases, evenly spread over one fz, are averaged. A
    passage farther than W along the path cannot cut deeper than the nearest one (its ball lies
    δ²/2R higher at the point, more than any lag difference 2·a_max plus the nearest passage's own
    feed mark; its lag along the path moves it by at most a_max). Beyond ``d_near`` from a corner
    the lag changes so slowly along the path that the deepest passage gains less than
    ``ENV_TOL_UM`` over the smooth form (≈ R·(ℓ/λ)²/2 for a lag ℓ): the smooth form is used there.

    Per near point, phase and passage (offset δ): the ray entry into the nominal ball, A0 − √(R² − P0)
    (A0 = (c − p)·n, P0 = |(c − p)⊥n|²), and the lag's unit vector bm = b·sin(θ/2)/sin 45° as
    B = bm·n, Q = (c − p)⊥·bm⊥, S = |bm⊥|², with the passage's corner distance: a lag g = a·e^(−d/λ)
    moves the entry to A0 + g·B − √(R² − P0 − 2gQ − g²S).
    """
    geo = F["_geometry"]
    for g in geo["cache"]:
        if g["a_max"] >= a_max_um and g["lam_max"] >= lam_max_mm:
            return g
    from stages.geometry.paths import corner_features, path_point
    R, Z = float(geo["R"]), int(geo["flutes"])
    amax = abs(a_max_um) * 1e-3 * math.sqrt(2)                   # mm; sin(θ/2)/sin 45° ≤ √2
    fz = F["feed_mm_min"] / np.maximum(F["rpm"] * Z, 1e-9)
    W = np.sqrt(2 * R * 2 * amax + (fz / 2) ** 2) + amax
    lag_tol = lam_max_mm * math.sqrt(2 * ENV_TOL_UM * 1e-3 / R)
    d_near = W + lam_max_mm * math.log(max(amax / lag_tol, 1.0))
    cd = F["corner_dist_mm"]
    idx = np.flatnonzero(np.isfinite(cd) & (cd < d_near) & (fz > 0))
    out = {"a_max": float(abs(a_max_um)), "lam_max": float(lam_max_mm), "idx": idx}
    geo["cache"].append(out)
    if not idx.size:
        return out
    K = int(min(np.ceil((W[idx] / fz[idx]).max()), 400))
    off = ((np.arange(ENV_PHASES) + 0.5) / ENV_PHASES - 0.5)[:, None] + np.arange(-K, K + 1)[None, :]
    delta = off[None] * fz[idx, None, None]                      # (m, phases, passages) mm
    shape = delta.shape
    arr = {k: np.full(shape, np.inf if k == "dist" else 0.0) for k in ("A0", "P0", "B", "Q", "S", "dist")}
    valid = np.abs(delta) <= (W[idx] + fz[idx])[:, None, None]
    pts = np.stack([F["x_mm"], F["y_mm"], F["z_mm"]], 1)[idx]
    nrm = np.stack([F["nx"], F["ny"], F["nz"]], 1)[idx]
    prog = F["program_id"][idx]
    for pid, path in geo["paths"].items():
        m = np.flatnonzero(prog == pid)
        if not m.size or len(path.pass_id) == 0:
            continue
        s = (F["s_mm"][idx[m]][:, None, None] + delta[m]).ravel()
        c, row = path_point(path, s)
        dist, ang, b = corner_features(path, row, (s - path.s0[row]) / path.length[row])
        sh = (len(m),) + shape[1:]
        cp = c.reshape(sh + (3,)) - pts[m][:, None, None, :]
        n = nrm[m][:, None, None, :]
        bm = (b * (np.sin(np.radians(ang) / 2) / math.sin(math.pi / 4))[:, None]).reshape(sh + (3,))
        A0 = np.sum(cp * n, -1)
        B = np.sum(bm * n, -1)
        arr["A0"][m], arr["B"][m] = A0, B
        arr["P0"][m] = np.sum(cp * cp, -1) - A0 * A0
        arr["Q"][m] = np.sum(cp * bm, -1) - A0 * B
        arr["S"][m] = np.sum(bm * bm, -1) - B * B
        arr["dist"][m] = dist.reshape(sh)
    inner = R * R - arr["P0"]
    e0 = np.where(valid & (inner >= 0), arr["A0"] - np.sqrt(np.maximum(inner, 0.0)), np.inf)
    out.update(arr, valid=valid, e0=e0.min(axis=2), R=R)
    return out


def servo_signature(F, a_um: float, lam_mm: float, geometry: Optional[dict] = None) -> np.ndarray:
    """The surface a servo lag (a µm, decay λ mm) leaves (µm along n): the envelope of the tooth
    passages around each point near a corner, averaged over the spindle phase (``_env_geometry``),
    and a·``servo_smooth`` where the two agree within ``ENV_TOL_UM``. Without the path geometry
    (features built elsewhere) the smooth form. ``geometry``: an ``_env_geometry`` result that
    covers (a, λ), used instead of the first adequate one of the cache (finite differences must
    read every (a, λ) with the same passages)."""
    sig = a_um * servo_smooth(F, lam_mm)
    if "_geometry" not in F or a_um == 0:
        return sig
    g = geometry if geometry is not None else _env_geometry(F, abs(a_um), lam_mm)
    if not g["idx"].size:
        return sig
    R = g["R"]
    gl = a_um * 1e-3 * np.exp(-g["dist"] / lam_mm)
    inner = R * R - (g["P0"] + 2 * gl * g["Q"] + gl * gl * g["S"])
    e = np.where(g["valid"] & (inner >= 0), g["A0"] + gl * g["B"] - np.sqrt(np.maximum(inner, 0.0)), np.inf)
    d = e.min(axis=2) - g["e0"]
    ok = np.isfinite(d)
    env = np.where(ok, d, 0.0).sum(axis=1) / np.maximum(ok.sum(axis=1), 1) * 1e3
    sig[g["idx"]] = np.where(ok.any(axis=1), env, sig[g["idx"]])
    return sig


def refine_servo(F, y, mask, chosen: list, beta: np.ndarray):
    """The servo lag of ``chosen`` re-fitted with the tooth-passage envelope (``servo_signature``).

    The effects are chosen with the smooth form; its fit (a_s, λ_s) starts a Nelder–Mead search of
    (a, λ) within [a_s/2, 2·a_s] × [λ_s/2, 2·λ_s], the other effects' linear parameters solved at
    each step. Returns (chosen with the servo entry's value (λ, a), betas in the same layout)."""
    names = [e.name for e, _ in chosen]
    if "servo_corner" not in names or "_geometry" not in F:
        return chosen, beta
    from scipy.optimize import minimize
    i = names.index("servo_corner")
    k0 = sum(e.n_lin for e, _ in chosen[:i])
    e_s, th = chosen[i]
    lam_s = float(th[0])
    a_s = float(beta[k0])                       # µm of lag in both forms of the basis
    if not np.isfinite(a_s) or abs(a_s) < 1e-6:
        return chosen, beta
    _env_geometry(F, 2 * abs(a_s), 2 * lam_s)
    others = [(e, t) for j, (e, t) in enumerate(chosen) if j != i]
    Xo = np.hstack([e.basis(F, t) for e, t in others])[mask] if others else None
    ym = y[mask]

    def solve(x):
        a, lam = a_s * x[0], lam_s * math.exp(x[1])
        r = ym - servo_signature(F, a, lam)[mask]
        bo = np.linalg.lstsq(Xo, r, rcond=None)[0] if Xo is not None else np.zeros(0)
        if Xo is not None:
            r = r - Xo @ bo
        return float(r @ r), bo

    def cost(x):
        if not (0.5 <= x[0] <= 2.0 and abs(x[1]) <= math.log(2.0)):
            return np.inf
        return solve(x)[0]

    sol = minimize(cost, np.array([1.0, 0.0]), method="Nelder-Mead",
                   options={"initial_simplex": [[1.0, 0.0], [1.1, 0.0], [1.0, 0.1]], "xatol": 1e-4, "fatol": 1e-9,
                            "maxiter": 400})
    x = sol.x if np.isfinite(sol.fun) else np.array([1.0, 0.0])
    a, lam = a_s * float(x[0]), lam_s * math.exp(float(x[1]))
    _, bo = solve(x)
    out = list(chosen)
    out[i] = (e_s, (lam, a))
    b = np.empty(len(beta))
    j, k = 0, 0
    for jj, (e, _) in enumerate(chosen):
        if jj == i:
            b[k] = a
        else:
            b[k:k + e.n_lin] = bo[j:j + e.n_lin]
            j += e.n_lin
        k += e.n_lin
    return out, b


_BASIS = {
    "runout": lambda F, th: runout_response(F, th[0] if th else 1.0),
    "tool_contour": lambda F, th: np.exp(-0.5 * ((F["q_deg"] - th[0]) / th[1]) ** 2)[:, None],
    "tool_wear": lambda F, th: (F["cut_len_mm"] * 1e-3)[:, None],
    "thermal_drift": lambda F, th: (np.stack([F["nx"], F["ny"], F["nz"]], 1)
                                    * (1 - np.exp(-np.maximum(F["t_s"], 0) / th[0]))[:, None]),
    "force_scale": lambda F, th: F["pred_deflection_um"][:, None],
    # th = (λ,): the smooth form (effect selection); th = (λ, a): the tooth-passage envelope of a
    # lag a, per µm of a (the fitted model: ``refine_servo``)
    "servo_corner": lambda F, th: (servo_smooth(F, th[0]) if len(th) == 1
                                   else servo_signature(F, th[1], th[0]) / th[1])[:, None],
    "machine_geometry": lambda F, th: np.stack([F["nx"] * F["tip_x_mm"], F["ny"] * F["tip_y_mm"], F["nz"] * F["tip_z_mm"],
                                                F["nx"] * F["tip_y_mm"], F["nx"] * F["tip_z_mm"], F["ny"] * F["tip_z_mm"]], 1),
}
_PARAMS = {
    # with the prediction's response: e (geometric part) and e·s (the deflection part scales with
    # the force model: its own coefficient, = e when the force model is right)
    "runout": lambda b, th: {"e_um": float(b[0])} if len(b) == 1 else {"e_um": float(b[0]), "e_force_um": float(b[1])},
    "tool_contour": lambda b, th: {"a_um": float(b[0]), "q0_deg": float(th[0]), "width_deg": float(th[1])},
    "tool_wear": lambda b, th: {"rate_um_per_m": float(b[0])},
    "thermal_drift": lambda b, th: {"ax_um": float(b[0]), "ay_um": float(b[1]), "az_um": float(b[2]), "tau_s": float(th[0])},
    "force_scale": lambda b, th: {"scale": float(1 + b[0])},
    "servo_corner": lambda b, th: {"a_um": float(b[0]), "lambda_mm": float(th[0])},
    "machine_geometry": lambda b, th: dict(zip(("sx", "sy", "sz", "exy", "exz", "eyz"), map(float, b))),
}
NONNEG = {"runout", "tool_wear"}

# Physical limits of a fitted effect: 4 × the largest the seeds measured on real machines (seed 003:
# thermal drift ≈ 50 µm after 3 h of running; an X → Y error of 0–50 µm over ±20 mm, 2.5 µm/mm; a new
# tool ≈ 10 µm off its nominal profile from holder runout). A fit beyond them is no cause but two
# effects cancelling each other where their signatures are nearly collinear (on two raster rows: a
# 226 µm drift against a −271 µm/mm scale error, next to the real 10 µm runout); such a combination
# is not chosen. Sizes: the drift reached by the end of the run |A|·(1 − exp(−T/τ)) (µm), the
# largest geometry coefficient (µm/mm), the runout e and the contour amplitude |a| (µm).
LIMITS = {"thermal_drift": 200.0, "machine_geometry": 10.0, "runout": 40.0, "tool_contour": 40.0}


def beyond_limits(F, effects: list, beta: np.ndarray) -> list[str]:
    """Names of the ``effects`` ((Effect, grid value), linear parameters ``beta`` in order) whose fitted
    size exceeds its physical limit (``LIMITS``)."""
    T = max(float(np.max(F["t_s"])), 0.0) if len(F["t_s"]) else 0.0
    out, k = [], 0
    for e, th in effects:
        b = np.asarray(beta[k:k + e.n_lin], float)
        k += e.n_lin
        if e.name not in LIMITS:
            continue
        if e.name == "thermal_drift":
            size = float(np.linalg.norm(b[:3])) * (1.0 - math.exp(-T / max(th[0], 1e-12)))
        else:
            size = float(np.abs(b).max())
        if size > LIMITS[e.name]:
            out.append(e.name)
    return out


def catalogue(F) -> list[Effect]:
    """The effects with nonlinear grids sized to the data (q range, duration, corner spacing)."""
    qlo, qhi = np.percentile(F["q_deg"], [1, 99])
    T = max(float(F["t_s"].max()), 1e-6)
    q0s = np.arange(max(0.0, qlo), qhi + 1e-9, 2.0)
    widths = [4.0, 5.0, 6.5, 8.0, 10.0, 12.5, 15.0, 17.5, 20.0]   # a local profile error, not a size error
    taus = list(T * np.geomspace(0.02, 10.0, 28))
    lams = list(np.geomspace(0.05, 5.0, 24))
    cat = [
        (Effect("runout", [(float(e),) for e in F["runout_grid_um"]], 2) if "runout_resp_um" in F
         else Effect("runout", [()], 1)),
        Effect("tool_contour", [(a, w) for a in q0s for w in widths], 1),
        Effect("tool_wear", [()], 1),
        Effect("thermal_drift", [(t,) for t in taus], 3),
        Effect("force_scale", [()], 1),
        Effect("servo_corner", [(lm,) for lm in lams], 1),
        Effect("machine_geometry", [()], 6),
    ]
    if not np.any(np.abs(F["pred_deflection_um"]) > 0):
        cat = [e for e in cat if e.name != "force_scale"]
    if not np.any(np.isfinite(F["corner_dist_mm"])):
        cat = [e for e in cat if e.name != "servo_corner"]
    return cat


def _lstsq(X, y, nonneg_first=False):
    beta, *_ = np.linalg.lstsq(X, y, rcond=None)
    return beta


def fit_effects(F, y, train, chosen: list, cand: Effect):
    """Fit ``chosen`` (fixed nonlinear params) + ``cand`` on ``train``: best grid value, betas.

    Grid search over the candidate's nonlinear parameters, then one coordinate-wise refinement
    between the best value's grid neighbours (9 values per parameter). Linear parameters by least
    squares (normal equations); runout and wear are constrained to be ≥ 0.
    """
    base = np.hstack([e.basis(F, th) for e, th in chosen])[train] if chosen else np.zeros((int(train.sum()), 0))
    yt = y[train]
    Gbb = base.T @ base
    gb = base.T @ yt
    yy = float(yt @ yt)

    def solve(th):
        Xc = cand.basis(F, th)[train]
        G = np.block([[Gbb, base.T @ Xc], [Xc.T @ base, Xc.T @ Xc]])
        g = np.concatenate([gb, Xc.T @ yt])
        beta = np.linalg.lstsq(G, g, rcond=None)[0]
        if cand.name in NONNEG and beta[len(gb)] < 0:
            beta = np.concatenate([np.linalg.lstsq(Gbb, gb, rcond=None)[0] if len(gb) else np.zeros(0),
                                   np.zeros(cand.n_lin)])
        sse = yy - 2 * beta @ g + beta @ G @ beta
        return float(sse), beta

    best = None
    for th in cand.grid:
        sse, beta = solve(th)
        if best is None or sse < best[0]:
            best = (sse, th, beta)
    if best[1]:
        th = list(best[1])
        for d in range(len(th)):
            vals = np.unique([g[d] for g in cand.grid])
            i = int(np.searchsorted(vals, th[d]))
            lo, hi = vals[max(i - 1, 0)], vals[min(i + 1, len(vals) - 1)]
            if hi <= lo:
                continue
            fine = np.geomspace(lo, hi, 9) if lo > 0 else np.linspace(lo, hi, 9)
            for v in fine:
                trial = tuple(th[:d] + [float(v)] + th[d + 1:])
                sse, beta = solve(trial)
                if sse < best[0]:
                    best = (sse, trial, beta)
            th = list(best[1])
    return best[1], best[2]


def blocks(F, n_cells: int = 6) -> np.ndarray:
    """Spatial block index of each point (cubic cells, ~n_cells along the longest extent)."""
    p = np.stack([F["x_mm"], F["y_mm"], F["z_mm"]], 1)
    lo, hi = p.min(0), p.max(0)
    h = max(float((hi - lo).max()) / n_cells, 1e-6)
    c = np.floor((p - lo) / h).astype(np.int64)
    _, inv = np.unique(c, axis=0, return_inverse=True)
    return inv.ravel()


def folds(block: np.ndarray, k: int = K_FOLDS) -> np.ndarray:
    """Fold of each point: blocks dealt to folds in a fixed pseudo-random order."""
    nb = block.max() + 1
    perm = np.random.default_rng(12345).permutation(nb)
    return (perm[block] % k).astype(np.int64)


def noise_sigma(F, y) -> float:
    """Robust σ of the probe noise: MAD of differences of consecutive points along the path."""
    same = (F["program_id"][1:] == F["program_id"][:-1])
    step = np.hypot(np.hypot(np.diff(F["x_mm"]), np.diff(F["y_mm"])), np.diff(F["z_mm"]))
    ok = same & (step < 1.0)
    d = np.diff(y)[ok] if ok.sum() >= 10 else np.diff(y)
    if len(d) == 0:
        return float(np.std(y)) or 1.0
    return max(float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2)), 1e-6)


GRID_POINTS = 20000   # grid searches run on at most this many training points (fixed subset)


def _subset(train: np.ndarray) -> np.ndarray:
    idx = np.flatnonzero(train)
    if len(idx) <= GRID_POINTS:
        return train
    keep = np.zeros_like(train)
    keep[np.sort(np.random.default_rng(0).choice(idx, GRID_POINTS, replace=False))] = True
    return keep


def fit_joint(F, y, train, chosen: list, cand: Effect):
    """Add ``cand`` to ``chosen`` on ``train``, re-fitting the chosen effects' nonlinear parameters.

    Coordinate descent, one pass: candidate grid with the others fixed, each chosen effect's grid
    with the rest (candidate included) fixed, the candidate again. Returns (chosen with updated
    nonlinear parameters, candidate's value, betas on the whole training set).
    """
    sub = _subset(train)
    th, _ = fit_effects(F, y, sub, chosen, cand)
    chosen = list(chosen)
    if chosen:
        for i, (e, t) in enumerate(chosen):
            if not t:
                continue
            others = chosen[:i] + chosen[i + 1:] + [(cand, th)]
            t2, _ = fit_effects(F, y, sub, others, e)
            chosen[i] = (e, t2)
        th, _ = fit_effects(F, y, sub, chosen, cand)
    X = np.hstack([e.basis(F, t) for e, t in chosen] + [cand.basis(F, th)])
    beta = np.linalg.lstsq(X[train], y[train], rcond=None)[0]
    k = X.shape[1] - cand.n_lin                    # the candidate's first linear parameter
    if cand.name in NONNEG and beta[k] < 0 and chosen:
        Xb = X[:, :k]
        beta = np.concatenate([np.linalg.lstsq(Xb[train], y[train], rcond=None)[0], np.zeros(cand.n_lin)])
    elif cand.name in NONNEG and beta[k] < 0:
        beta = np.zeros(X.shape[1])
    return chosen, th, beta


def insample_fit(F, y, chosen: list, cand: Effect) -> tuple[float, float, float]:
    """``chosen`` + ``cand`` fitted on all points (``fit_joint``): (SSE, RMS of the candidate's own
    contribution where it acts, its signature's canonical correlation with the chosen effects'
    at the fitted values). The SSE is the in-sample side of a comparison between candidates whose
    signatures are nearly collinear (``_pick``, ``swap_pass``); the contribution is the size of
    such a candidate (``diagnose``)."""
    ch, th, beta = fit_joint(F, y, np.ones(len(y), bool), chosen, cand)
    r = y - _predict(F, ch + [(cand, th)], beta)
    k = sum(e.n_lin for e, _ in ch)
    return float(r @ r), acting_rms(cand.basis(F, th) @ beta[k:]), collinearity(F, ch, cand.basis(F, th))


def collinearity(F, chosen: list, X: np.ndarray) -> float:
    """Largest canonical correlation between the columns of ``X`` and the chosen effects'
    signatures (on the grid-search subset of the points); 0 when none is chosen."""
    if not chosen or X.shape[1] == 0:
        return 0.0
    sub = _subset(np.ones(len(X), bool))
    Qc = _orth(np.hstack([e.basis(F, t) for e, t in chosen])[sub])
    Qg = _orth(X[sub])
    if Qc.shape[1] == 0 or Qg.shape[1] == 0:
        return 0.0
    return float(min(np.linalg.svd(Qg.T @ Qc, compute_uv=False)[0], 1.0))


def insample_sse(F, y, chosen: list, cand: Effect) -> float:
    """SSE of ``chosen`` + ``cand`` fitted on all points (``insample_fit``)."""
    return insample_fit(F, y, chosen, cand)[0]


def collinear_size(explained: float, own: float, rho: float) -> float:
    """The size an effect is judged by (``diagnose``, ``backward_check``): the RMS it explains
    beyond the other effects, or its own fitted contribution when its signature is nearly collinear
    with theirs (canonical correlation ≥ ``AMBIGUOUS_RHO``)."""
    return max(explained, own) if rho >= AMBIGUOUS_RHO else explained


def acting_rms(c: np.ndarray) -> float:
    """RMS of a contribution where it acts: the points beyond a tenth of its peak."""
    a = np.abs(c)
    if not a.size or not a.max() > 0:
        return 0.0
    return float(np.sqrt(np.mean(c[a > 0.1 * a.max()] ** 2)))


def cv_predict(F, y, fold, effects: list, cand: Optional[Effect] = None):
    """Held-out prediction of ``effects`` (+ cand): each fold predicted by the fit on the others.

    ``effects`` are (Effect, grid value); with a candidate, all nonlinear parameters are re-fitted
    on each training set (``fit_joint``), else they stay fixed.
    """
    pred = np.zeros_like(y)
    for f in range(fold.max() + 1):
        test = fold == f
        train = ~test
        if cand is not None:
            ch, th, beta = fit_joint(F, y, train, effects, cand)
            X = np.hstack([e.basis(F, t) for e, t in ch] + [cand.basis(F, th)])
        else:
            X = np.hstack([e.basis(F, t) for e, t in effects])
            beta, *_ = np.linalg.lstsq(X[train], y[train], rcond=None)
        pred[test] = X[test] @ beta
    return pred


def fold_fits(F, y, fold, chosen: list) -> list:
    """The chosen effects fitted without each held-out fold (nonlinear parameters re-fitted on the
    training blocks): [(test mask, [(Effect, grid value, linear parameters)])]."""
    out = []
    for f in range(int(fold.max()) + 1):
        test = fold == f
        if not chosen:
            out.append((test, []))
            continue
        ch, th, beta = fit_joint(F, y, ~test, chosen[:-1], chosen[-1][0])
        ch, beta = refine_servo(F, y, ~test, ch + [(chosen[-1][0], th)], beta)
        items, k = [], 0
        for e, t in ch:
            items.append((e, t, beta[k:k + e.n_lin]))
            k += e.n_lin
        out.append((test, items))
    return out


def apply_baseline(F: dict, force_scale: float, corner: Optional[tuple] = None) -> dict:
    """The prediction with its force model scaled and, given ``corner`` = (a µm, λ mm), the model's
    own floor near path corners added (both calibrations found on a reference part:
    ``corner_floor``)."""
    F = dict(F)
    F["predicted_um"] = F["predicted_um"] + (force_scale - 1.0) * F["pred_deflection_um"]
    F["pred_deflection_um"] = force_scale * F["pred_deflection_um"]
    if corner is not None:
        extra = servo_signature(F, corner[0], corner[1])
        F["predicted_um"] = F["predicted_um"] + extra
        # kept apart: a re-run of the prediction (``pipeline.gap.how_far``) adds it again
        F["baseline_extra_um"] = F.get("baseline_extra_um", 0.0) + extra
    F["residual_um"] = F["measured_um"] - F["predicted_um"]
    return F


FLOOR_Z = 3.0   # the corner floor is taken when its amplitude is at least this many standard errors


def corner_floor(F: dict) -> Optional[tuple]:
    """The prediction's floor near path corners on a reference part (no effect), as the servo lag it
    reads as: (a µm, λ mm), or None without corners.

    Near corners the prediction (one generating point per pass) and a real machine differ by a
    pattern set by the path, not by the machine's state: on the sample raster, where a servo lag
    shows only ~1 µm RMS on ~100 points (the bisector lies nearly in the surface), it reads as a
    lag of about +30 µm with λ 0.05 mm. Left in, it adds to a real lag and pulls the fit along
    the a–λ ridge (a +12.5 µm, λ 0.31 mm lag read as +30 µm, λ 0.17 mm at σ 0.3 µm, 4.7 and 8.9
    stated SE off; all 6 servo misses over 3 fresh blind-check seeds were lags of that sign).
    Taken from the reference it is part of the baseline, like the force scale: on that seed the
    servo misses went from 3 to 2 (the σ 0.3 µm case within 20 %); the ones left, at σ ≥ 0.6 µm,
    are still lags of that sign. None when the reference does not pin it: amplitude below
    ``FLOOR_Z`` standard errors (``param_uncertainty`` at the polished fit)."""
    cand = [e for e in catalogue(F) if e.name == "servo_corner"]
    if not cand:
        return None
    y = F["residual_um"].astype(float)
    ones = np.ones(len(y), bool)
    th, beta = fit_effects(F, y, ones, [], cand[0])
    chosen, beta = refine_servo(F, y, ones, [(cand[0], th)], beta)
    chosen, beta = polish_fit(F, y, chosen, beta)
    p = _params_of(chosen, beta)["servo_corner"]
    a, lam = p["a_um"], p["lambda_mm"]
    if not (np.isfinite(a) and a != 0):
        return None
    # taken only when the reference pins it: read from the few points within ~0.1 mm of the
    # corners, one reference at σ 0.65 µm on the sample plan gives it to ±35–140 µm (+28 µm, λ 0.037
    # mm from one draw, +75 µm, λ 0.057 mm from another, +37 µm, λ 0.048 mm noise-free); subtracted
    # from every case, the second made 2 of 8 no-effect cases of its blind check claim a lag of −17 µm
    se = param_uncertainty(F, y, chosen, beta, noise_sigma(F, y))["se"].get("servo_corner", {}).get("a_um")
    if se is None or not abs(a) >= FLOOR_Z * se:
        return None
    return (a, lam)


def diagnose(F: dict, noise_um: Optional[float] = None, floor_um: float = 0.0) -> dict:
    """Rank the catalogue on held-out blocks, choose effects greedily, measure the shrink.

    Returns a dict: effect, effects, params, ranking (list of dicts), sigma_um, rms/p95/max before and
    after (held-out), cv residual after (array), fitted contribution per effect (arrays).
    """
    y = F["residual_um"].astype(float)
    n = len(y)
    blk = blocks(F)
    fold = folds(blk)
    sigma = float(noise_um) if noise_um else noise_sigma(F, y)
    cat = catalogue(F)
    from scipy.stats import chi2
    chosen: list = []                          # (Effect, grid value)
    ranking = []
    base_pred = np.zeros(n)
    sse_base = float(np.sum(y ** 2))
    first_round = None
    rejected: list = []                        # candidates whose fit went beyond the physical limits
    for step in range(MAX_EFFECTS):
        rows = []
        for eff in cat:
            if any(e.name == eff.name for e, _ in chosen):
                continue
            pred = cv_predict(F, y, fold, chosen, eff)
            sse = float(np.sum((y - pred) ** 2))
            gain = (sse_base - sse) / sigma ** 2
            thr = float(chi2.ppf(1 - ALPHA, eff.n_params))
            # practical size: where the effect acts (beyond a tenth of its peak), the held-out RMS it
            # explains must reach half the noise level (probe noise and, when known, the model's own
            # floor on a reference part) — or, for a candidate nearly collinear with the effects
            # already chosen (``collinear_size``), its own fitted contribution: next to such an
            # effect a real one explains little more. A tool wear of 3.5 µm RMS next to a 1.7 µm
            # thermal drift (sample plan, correlation 0.998) explained 0.3 µm beyond the drift
            # alone, which had stretched its τ to 150 s to mimic the wear's ramp; fitted together
            # they came out at the true wear within 3 % and the drift's τ within 15 %. Not for any
            # candidate: the in-sample contribution of one fitted to the model's own floor can
            # reach σ/2 where it holds out at less (100,000 points: a 0.5 µm tool-contour dent next
            # to the true drift). Significance stays with the held-out gain; a cancelling pair is
            # caught by ``LIMITS``.
            delta = pred - base_pred
            support = max(int(np.sum(np.abs(delta) > 0.1 * np.abs(delta).max())) if np.any(delta) else n, 1)
            explained = math.sqrt(max(sse_base - sse, 0.0) / support)
            sse_in, own, rho = insample_fit(F, y, chosen, eff)
            big = collinear_size(explained, own, rho) >= 0.5 * math.hypot(sigma, floor_um)
            rows.append({"effect": eff.name, "sse": sse, "gain": gain, "threshold": thr, "eff": eff, "pred": pred,
                         "explained_um": explained, "own_um": own, "rho": rho, "big": big,
                         "sse_in_sigma2": sse_in / sigma ** 2})
        if not rows:
            break
        rows.sort(key=lambda r: -r["gain"])
        if first_round is None:
            first_round = list(rows)
        picked = None
        while rows:
            top = _pick(rows)
            if top is None:
                break
            ch, th, beta = fit_joint(F, y, np.ones(n, bool), chosen, top["eff"])
            bad = beyond_limits(F, ch + [(top["eff"], th)], beta)
            if not bad:
                picked = (ch, th, top)
                break
            # a cancelling combination: the candidate is not chosen at this step
            rejected.append({"step": step + 1, "effect": top["effect"], "beyond_limits": bad,
                             "params": _params_of(ch + [(top["eff"], th)], beta)})
            rows = [r for r in rows if r is not top]
        if picked is None:
            break
        chosen, th, top = picked
        chosen.append((top["eff"], th))
        sse_base = top["sse"]
        base_pred = top["pred"]
    chosen, sse_base, base_pred = settle(F, y, fold, cat, chosen, sse_base, base_pred, sigma, floor_um, rejected)
    # final fit on all points: parameters and each effect's contribution
    params, contrib = {}, {}
    if chosen:
        chosen, beta = final_fit(F, y, chosen)
        k = 0
        for e, t in chosen:
            b = beta[k:k + e.n_lin]
            params[e.name] = e.params(b, t)
            contrib[e.name] = e.basis(F, t) @ b
            k += e.n_lin
    # how well the data pin each parameter: the final model linearised at the fit
    unc = param_uncertainty(F, y, chosen, beta if chosen else np.zeros(0), sigma)
    order = sorted(contrib, key=lambda nme: -float(np.sqrt(np.mean(contrib[nme] ** 2))))
    limits = detection_limits(F, chosen, cat, sigma, floor_um)
    after = y - base_pred
    rms_b, rms_a = _rms(y), _rms(after)
    for i, r in enumerate(first_round or []):
        ranking.append({"effect": r["effect"], "rank": i + 1, "rms_before_um": rms_b,
                        "rms_after_um": _rms(y - r["pred"]), "gain_sigma2": r["gain"],
                        "threshold_sigma2": r["threshold"], "explained_um": r["explained_um"],
                        "significant": bool(r["gain"] > r["threshold"] and r["big"])})
    return {
        "effect": order[0] if order else "none",
        "effects": order,
        "params": {k: params[k] for k in order},
        "params_se": {k: unc["se"][k] for k in order},
        "params_cov": unc["cov"],
        "params_se_info": {kk: unc[kk] for kk in ("sigma_um", "noise_sigma_um", "residual_rms_um", "n_points",
                                                  "n_params", "not_identifiable")},
        "sigma_um": sigma, "floor_um": floor_um,
        "n_points": n,
        "n_blocks": int(blk.max() + 1),
        "rms_before_um": rms_b, "rms_after_um": rms_a,
        "p95_before_um": float(np.percentile(np.abs(y), 95)), "p95_after_um": float(np.percentile(np.abs(after), 95)),
        "max_before_um": float(np.abs(y).max()), "max_after_um": float(np.abs(after).max()),
        "shrink": float(1 - rms_a / rms_b) if rms_b > 0 else 0.0,
        # the same on the points where the chosen effects act (held-out prediction > 10 % of its peak)
        "shrink_where_acting": _shrink_acting(y, after, base_pred),
        "ranking": ranking,
        "detection_limits": limits,
        "ambiguous_with": ambiguous_with(limits, order),
        "beyond_limits": rejected,
        "_after": after, "_contrib": contrib, "_blocks": blk, "_fold": fold, "_chosen": chosen,
    }


def settle(F, y, fold, cat: list, chosen: list, sse_base: float, base_pred: np.ndarray, sigma: float,
           floor_um: float, rejected: list):
    """The forward selection's effects settled: a swap pass (``swap_pass``), then the backward check
    (``backward_check``), again while the check drops an effect. The swaps were judged next to the
    dropped effect: without it a richer effect may be no better than a simpler one (a 3.5 µm tool
    wear next to a force scale of 2.8 on the sample plan: a geometry error chosen first, then the
    force scale, then a thermal drift by 25 σ² over the wear; once the geometry error is dropped
    the drift is not better than the wear by the χ² margin of its three extra parameters).
    Returns (chosen, held-out SSE, held-out prediction)."""
    for _ in range(MAX_EFFECTS):
        chosen, sse_base, base_pred = swap_pass(F, y, fold, cat, chosen, sse_base, base_pred, sigma, rejected)
        n_before = len(chosen)
        chosen, sse_base, base_pred = backward_check(F, y, fold, chosen, sse_base, base_pred, sigma, floor_um)
        if len(chosen) == n_before or len(chosen) < 2:
            break
    return chosen, sse_base, base_pred


def swap_pass(F, y, fold, cat: list, chosen: list, sse_base: float, base_pred: np.ndarray, sigma: float,
              rejected: list):
    """One swap pass: an effect picked early may have soaked up part of a later one; each chosen
    effect is replaced by each other candidate when that fits the held-out blocks significantly
    better, or equally well (within the χ² margin) with fewer parameters. Returns (chosen, sse,
    held-out prediction)."""
    from scipy.stats import chi2
    n = len(y)
    if len(chosen) >= 2:
        for i in range(len(chosen)):
            rest = chosen[:i] + chosen[i + 1:]
            cur_p = chosen[i][0].n_params
            sse_in_cur = None
            for eff in cat:
                if any(e.name == eff.name for e, _ in chosen):
                    continue
                pred = cv_predict(F, y, fold, rest, eff)
                sse = float(np.sum((y - pred) ** 2))
                dp = eff.n_params - cur_p
                margin = float(chi2.ppf(1 - ALPHA, abs(dp))) * sigma ** 2 if dp else 0.0
                better = sse < sse_base - margin if dp > 0 else sse < sse_base + margin
                if dp != 0 and (better == (dp > 0)):
                    # a richer replacement must fit better in-sample too; a simpler one may (``_pick``)
                    if sse_in_cur is None:
                        sse_in_cur = insample_sse(F, y, rest, chosen[i][0])
                    sse_in = insample_sse(F, y, rest, eff)
                    better = (better and sse_in < sse_in_cur - margin) if dp > 0 else sse_in < sse_in_cur + margin
                if better:
                    ch, th, beta = fit_joint(F, y, np.ones(n, bool), rest, eff)
                    bad = beyond_limits(F, ch + [(eff, th)], beta)
                    if bad:
                        rejected.append({"step": "swap", "effect": eff.name, "beyond_limits": bad,
                                         "params": _params_of(ch + [(eff, th)], beta)})
                        continue
                    rest = ch
                    chosen = rest[:i] + [(eff, th)] + rest[i:]
                    sse_base, base_pred = sse, pred
                    break
    return chosen, sse_base, base_pred


def backward_check(F, y, fold, chosen: list, sse_base: float, base_pred: np.ndarray, sigma: float,
                   floor_um: float):
    """Every kept effect must still pay for itself given the others (χ² and size); the weakest that
    does not is dropped, until all do. Returns (chosen, sse, held-out prediction)."""
    from scipy.stats import chi2
    n = len(y)
    while chosen:
        drops = []
        # each effect's own contribution in the joint fit on all points (the size test of ``diagnose``)
        X = np.hstack([e.basis(F, t) for e, t in chosen])
        beta = np.linalg.lstsq(X, y, rcond=None)[0]
        ks = np.cumsum([0] + [e.n_lin for e, _ in chosen])
        for i, (e, t) in enumerate(chosen):
            rest = chosen[:i] + chosen[i + 1:]
            pred = cv_predict(F, y, fold, rest) if rest else np.zeros(n)
            d_sse = float(np.sum((y - pred) ** 2)) - sse_base
            delta = base_pred - pred
            support = max(int(np.sum(np.abs(delta) > 0.1 * np.abs(delta).max())) if np.any(delta) else n, 1)
            own = acting_rms(X[:, ks[i]:ks[i + 1]] @ beta[ks[i]:ks[i + 1]])
            size = collinear_size(math.sqrt(max(d_sse, 0.0) / support), own,
                                  collinearity(F, rest, X[:, ks[i]:ks[i + 1]]))
            ok = (d_sse / sigma ** 2 > float(chi2.ppf(1 - ALPHA, e.n_params))
                  and size >= 0.5 * math.hypot(sigma, floor_um))
            drops.append((d_sse, i, ok, pred))
        weak = [d for d in drops if not d[2]]
        if not weak:
            break
        d_sse, i, _, pred = min(weak)
        chosen = chosen[:i] + chosen[i + 1:]
        sse_base += d_sse
        base_pred = pred
    return chosen, sse_base, base_pred


def _pick(rows: list) -> Optional[dict]:
    """The effect to add among ``rows`` (sorted by held-out gain): the best, or a simpler significant
    one when the richer model is not significantly better — its held-out gain, or its in-sample
    SSE (``sse_in_sigma2``), within the χ² margin of its extra parameters; None when the one chosen
    is not significant (χ² and practical size).

    Both must favour the richer model because the held-out gains of nearly collinear candidates
    depend on how each refits the earlier effects' nonlinear values without a block: with the block
    holding the peak of a 12 µm tool-contour error held out, the contour next to a tool wear slid to
    another centre and width on the remaining flanks and missed the block by 220 µm² noise-free,
    next to a thermal drift it did not; the drift won by 200 σ² on held-out blocks while it fitted
    the whole part worse than the wear (sample plan, wear 45 µm/m + that contour)."""
    from scipy.stats import chi2
    top = rows[0]
    for r in sorted(rows, key=lambda r: r["eff"].n_params):
        dp = top["eff"].n_params - r["eff"].n_params
        if dp <= 0 or not (r["gain"] > r["threshold"] and r["big"]):
            continue
        margin = float(chi2.ppf(1 - ALPHA, dp))
        if top["gain"] - r["gain"] < margin or r["sse_in_sigma2"] - top["sse_in_sigma2"] < margin:
            top = r
            break
    return top if (top["gain"] > top["threshold"] and top["big"]) else None


def _params_of(effects: list, beta: np.ndarray) -> dict:
    out, k = {}, 0
    for e, th in effects:
        out[e.name] = e.params(beta[k:k + e.n_lin], th)
        k += e.n_lin
    return out


SE_STEP = 1e-3        # central-difference step of a nonlinear parameter: SE_STEP × max(|value|, 1)
SE_RANK_TOL = 1e-7    # singular value of the column-scaled Jacobian (relative to the largest) below
                      # which a direction of the parameters is not identifiable on the points


def _free_parameters(F, e: "Effect", th, b):
    """One chosen effect in the linearised model: (internal names, values, linear flags,
    contribution(v), reported(v) → dict, basis at the fit or None).

    Linear parameters are the effect's amplitudes (their Jacobian columns are its basis columns);
    nonlinear ones its grid values (τ, q0, width, λ, the runout response's e), differentiated by
    central differences. The servo lag's fitted form (th = (λ, a)) is the tooth-passage envelope,
    not linear in a either: both a and λ by central differences, every value read with one
    passage geometry that covers them."""
    b = np.asarray(b, float)
    if e.name == "servo_corner" and len(th) == 2:
        a, lam = float(b[0]), float(th[0])
        g = None
        if "_geometry" in F and a != 0:
            g = _env_geometry(F, abs(a) + 2 * SE_STEP * max(abs(a), 1.0), lam + 2 * SE_STEP * max(lam, 1.0))
        return (["servo_corner.a_um", "servo_corner.lambda_mm"], np.array([a, lam]), [False, False],
                lambda v: servo_signature(F, float(v[0]), float(v[1]), g),
                lambda v: {"a_um": float(v[0]), "lambda_mm": float(v[1])}, None)
    nl = e.n_lin
    th = tuple(float(t) for t in th)
    keys = list(e.params(b, th))
    # internal names (for the reasons of a non-identifiable parameter): amplitudes are the first
    # reported keys, nonlinear values the rest; the runout response's e is not reported
    names = [f"{e.name}.{keys[i] if i < len(keys) else 'lin' + str(i)}" for i in range(nl)]
    rest = keys[nl:]
    names += [f"{e.name}.{'response_at_e_um' if e.name == 'runout' else rest[j] if j < len(rest) else 'th' + str(j)}"
              for j in range(len(th))]
    return (names, np.concatenate([b, np.asarray(th, float)]), [True] * nl + [False] * len(th),
            lambda v: e.basis(F, tuple(float(t) for t in v[nl:])) @ v[:nl],
            lambda v: e.params(v[:nl], tuple(float(t) for t in v[nl:])), e.basis(F, th))


def _linearise(F, chosen: list, beta: np.ndarray):
    """The combined prediction of ``chosen`` at ``beta`` and its derivative with respect to every free
    parameter (``_free_parameters``): (prediction, J (n, p), internal names, free values per effect,
    [(effect, reported keys, G = d reported / d free)])."""
    n = len(F["q_deg"])
    cols, names, blocks, values = [], [], [], []
    pred = np.zeros(n)
    k = 0
    for e, th in chosen:
        b = beta[k:k + e.n_lin]
        k += e.n_lin
        nm, v0, is_lin, f, rep, X = _free_parameters(F, e, th, b)
        pred += f(v0)
        h = SE_STEP * np.maximum(np.abs(v0), 1.0)
        J = np.empty((n, len(v0)))
        keys = list(rep(v0))
        G = np.zeros((len(keys), len(v0)))
        for i in range(len(v0)):
            vp, vm = v0.copy(), v0.copy()
            vp[i] += h[i]
            vm[i] -= h[i]
            J[:, i] = X[:, i] if is_lin[i] else (f(vp) - f(vm)) / (2 * h[i])
            rp, rm = rep(vp), rep(vm)
            G[:, i] = [(rp[kk] - rm[kk]) / (2 * h[i]) for kk in keys]
        cols.append(J)
        names += nm
        values.append(v0)
        blocks.append((e.name, keys, G))
    J = np.hstack(cols) if cols else np.zeros((n, 0))
    return pred, J, names, values, blocks


def _predict(F, chosen: list, beta: np.ndarray) -> np.ndarray:
    """Σ of the chosen effects' contributions (basis × amplitudes)."""
    out, k = np.zeros(len(F["q_deg"])), 0
    for e, th in chosen:
        out += e.basis(F, th) @ beta[k:k + e.n_lin]
        k += e.n_lin
    return out


def _with_free(e: "Effect", th, v: np.ndarray):
    """(grid value, amplitudes) of effect ``e`` from its free parameter values (``_free_parameters``)."""
    if e.name == "servo_corner" and len(th) == 2:
        return (float(v[1]), float(v[0])), np.array([v[0]], float)
    return tuple(float(t) for t in v[e.n_lin:]), np.asarray(v[:e.n_lin], float)


def _free_bounds(e: "Effect", th, v0: np.ndarray):
    """How far ``polish_fit`` may move an effect's nonlinear values from the selection's: within a
    factor 2 (positive values: τ, λ, width, the runout response's e, the servo lag a with its sign),
    the contour's centre q0 within ± its width."""
    lo, hi = np.full(len(v0), -np.inf), np.full(len(v0), np.inf)
    nonlin = range(len(v0)) if (e.name == "servo_corner" and len(th) == 2) else range(e.n_lin, len(v0))
    for i in nonlin:
        if e.name == "tool_contour" and i == e.n_lin:                 # q0: any sign
            w = abs(float(v0[i + 1]))
            lo[i], hi[i] = v0[i] - w, v0[i] + w
        else:
            lo[i], hi[i] = sorted((0.5 * v0[i], 2.0 * v0[i]))
    return lo, hi


def polish_fit(F, y: np.ndarray, chosen: list, beta: np.ndarray, max_iter: int = 30):
    """All parameters of the chosen effects refined jointly by least squares (Levenberg–Marquardt on
    the linearised model of ``_linearise``), from the selection's fit.

    The selection's nonlinear values come from grids refined once between neighbours (τ in steps
    of ~6 %, q0 of 0.5°, width of ~0.3–0.6°): at a strong signal that step is as large as the noise's
    own spread of the value, so the reported value would sit on a grid point and its standard error
    (``param_uncertainty``, which assumes the least-squares optimum) would not describe it. The
    nonlinear values stay within ``_free_bounds`` of the selection's; a step is taken only when it
    lowers the sum of squares. Returns (chosen, beta) in the same layout."""
    if not chosen:
        return chosen, beta
    chosen, beta = list(chosen), np.asarray(beta, float).copy()
    pred, J, _, values, _ = _linearise(F, chosen, beta)
    bounds = [_free_bounds(e, th, v) for (e, th), v in zip(chosen, values)]
    lo = np.concatenate([b[0] for b in bounds])
    hi = np.concatenate([b[1] for b in bounds])
    sizes = [len(v) for v in values]
    v = np.concatenate(values)
    r = y - pred
    sse = float(r @ r)
    lam = 1e-4

    def unpack(vv):
        ch, bb, k = [], [], 0
        for (e, th), m in zip(chosen, sizes):
            t2, b2 = _with_free(e, th, vv[k:k + m])
            ch.append((e, t2))
            bb.append(b2)
            k += m
        return ch, np.concatenate(bb)

    for _ in range(max_iter):
        A, g = J.T @ J, J.T @ r
        D = np.where(np.diag(A) > 0, np.diag(A), 1.0)
        step = None
        while lam < 1e10:
            try:
                delta = np.linalg.solve(A + lam * np.diag(D), g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            vn = v + delta
            if np.all(np.isfinite(vn)) and np.all(vn >= lo) and np.all(vn <= hi):
                ch, bb = unpack(vn)
                rn = y - _predict(F, ch, bb)
                sn = float(rn @ rn)
                if sn < sse:
                    step = (vn, ch, bb, rn, sn)
                    lam = max(lam / 10, 1e-9)
                    break
            lam *= 10
        if step is None:
            break
        vn, chosen, beta, r, sn = step
        done = sse - sn <= 1e-12 * sse
        v, sse = vn, sn
        if done:
            break
        _, J, _, _, _ = _linearise(F, chosen, beta)
    return chosen, beta


def param_uncertainty(F, y: np.ndarray, chosen: list, beta: np.ndarray, sigma: float) -> dict:
    """Standard errors of every reported parameter of the final model (all chosen effects jointly,
    on all points), from the model linearised at the fit.

    J: the derivative of the combined prediction Σ_e contribution_e with respect to every free
    parameter (``_free_parameters``: amplitudes → basis columns; nonlinear parameters → central
    differences of the basis, step ``SE_STEP``). cov = s²·(JᵀJ)⁻¹ with s = max(σ, residual RMS
    √(SSE/(n − p))), propagated to the reported form (force scale = 1 + b, …) by the Jacobian of the
    reported parameters, G·cov·Gᵀ. JᵀJ is inverted through the SVD of J with unit-norm columns:
    directions whose singular value is below ``SE_RANK_TOL`` of the largest are not identifiable, and a
    reported parameter that depends on one gets se None with the reason (the parameters it cannot
    be told from); the others are read from the pseudo-inverse. It assumes independent residuals
    and the linearisation: a residual the model does not explain (the prediction's own floor)
    enters through s only.

    Returns {"se": {effect: {key: se | None}}, "cov": {"names", "matrix"}, "not_identifiable":
    {effect.key: reason}, "sigma_um": s, "noise_sigma_um", "residual_rms_um", "n_points", "n_params"}.
    """
    n = len(y)
    pred, J, names, _, blocks = _linearise(F, chosen, beta)
    se = {e.name: {} for e, _ in chosen}
    rep_names = []
    p = len(names)
    out = {"se": se, "cov": {"names": [], "matrix": []}, "not_identifiable": {}, "noise_sigma_um": float(sigma),
           "n_points": int(n), "n_params": int(p)}
    if not p:
        out.update(sigma_um=float(sigma), residual_rms_um=_rms(y))
        return out
    Gf = np.zeros((sum(len(kk) for _, kk, _ in blocks), p))
    r = c = 0
    for name, keys, G in blocks:
        Gf[r:r + len(keys), c:c + G.shape[1]] = G
        rep_names += [f"{name}.{kk}" for kk in keys]
        r += len(keys)
        c += G.shape[1]
    resid = y - pred
    rms_dof = float(np.sqrt(resid @ resid / max(n - p, 1)))
    s = max(float(sigma), rms_dof)
    out.update(sigma_um=s, residual_rms_um=rms_dof)
    reason = {}
    if n <= p or not np.all(np.isfinite(J)):
        why = (f"{n} points for {p} parameters" if n <= p else "the model's derivative is not finite at the fit")
        for nm in rep_names:
            reason[nm] = why
        cov = np.full((len(rep_names), len(rep_names)), np.nan)
    else:
        cn = np.linalg.norm(J, axis=0)
        cn = np.where(cn > 0, cn, 1.0)
        _, S, Vt = np.linalg.svd(J / cn, full_matrices=False)
        keep = S > S[0] * SE_RANK_TOL if S[0] > 0 else np.zeros(len(S), bool)
        Vk = Vt[keep].T / S[keep]
        cov_v = (Vk @ Vk.T) / np.outer(cn, cn) * s * s
        cov = Gf @ cov_v @ Gf.T
        N = Vt[~keep].T                                   # null directions, in column-scaled units
        if N.size:
            Gw = Gf / cn
            for j, nm in enumerate(rep_names):
                g = Gw[j]
                if np.linalg.norm(g @ N) > 1e-6 * max(np.linalg.norm(g), 1e-300):
                    w = np.abs(N @ (N.T @ g))
                    with_ = [names[i] for i in np.argsort(-w) if w[i] > 0.1 * w.max() and names[i] != nm][:4]
                    reason[nm] = ("not identifiable on these points: a combination of it and "
                                  + (", ".join(with_) if with_ else "nothing else")
                                  + f" leaves the prediction unchanged (singular value {S[~keep].max() / S[0]:.1e} "
                                    "of the column-scaled Jacobian)")
    bad = np.array([nm in reason for nm in rep_names])
    cov[bad, :] = np.nan
    cov[:, bad] = np.nan
    for j, nm in enumerate(rep_names):
        eff, key = nm.split(".", 1)
        v = cov[j, j]
        se[eff][key] = float(math.sqrt(v)) if np.isfinite(v) and v >= 0 else None
    out["not_identifiable"] = reason
    out["cov"] = {"names": rep_names,
                  "matrix": [[float(x) if np.isfinite(x) else None for x in row] for row in cov]}
    return out


AMBIGUOUS_RHO = 0.95   # reported as ambiguous: the chosen effect's signatures explain ≥ 90 % of the other's


def _orth(X: np.ndarray) -> np.ndarray:
    """Orthonormal basis of the columns of X (rank-revealing)."""
    if X.shape[1] == 0:
        return X
    U, sv, _ = np.linalg.svd(X, full_matrices=False)
    return U[:, sv > max(sv[0], 1e-300) * 1e-9] if sv.size and sv[0] > 0 else U[:, :0]


def final_fit(F, y: np.ndarray, chosen: list):
    """The reported fit of the chosen effects on all points: amplitudes by least squares at the
    selection's nonlinear values, the servo lag re-fitted with the tooth-passage envelope
    (``refine_servo``), then every parameter jointly to the least-squares optimum (``polish_fit``).
    Returns (chosen, beta)."""
    n = len(y)
    X = np.hstack([e.basis(F, t) for e, t in chosen])
    beta, *_ = np.linalg.lstsq(X, y, rcond=None)
    chosen, beta = refine_servo(F, y, np.ones(n, bool), chosen, beta)
    return polish_fit(F, y, chosen, beta)


def detection_limits(F, chosen: list, cat: list, sigma: float, floor_um: float = 0.0) -> dict:
    """What the selection could have missed: for every catalogue effect not chosen, the largest RMS
    (µm over the points) of a signature of it that would not be claimed next to the chosen effects.

    A signature v of effect G (any of its nonlinear values, any combination of its linear ones) of
    RMS r has the part (1 − ρ²)·r² not explained by the chosen effects' signatures (ρ: its largest
    canonical correlation with them at their fitted values; 0 when none was chosen). The selection
    claims it only when it passes both tests of ``diagnose``: n·(1 − ρ²)·r²/σ² beyond the χ²
    quantile of G's parameter count, and the size test (``collinear_size``): √(n·(1 − ρ²)·r²/support)
    ≥ ½·hypot(σ, floor), support = the points where v exceeds a tenth of its peak, or when ρ ≥
    ``AMBIGUOUS_RHO`` its own RMS where it acts, r·√(n/support), ≥ ½·hypot(σ, floor).
    ``hidden_up_to_um`` is the larger r at which either fails, maximised over G's signatures;
    ``correlation`` is that signature's ρ and ``masked_by`` the chosen effect whose own signatures
    correlate most with it. A nearly collinear pair on the part (ρ → 1) makes the limit large: the
    data cannot tell the two effects apart.
    """
    from scipy.stats import chi2
    n = len(F["q_deg"])
    sub = _subset(np.ones(n, bool))
    names = {e.name for e, _ in chosen}
    Qc = _orth(np.hstack([e.basis(F, t) for e, t in chosen])[sub]) if chosen else None
    Qe = [(e.name, _orth(e.basis(F, t)[sub])) for e, t in chosen]
    size = 0.5 * math.hypot(sigma, floor_um)
    out = {}
    for G in cat:
        if G.name in names:
            continue
        thr = float(chi2.ppf(1 - ALPHA, G.n_params))
        best = None
        for th in G.grid:
            Qg = _orth(G.basis(F, th)[sub])
            if Qg.shape[1] == 0:
                continue
            if Qc is not None and Qc.shape[1]:
                u, sv, _ = np.linalg.svd(Qg.T @ Qc, full_matrices=False)
                rho, v = float(min(sv[0], 1.0)), Qg @ u[:, 0]
            else:
                rho, v = 0.0, Qg[:, 0]
            unique = max(1.0 - rho * rho, 1e-12)
            frac = float(np.mean(np.abs(v) > 0.1 * np.abs(v).max()))
            # the size test as ``collinear_size``: its own RMS where it acts when nearly
            # collinear, else the part the chosen effects do not explain
            r = max(sigma * math.sqrt(thr / (n * unique)),
                    size * math.sqrt(frac if rho >= AMBIGUOUS_RHO else frac / unique))
            if best is None or r > best[0]:
                by = max(Qe, key=lambda q: float(np.linalg.norm(q[1].T @ v)))[0] if Qe else None
                best = (r, rho, by)
        if best is not None:
            out[G.name] = {"hidden_up_to_um": best[0], "correlation": best[1], "masked_by": best[2]}
    return out


def ambiguous_with(limits: dict, effects: list) -> dict:
    """Per chosen effect, the effects not chosen whose signatures on these points it explains to a
    canonical correlation of at least ``AMBIGUOUS_RHO``: the data cannot tell them apart, and up to
    ``hidden_up_to_um`` of them may be inside the chosen effect's fit."""
    out = {e: [] for e in effects}
    for g, lim in sorted(limits.items(), key=lambda kv: -kv[1]["correlation"]):
        if lim["masked_by"] in out and lim["correlation"] >= AMBIGUOUS_RHO:
            out[lim["masked_by"]].append({"effect": g, "correlation": lim["correlation"],
                                          "hidden_up_to_um": lim["hidden_up_to_um"]})
    return {k: v for k, v in out.items() if v}


def _shrink_acting(y, after, pred) -> Optional[float]:
    if not np.any(pred):
        return None
    m = np.abs(pred) > 0.1 * np.abs(pred).max()
    b = _rms(y[m])
    return float(1 - _rms(after[m]) / b) if b > 0 else None


def _rms(v) -> float:
    return float(np.sqrt(np.mean(np.square(v)))) if len(v) else 0.0


def where(F, y, sigma: float, blk: np.ndarray, z: float = 3.0, top: int = 20) -> list[dict]:
    """Blocks whose mean residual is significantly non-zero (|mean| > z·se and > σ/2)."""
    nb = blk.max() + 1
    cnt = np.bincount(blk, minlength=nb)
    mean = np.bincount(blk, y, nb) / np.maximum(cnt, 1)
    var = np.bincount(blk, y * y, nb) / np.maximum(cnt, 1) - mean ** 2
    se = np.sqrt(np.maximum(var, sigma ** 2) / np.maximum(cnt, 1))
    sig = (cnt >= 3) & (np.abs(mean) > z * se) & (np.abs(mean) > 0.5 * sigma)
    out = []
    for b in np.flatnonzero(sig)[np.argsort(-np.abs(mean[sig]))][:top]:
        m = blk == b
        progs = sorted(set(F["program_id"][m].tolist()))
        out.append({
            "bbox_mm": [float(F["x_mm"][m].min()), float(F["y_mm"][m].min()), float(F["z_mm"][m].min()),
                        float(F["x_mm"][m].max()), float(F["y_mm"][m].max()), float(F["z_mm"][m].max())],
            "programs": progs,
            "pass_range": [int(F["pass_id"][m].min()), int(F["pass_id"][m].max())],
            "contact_deg": [float(F["q_deg"][m].min()), float(F["q_deg"][m].max())],
            "time_s": [float(F["t_s"][m].min()), float(F["t_s"][m].max())],
            "n_points": int(cnt[b]),
            "mean_residual_um": float(mean[b]),
            "ci95_um": [float(mean[b] - 1.96 * se[b]), float(mean[b] + 1.96 * se[b])],
        })
    return out


def gap_points_table(F, after) -> pa.Table:
    cols = {
        "point_id": pa.array(F["point_id"].astype(np.int64)),
        "program_id": pa.array(F["program_id"].astype(str).tolist(), pa.string()),
        "pass_id": pa.array(F["pass_id"].astype(np.int32)),
        "predicted_um": F["predicted_um"], "measured_um": F["measured_um"], "residual_um": F["residual_um"],
    }
    for k in EXTRA_POINT_COLUMNS:
        if k == "residual_after_um":
            cols[k] = after
        else:
            cols[k] = np.asarray(F[k], dtype=float)
    return pa.table(cols)


EXTRA_POINT_COLUMNS = ("x_mm", "y_mm", "z_mm", "nx", "ny", "nz", "q_deg", "phi_deg", "t_s", "cut_len_mm",
                       "corner_dist_mm", "corner_deg", "feed_mm_min", "pred_deflection_um", "dist_mm",
                       "residual_after_um")


def gap_effects_table(res: dict) -> pa.Table:
    rows = res["ranking"]
    chosen = res["params"]
    return pa.table({
        "effect": pa.array([r["effect"] for r in rows], pa.string()),
        "params": pa.array([json.dumps(chosen.get(r["effect"], {})) for r in rows], pa.string()),
        "params_se": pa.array([json.dumps(res.get("params_se", {}).get(r["effect"], {})) for r in rows], pa.string()),
        "rms_before_um": [r["rms_before_um"] for r in rows],
        "rms_after_um": [r["rms_after_um"] for r in rows],
        "explained": [1 - r["rms_after_um"] / r["rms_before_um"] if r["rms_before_um"] > 0 else 0.0 for r in rows],
        "rank": pa.array([r["rank"] for r in rows], pa.int32()),
        "gain_sigma2": [r["gain_sigma2"] for r in rows],
        "threshold_sigma2": [r["threshold_sigma2"] for r in rows],
        "chosen": [r["effect"] in chosen for r in rows],
        "hidden_up_to_um": [float(res.get("detection_limits", {}).get(r["effect"], {}).get("hidden_up_to_um", np.nan))
                            for r in rows],
        "ambiguous_with": pa.array([json.dumps(res.get("ambiguous_with", {}).get(r["effect"], [])) for r in rows],
                                   pa.string()),
    })
