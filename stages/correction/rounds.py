"""Correction rounds: one round of vertex moves over a program (:func:`correct_once`), and the rounds.

- Vertices inside a pass that merges several short blocks get the error of that pass alone.
- A pass without an error row (pruned, non-cutting, rapid) contributes nothing: a vertex between it
  and a predicted pass follows the predicted pass; a vertex with no predicted pass does not move.
- Moves are clipped at ``max_move_um`` (the total move over all rounds); clipped vertices are
  flagged in the ``clipped`` column.
- Gouge limit (``correct.gouge_limit``): a vertex is not moved so far that the tool cuts past the
  generating point of another surface it passes beside; ``gouge_limit_um`` lists what was taken off.

Iteration (seed 003, DESIGN §7): :func:`correct_once` takes blocks, their passes and errors plus the
previous ``corrected`` table; it adds its move to the blocks' own offset from the original
coordinates (kept from the previous table), clips the total, counts rounds and reports the change
against the previous table's coordinates. Two kinds of errors drive it:

- residuals against the ORIGINAL surface (a measurement, or a closed-loop simulation): pass the
  current (corrected) blocks; the moves accumulate. :func:`correct_iteratively` runs this loop
  around any callable that machines and measures a program.
- predictions, which are relative to the path they were made for (the surface of path P is
  P + e(P)·n): the command that leaves the original surface is the fixed point P = P0 − e(P)·n, so
  the move for the errors predicted on the corrected path is applied to the ORIGINAL blocks with a
  relaxation (``relax``): a vertex whose change does not shrink from round to round takes half its
  step (again halved while it does not contract).

:func:`apply_corrected` turns a ``corrected`` table back into ``blocks`` for the next prediction.
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa

from stages import InputError
from stages.correction.arcs import PLANE_AXES_LUT, arc_sweep, refit_arcs
from stages.correction.moves import (
    EPS_UM,
    LINE_TURN_DEG,
    NORMAL_TOL_DEG,
    gouge_limit,
    node_turn_cos,
    straight_through,
    vertex_moves,
)
from stages.tables import col as _col
from stages.tables import xyz as _xyz

DEFAULTS = {"max_move_um": 50.0, "tol_um": 0.1, "max_iter": 5, "relax": 1.0, "ln_normals": False,
            "comp_table": False, "gouge_limit": True, "normal_tol_deg": None}


# smallest step fraction of a vertex whose rounds do not contract (see correct_once)
MIN_RELAX = 1.0 / 16


def _errors_per_pass(passes: pa.Table, errors: pa.Table):
    """Error, unit normal and has-flag per pass row (passes in pass_id order)."""
    pid = _col(passes, "pass_id", np.int64)
    n = pid.size
    err = np.zeros(n)
    nrm = np.zeros((n, 3))
    has = np.zeros(n, bool)
    if errors is None or errors.num_rows == 0 or n == 0:
        return err, nrm, has
    eid = _col(errors, "pass_id", np.int64)
    order = np.argsort(pid, kind="stable")
    pos = np.searchsorted(pid[order], eid)
    pos_c = np.minimum(pos, n - 1)
    found = pid[order][pos_c] == eid
    if not found.all():
        bad = int(eid[~found][0])
        raise InputError(f"errors.pass_id {bad}: no such pass in the program")
    rows = order[pos_c]
    e = _col(errors, "err_um")
    nn = _xyz(errors, ("nx", "ny", "nz"))
    length = np.linalg.norm(nn, axis=1)
    good = np.isfinite(e) & np.isfinite(length) & (length > 1e-12)
    err[rows[good]] = e[good]
    nrm[rows[good]] = nn[good] / length[good, None]
    has[rows[good]] = True
    return err, nrm, has


def _generating_points(generating: pa.Table, passes: pa.Table):
    """Generating points (mm), unit normals and pass index (into ``passes`` sorted by pass id)."""
    if generating is None or generating.num_rows == 0 or passes.num_rows == 0:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64)
    xyz = _xyz(generating, ("gen_x_mm", "gen_y_mm", "gen_z_mm"))
    n = _xyz(generating, ("nx", "ny", "nz"))
    ids = _col(passes, "pass_id", np.int64)
    gid = _col(generating, "pass_id", np.int64)
    k = np.minimum(np.searchsorted(ids, gid), ids.size - 1)
    ok = (ids[k] == gid) & np.isfinite(xyz).all(axis=1) & np.isfinite(n).all(axis=1)
    n = n[ok] / np.maximum(np.linalg.norm(n[ok], axis=1), 1e-12)[:, None]
    xyz, k = xyz[ok], k[ok]
    return xyz, n, k


def _params(params: dict) -> dict:
    p = dict(DEFAULTS)
    p.update((params or {}).get("correct") or {})
    return p


def _normal_tol(p: dict) -> float:
    """The refinement's normal tolerance, degrees (``correct.normal_tol_deg``, None: the default)."""
    return NORMAL_TOL_DEG if p.get("normal_tol_deg") is None else float(p["normal_tol_deg"])


def correct_once(blocks: pa.Table, passes: pa.Table, errors: pa.Table, params: dict,
                 previous: pa.Table | None = None, relax: float | None = None,
                 generating: pa.Table | None = None, tool_shape=None, design=None) -> pa.Table:
    """One correction round: move every NC vertex of ``blocks`` against ``errors``.

    Parameters
    ----------
    blocks : ``blocks`` table of the program as it is now (the original, or the corrected program
        of the previous round, see :func:`apply_corrected`)
    passes : ``passes`` table split from ``blocks``
    errors : ``errors`` table predicted for ``passes`` (rows may be missing: pruned passes)
    params : dict with ``params["correct"]`` = {max_move_um, ...}
    previous : the ``corrected`` table of the previous round, or None on the first
    relax : None (moves accumulate: residual errors) or, for errors predicted on the corrected path
        (rounds of the fixed point P = P0 − e(P)·n), the largest fraction of the way a vertex goes
        from its previous total move to the one this round computes. A vertex whose change does not
        shrink from one round to the next (the iteration is not contracting there: an error that
        falls faster than the path moves in, or a generating point that jumps between rounds) has
        its fraction halved (down to :data:`MIN_RELAX`) and keeps it; elsewhere it takes the full
        step, so a smooth prediction converges as fast as the plain fixed point
    generating, tool_shape : the ``generating`` table of the ORIGINAL program's passes and the
        tool (:class:`Cutter`): with both, moves are limited so that the tool
        does not cut into the surface other passes generate (:func:`gouge_limit`); else unlimited
    design : the nominal model (:class:`stages.geometry.workpiece.DesignSurface`) or None: its
        samples near the program limit the moves too, as the surfaces of passes of no program
        here (the corners a later program of the job finishes)

    Returns
    -------
    ``corrected`` table: one row per motion block (G0–G3), original and new coordinates (mm),
    new arc centres, total move and this round's change (µm), clipped flag, iteration count.
    """
    from schemas.corrected import SCHEMA
    p = _params(params)
    max_move = float(p["max_move_um"])
    motion_all = _col(blocks, "motion", np.int64) if blocks.num_rows else np.zeros(0, np.int64)
    keep = motion_all <= 3
    blk = blocks.filter(pa.array(keep)) if not keep.all() else blocks
    nb = blk.num_rows
    if nb == 0:
        return SCHEMA.empty_table()
    program_id = blk.column("program_id")
    block_no = _col(blk, "block_no", np.int64)
    motion = motion_all[keep]
    end = _xyz(blk, ("x1_mm", "y1_mm", "z1_mm"))

    passes = passes.sort_by("pass_id") if passes.num_rows else passes
    err, nrm, has = _errors_per_pass(passes, errors)
    n_pass = passes.num_rows
    if n_pass:
        pb0 = _col(passes, "block_no", np.int64)
        pb1 = _col(passes, "block_end", np.int64)
        pend = _xyz(passes, ("x1_mm", "y1_mm", "z1_mm"))
        pstart = _xyz(passes, ("x0_mm", "y0_mm", "z0_mm"))
        # node k: start of pass k (k < P) / end of pass P−1 (k = P); between passes k−1 and k
        has_b = np.concatenate(([False], has))
        has_a = np.concatenate((has, [False]))
        eb, ea = np.concatenate(([0.0], err)), np.concatenate((err, [0.0]))
        nb_, na_ = np.vstack([np.zeros((1, 3)), nrm]), np.vstack([nrm, np.zeros((1, 3))])
        node_move = vertex_moves(eb, nb_, has_b, ea, na_, has_a,
                                 refine=node_turn_cos(pstart, pend)[0] <= np.cos(np.radians(LINE_TURN_DEG)),
                                 along_path=straight_through(pstart, pend), normal_tol_deg=_normal_tol(p))
        node_xyz = np.vstack([pstart, pend[-1:]])
        node_normal = nb_ * has_b[:, None] + na_ * has_a[:, None]
        # vertex → node: the last pass starting at or before the block
        q = np.searchsorted(pb0, block_no, side="right") - 1
        qc = np.maximum(q, 0)
        inside = (q >= 0) & (pb1[qc] > block_no)          # interior vertex of a merged pass
        node = np.where(q < 0, 0, qc + 1)
        move = node_move[node]
        k_in = qc[inside]
        move[inside] = vertex_moves(err[k_in], nrm[k_in], has[k_in], err[k_in], nrm[k_in], has[k_in])
        vnormal = node_normal[node]
        vnormal[inside] = nrm[qc[inside]] * has[qc[inside], None]
        # the vertex's own passes (they set its move; the gouge limit checks the others)
        own = np.stack([node - 1, np.where(node < n_pass, node, -1)], 1)
        own[inside] = qc[inside, None]
        n_own = np.where(has[:, None], nrm, 0.0)
        own_normals = np.where((own >= 0)[..., None], n_own[np.maximum(own, 0)], 0.0)
        # pass coordinates are the tool tip; blocks may be the ball centre (control_point: center)
        frame = np.median(end[~inside] - node_xyz[node[~inside]], axis=0) if (~inside).any() else np.zeros(3)
    else:
        move = np.zeros((nb, 3))
        vnormal = np.zeros((nb, 3))
        node_move = node_xyz = None

    # accumulate over rounds, clip the total move
    if previous is not None and previous.num_rows:
        prev_bn = _col(previous, "block_no", np.int64)
        if prev_bn.size != nb or np.any(prev_bn != block_no):
            raise InputError("corrected: previous round has a different block structure than blocks")
        orig = _xyz(previous, ("x_mm", "y_mm", "z_mm"))
        iteration = int(_col(previous, "iteration", np.int64).max()) + 1
        prev_n = _xyz(previous, ("nx", "ny", "nz"))
        last = _xyz(previous, ("x_new_mm", "y_new_mm", "z_new_mm"))   # the change is against these
    else:
        orig = end.copy()
        iteration = 1
        prev_n = np.full((nb, 3), np.nan)
        last = end
    total_um = (end - orig) * 1000.0 + move
    last_um = (last - orig) * 1000.0
    step = total_um - last_um                   # what this round's errors ask of each vertex
    step_frac = np.ones(nb)
    if previous is not None and previous.num_rows and relax is not None:
        prev_frac = (_col(previous, "relax") if "relax" in previous.column_names else np.ones(nb))
        prev_frac = np.where(np.isfinite(prev_frac), prev_frac, 1.0)
        # the step it asked for last round: its change over the fraction it took
        asked = _col(previous, "change_um") / prev_frac
        contracting = np.linalg.norm(step, axis=1) <= asked * (1 + 1e-9) + EPS_UM
        step_frac = np.minimum(float(relax), np.where(contracting, prev_frac, np.maximum(prev_frac / 2, MIN_RELAX)))
        total_um = last_um + step_frac[:, None] * step
    if previous is not None and previous.num_rows:
        # a vertex no pass of this round predicts (a render lost its pass on the corrected path)
        # keeps the last round's move instead of snapping back to the original program
        stale = np.linalg.norm(vnormal, axis=1) <= 1e-12
        total_um[stale] = (last[stale] - orig[stale]) * 1000.0
    gouge_um = np.zeros(nb)
    if n_pass and tool_shape is not None and (generating is not None or design is not None):
        gen_xyz, gen_n, gen_pass = _generating_points(generating, passes)
        if design is not None:
            reach = tool_shape.radius_mm + max_move / 1000.0
            tips = orig - frame
            d_xyz, d_n = design.samples(tips.min(axis=0) - reach, tips.max(axis=0) + reach + [0, 0, tool_shape.stickout_mm])
            gen_xyz, gen_n = np.concatenate([gen_xyz, d_xyz]), np.concatenate([gen_n, d_n])
            gen_pass = np.concatenate([gen_pass, np.full(len(d_xyz), -2, np.int64)])   # no vertex's own pass
        total_um, gouge_um = gouge_limit(total_um, orig - frame, own, own_normals, gen_xyz, gen_n,
                                         gen_pass, tool_shape)
    size = np.linalg.norm(total_um, axis=1)
    clipped = size > max_move * (1 + 1e-12)
    total_um[clipped] *= (max_move / size[clipped])[:, None]
    new = orig + total_um / 1000.0
    # a full circle (I J K with the end on the start) stays full: its end follows its start, else
    # a tiny difference would turn it into a sliver arc
    arc = (motion == 2) | (motion == 3)
    start_now = _xyz(blk, ("x0_mm", "y0_mm", "z0_mm"))
    full = arc & (np.linalg.norm(end - start_now, axis=1) < 1e-9)
    full[0] = False
    if full.any():
        src = np.maximum.accumulate(np.where(~full, np.arange(nb), 0))
        new[full] = new[src[full]]
        total_um[full] = (new[full] - orig[full]) * 1000.0
        clipped[full] = clipped[src[full]]
    change_um = np.linalg.norm((new - last) * 1000.0, axis=1)

    vlen = np.linalg.norm(vnormal, axis=1)
    vn = np.where(vlen[:, None] > 1e-12, vnormal / np.where(vlen > 1e-12, vlen, 1.0)[:, None], np.nan)
    vn = np.where(np.isnan(vn) & ~np.isnan(prev_n), prev_n, vn)   # keep last round's normal

    centre = np.full((nb, 3), np.nan)
    if arc.any():
        rows = np.flatnonzero(arc)
        plane = _col(blk, "plane", np.int64)[rows]
        ax = PLANE_AXES_LUT[np.clip(plane, 0, 19)]

        def refit():
            c, free = refit_arcs(blk, arc, end, new, max_move, passes, node_move, node_xyz,
                                  frame if n_pass else np.zeros(3))
            centre[arc] = c
            return free

        for _ in range(2):
            free = refit()
            if not free.any():
                break
            # long arcs fitted freely: their end goes back onto the circle (radially, in the plane);
            # the arcs after them are refitted to that end on the next pass
            f, fa = rows[free], ax[free]
            k = np.arange(f.size)
            prev_f = np.vstack([new[:1], new[:-1]])[f]
            c0, c1 = centre[f, fa[:, 0]], centre[f, fa[:, 1]]
            rs = np.hypot(prev_f[k, fa[:, 0]] - c0, prev_f[k, fa[:, 1]] - c1)
            da, db = new[f, fa[:, 0]] - c0, new[f, fa[:, 1]] - c1
            re = np.maximum(np.hypot(da, db), 1e-12)
            new[f, fa[:, 0]] = c0 + da * rs / re
            new[f, fa[:, 1]] = c1 + db * rs / re
        else:
            refit()
        # an arc whose sweep would still jump (a near-180° arc turning to the other side, ...) is
        # translated with its start instead of refitted, and the arc after it refitted
        ccw = motion[rows] == 3
        old_c = _xyz(blk, ("cx_mm", "cy_mm", "cz_mm"))[rows]
        prev_new = np.vstack([new[:1], new[:-1]])[rows]
        s_old = arc_sweep(start_now[rows], end[rows], old_c, plane, ccw)
        s_new = arc_sweep(prev_new, new[rows], centre[rows], plane, ccw)
        jump = np.abs(s_new - s_old) > np.pi / 2
        if jump.any():
            j = rows[jump]
            shift = prev_new[jump] - start_now[j]
            new[j] = end[j] + shift
            centre[j] = old_c[jump] + shift
            follow = np.zeros(nb, bool)
            follow[np.minimum(j + 1, nb - 1)] = True
            follow &= arc
            follow[j] = False
            if follow.any():
                keep_c = centre.copy()
                refit()
                centre[~follow] = keep_c[~follow]
        total_um = (new - orig) * 1000.0
        clipped |= np.linalg.norm(total_um, axis=1) > max_move * (1 + 1e-9)
        change_um = np.linalg.norm((new - last) * 1000.0, axis=1)

    return pa.table({
        "program_id": program_id,
        "block_no": block_no.astype(np.int32),
        "line_no": _col(blk, "line_no", np.int32),
        "motion": motion.astype(np.int8),
        "x_mm": orig[:, 0], "y_mm": orig[:, 1], "z_mm": orig[:, 2],
        "x_new_mm": new[:, 0], "y_new_mm": new[:, 1], "z_new_mm": new[:, 2],
        "cx_new_mm": pa.array(centre[:, 0], mask=~arc), "cy_new_mm": pa.array(centre[:, 1], mask=~arc),
        "cz_new_mm": pa.array(centre[:, 2], mask=~arc),
        "move_um": np.linalg.norm(total_um, axis=1),
        "change_um": change_um,
        "clipped": clipped,
        "gouge_limit_um": gouge_um,
        "iteration": np.full(nb, iteration, np.int32),
        "relax": step_frac,
        "step_x_um": step[:, 0], "step_y_um": step[:, 1], "step_z_um": step[:, 2],
        "nx": vn[:, 0], "ny": vn[:, 1], "nz": vn[:, 2],
        "drift_x_um": np.zeros(nb), "drift_y_um": np.zeros(nb), "drift_z_um": np.zeros(nb),
    }, schema=SCHEMA)


def apply_corrected(blocks: pa.Table, corrected: pa.Table) -> pa.Table:
    """The ``blocks`` table with the new coordinates and arc centres of ``corrected``.

    Start points follow the new end points of the preceding motion block; dwell rows keep their
    place (at the new position of the move before them).
    """
    nb = blocks.num_rows
    if nb == 0 or corrected.num_rows == 0:
        return blocks
    bno = _col(blocks, "block_no", np.int64)
    cbn = _col(corrected, "block_no", np.int64)
    pos = np.searchsorted(cbn, bno)
    posc = np.minimum(pos, cbn.size - 1)
    hit = cbn[posc] == bno
    end = _xyz(blocks, ("x1_mm", "y1_mm", "z1_mm"))
    new = _xyz(corrected, ("x_new_mm", "y_new_mm", "z_new_mm"))
    end[hit] = new[posc[hit]]
    # rows without a corrected row (dwells) stay at the position reached before them
    last = np.maximum.accumulate(np.where(hit, np.arange(nb), -1))
    has_last = last >= 0
    end[~hit & has_last] = end[last[~hit & has_last]]
    start = np.vstack([end[:1], end[:-1]])
    start[0] = end[0]
    cen = _xyz(blocks, ("cx_mm", "cy_mm", "cz_mm"))
    ncen = np.stack([corrected.column(c).to_numpy(zero_copy_only=False).astype(float)
                     for c in ("cx_new_mm", "cy_new_mm", "cz_new_mm")], 1)
    motion = _col(blocks, "motion", np.int64)
    is_arc = (motion == 2) | (motion == 3)
    take = hit & is_arc
    cen[take] = ncen[posc[take]]
    out = blocks
    for i, (c0, c1, cc) in enumerate(zip(("x0_mm", "y0_mm", "z0_mm"), ("x1_mm", "y1_mm", "z1_mm"),
                                         ("cx_mm", "cy_mm", "cz_mm"))):
        out = out.set_column(out.schema.get_field_index(c0), c0, pa.array(start[:, i]))
        out = out.set_column(out.schema.get_field_index(c1), c1, pa.array(end[:, i]))
        out = out.set_column(out.schema.get_field_index(cc), out.schema.field(cc),
                             pa.array(cen[:, i], mask=~is_arc))
    return out


def correct_iteratively(blocks: pa.Table, predict, params: dict, on_round=None) -> pa.Table:
    """Predict → correct → predict again until the largest change is below ``tol_um``.

    Parameters
    ----------
    blocks : the original ``blocks`` table
    predict : callable(blocks) -> (passes, errors): the whole prediction chain on a (corrected)
        program; the caller owns it (split, render, forces, deflection, errors)
    params : dict with ``params["correct"]``
    on_round : optional callable(round, corrected, passes, errors) for reporting

    Returns
    -------
    the last ``corrected`` table (its ``iteration`` column is the number of rounds run).
    """
    p = _params(params)
    corrected = None
    current = blocks
    for k in range(int(p["max_iter"])):
        passes, errors = predict(current)
        corrected = correct_once(current, passes, errors, params, previous=corrected)
        if on_round is not None:
            on_round(k + 1, corrected, passes, errors)
        current = apply_corrected(blocks, corrected)
        change = _col(corrected, "change_um")
        if change.size == 0 or float(change.max()) < float(p["tol_um"]):
            break
    return corrected


def errors_on_passes(errors: pa.Table, passes_from: pa.Table, passes_to: pa.Table) -> pa.Table:
    """Re-key an ``errors`` table from one split of a program to another split of the same blocks.

    A corrected program is split again for its prediction; its passes usually match the original's
    one to one (same ``block_no``/``block_end``), and then the table is returned as it is. Where
    the splitter merged or split differently, each error row goes to the pass of ``passes_to`` in
    the same block whose midpoint is nearest to the midpoint of its own pass; rows without such a
    pass are dropped.
    """
    if errors.num_rows == 0:
        return errors
    target, ok = match_passes(_col(errors, "pass_id", np.int64), passes_from, passes_to)
    if ok is None:
        return errors
    out = errors.filter(pa.array(ok))
    return out.set_column(out.schema.get_field_index("pass_id"), "pass_id",
                          pa.array(target[ok], out.schema.field("pass_id").type))


def match_passes(pass_ids: np.ndarray, passes_from: pa.Table, passes_to: pa.Table):
    """The pass of ``passes_to`` that each pass ``pass_ids`` of ``passes_from`` corresponds to.

    Same block, nearest midpoint (see :func:`errors_on_passes`).

    Returns
    -------
    (target pass ids, found flags); ``(pass_ids, None)`` when both splits are the same.
    """
    def sig(p):
        return (_col(p, "pass_id", np.int64), _col(p, "block_no", np.int64), _col(p, "block_end", np.int64))
    a, b = sig(passes_from.sort_by("pass_id")), sig(passes_to.sort_by("pass_id"))
    if a[0].size == b[0].size and all(np.array_equal(x, y) for x, y in zip(a, b)):
        return pass_ids, None
    from scipy.spatial import cKDTree
    pf, pt = passes_from.sort_by("pass_id"), passes_to.sort_by("pass_id")
    row = np.minimum(np.searchsorted(a[0], pass_ids), max(a[0].size - 1, 0))
    ok = a[0][row] == pass_ids
    k = min(8, pt.num_rows)
    dist, idx = cKDTree(pass_midpoints(pt)).query(pass_midpoints(pf)[row], k=k)
    idx = idx.reshape(row.size, k)
    same = b[1][idx] == a[1][row][:, None]
    first = np.argmax(same, axis=1)
    ok &= same[np.arange(row.size), first]
    return b[0][idx[np.arange(row.size), first]], ok


def pass_midpoints(passes: pa.Table) -> np.ndarray:
    """Midpoint of each pass's chord (mm), in table order."""
    return (_xyz(passes, ("x0_mm", "y0_mm", "z0_mm")) + _xyz(passes, ("x1_mm", "y1_mm", "z1_mm"))) / 2


def with_missing_from(errors: pa.Table, fallback: pa.Table | None) -> pa.Table:
    """``errors`` plus the rows of ``fallback`` (same passes) for passes ``errors`` has no finite error for."""
    if fallback is None or fallback.num_rows == 0:
        return errors
    have = _col(errors, "pass_id", np.int64)[np.isfinite(_col(errors, "err_um"))] if errors.num_rows else np.zeros(0, np.int64)
    add = fallback.filter(pa.array(~np.isin(_col(fallback, "pass_id", np.int64), have)
                                   & np.isfinite(_col(fallback, "err_um"))))
    if add.num_rows == 0:
        return errors
    return pa.concat_tables([errors, add.select(errors.column_names).cast(errors.schema)])
