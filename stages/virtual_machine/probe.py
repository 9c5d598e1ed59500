"""Probing the machined surface: discrete tooth passages cut every plan point; the probe plan.

Every plan point p (normal n) is cut by discrete tooth passages: for each flute and the spindle
revolutions :data:`PASSAGES` around the time the nominal centre passes p, the flute's sphere (radius
R less the tool's measured shape error ``tool.profile`` at the contact angle and the effects'
profile changes; centre = path position at that instant + deflection at the spindle angle of the
passage + the effects' machine offsets + flute offset ρ along the contact direction) removes
material. The surface left along n is the lowest entry of the ray p + s·n into any of these
spheres; the deviation is s (µm, positive = material left, DESIGN §5) plus probe noise.
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from stages.geometry.paths import path_point
from stages.virtual_machine.effects import machine_offsets, radius_loss

# passes whose tooth passages a probe point is tested against (the nearest ones). 1: the surface at
# a point is that of the pass nearest it (as the closed forms of tests/test_gap.py assume). 3 is the
# more physical probe between rows (the deepest of the neighbours' cuts) but it also shows what a
# correction along the normal cannot remove: the tangential part of the deflection shifts the cusps
# between rows (3-level cylinder of tests/test_iterate.py at 1 N/µm: 9.6 % with 1, 23 % with 3;
# seed's 51-level cylinder bench: 16 % with 3) -- kept switchable, see the issue-5 note
PROBE_PASSES = 1
PASSAGES = (-1, 0, 1)   # spindle revolutions around the nominal passage that cut each point


def machined_deviation(vm, pts: np.ndarray, normals: np.ndarray, effects: Optional[dict] = None,
                       noise_um: float = 0.0, rng: Optional[np.random.Generator] = None,
                       probe_passes: int = PROBE_PASSES, deflection=None) -> np.ndarray:
    """Deviation of the machined surface at each plan point along its normal.

    Parameters
    ----------
    vm : VirtualMachine
        The loaded machine (path, tool, stations and their deflection).
    pts, normals : (n, 3) float
        Plan points (mm) and outward normals.
    effects : dict, optional
        Effect name → parameters (``effects.EFFECTS``).
    noise_um : float
        Standard deviation of the probe noise added.
    rng : numpy Generator, optional
        For the noise.
    probe_passes : int
        How many of the nearest passes' tooth passages cut each point (:data:`PROBE_PASSES`).
    deflection : (dx, dy), optional
        Deflection (µm, (stations, n_rot) each) to cut with instead of the machine's own, e.g. one
        a test prescribes; a ``force_scale`` effect scales it.

    Returns
    -------
    (n,) float
        µm, + = material left.
    """
    effects = effects or {}
    if len(pts) == 0:
        return np.zeros(0)
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    cstar = pts + vm.R * n
    rows, us = near_passes(vm.path, cstar, probe_passes)
    ro = effects.get("runout", {})
    e_um, ph = float(ro.get("e_um", 0.0)), float(ro.get("phase_deg", 0.0))
    rho = vm.flute_offsets(e_um + vm.base_runout, ph)
    scale = float(effects.get("force_scale", {}).get("scale", 1.0))
    if deflection is None:
        dx_rev, dy_rev = vm.deflection(e_um, ph, scale)
    else:
        dx_rev, dy_rev = (np.asarray(v, float) * scale for v in deflection)
    # the surface is the deepest cut of the passes whose centres pass nearest (a point between
    # two rows, or at a pass end, may be finished by the neighbour)
    best = np.min(np.stack([_surface(vm, pts, n, rows[:, k], us[:, k], rho, dx_rev, dy_rev, effects)
                            for k in range(rows.shape[1])]), axis=0)
    err = best * 1e3
    if noise_um > 0:
        rng = rng or np.random.default_rng()
        err = err + rng.normal(0.0, noise_um, len(err))
    return err


def _surface(vm, pts, n, row, u, rho, dx_rev, dy_rev, effects):
    """Entry depth (mm along n) of the ray p + s·n into the flutes' spheres of pass ``row`` near ``u``."""
    p = vm.path
    R, Z = vm.R, vm.flutes
    n_rot = dx_rev.shape[1]
    d = p.c1 - p.c0
    ln = p.length
    T = 60.0 / p.rpm[row]
    t_star = p.t0[row] + u * (p.t1[row] - p.t0[row])
    v = ln[row] / np.maximum(p.t1[row] - p.t0[row], 1e-12)             # mm/s along the pass
    q = np.degrees(np.arccos(np.clip(n[:, 2], -1, 1)))
    alpha = np.arctan2(-n[:, 1], -n[:, 0])                              # azimuth of the contact point
    feed_ang = np.arctan2(d[row, 1], d[row, 0])
    phi_c = (alpha - feed_ang) % (2 * np.pi)                            # from the feed direction
    zc = R * (1 - n[:, 2].clip(-1, 1))
    lag = zc * math.tan(vm.helix) / R
    best = np.full(len(pts), np.inf)
    theta_star = (360.0 * t_star / T) % 360.0
    for j in range(Z):
        # spindle angle at which flute j passes φ_C at height zc: φ = −θ − 360 j/Z + lag
        th = np.degrees(-phi_c - 2 * np.pi * j / Z + lag) % 360.0
        dt0 = ((th - theta_star + 180.0) % 360.0 - 180.0) / 360.0 * T
        for m in PASSAGES:
            t = t_star + dt0 + m * T
            s_along = u * ln[row] + (t - t_star) * v
            # the centre continues into the neighbouring passes instead of extrapolating a pass
            c, at = path_point(p, p.s0[row] + s_along)
            st = vm.stations.at(at, p.s0[row] + s_along)
            # the deflection of the pass the tool is on at that passage: a passage a
            # revolution beyond the end of a short pass is on its neighbour, and after a
            # pocket corner's 120 µm the next pass's own small deflection there over-cut.
            # Each pass's revolution is indexed from its own feed direction (θ_rel = Θ +
            # feed angle, Θ the spindle's machine-frame angle): read the neighbour's at the
            # same instant, th + its turn (in the own pass's frame, a 94° corner read it
            # 94° off in the tooth cycle: −5 µm where +4 µm was right)
            turn = np.degrees(np.arctan2(d[at, 1], d[at, 0]) - feed_ang)
            fi = ((th + turn) % 360.0) / 360.0 * n_rot
            i0 = np.floor(fi).astype(np.int64) % n_rot
            w = fi - np.floor(fi)
            i1 = (i0 + 1) % n_rot
            ddx = (1 - w) * dx_rev[st, i0] + w * dx_rev[st, i1]
            ddy = (1 - w) * dy_rev[st, i0] + w * dy_rev[st, i1]
            off = np.stack([ddx, ddy, np.zeros_like(ddx)], 1) * 1e-3
            off += rho[j] * np.stack([np.cos(alpha), np.sin(alpha), np.zeros_like(alpha)], 1)
            radius = np.full(len(pts), R)
            off += machine_offsets(effects, p, c, row, s_along / ln[row], t, R)
            cut_len = p.L0[row] + np.clip(s_along, 0, None)
            radius -= radius_loss(effects, q, cut_len, vm.profile) * 1e-3
            cp = c + off - pts
            a = np.einsum("ij,ij->i", cp, n)
            perp2 = np.einsum("ij,ij->i", cp, cp) - a * a
            disc = radius * radius - perp2
            s_lo = np.where(disc >= 0, a - np.sqrt(np.maximum(disc, 0)), np.inf)
            best = np.minimum(best, s_lo)
    return best


def near_passes(path, cstar: np.ndarray, k_pass: int):
    """The ``k_pass`` distinct passes whose centre segments are nearest each point.

    Parameters
    ----------
    path : Path3
    cstar : (n, 3) float
        Ball-centre positions (a plan point + R·normal).
    k_pass : int

    Returns
    -------
    rows, u : (n, k_pass) int and float
        Pass rows (nearest first; later passes first among ties) and the parameter of the nearest
        point on each; with fewer distinct passes in reach, the nearest is repeated.
    """
    from scipy.spatial import cKDTree
    p = path
    ln = p.length
    nsub = np.maximum(1, np.ceil(ln / 0.25).astype(np.int64))
    owner, frac = _subsamples(nsub)
    kk = min(32, len(owner))
    _, cand = cKDTree(p.c0[owner] + frac[:, None] * (p.c1 - p.c0)[owner]).query(cstar, k=kk)
    cand = owner[np.asarray(cand).reshape(len(cstar), kk)]
    a, ab = p.c0[cand], (p.c1 - p.c0)[cand]
    u = np.clip(np.einsum("pkj,pkj->pk", cstar[:, None, :] - a, ab)
                / np.maximum(np.einsum("pkj,pkj->pk", ab, ab), 1e-30), 0, 1)
    dist = np.linalg.norm(a + u[..., None] * ab - cstar[:, None, :], axis=2)
    # one entry per pass (its nearest sub-sample), later passes first among ties
    score = dist - 1e-7 * cand / max(len(ln), 1)
    o = np.argsort(cand + score / (score.max() + 1.0) * 0.5, axis=1)
    cs = np.take_along_axis(cand, o, 1)
    first = np.concatenate([np.ones((len(cand), 1), bool), cs[:, 1:] != cs[:, :-1]], axis=1)
    sc = np.where(first, np.take_along_axis(score, o, 1), np.inf)
    pick = np.argsort(sc, axis=1)[:, :k_pass]
    rows = np.take_along_axis(cs, pick, 1)
    uu = np.take_along_axis(np.take_along_axis(u, o, 1), pick, 1)
    # fewer distinct passes than asked: repeat the nearest
    bad = ~np.isfinite(np.take_along_axis(sc, pick, 1))
    rows = np.where(bad, rows[:, :1], rows)
    uu = np.where(bad, uu[:, :1], uu)
    return rows, uu


def _subsamples(nsub: np.ndarray):
    """Equal sub-samples of every pass: (owner row, fraction along it at the sub-sample's middle)."""
    owner = np.repeat(np.arange(len(nsub)), nsub)
    frac = (np.arange(nsub.sum()) - np.repeat(np.cumsum(nsub) - nsub, nsub) + 0.5) / np.repeat(nsub, nsub)
    return owner, frac


def grid_plan(vm, spacing_mm: float = 0.5, k: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """Probe points along the cutting passes' contact lines when no plan is given.

    The surface normal is that of the ball-centre surface (the offset surface has the part's
    normals): the smallest principal axis of the ``k`` nearest centre samples (0.1 mm apart along
    the passes, so ``k`` must reach the neighbouring rows: with 12 the samples of one row are
    collinear and the normal is any direction across it), turned up (3-axis ball: the contact is
    on the lower half) and made normal to the pass.

    Parameters
    ----------
    vm : VirtualMachine
    spacing_mm : float
        Distance between points along a pass.
    k : int
        Centre samples the normal is fitted to.

    Returns
    -------
    points, normals : (n, 3) float
        Only where the stock was cut (the surface exists) and no other pass cut deeper.
    """
    from scipy.spatial import cKDTree
    p = vm.path
    ln = p.length
    nsub = np.maximum(1, np.floor(ln / spacing_mm).astype(np.int64))
    owner, frac = _subsamples(nsub)
    c = p.c0[owner] + frac[:, None] * (p.c1 - p.c0)[owner]
    dense_n = np.maximum(1, np.ceil(ln / 0.1).astype(np.int64))
    o2, f2 = _subsamples(dense_n)
    cloud = p.c0[o2] + f2[:, None] * (p.c1 - p.c0)[o2]
    _, nb = cKDTree(cloud).query(c, k=min(k, len(cloud)))
    nbp = cloud[nb] - cloud[nb].mean(axis=1, keepdims=True)
    cov = np.einsum("pki,pkj->pij", nbp, nbp)
    _, vec = np.linalg.eigh(cov)
    n = vec[:, :, 0]
    n = np.where(n[:, 2:3] < 0, -n, n)
    # a ball touches the surface in the plane normal to its motion
    t = (p.c1 - p.c0)[owner] / np.maximum(ln[owner], 1e-12)[:, None]
    n = n - np.einsum("ij,ij->i", n, t)[:, None] * t
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    pts = c - vm.R * n
    # keep points where the stock was cut (the surface exists) and that no other pass cut deeper:
    # at the edge of a raster the fitted normal tilts and puts the point on the flank of the last
    # row, which its neighbour has cut away (100+ µm above the finished surface)
    keep = pts[:, 2] < vm.stock_h(pts[:, 0], pts[:, 1])
    near = cKDTree(cloud).query_ball_point(pts, vm.R - 0.005, return_length=True)
    keep &= near == 0
    return pts[keep], n[keep]
