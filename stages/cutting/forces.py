"""Mechanistic micro-edge cutting-force kernels (DESIGN §7; seed 000 paras 0059–0061).

The tool's flutes are cut into micro-edges, one per axial level of the engagement grid (the cutting
region found by rendering, claim 5). At every rotation step each micro-edge that lies inside the
cutting region removes a chip of thickness ``h`` and feels the Altintas / Lee–Altintas forces::

    dFt = Ktc·h·db + Kte·dS      (tangential, against the cutting speed)
    dFr = Krc·h·db + Kre·dS      (radial, along the envelope normal, pushing the edge out of the cut)
    dFa = Kac·h·db + Kae·dS      (axial, along the envelope generator)

which are rotated into x, y, z and summed over flutes and micro-edges.

Conventions (all angles in degrees in the public API)
-----------------------------------------------------
Feed frame: x_f = feed direction, y_f = 90° counter-clockwise from it seen from above (the left of
the feed), z up along the tool axis, origin at the tool tip.

Position angle φ: angle of a point about the tool axis, counter-clockwise from x_f seen from above
(DESIGN §5); the point is at (r·cos φ, r·sin φ, z).

Spindle angle θ (``rotation_deg`` of the forces/deflection tables): the spindle turns clockwise
seen from above (M3), so a flute's φ *decreases* as θ grows. θ = 0 when the tip end (z = 0) of
flute 0 points along the feed direction. Flute ``j`` (0 … N−1) at height z sits at::

    φ_j(θ, z) = −θ − 360·j/N + lag(z),     lag(z) = z·tan(β)/R  (rad → deg)

(right-hand helix, constant lead: the edge higher up trails the tip end, i.e. sits at larger φ).
θ is proportional to time: t = θ/360 · 60/rpm.

Immersion angle (Altintas) ψ = 90° − φ: measured clockwise from +y_f, ψ = 0 at the left of the
feed (where an up-milling chip starts), 90° ahead of the tool, 180° at the right (where a
down-milling chip ends). Chip thickness ``h = fz·sin ψ·sin κ = fz·cos φ·sin κ`` with κ the axial
immersion angle (angle between the downward tool axis and the outward envelope normal: κ equals the
contact angle q on a ball or corner, 90° on the cylindrical side). Only h > 0 cuts (front half).

Forces returned are the forces **acting on the tool** (the reaction of the cutting force acting on
the workpiece): the tangential force on the tool points along the cutting speed's opposite, the
radial force pushes the tool away from the material, and with a right-hand helix the axial force
pulls the tool down (Fz < 0). In the feed frame (Lee & Altintas 1996 with ψ = 90° − φ)::

    dFx = −dFr·sin κ·cos φ − dFt·sin φ − dFa·cos κ·cos φ
    dFy = −dFr·sin κ·sin φ + dFt·cos φ − dFa·cos κ·sin φ
    dFz = +dFr·cos κ       − dFa·sin κ

Ramps: a pass that climbs or descends moves the tool along the unit vector v = (cos α, 0, sin α)
in the feed frame (α the ramp angle above the horizontal). The chip of an edge point is the feed
per tooth along that edge's outward envelope normal u = (sin κ cos φ, sin κ sin φ, −cos κ)::

    h = fz·(v·u) = fz·(cos α·sin κ·cos φ − sin α·cos κ)

which is Altintas' fz·sin ψ·sin κ for a level pass (α = 0); climbing a wall (α → 90°) the ball's
underside no longer cuts and the side cuts only the small horizontal feed, plunging (α → −90°) the
underside cuts fz·cos κ. With runout the flutes' radial offsets project on u as Δρ·sin κ.

Chip width and edge length: ``db = dS`` = length of the envelope generator (the tool profile in a
meridian plane) between the level's bounds, exact for ball, bull-nose and flat side. So for a
flat end mill db = dS = dz whatever the helix, which is the definition under which Altintas'
mean-force formulas hold (edge coefficients are per unit length of generator; a helical edge is
1/cos β longer — that factor is absorbed by calibration with this same model). The flat bottom
face (κ = 0) is not in the engagement grid (levels are at z > 0) and removes no chip thickness;
its edge rubbing is neglected.

Runout: the rotation axis is offset by ``runout_um`` (eccentricity e) towards flute 0, so flute j
turns on radius R + ρ_j with ρ_j = e·cos(2π j/N) (flute 0 at the maximum). With the clockwise
spindle, flute j+1 passes any angle 360/N before flute j, so the chip of flute j is the material
left by the most recent flute ahead of it, j+m, that cut deeper (Kline–DeVor, generalised)::

    h_j = sin κ · max(0, min_{m=1..N} (m·fz·cos φ + ρ_j − ρ_{j+m}))

Engagement grid (the ``engagement`` table): bool E of shape (n_z, n_phi); E[k, i] is True when the
envelope point at height z_k = (k+0.5)·dz above the tip and angle φ_i = (i+0.5)·360/n_phi is inside
the material being cut. Stored as ``np.packbits(E.ravel())`` (C order).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.geometry.cutter import Cutter

COEFF_NAMES = ("ktc", "krc", "kac", "kte", "kre", "kae")
DEFAULT_N_ROT = 128


def spindle_angle_at(phi_deg, z_mm, flute, cutter: Cutter):
    """Spindle angle θ (deg, in [0, 360)) at which ``flute`` passes position angle φ at height z.

    Inverts φ_j(θ, z) = −θ − 360·j/N + lag(z) (see module docstring).
    """
    theta = -np.asarray(phi_deg, dtype=float) - 360.0 * np.asarray(flute) / cutter.flutes \
        + cutter.helix_lag_deg(z_mm)
    return np.mod(theta, 360.0)


# --------------------------------------------------------------------------------------------
# engagement grid
# --------------------------------------------------------------------------------------------
def pack_engagement(engaged: np.ndarray) -> bytes:
    """Pack one bool grid (n_z, n_phi) as the ``engagement.mask`` column stores it."""
    return np.packbits(np.asarray(engaged, dtype=bool).ravel()).tobytes()


def unpack_engagement(masks, n_z: int, n_phi: int) -> np.ndarray:
    """Unpack ``engagement.mask`` values (packbits of bool (n_z, n_phi), C order).

    Parameters
    ----------
    masks : sequence of bytes, or uint8 array (P, n_bytes)
    n_z, n_phi : int
        Grid shape shared by all rows given.

    Returns
    -------
    ndarray of bool, shape (P, n_z, n_phi)
    """
    n_cells = int(n_z) * int(n_phi)
    n_bytes = (n_cells + 7) // 8
    if isinstance(masks, np.ndarray) and masks.dtype == np.uint8 and masks.ndim == 2:
        raw = masks
    else:
        masks = list(masks)
        if any(len(m) != n_bytes for m in masks):
            raise ValueError(f"engagement mask length differs from ceil({n_z}·{n_phi}/8) = {n_bytes} bytes")
        raw = np.frombuffer(b"".join(masks), dtype=np.uint8).reshape(len(masks), n_bytes)
    bits = np.unpackbits(raw, axis=1, count=n_cells)
    return bits.reshape(len(raw), n_z, n_phi).view(bool)


# --------------------------------------------------------------------------------------------
# micro-edge force model
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class EdgeGrid:
    """Micro-edge geometry of one tool on one engagement grid (one entry per axial level)."""

    z_mm: np.ndarray       # level centres
    kappa_rad: np.ndarray  # axial immersion angle at the centre
    ds_mm: np.ndarray      # generator length of the level (= chip width db = edge length dS)
    lag_deg: np.ndarray    # helix lag of the level centre
    radius_mm: float
    flutes: int


def edge_grid(cutter: Cutter, dz_mm: float, n_z: int) -> EdgeGrid:
    """Micro-edges at the engagement grid's levels z_k = (k+0.5)·dz of ``cutter``."""
    z = (np.arange(n_z) + 0.5) * dz_mm
    _, kappa = cutter.immersion(z)
    s = cutter.generator_length(np.arange(n_z + 1) * dz_mm)
    return EdgeGrid(z_mm=z, kappa_rad=kappa, ds_mm=np.diff(s), lag_deg=cutter.helix_lag_deg(z),
                    radius_mm=cutter.radius_mm, flutes=cutter.flutes)


def rotation_grid_deg(n_rot: int = DEFAULT_N_ROT) -> np.ndarray:
    """Spindle angles θ_i = i·360/n_rot (deg) sampled over one revolution."""
    return np.arange(n_rot) * (360.0 / n_rot)


def flute_positions_deg(grid: EdgeGrid, rotation_deg) -> np.ndarray:
    """φ (deg, in [0, 360)) of every micro-edge: shape (n_rot, flutes, n_z)."""
    theta = np.asarray(rotation_deg, dtype=float)[:, None, None]
    j = np.arange(grid.flutes)[None, :, None]
    return np.mod(-theta - 360.0 * j / grid.flutes + grid.lag_deg[None, None, :], 360.0)


def chip_thickness_mm(fz_mm: float, cos_phi, sin_kappa, rho_mm=None, ramp_deg: float = 0.0):
    """Chip thickness of each flute, shape of ``cos_phi`` (…, flutes, n_z), with runout and ramp.

    ``h_j = max(0, min_m (m·fz·(v·u) + (ρ_j − ρ_{j+m})·sin κ))`` with v·u = cos α·sin κ·cos φ −
    sin α·cos κ (see the module docstring; flute j+m passed m tooth periods before j); on a level
    pass without runout h = fz·cos φ·sin κ clipped at 0.
    """
    cos_phi = np.asarray(cos_phi, dtype=float)
    sin_kappa = np.asarray(sin_kappa, dtype=float)
    if ramp_deg:
        a = np.radians(float(ramp_deg))
        cos_kappa = np.sqrt(np.clip(1.0 - sin_kappa ** 2, 0.0, None))   # κ ≤ 90° on the envelope
        vu = np.cos(a) * sin_kappa * cos_phi - np.sin(a) * cos_kappa
    else:
        vu = sin_kappa * cos_phi
    if rho_mm is None or not np.any(rho_mm):
        return np.maximum(fz_mm * vu, 0.0)
    n = len(rho_mm)
    j = np.arange(n)
    best = None
    for m in range(1, n + 1):
        # flute j+1 passes a given φ 360/N before flute j (φ_j = −θ − 360·j/N): j+m is the m-th
        # flute ahead of j, whose surface j cuts when the ones in between missed
        delta = rho_mm[j] - rho_mm[(j + m) % n]                      # (flutes,)
        cand = m * fz_mm * vu + delta[:, None] * sin_kappa
        best = cand if best is None else np.minimum(best, cand)
    return np.maximum(best, 0.0)


def edge_force_basis(cos_phi, sin_phi, kappa_rad, coeffs: dict):
    """Feed-frame force on the tool per unit chip area and per unit edge length of micro-edges.

    A micro-edge of length ds with chip h (cutting where h > 1e-12, thinner is a rounding remnant
    at ψ = 0 or 180°) carries ``h·ds·cut + ds·edge``, tangential, radial and axial forces
    (kt, kr, ka)·(h·ds) + (kte, kre, kae)·ds turned into x (feed), y, z. Returns (cut, edge),
    each with the shape of ``cos_phi`` and a trailing axis of 3.
    """
    sk, ck = np.sin(kappa_rad), np.cos(kappa_rad)

    def basis(kt, kr, ka):
        return np.stack([-kr * sk * cos_phi - kt * sin_phi - ka * ck * cos_phi,
                         -kr * sk * sin_phi + kt * cos_phi - ka * ck * sin_phi,
                         np.broadcast_to(kr * ck - ka * sk, cos_phi.shape)], axis=-1)

    g = {k: float(coeffs.get(k, 0.0) or 0.0) for k in COEFF_NAMES}
    return basis(g["ktc"], g["krc"], g["kac"]), basis(g["kte"], g["kre"], g["kae"])


def _gather_matmul(packed: np.ndarray, cells: np.ndarray, weights: np.ndarray, out: np.ndarray,
                   rows=None, fz=None, chunk: int = 1024) -> None:
    """out[c, p, i] = Σ_m E[p, cells[i, m]]·W[i, m, c] straight from packed bits, chunked over passes.

    ``packed`` is (P, n_bytes) uint8 (``np.packbits`` of the raveled grids). The grid is never
    unpacked: the byte holding each cell is gathered and its bit kept with a mask; the weights are
    divided by the mask value so that (byte & mask)·W/mask = bit·W. ``out`` is (3, P_all, n_rot),
    written at ``rows`` (default all). With ``fz`` given, W has 6 components (cutting per unit fz,
    then edge) and out = fz·cutting + edge.
    """
    n_pass = packed.shape[0]
    rows = np.arange(n_pass) if rows is None else np.asarray(rows)
    byte = cells >> 3
    mask = (1 << (7 - (cells & 7))).astype(np.uint8)                          # (n_rot, M)
    wt = weights / mask[..., None].astype(float)
    wt = np.ascontiguousarray(wt.transpose(0, 2, 1), dtype=np.float32)         # (n_rot, C, M)
    mask3 = mask[:, :, None]
    for s in range(0, n_pass, chunk):
        pt = np.ascontiguousarray(packed[s:s + chunk].T)                       # (n_bytes, p)
        g = pt[byte]                                                           # (n_rot, M, p)
        np.bitwise_and(g, mask3, out=g)
        f = np.matmul(wt, g.astype(np.float32)).transpose(1, 2, 0)             # (C, p, n_rot)
        if fz is not None:
            f = fz[None, s:s + chunk, None] * f[:3] + f[3:]
        out[:, rows[s:s + chunk], :] = f


def cutting_forces(engaged: np.ndarray, dz_mm: float, fz_mm, cutter: Cutter, coeffs: dict,
                   rotation_deg=None, ramp_deg=0.0) -> np.ndarray:
    """Forces on the tool over one revolution for passes sharing one engagement grid.

    Parameters
    ----------
    engaged : bool ndarray (P, n_z, n_phi)
        Cutting region per pass (see module docstring).
    dz_mm : float
        Level spacing of the grid.
    fz_mm : float or ndarray (P,)
        Feed per tooth of each pass.
    cutter : :class:`stages.geometry.cutter.Cutter` (its runout sets the flutes' offsets)
    coeffs : dict
        ktc, krc, kac (N/mm²), kte, kre, kae (N/mm).
    rotation_deg : array_like, optional
        Spindle angles; default ``rotation_grid_deg(128)``.
    ramp_deg : float or ndarray (P,), optional
        Angle of each pass's feed above the horizontal (+ climbing); see the module docstring.

    Returns
    -------
    ndarray (P, n_rot, 3)
        Fx, Fy, Fz on the tool in the **feed frame** (N); see ``to_machine_frame``. (A view of a
        (3, P, n_rot) array: ``F[..., c]`` is contiguous.)
    """
    engaged = np.asarray(engaged, dtype=bool)
    n_pass, n_z, n_phi = engaged.shape
    packed = np.packbits(engaged.reshape(n_pass, -1), axis=1)
    return cutting_forces_packed(packed, n_z, n_phi, dz_mm, fz_mm, cutter, coeffs, rotation_deg, ramp_deg)


RAMP_STEP_DEG = 0.5     # passes are grouped by ramp angle to this step (h changes by < fz·0.005)


def cutting_forces_packed(packed: np.ndarray, n_z: int, n_phi: int, dz_mm: float, fz_mm, cutter: Cutter,
                          coeffs: dict, rotation_deg=None, ramp_deg=0.0) -> np.ndarray:
    """``cutting_forces`` on grids given as packed bits (P, ceil(n_z·n_phi/8)) uint8, the form the
    ``engagement`` table stores; memory stays O(chunk), whatever P and the grid size.

    The micro-edges' positions over the revolution are computed once; passes are grouped by ramp
    angle (``RAMP_STEP_DEG``), which changes the chip and so the weights, not by pass.
    """
    packed = np.asarray(packed, dtype=np.uint8)
    n_pass = packed.shape[0]
    if packed.ndim != 2 or packed.shape[1] != (n_z * n_phi + 7) // 8:
        raise ValueError(f"packed grids must be (P, {(n_z * n_phi + 7) // 8}) bytes for {n_z}×{n_phi} cells")
    theta = rotation_grid_deg() if rotation_deg is None else np.asarray(rotation_deg, dtype=float)
    fz = np.ascontiguousarray(np.broadcast_to(np.asarray(fz_mm, dtype=float), (n_pass,)))
    if np.any(~(fz > 0)):
        raise ValueError("feed per tooth must be > 0")
    comp = np.zeros((3, n_pass, len(theta)))
    out = np.moveaxis(comp, 0, -1)            # (P, n_rot, 3) view; comp[c] stays contiguous
    if n_pass == 0:
        return out
    # only levels engaged in some pass cost anything (finishing cuts touch a thin band)
    union = np.unpackbits(np.bitwise_or.reduce(packed, axis=0), count=n_z * n_phi).reshape(n_z, n_phi)
    active = np.flatnonzero(union.any(axis=1))
    if active.size == 0:
        return out
    full = edge_grid(cutter, dz_mm, n_z)
    grid = EdgeGrid(full.z_mm[active], full.kappa_rad[active], full.ds_mm[active],
                    full.lag_deg[active], full.radius_mm, full.flutes)
    phi = flute_positions_deg(grid, theta)                          # (n_rot, N, n_active)
    cos_phi, sin_phi = np.cos(np.radians(phi)), np.sin(np.radians(phi))
    bins = np.minimum((phi * (n_phi / 360.0)).astype(np.int64), n_phi - 1)
    cells = (active[None, None, :] * n_phi + bins).reshape(len(theta), -1)
    sin_kappa = np.sin(grid.kappa_rad)
    g_cut, g_edge = edge_force_basis(cos_phi, sin_phi, grid.kappa_rad, coeffs)
    n_rot = len(theta)

    def chips(fz_value, ramp):
        """Chip area h·ds and cutting edge length of each micro-edge, (n_rot, N, n_active, 1)."""
        h = chip_thickness_mm(fz_value, cos_phi, sin_kappa, rho, ramp)
        return (h * grid.ds_mm)[..., None], np.where(h > 1e-12, grid.ds_mm, 0.0)[..., None]

    j = np.arange(grid.flutes)
    rho = (cutter.runout_um * 1e-3) * np.cos(2 * np.pi * j / grid.flutes)
    steps = np.round(np.broadcast_to(np.asarray(ramp_deg, dtype=float), (n_pass,)) / RAMP_STEP_DEG)
    uniq, inv = np.unique(steps, return_inverse=True)
    for g, step in enumerate(uniq):
        sel = np.arange(n_pass) if len(uniq) == 1 else np.flatnonzero(inv.ravel() == g)
        ramp = float(step) * RAMP_STEP_DEG
        if cutter.runout_um == 0.0:
            # without runout the force is linear in fz: F = fz·F(cutting, fz=1) + F(edge)
            area, length = chips(1.0, ramp)
            w = np.concatenate([(area * g_cut).reshape(n_rot, -1, 3), (length * g_edge).reshape(n_rot, -1, 3)], axis=2)
            _gather_matmul(packed[sel], cells, w, comp, rows=sel, fz=fz[sel])
            continue
        # with runout the chip is piecewise in fz: one weight set per distinct feed per tooth
        fu, finv = np.unique(fz[sel], return_inverse=True)
        for u, value in enumerate(fu):
            rows = sel[finv.ravel() == u]
            area, length = chips(float(value), ramp)
            _gather_matmul(packed[rows], cells, (area * g_cut + length * g_edge).reshape(n_rot, -1, 3), comp, rows=rows)
    return out


def to_machine_frame(forces_feed: np.ndarray, feed_dir_x, feed_dir_y) -> np.ndarray:
    """Rotate (…, 3) feed-frame vectors of each pass to the machine frame.

    ``feed_dir`` is the unit feed direction in machine x, y (P,); x_f ↦ (cx, cy), y_f ↦ (−cy, cx).
    """
    c = np.asarray(feed_dir_x, dtype=float)
    s = np.asarray(feed_dir_y, dtype=float)
    norm = np.hypot(c, s)
    norm = np.where(norm > 0, norm, 1.0)
    c, s = (c / norm)[:, None], (s / norm)[:, None]
    out = np.empty_like(forces_feed)
    out[..., 0] = c * forces_feed[..., 0] - s * forces_feed[..., 1]
    out[..., 1] = s * forces_feed[..., 0] + c * forces_feed[..., 1]
    out[..., 2] = forces_feed[..., 2]
    return out


def feed_per_tooth_mm(feed_mm_min, spindle_rpm, flutes: int):
    """fz = F / (S·N)."""
    return np.asarray(feed_mm_min, dtype=float) / (np.asarray(spindle_rpm, dtype=float) * flutes)
