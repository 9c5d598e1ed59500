"""The machining error a pass leaves at its generating point (DESIGN §5, §7; seed 000 paras 0072–0073).

For the generating point C of a pass (φ_C, q_C, n_C) and each flute j::

    e_j = (dx, dy, 0)(θ_Cj)·n_C  −  ρ_j·sin q_C          (µm)
    err = min_j e_j + shape_error(q_C)

- θ_Cj is the spindle angle at which flute j passes φ_C at C's height z_C
  (:func:`stages.cutting.forces.spindle_angle_at`); the deflection over one revolution is read
  there (periodic linear interpolation).
- Sign: n points out of the material and the deflection is that of the tool, along the force acting
  on the tool. A tool pushed away from the wall (d·n > 0) cuts less: material left, positive error.
- Runout: flute j turns on radius R + ρ_j (ρ_j = e·cos(2πj/N)); moving the edge out by ρ_j along the
  tool radius moves the surface into the material by ρ_j·sin q. The deepest flute leaves the surface.
- The deepest tooth passage leaves it too: C is also swept by the passages of the neighbouring
  passes within ``passages.PASSAGE_REVS`` revolutions of feed, each with its own pass's deflection;
  the error is the minimum of their stand-off from C plus their error at C (:func:`deepest_passage`).
- Shape error: the tool profile table (claim 2, CSV ``contact_deg,error_um``, + = the tool is smaller
  than nominal = material left), interpolated at q_C, held constant beyond its ends. A profile
  measured on the *rotating* tool already contains −e·sin q: give ``runout_um: 0`` with it.

The height z_C of C above the tip (it sets the helix lag): on the corner (q < 90°) rc(1 − cos q); on
the side (q = 90°, always for a flat end mill) gen_z − tip z of the pass at the point nearest C.
"""
from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pyarrow as pa

from stages import InputError
from stages.cutting import passages as pe
from stages.cutting.forces import (
    COEFF_NAMES,
    cutting_forces,
    feed_per_tooth_mm,
    spindle_angle_at,
)
from stages.geometry.cutter import Cutter
from stages.geometry.passes import CONTINUE_DEG
from stages.tables import list_values, match_passes


# --------------------------------------------------------------------------------------------
# tool profile table (claim 2)
# --------------------------------------------------------------------------------------------
@functools.lru_cache(maxsize=16)
def _read_profile_cached(path: str, mtime: float):
    lines = Path(path).read_text().splitlines()
    if not lines:
        raise InputError(f"{path}:1: empty tool profile (expected header contact_deg,error_um)")
    header = [h.strip().lower() for h in lines[0].split(",")]
    if "contact_deg" not in header or "error_um" not in header:
        raise InputError(f"{path}:1: tool profile header must name contact_deg and error_um, got {lines[0]!r}")
    iq, ie = header.index("contact_deg"), header.index("error_um")
    q, e = [], []
    for n, line in enumerate(lines[1:], start=2):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.split(",")
        try:
            q.append(float(parts[iq]))
            e.append(float(parts[ie]))
        except (ValueError, IndexError):
            raise InputError(f"{path}:{n}: expected numbers contact_deg,error_um, got {line!r}") from None
    if not q:
        raise InputError(f"{path}: tool profile has no rows")
    q, e = np.array(q), np.array(e)
    if np.any(np.diff(q) <= 0):
        raise InputError(f"{path}: contact_deg must be strictly ascending")
    return q, e


def read_profile(path) -> tuple[np.ndarray, np.ndarray]:
    """Read a tool profile CSV (contact_deg, error_um) → (q_deg, error_um) ascending."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"tool.profile: no such file {path}")
    return _read_profile_cached(str(p.resolve()), p.stat().st_mtime)


def shape_error_um(contact_deg, profile) -> np.ndarray:
    """Tool shape error (µm, + = material left) at contact angles q; 0 when ``profile`` is None."""
    q = np.asarray(contact_deg, dtype=float)
    if profile is None:
        return np.zeros_like(q)
    pq, pe = profile
    return np.interp(q, pq, pe)


# --------------------------------------------------------------------------------------------
# kernel
# --------------------------------------------------------------------------------------------
def periodic_interp(values: np.ndarray, theta_deg: np.ndarray) -> np.ndarray:
    """Linear interpolation of (P, n) samples at θ_i = i·360/n, at angles ``theta_deg`` (P, …)."""
    n = values.shape[1]
    pos = np.mod(theta_deg, 360.0) * (n / 360.0)
    i0 = np.floor(pos).astype(np.int64)
    w = pos - i0
    i0 %= n
    i1 = (i0 + 1) % n
    rows = np.arange(values.shape[0]).reshape((-1,) + (1,) * (theta_deg.ndim - 1))
    return (1 - w) * values[rows, i0] + w * values[rows, i1]


def machining_error(dx_um, dy_um, phi_c_deg, contact_deg, normal, z_c_mm, cutter: Cutter, profile=None):
    """Error at the generating point of each pass (see module docstring).

    Parameters
    ----------
    dx_um, dy_um : ndarray (P, n_rot)
        Tool deflection over one revolution at θ_i = i·360/n_rot, machine frame.
    phi_c_deg, contact_deg : ndarray (P,)
        φ_C (feed frame, CCW from the feed) and q_C of the generating point.
    normal : ndarray (P, 3)
        Unit surface normal at C (out of the material), machine frame.
    z_c_mm : ndarray (P,)
        Height of C above the tool tip.
    cutter : :class:`stages.geometry.cutter.Cutter`
    profile : (q_deg, error_um) or None

    Returns
    -------
    dict of ndarray (P,): err_deflection_um, defl_x_um, defl_y_um (the tool's deflection vector at
    the generating flute's passage, whose projection on n is err_deflection_um), err_runout_um,
    err_shape_um, err_um, spindle_deg, flute
    """
    j = np.arange(cutter.flutes)
    phi = np.asarray(phi_c_deg, dtype=float)
    q = np.asarray(contact_deg, dtype=float)
    n = np.asarray(normal, dtype=float)
    theta = spindle_angle_at(phi[:, None], np.asarray(z_c_mm, float)[:, None], j[None, :], cutter)  # (P, N)
    ddx = periodic_interp(np.asarray(dx_um, float), theta)
    ddy = periodic_interp(np.asarray(dy_um, float), theta)
    e_def = ddx * n[:, 0:1] + ddy * n[:, 1:2]
    rho_um = cutter.flute_offsets_mm() * 1e3
    e_run = -rho_um[None, :] * np.sin(np.radians(np.clip(q, 0.0, 90.0)))[:, None]
    total = e_def + e_run
    # the deepest flute leaves the surface; NaN rows (no generating point) stay NaN
    best = np.argmin(np.where(np.isnan(total), np.inf, total), axis=1)
    rows = np.arange(len(best))
    shape = shape_error_um(q, profile)
    return {
        "err_deflection_um": e_def[rows, best],
        "defl_x_um": ddx[rows, best],
        "defl_y_um": ddy[rows, best],
        "err_runout_um": e_run[rows, best],
        "err_shape_um": shape,
        "err_um": total[rows, best] + shape,
        "spindle_deg": theta[rows, best],
        "flute": best.astype(np.int32),
    }


def contact_height_mm(cutter: Cutter, contact_deg, gen_z_mm, tip_z_mm) -> np.ndarray:
    """Height of the generating point above the tip: on the corner from q, on the side from z."""
    rc = cutter.corner_mm
    q = np.asarray(contact_deg, dtype=float)
    on_side = ~(q < 89.999) | (rc <= 0)
    side = np.maximum(np.asarray(gen_z_mm, float) - np.asarray(tip_z_mm, float), rc)
    return np.where(on_side, side, cutter.corner_height(q))


def tip_z_nearest(passes: pa.Table, rows: np.ndarray, gen_xyz: np.ndarray) -> np.ndarray:
    """Tip z of each pass at the point of its segment nearest the generating point."""
    p0 = np.stack([passes.column(c).to_numpy()[rows] for c in ("x0_mm", "y0_mm", "z0_mm")], axis=1)
    p1 = np.stack([passes.column(c).to_numpy()[rows] for c in ("x1_mm", "y1_mm", "z1_mm")], axis=1)
    seg = p1 - p0
    ll = np.einsum("ij,ij->i", seg, seg)
    t = np.where(ll > 0, np.einsum("ij,ij->i", gen_xyz - p0, seg) / np.where(ll > 0, ll, 1), 0.0)
    t = np.clip(t, 0.0, 1.0)
    return p0[:, 2] + t * seg[:, 2]


def second_contact_error(gen: pa.Table, passes: pa.Table, rows: np.ndarray, dx, dy, cutter: Cutter, profile) -> dict:
    """Error at each pass's second contact (``generating``'s ``*2`` columns; NaN where it has none,
    or the table has no such columns): the same kernel with the pass's own deflection, read where a
    flute passes the second contact (no neighbouring passage: the contacts that need a second point
    are those of a ball in a corner, where the pass's own passages leave both walls)."""
    cols = ("gen2_x_mm", "gen2_y_mm", "gen2_z_mm", "nx2", "ny2", "nz2", "contact2_deg", "rotation2_deg")
    n = gen.num_rows
    out = {k: np.full(n, np.nan) for k in ("err2_um", "nx2", "ny2", "nz2", "contact2_deg")}
    if not all(c in gen.column_names for c in cols):
        return out
    v = {c: gen.column(c).to_numpy(zero_copy_only=False).astype(float) for c in cols}
    ok = np.isfinite(v["contact2_deg"]) & np.isfinite(dx).all(axis=1)
    if not ok.any():
        return out
    xyz = np.stack([v["gen2_x_mm"], v["gen2_y_mm"], v["gen2_z_mm"]], axis=1)[ok]
    normal = np.stack([v["nx2"], v["ny2"], v["nz2"]], axis=1)[ok]
    q = v["contact2_deg"][ok]
    tip_z = tip_z_nearest(passes, rows[ok], xyz) - cutter.control_offset_mm
    res = machining_error(dx[ok], dy[ok], v["rotation2_deg"][ok], q, normal,
                          contact_height_mm(cutter, q, xyz[:, 2], tip_z), cutter, profile)
    out["err2_um"][ok] = res["err_um"]
    out["nx2"][ok], out["ny2"][ok], out["nz2"][ok] = normal.T
    out["contact2_deg"][ok] = q
    return out


PAIR_CHUNK = 50_000     # (point, neighbouring pass) pairs per chunk: bounds the deflection rows held


def deepest_passage(res: dict, finished_by: np.ndarray, passes: pa.Table, rows: np.ndarray,
                    gen_xyz: np.ndarray, normal: np.ndarray, defl: pa.Table, cutter: Cutter, profile) -> None:
    """Replace each generating point's error by the deepest tooth passage of the neighbouring passes
    within ``PASSAGE_REVS`` revolutions of feed along the path, where one cuts deeper (in place).

    Only passes with a deflection row take part (the others' force is not known: pruned or not
    cutting). See :mod:`stages.cutting.passages`.
    """
    pcol = lambda c: passes.column(c).to_numpy(zero_copy_only=False).astype(float)  # noqa: E731
    tip0 = np.stack([pcol("x0_mm"), pcol("y0_mm"), pcol("z0_mm")], 1)
    tip1 = np.stack([pcol("x1_mm"), pcol("y1_mm"), pcol("z1_mm")], 1)
    tip0[:, 2] -= cutter.control_offset_mm
    tip1[:, 2] -= cutter.control_offset_mm
    n_p = passes.num_rows
    order_p = np.argsort(passes.column("pass_id").to_numpy(), kind="stable")   # execution order
    inv = np.empty(n_p, np.int64)
    inv[order_p] = np.arange(n_p)
    tip0, tip1 = tip0[order_p], tip1[order_p]
    feed_move = passes.column("motion").to_numpy(zero_copy_only=False)[order_p] != 0
    d_rows = match_passes(passes, defl.column("pass_id").to_numpy().astype(np.int64), "deflection")
    has_defl = np.zeros(n_p, bool)
    has_defl[inv[d_rows]] = True
    dx_all = np.zeros((n_p, list_values(defl.column("dx_um"), "deflection.dx_um").shape[1]))
    dy_all = np.zeros_like(dx_all)
    dx_all[inv[d_rows]] = list_values(defl.column("dx_um"), "deflection.dx_um")
    dy_all[inv[d_rows]] = list_values(defl.column("dy_um"), "deflection.dy_um")
    s0, chain = pe.path_chains(tip0, tip1, feed_move)
    length = np.linalg.norm(tip1 - tip0, axis=1) * feed_move
    usable = feed_move & has_defl
    owner = inv[rows]
    ok = usable[owner]
    if not ok.any():
        return
    d_own, t_own, _, _, n_own = pe.sweep_distance(gen_xyz, tip0[owner], tip1[owner], cutter)
    s_c = s0[owner] + t_own * length[owner]
    flutes = cutter.flutes
    # C is the mean of surviving pixels, microns inside or off the pass's own nominal envelope (the
    # sagitta of the patch): the stand-offs are measured from C moved onto it
    c_on = gen_xyz - d_own[:, None] * n_own
    f_rev = (pcol("feed_mm_min")[order_p] / np.maximum(pcol("spindle_rpm")[order_p], 1e-9))[owner]
    reach = np.where(ok, pe.PASSAGE_REVS * f_rev, -1.0)
    r, j, ta, tb = pe.passage_pairs(owner, s_c, reach, s0, length, chain, has_defl)
    if r.size == 0:
        return
    own_dir = tip1[owner] - tip0[owner]
    own_dir /= np.maximum(np.linalg.norm(own_dir, axis=1, keepdims=True), 1e-12)
    cos_continue = np.cos(np.radians(CONTINUE_DEG))
    pos_own = tip0[owner] + t_own[:, None] * (tip1[owner] - tip0[owner])   # the tool nearest C

    def passage(sl):
        """Stand-off, error parts and contact angle of the pairs ``sl``, and whether the pair is a
        passage at all (see below)."""
        jj, rr = j[sl], r[sl]
        seg = tip1[jj] - tip0[jj]
        a, b = tip0[jj] + ta[sl, None] * seg, tip0[jj] + tb[sl, None] * seg
        dist, t, q, height, _ = pe.sweep_distance(c_on[rr], a, b, cutter)
        rel = c_on[rr] - (a + t[:, None] * (b - a))
        phi = np.degrees(np.arctan2(rel[:, 1], rel[:, 0]) - np.arctan2(seg[:, 1], seg[:, 0]))
        e = machining_error(dx_all[jj], dy_all[jj], phi, q, normal[rr], height, cutter, profile)
        # A neighbour that carries the pass's own line on (a piece of the same line, split for
        # length or at a via point) is nearest C at its end, where the tool does not stop: the
        # passages over C are spaced a tooth's feed apart along the line, the nearest within half
        # of it from C's own position, and those farther off are the pass's own. Read at that end
        # the neighbour's deflection comes at a spindle angle the azimuth of the offset away (on
        # the seed's cylinder at q 10.7° a 0.25 mm offset turns it 7.7°, and the deflection there
        # swings 100 µm in a revolution), and the deepest of them would make a line cut into
        # 0.5 mm passes leave another surface than the line itself. Such a passage counts only
        # within half a tooth's feed of the tool's position nearest C along the line, where it is
        # real (``tests/test_passage_envelope.py``).
        cont = np.einsum("ij,ij->i", seg, own_dir[rr]) > cos_continue * np.linalg.norm(seg, axis=1)
        at_end = (t <= 1e-9) | (t >= 1.0 - 1e-9)
        along = np.einsum("ij,ij->i", a + t[:, None] * (b - a) - pos_own[rr], own_dir[rr])
        off_tooth = np.abs(along) > 0.5 * f_rev[rr] / flutes + 1e-6
        real = ~(cont & at_end & off_tooth)
        return dist * 1000.0, e, q, real

    # the deepest passage per point, over chunks of pairs (memory: a chunk's deflection rows)
    best_total = np.full(len(rows), np.inf)
    best_pair = np.full(len(rows), -1, np.int64)
    for c0 in range(0, r.size, PAIR_CHUNK):
        sl = np.arange(c0, min(c0 + PAIR_CHUNK, r.size))
        off, e, _, real = passage(sl)
        total = np.where(real, off + e["err_um"], np.inf)
        o = np.lexsort((total, r[sl]))
        first = np.concatenate([[True], r[sl][o][1:] != r[sl][o][:-1]])
        cb = o[first]
        better = total[cb] < best_total[r[sl][cb]]
        best_total[r[sl][cb][better]] = total[cb][better]
        best_pair[r[sl][cb][better]] = sl[cb][better]
    win = (best_pair >= 0) & (best_total < res["err_um"])
    k = np.flatnonzero(win)
    if not k.size:
        return
    w = best_pair[k]
    off, e, q, _ = passage(w)
    res["err_deflection_um"][k] = e["err_deflection_um"] + off   # the stand-off counts as material left
    res["defl_x_um"][k] = e["defl_x_um"]
    res["defl_y_um"][k] = e["defl_y_um"]
    res["err_runout_um"][k] = e["err_runout_um"]
    res["err_shape_um"][k] = e["err_shape_um"]
    res["err_um"][k] = off + e["err_um"]
    res["contact_deg"][k] = q
    res["spindle_deg"][k] = e["spindle_deg"]
    res["flute"][k] = e["flute"]
    finished_by[k] = passes.column("pass_id").to_numpy()[order_p][j[w]]


# --------------------------------------------------------------------------------------------
# analytic benchmark: error vs contact angle on a wall finished by a ball end mill (seed Fig. 19)
# --------------------------------------------------------------------------------------------
def wall_engagement(radius_mm: float, contact_deg: float, step_mm: float, stock_mm: float,
                    n_z: int = 64, n_phi: int = 360, side: str = "right") -> tuple[np.ndarray, float]:
    """Cutting region of a ball end mill finishing a wall inclined at q (analytic, no rendering).

    Feed along +x (feed frame = machine frame); the wall is on the ``side`` of the feed ('right':
    φ = −90°, down milling with M3; 'left': φ = +90°, up milling), tangent to the ball at contact
    angle q. The material before the pass is
    everything within ``stock_mm`` of the nominal wall, minus the groove of the previous pass, whose
    ball centre lies ``step_mm`` up along the wall. Only the front half cuts (the back half is in the
    groove of the previous tooth).

    Returns
    -------
    engaged : bool (n_z, n_phi), dz_mm : float
    """
    R = float(radius_mm)
    q = np.radians(contact_deg)
    dz = R / n_z                                   # levels over the ball only
    z = (np.arange(n_z) + 0.5) * dz
    phi = np.radians((np.arange(n_phi) + 0.5) * 360.0 / n_phi)
    r, _ = Cutter("ball", R, R).immersion(z)
    sign = {"right": -1.0, "left": 1.0}[side]
    u = sign * r[:, None] * np.sin(phi)[None, :]   # toward the wall
    w = (z - R)[:, None] * np.ones_like(phi)[None, :]
    # height of the point above the nominal wall plane (along its normal, 0 at the contact point;
    # every point of the ball is ≥ 0): inside the stock layer when below stock_mm
    height = -u * np.sin(q) + w * np.cos(q) + R
    in_stock = height < stock_mm
    cu, cw = step_mm * np.cos(q), step_mm * np.sin(q)
    outside_prev = (u - cu) ** 2 + (w - cw) ** 2 > R * R
    front = np.cos(phi)[None, :] > 0
    return in_stock & outside_prev & front, dz


def error_vs_contact_angle(contact_deg, cutter: Cutter, material: dict, frf: dict, feed_mm_min: float,
                           spindle_rpm: float, step_mm: float = 0.3, stock_mm: float = 0.1,
                           n_z: int = 64, n_phi: int = 360, profile=None, side: str = "right") -> dict:
    """Predicted error on walls inclined at each contact angle q, ball end mill (seed Fig. 19 check).

    Chains the analytic cutting region (``wall_engagement``), the force model, the FFT deflection
    and ``machining_error`` with C at φ = ∓90°, q, normal (0, ±sin q, cos q) for a wall on the
    right/left of the feed. The seed's cylinder (Fig. 16: Ø20 ball, 2 flutes, 6000 min⁻¹,
    0.4 mm/tooth, 0.2 mm stock, 0.63 mm pitch, zigzag) alternates both sides.
    """
    from stages.cutting.frf import tool_deflection
    if cutter.kind != "ball":
        raise ValueError("error_vs_contact_angle models a ball end mill")
    qs = np.atleast_1d(np.asarray(contact_deg, dtype=float))
    R = cutter.radius_mm
    grids = []
    for qd in qs:
        e, dz = wall_engagement(R, qd, step_mm, stock_mm, n_z, n_phi, side)
        grids.append(e)
    engaged = np.stack(grids)
    fz = feed_per_tooth_mm(feed_mm_min, spindle_rpm, cutter.flutes)
    coeffs = {k: float(material.get(k) or 0.0) for k in COEFF_NAMES}
    f = cutting_forces(engaged, dz, fz, cutter, coeffs)
    rpm = np.full(len(qs), float(spindle_rpm))
    d = tool_deflection(f, rpm, frf)
    qr = np.radians(qs)
    sign = {"right": 1.0, "left": -1.0}[side]
    normal = np.stack([np.zeros_like(qr), sign * np.sin(qr), np.cos(qr)], axis=1)
    res = machining_error(d[..., 0], d[..., 1], np.full(len(qs), -90.0 * sign), qs, normal,
                          cutter.corner_height(qs), cutter, profile)
    res["contact_deg"] = qs
    res["forces_n"] = f
    return res
