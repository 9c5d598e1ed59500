"""Virtual machine: an independent, higher-fidelity simulation of machining that writes "measured" data.

It exists to test the gap diagnosis (DESIGN §8.5, issue 7): it machines the programs' passes with
its own models and probes the finished surface at the points of a measurement plan, optionally with
unmodelled effects switched on. It shares nothing with the prediction path (``cutting``, ``frf``,
``forces``, ``deflection``, ``errors``, ``generating``, ``render``); it reads parsed passes only.

Model (all vectorised over passes / points)
-------------------------------------------
- Engagement: micro-edges of the ball (``N_Z`` levels) and of the cylindrical side up to the
  stick-out (every ``SHANK_DZ_MM``), × ``N_PHI`` position angles, at each pass's mid point (or, with
  ``deflection_step_mm``, at the mid point of each of its equal pieces of at most that length, so
  that the deflection's resolution along the path does not follow the program's blocks) are in
  the material when they lie below the stock (a height field rasterised from the stock mesh, or
  the box) and outside the tool (ball and side) swept along every earlier pass (exact distances to
  the candidate passes from a plan-view KD-tree).
- Forces: discrete flutes with helix lag; chip ``h_j = max(0, min_m(m·fz·(v·u) + (ρ_j − ρ_{j+m})·sin κ))``
  with v the 3-D feed direction, u the edge's outward normal (v·u = sin κ cos φ on a level pass)
  and the flutes' radial offsets ρ_j (runout); Lee–Altintas tangential / radial / axial forces.
- Dynamics: each mode (x and y) integrated in the time domain with the exact zero-order-hold
  state-transition matrix from rest until the free response has died out; the last revolution is
  the periodic deflection of the pass or piece (no FFT, no frequency-domain compliance).
- Surface: every plan point p (normal n) is cut by discrete tooth passages: for each flute and the
  spindle revolutions around the time the nominal centre passes p, the flute's sphere (radius R
  less the tool's measured shape error ``tool.profile`` at the contact angle, and the effects'
  profile changes, centre = path position at that instant + deflection at the
  spindle angle of the passage + the effects' machine offsets + flute offset ρ along the contact
  direction) removes material; the surface left along n is the lowest entry of the ray p + s·n
  into any of these spheres. ``err_um`` = s (positive = material left, DESIGN §5) + probe noise.

Effects (name, parameters, signature on the measured deviation r)
-----------------------------------------------------------------
- ``runout``: ``e_um`` (radial runout of the largest flute), ``phase_deg``: ρ_j = e·cos(2πj/N + phase);
  the largest flute cuts the surface: r ≈ −ρ_max·sin q; also changes the chip of each flute.
- ``tool_contour``: ``a_um``, ``q0_deg``, ``width_deg``: profile error w(q) = a·exp(−½((q−q0)/width)²),
  positive = tool smaller there (seed 002 sign): r = +w(q).
- ``tool_wear``: ``rate_um_per_m``: radius loss = rate·L (L = cut length so far, m): r = +rate·L.
- ``thermal_drift``: ``ax_um``, ``ay_um``, ``az_um``, ``tau_s``: tool offset A·(1 − exp(−t/τ)):
  r = n·A·(1 − exp(−t/τ)).
- ``force_scale``: ``scale``: every cutting coefficient × scale (mis-calibrated material): the
  deflection part of the error scales by it.
- ``servo_corner``: ``a_um``, ``lambda_mm``: near a path corner of angle θ the tool lags towards the
  inside of the turn (unit bisector b) by a·sin(θ/2)/sin(45°)·exp(−d/λ), d = path distance to the
  corner: r = (b·n)·that.
- ``machine_geometry``: ``sx``, ``sy``, ``sz`` (scale, µm/mm), ``exy``, ``exz``, ``eyz`` (squareness,
  µm/mm): tool offset dx = sx·x + exy·y + exz·z, dy = sy·y + eyz·z, dz = sz·z at the tool tip
  position (machine frame): r = n·offset.
"""
from __future__ import annotations

import math
import os
from typing import Optional

import numpy as np
import pyarrow as pa

from stages import InputError
from stages.geometry.paths import CORNER_DEG, Path3, corner_features, nearest_pass, program_paths  # noqa: F401

# Grid fine enough that the simulated error has converged: a finishing crescent is only a few
# tenths of a millimetre wide, and on a coarser grid (30 × 96 × 96) the error jumped by ±5 µm from
# pass to pass on the seed's cylinder; at 120 × 360 × 192 it is within 0.5 µm of 240 × 720 × 192.
N_Z = 120         # micro-edge levels over the ball
N_PHI = 360       # position angles of the engagement grid
N_ROT = 192       # spindle angle samples per revolution
SHANK_DZ_MM = 0.25  # micro-edge length on the cylindrical side (walls: mm-long straight contacts)
# passes whose tooth passages a probe point is tested against (the nearest ones). 1: the surface at
# a point is that of the pass nearest it (as the closed forms of tests/test_gap.py assume). 3 is the
# more physical probe between rows (the deepest of the neighbours' cuts) but it also shows what a
# correction along the normal cannot remove: the tangential part of the deflection shifts the cusps
# between rows (3-level cylinder of tests/test_iterate.py at 1 N/µm: 9.6 % with 1, 23 % with 3;
# seed's 51-level cylinder bench: 16 % with 3) -- kept switchable, see the issue-5 note
PROBE_PASSES = 1
PASSAGES = (-1, 0, 1)   # spindle revolutions around the nominal passage that cut each point
STEP_SLACK = 0.005      # fraction of a deflection step a pass may exceed a whole number of steps by
K_NEAR = 8              # engagement: sub-segments tested first for each micro-edge (a speed-up only; 0: none)

EFFECTS = {
    "runout": ("e_um", "phase_deg"),
    "tool_contour": ("a_um", "q0_deg", "width_deg"),
    "tool_wear": ("rate_um_per_m",),
    "thermal_drift": ("ax_um", "ay_um", "az_um", "tau_s"),
    "force_scale": ("scale",),
    "servo_corner": ("a_um", "lambda_mm"),
    "machine_geometry": ("sx", "sy", "sz", "exy", "exz", "eyz"),
}
DEFAULTS = {
    "runout": {"e_um": 5.0, "phase_deg": 0.0},
    "tool_contour": {"a_um": 5.0, "q0_deg": 30.0, "width_deg": 10.0},
    "tool_wear": {"rate_um_per_m": 20.0},
    "thermal_drift": {"ax_um": 0.0, "ay_um": 0.0, "az_um": -10.0, "tau_s": 600.0},
    "force_scale": {"scale": 1.5},
    "servo_corner": {"a_um": 10.0, "lambda_mm": 0.5},
    "machine_geometry": {"sx": 0.0, "sy": 0.0, "sz": 0.0, "exy": 0.0, "exz": 0.0, "eyz": 0.0},
}


def parse_effect(text: str) -> tuple[str, dict]:
    """``NAME:key=value,...`` → (name, params with defaults filled); InputError naming what is wrong."""
    name, _, rest = text.partition(":")
    name = name.strip()
    if name not in EFFECTS:
        raise InputError(f"--effect {text!r}: unknown effect {name!r} (known: {', '.join(EFFECTS)})")
    params = dict(DEFAULTS[name])
    for item in filter(None, (s.strip() for s in rest.split(","))):
        k, eq, v = item.partition("=")
        if not eq or k.strip() not in EFFECTS[name]:
            raise InputError(f"--effect {text!r}: {item!r} is not key=value with key in {EFFECTS[name]}")
        try:
            params[k.strip()] = float(v)
        except ValueError:
            raise InputError(f"--effect {text!r}: {k.strip()}={v!r} is not a number") from None
    if name == "force_scale" and not params["scale"] > 0:
        raise InputError(f"--effect {text!r}: scale must be > 0")
    if name == "thermal_drift" and not params["tau_s"] > 0:
        raise InputError(f"--effect {text!r}: tau_s must be > 0")
    if name == "servo_corner" and not params["lambda_mm"] > 0:
        raise InputError(f"--effect {text!r}: lambda_mm must be > 0")
    if name == "runout" and params["e_um"] < 0:
        raise InputError(f"--effect {text!r}: e_um must be >= 0")
    return name, params


# ----------------------------------------------------------------------------------- stock
def stock_height_fn(stock, cell_mm: float = 0.05):
    """z_top(x, y) of the stock (3-axis: the highest up-facing surface); -inf outside it."""
    if isinstance(stock, dict) and "box" in stock:
        x0, y0, z0, x1, y1, z1 = [float(v) for v in stock["box"]]

        def box_h(x, y):
            inside = (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
            return np.where(inside, z1, -np.inf)
        return box_h
    import trimesh
    path = os.fspath(stock)
    if not os.path.exists(path):
        raise InputError(f"{path}: stock model not found")
    m = trimesh.load(path, force="mesh")
    tris = np.asarray(m.triangles, float)
    nz = np.asarray(m.face_normals)[:, 2]
    tris = tris[nz > 1e-6]
    lo = tris.min(axis=(0, 1))
    hi = tris.max(axis=(0, 1))
    nx = int(np.ceil((hi[0] - lo[0]) / cell_mm)) + 1
    ny = int(np.ceil((hi[1] - lo[1]) / cell_mm)) + 1
    H = np.full(nx * ny, -np.inf)
    # cells whose centre lies in each triangle's bounding box, tested by barycentric coordinates
    i0 = np.floor((tris[:, :, 0].min(1) - lo[0]) / cell_mm).astype(np.int64)
    i1 = np.ceil((tris[:, :, 0].max(1) - lo[0]) / cell_mm).astype(np.int64)
    j0 = np.floor((tris[:, :, 1].min(1) - lo[1]) / cell_mm).astype(np.int64)
    j1 = np.ceil((tris[:, :, 1].max(1) - lo[1]) / cell_mm).astype(np.int64)
    wi, wj = i1 - i0 + 1, j1 - j0 + 1
    cnt = wi * wj
    for start in range(0, len(tris), 20000):
        sl = slice(start, start + 20000)
        c = cnt[sl]
        t = np.repeat(np.arange(start, min(start + 20000, len(tris))), c)
        loc = np.arange(c.sum()) - np.repeat(np.cumsum(c) - c, c)
        ii = i0[t] + loc % wi[t]
        jj = j0[t] + loc // wi[t]
        ok = (ii >= 0) & (ii < nx) & (jj >= 0) & (jj < ny)
        t, ii, jj = t[ok], ii[ok], jj[ok]
        px, py = lo[0] + ii * cell_mm, lo[1] + jj * cell_mm
        a, b, cc = tris[t, 0], tris[t, 1], tris[t, 2]
        v0x, v0y = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
        v1x, v1y = cc[:, 0] - a[:, 0], cc[:, 1] - a[:, 1]
        v2x, v2y = px - a[:, 0], py - a[:, 1]
        den = v0x * v1y - v1x * v0y
        den = np.where(np.abs(den) > 1e-15, den, np.nan)
        l1 = (v2x * v1y - v1x * v2y) / den
        l2 = (v0x * v2y - v2x * v0y) / den
        inside = (l1 >= -1e-9) & (l2 >= -1e-9) & (l1 + l2 <= 1 + 1e-9)
        z = a[:, 2] + l1 * (b[:, 2] - a[:, 2]) + l2 * (cc[:, 2] - a[:, 2])
        np.maximum.at(H, (jj * nx + ii)[inside], z[inside])
    H = H.reshape(ny, nx)

    def mesh_h(x, y):
        fi = (np.asarray(x) - lo[0]) / cell_mm
        fj = (np.asarray(y) - lo[1]) / cell_mm
        i = np.clip(np.floor(fi).astype(np.int64), 0, nx - 2)
        j = np.clip(np.floor(fj).astype(np.int64), 0, ny - 2)
        tx, ty = np.clip(fi - i, 0, 1), np.clip(fj - j, 0, 1)
        with np.errstate(invalid="ignore"):
            h = ((1 - tx) * (1 - ty) * H[j, i] + tx * (1 - ty) * H[j, i + 1]
                 + (1 - tx) * ty * H[j + 1, i] + tx * ty * H[j + 1, i + 1])
        out = (fi < 0) | (fi > nx - 1) | (fj < 0) | (fj > ny - 1)
        return np.where(out | ~np.isfinite(h), -np.inf, h)
    return mesh_h


# ----------------------------------------------------------------------------------- machine
def machine_modes(frf: Optional[dict], axis: str) -> list[tuple[float, float, float]]:
    """Modes (fn_hz, zeta, k_n_per_um) of one axis; a measured table is fitted (:func:`fit_modes`)."""
    if not frf:
        raise InputError("machine.frf: the virtual machine needs the machine's compliance (modes or table)")
    if frf.get(axis):
        return [(float(m["fn_hz"]), float(m["zeta"]), float(m["k_n_per_um"])) for m in frf[axis]]
    from stages.tables import read_numeric_csv
    tab = read_numeric_csv(frf["table"], ["freq_hz", f"{axis}{axis}_re", f"{axis}{axis}_im"], "FRF table")
    modes = fit_modes(tab[:, 0], tab[:, 1] + 1j * tab[:, 2])
    if not modes:
        raise InputError(f"{frf['table']}: no resonance peak in {axis}{axis} (−Im of the compliance)")
    return modes


def modal_frf(f_hz, modes) -> np.ndarray:
    """Compliance (µm/N) of a sum of modes: G = Σ 1/(k(1 − r² + 2iζr)), r = f/fn."""
    f = np.asarray(f_hz, float)
    return sum(1.0 / (k * (1 - (f / fn) ** 2 + 2j * z * f / fn)) for fn, z, k in modes)


def fit_modes(f_hz, G, prominence: float = 0.05) -> list[tuple[float, float, float]]:
    """Modes of a measured compliance FRF (standard modal identification).

    Peaks of −Im G that stand out of the measurement noise (prominence at least ``prominence`` of
    the largest) start the modes: fn at the peak, ζ from the half-power width, k from the peak
    height (−Im G = 1/(2ζk) at fn). All modes are then fitted jointly to the complex FRF by least
    squares. Every local maximum of a noisy peak is not a mode: counting each as one multiplied the
    compliance of the sample table by 5 (static) to 15 (at 2.4 kHz).
    """
    from scipy.optimize import least_squares
    from scipy.signal import find_peaks
    f = np.asarray(f_hz, float)
    G = np.asarray(G, complex)
    im = -G.imag
    if not np.any(im > 0):
        return []
    pk, _ = find_peaks(im, prominence=prominence * im.max())
    x0 = []
    for p in pk:
        half = im[p] / 2
        lo, hi = p, p
        while lo > 0 and im[lo] > half:
            lo -= 1
        while hi < len(im) - 1 and im[hi] > half:
            hi += 1
        zeta = float(np.clip((f[hi] - f[lo]) / (2 * f[p]), 1e-3, 0.5))
        x0 += [f[p], np.log(zeta), np.log(1.0 / (2 * zeta * im[p]))]
    if not x0:
        return []

    def modes_of(x):
        return [(x[i], np.exp(x[i + 1]), np.exp(x[i + 2])) for i in range(0, len(x), 3)]

    def resid(x):
        d = modal_frf(f, modes_of(x)) - G
        return np.concatenate([d.real, d.imag])
    sol = least_squares(resid, np.array(x0, float), x_scale="jac")
    return [(float(a), float(b), float(c)) for a, b, c in modes_of(sol.x)]


def simulate_deflection(force: np.ndarray, rpm: np.ndarray, modes) -> np.ndarray:
    """Periodic deflection (µm) over the last revolution, time-domain modal integration from rest.

    force: (P, N_ROT) newton on the tool, repeating every revolution; exact ZOH discretisation of
    u'' + 2ζωn u' + ωn² u = ωn²/k · F for each mode.
    """
    out = np.zeros_like(force)
    for r in np.unique(rpm):
        sel = np.flatnonzero(rpm == r)
        T = 60.0 / r
        dt = T / force.shape[1]
        for fn, zeta, k in modes:
            wn = 2 * np.pi * fn
            A = np.array([[0.0, 1.0], [-wn * wn, -2 * zeta * wn]])
            from scipy.linalg import expm
            M = expm(np.block([[A, np.array([[0.0], [wn * wn / k]])], [np.zeros((1, 3))]]) * dt)
            Phi, Gam = M[:2, :2], M[:2, 2]
            n_rev = int(np.ceil(12.0 / (zeta * wn * T))) + 1
            x = np.zeros((len(sel), 2))
            f = force[sel]
            last = np.zeros((len(sel), force.shape[1]))
            for rev in range(n_rev):
                for i in range(force.shape[1]):
                    if rev == n_rev - 1:
                        last[:, i] = x[:, 0]
                    x = x @ Phi.T + f[:, i:i + 1] * Gam[None, :]
            out[sel] += last
    return out


def _inside_tool(x, a, ab, R, side):
    """Is point x inside the tool swept along the ball-centre segment a → a + ab (per row)?

    The tool is a ball of radius R on a cylinder of radius R reaching ``side`` above the centre.
    Ball: distance to the segment < R. Side: for the part of the segment whose centre height lies
    in [x_z − side, x_z], the plan-view distance to it < R.
    """
    ab2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-30)
    u = np.clip(np.einsum("ij,ij->i", x - a, ab) / ab2, 0, 1)
    ball = np.linalg.norm(a + u[:, None] * ab - x, axis=1) < R - 1e-6
    dz = ab[:, 2]
    flat = np.abs(dz) < 1e-12
    with np.errstate(divide="ignore", invalid="ignore"):
        s_a = np.where(flat, 0.0, (x[:, 2] - side - a[:, 2]) / dz)
        s_b = np.where(flat, 1.0, (x[:, 2] - a[:, 2]) / dz)
    lo = np.clip(np.minimum(s_a, s_b), 0, 1)
    hi = np.clip(np.maximum(s_a, s_b), 0, 1)
    level_ok = np.where(flat, (x[:, 2] >= a[:, 2]) & (x[:, 2] <= a[:, 2] + side),
                        np.maximum(s_a, s_b) >= 0) & (np.minimum(s_a, s_b) <= 1)
    abxy2 = np.maximum(np.einsum("ij,ij->i", ab[:, :2], ab[:, :2]), 1e-30)
    w = np.clip(np.einsum("ij,ij->i", (x - a)[:, :2], ab[:, :2]) / abxy2, lo, hi)
    cyl = level_ok & (np.linalg.norm(a[:, :2] + w[:, None] * ab[:, :2] - x[:, :2], axis=1) < R - 1e-6)
    return ball | cyl


# ----------------------------------------------------------------------------------- machine model
class VirtualMachine:
    """One program machined on the virtual machine; effects are applied per call of ``probe``."""

    def __init__(self, passes: pa.Table, tool: dict, material: dict, machine: dict, stock,
                 deflection_step_mm: Optional[float] = None):
        if tool["type"] != "ball":
            raise InputError(f"tool.type {tool['type']!r}: the virtual machine models ball-nose tools only")
        self.R = float(tool["diameter_mm"]) / 2
        self.flutes = int(tool["flutes"])
        self.helix = math.radians(float(tool.get("helix_deg") or 0.0))
        # the flutes run up the side to the stick-out (the same tool the prediction describes)
        self.stickout = float(tool.get("stickout_mm") or 4 * self.R)
        self.base_runout = float(tool.get("runout_um") or 0.0)
        # the real tool's shape (claim 2 table: contact_deg, error_um; + = tool smaller there)
        self.profile = None
        if tool.get("profile"):
            from stages.tables import read_numeric_csv
            tab = read_numeric_csv(tool["profile"], ["contact_deg", "error_um"], "tool.profile")
            o = np.argsort(tab[:, 0])
            self.profile = (tab[o, 0], tab[o, 1])
        self.coeffs = {k: float(material.get(k) or 0.0) for k in ("ktc", "krc", "kac", "kte", "kre", "kae")}
        frf = (machine or {}).get("frf")
        self.modes = {"x": machine_modes(frf, "x"), "y": machine_modes(frf, "y")}
        paths = program_paths(passes, self.R, tool.get("control_point", "tip"))
        if len(paths) != 1:
            raise InputError(f"virtual machine: one program at a time, got {len(paths)}")
        self.path = paths[0]
        if len(self.path.pass_id) == 0:
            raise InputError(f"{self.path.program_id}: no cutting moves to machine")
        self.stock_h = stock_height_fn(stock)
        self._stations(deflection_step_mm)
        self._engaged = self._engagement()
        self._defl_cache: dict = {}

    # -- deflection stations ----------------------------------------------------------------------
    def _stations(self, step_mm: Optional[float]):
        """The pieces of the passes the machine takes one engagement and deflection each for.

        ``None``: one per pass (its mid point). A step: every pass cut into equal pieces of at most
        ``step_mm`` (within :data:`STEP_SLACK`), so that the deflection's resolution along the path
        no longer follows the program's blocks (a line cut in two at a via point, or written as one
        block, machines the same; one deflection for a 4 mm climb whose foot is buried in a corner
        is not).
        """
        p = self.path
        ln = p.length
        if step_mm is None:
            n = np.ones(len(ln), np.int64)
        else:
            if not step_mm > 0:
                raise InputError(f"virtual machine: deflection_step_mm must be > 0, got {step_mm!r}")
            # a pass up to STEP_SLACK of a piece longer than a whole number of pieces keeps that
            # number: the machine's resolution must not jump where a via point moved by a µm
            # lengthens a 0.5 mm pass by a nanometre (it doubled there, and at the cylinder's stock
            # end, where the deflection falls 6 µm a piece, the surface jumped by µm)
            n = np.maximum(1, np.ceil(ln / float(step_mm) - STEP_SLACK).astype(np.int64))
        row = np.repeat(np.arange(len(ln)), n)
        k = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
        f0, f1 = k / n[row], (k + 1) / n[row]
        d = p.c1 - p.c0
        self.st_pass = row                                   # station -> pass (row of the path)
        self.st_first = np.cumsum(n) - n                     # pass -> its first station
        self.st_count = n
        self.st_mid = p.c0[row] + (0.5 * (f0 + f1))[:, None] * d[row]
        self.st_s0 = p.s0[row] + f0 * ln[row]                # path length where each station begins

    def _station_at(self, row, s_glob):
        """Station of pass ``row`` at path length ``s_glob`` (clamped to the pass's own stations)."""
        i = np.searchsorted(self.st_s0, s_glob, side="right") - 1
        return np.clip(i, self.st_first[row], self.st_first[row] + self.st_count[row] - 1)

    # -- engagement of every station at its mid point ---------------------------------------------
    def _edge_grid(self):
        """Micro-edge levels: N_Z over the ball (uniform in height), then the cylindrical side every
        SHANK_DZ_MM up to the tool's stick-out. Returns (zc, kappa, ds) per level."""
        R = self.R
        zc = (np.arange(N_Z) + 0.5) * R / N_Z                       # heights above the tip
        kappa = np.arccos(np.clip(1 - zc / R, -1, 1))             # axial immersion = contact angle
        ds = R * (np.arccos(np.clip(1 - (zc + 0.5 * R / N_Z) / R, -1, 1))
                  - np.arccos(np.clip(1 - (zc - 0.5 * R / N_Z) / R, -1, 1)))
        n_side = int(np.ceil(max(self.stickout - R, 0.0) / SHANK_DZ_MM))
        zs = R + (np.arange(n_side) + 0.5) * SHANK_DZ_MM
        return (np.concatenate([zc, zs]), np.concatenate([kappa, np.full(n_side, np.pi / 2)]),
                np.concatenate([ds, np.full(n_side, SHANK_DZ_MM)]))

    def _engagement(self, max_points: int = 400_000):
        """Engaged micro-edges at each station's mid point: (S, levels, N_PHI // 8) packed bits.

        A micro-edge is engaged when it lies below the stock's top and outside the tool (ball and
        cylindrical side up to the stick-out) of every earlier pass. Only the levels below the
        stock's top around a pass are tested (a finishing pass touches a thin band; a wall pass
        its height); memory is bounded by ``max_points``.
        """
        from scipy.spatial import cKDTree
        p = self.path
        R = self.R
        zc, kappa, _ = self._edge_grid()
        n_lev = len(zc)
        phi = (np.arange(N_PHI) + 0.5) * 2 * np.pi / N_PHI              # from the feed direction, CCW
        d = p.c1 - p.c0
        P = len(d)
        ln = p.length
        st = self.st_pass
        mid = self.st_mid
        S = len(mid)
        ang0 = np.arctan2(d[st, 1], d[st, 0])
        # levels that can touch the stock: below the highest stock top on the tool's outer ring
        ring = np.linspace(0.0, 2 * np.pi, 73)[:-1]
        top = np.max(self.stock_h(mid[:, None, 0] + R * np.cos(ring), mid[:, None, 1] + R * np.sin(ring)), axis=1)
        top = np.maximum(top, self.stock_h(mid[:, 0], mid[:, 1]))
        height = top - (mid[:, 2] - R)                                    # above the tip
        n_of = np.where(np.isfinite(height), np.searchsorted(zc, height, side="right"), 0).astype(np.int64)
        # earlier passes as exact sub-segments of at most 2 mm, found by their plan-view midpoints
        nsub = np.maximum(1, np.ceil(ln / 2.0).astype(np.int64))
        sub_owner = np.repeat(np.arange(P), nsub)
        k_sub = np.arange(nsub.sum()) - np.repeat(np.cumsum(nsub) - nsub, nsub)
        sub_ab = d[sub_owner] / nsub[sub_owner, None]
        sub_a = p.c0[sub_owner] + k_sub[:, None] * sub_ab
        tree = cKDTree((sub_a + 0.5 * sub_ab)[:, :2])
        tree3 = cKDTree(sub_a + 0.5 * sub_ab)
        reach = R + 0.5 * float((ln / nsub).max()) + 1e-6
        side = self.stickout - R                                          # cylinder above the centre
        eng = np.zeros((S, n_lev, (N_PHI + 7) // 8), np.uint8)
        rad = np.where(kappa < np.pi / 2 - 1e-12, R * np.sin(kappa), R)
        dzc = zc - R                                                      # relative to the centre
        cost = np.cumsum(n_of * N_PHI)
        s0 = 0
        while s0 < S:
            s1 = int(np.searchsorted(cost, (cost[s0 - 1] if s0 else 0) + max_points, side="right"))
            s1 = min(max(s1, s0 + 1), S)
            rows = np.repeat(np.arange(s0, s1), n_of[s0:s1])                 # (pass, level) pairs
            lev = np.arange(len(rows)) - np.repeat(np.cumsum(n_of[s0:s1]) - n_of[s0:s1], n_of[s0:s1])
            if len(rows):
                a_ = ang0[rows][:, None] + phi[None, :]
                pts = np.stack(np.broadcast_arrays(mid[rows, None, 0] + rad[lev, None] * np.cos(a_),
                                                   mid[rows, None, 1] + rad[lev, None] * np.sin(a_),
                                                   mid[rows, None, 2] + dzc[lev, None]), -1).reshape(-1, 3)
                owner = np.repeat(rows, N_PHI)
                inside = pts[:, 2] < self.stock_h(pts[:, 0], pts[:, 1]) - 1e-9
                removed = np.zeros(len(pts), bool)
                cand_idx = np.flatnonzero(inside)
                if cand_idx.size and K_NEAR:
                    # most points below the stock top were cut by a row just before: test the
                    # nearest sub-segments in space first, and only the points none of those
                    # removed against every earlier sub-segment in reach (the same answer: a
                    # removal is a removal, and any sub-segment that removes a point is in reach)
                    k_near = min(K_NEAR, len(sub_a))
                    _, near = tree3.query(pts[cand_idx], k=k_near)
                    pi = np.repeat(cand_idx, k_near)
                    sj = near.reshape(-1)
                    ok = sub_owner[sj] < st[owner[pi]]
                    pi, sj = pi[ok], sj[ok]
                    removed[pi[_inside_tool(pts[pi], sub_a[sj], sub_ab[sj], R, side)]] = True
                    cand_idx = cand_idx[~removed[cand_idx]]
                if cand_idx.size:
                    sdm = tree.sparse_distance_matrix(cKDTree(pts[cand_idx, :2]), reach, output_type="ndarray")
                    sj, pi = sdm["i"].astype(np.int64), cand_idx[sdm["j"]]
                    ok = sub_owner[sj] < st[owner[pi]]          # earlier passes only
                    pi, sj = pi[ok], sj[ok]
                    removed[pi[_inside_tool(pts[pi], sub_a[sj], sub_ab[sj], R, side)]] = True
                E = (inside & ~removed).reshape(-1, N_PHI)
                eng[rows, lev] = np.packbits(E, axis=1)
            s0 = s1
        return eng

    # -- forces and deflection --------------------------------------------------------------------
    def deflection(self, runout_e_um: float = 0.0, runout_phase_deg: float = 0.0, scale: float = 1.0):
        """(dx, dy) µm over one revolution per station (per pass without a deflection step), at
        spindle angles θ_i = i·360/N_ROT."""
        key = (round(runout_e_um, 6), round(runout_phase_deg, 6))
        if key not in self._defl_cache:
            self._defl_cache[key] = self._deflection(runout_e_um, runout_phase_deg)
        dx, dy = self._defl_cache[key]
        return dx * scale, dy * scale

    def flute_offsets(self, e_um: float, phase_deg: float) -> np.ndarray:
        j = np.arange(self.flutes)
        return e_um * 1e-3 * np.cos(2 * np.pi * j / self.flutes + math.radians(phase_deg))

    def _deflection(self, e_um, phase_deg):
        fx, fy = self.forces(e_um, phase_deg)
        rpm = self.path.rpm[self.st_pass]
        return (simulate_deflection(fx, rpm, self.modes["x"]),
                simulate_deflection(fy, rpm, self.modes["y"]))

    def forces(self, e_um: float = 0.0, phase_deg: float = 0.0):
        """Machine-frame (fx, fy) in N on the tool over one revolution per station (θ_i = i·360/N_ROT)."""
        zc, kappa, ds = self._edge_grid()
        Z = self.flutes
        theta = np.arange(N_ROT) * 2 * np.pi / N_ROT
        lag = zc * math.tan(self.helix) / self.R
        # position angle from the feed direction of flute j, level l at spindle angle θ (clockwise spindle)
        phi = (-theta[:, None, None] - 2 * np.pi * np.arange(Z)[None, :, None] / Z + lag[None, None, :]) % (2 * np.pi)
        rho = self.flute_offsets(e_um + self.base_runout, phase_deg)
        cphi, sphi = np.cos(phi), np.sin(phi)
        ibin = np.minimum((phi / (2 * np.pi) * N_PHI).astype(np.int64), N_PHI - 1)
        S = len(self.st_pass)
        fx, fy = np.zeros((S, N_ROT)), np.zeros((S, N_ROT))
        for s0 in range(0, S, 32):                               # memory bounded by the chunk
            sl = slice(s0, min(s0 + 32, S))
            fx[sl], fy[sl] = self._forces(sl, cphi, sphi, ibin, rho, kappa, ds)
        return fx, fy

    def _forces(self, sl, cphi, sphi, ibin, rho, kappa, ds):
        """Machine-frame (fx, fy) on the tool over one revolution for the stations in ``sl``.

        Chip of a micro-edge: the feed per tooth along the 3-D feed direction v, projected on the
        edge's outward normal u (ball: (sin κ cos φ, sin κ sin φ, −cos κ) in the feed frame; side:
        κ = 90°), plus the flutes' radial offsets (runout) projected on u.
        """
        p = self.path
        Z = self.flutes
        rows = self.st_pass[sl]
        fz = p.feed[rows] / (p.rpm[rows] * Z)                                # (P,)
        d = p.c1[rows] - p.c0[rows]
        alpha = np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1]))
        E = np.unpackbits(self._engaged[sl], axis=2, count=N_PHI).astype(bool)   # (P, levels, N_PHI)
        act = np.flatnonzero(E.any(axis=(0, 2)))                             # levels cut by some pass
        fxf = np.zeros((len(fz), N_ROT))
        fyf = np.zeros((len(fz), N_ROT))
        if act.size:
            cp, sp, ib = cphi[:, :, act], sphi[:, :, act], ibin[:, :, act]
            sk, ck, dsa = np.sin(kappa[act]), np.cos(kappa[act]), ds[act]
            vu = (np.cos(alpha)[:, None, None, None] * sk * cp[None]
                  - np.sin(alpha)[:, None, None, None] * ck)                  # (P, rot, Z, levels)
            best = None
            for m in range(1, Z + 1):
                delta = rho - rho[(np.arange(Z) + m) % Z]
                cand = m * fz[:, None, None, None] * vu + delta[None, None, :, None] * sk
                best = cand if best is None else np.minimum(best, cand)
            h = np.maximum(best, 0.0)
            eng = E[:, act[None, None, :], ib]                                # (P, rot, Z, levels)
            cut = eng & (h > 1e-12)
            c = self.coeffs
            ft = (c["ktc"] * h * dsa + c["kte"] * dsa) * cut
            fr = (c["krc"] * h * dsa + c["kre"] * dsa) * cut
            fa = (c["kac"] * h * dsa + c["kae"] * dsa) * cut
            fxf = np.sum(-fr * sk * cp - ft * sp - fa * ck * cp, axis=(2, 3))
            fyf = np.sum(-fr * sk * sp + ft * cp - fa * ck * sp, axis=(2, 3))
        f = np.arctan2(d[:, 1], d[:, 0])[:, None]
        return np.cos(f) * fxf - np.sin(f) * fyf, np.sin(f) * fxf + np.cos(f) * fyf

    # -- probing ----------------------------------------------------------------------------------
    def probe(self, pts: np.ndarray, normals: np.ndarray, effects: dict | None = None,
              noise_um: float = 0.0, rng: Optional[np.random.Generator] = None) -> np.ndarray:
        """Deviation (µm, + = material left) of the machined surface at each plan point along its normal."""
        effects = effects or {}
        if len(pts) == 0:
            return np.zeros(0)
        p = self.path
        R, Z = self.R, self.flutes
        n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
        cstar = pts + R * n
        rows, us = self._near_passes(cstar, PROBE_PASSES)
        ro = effects.get("runout", {})
        e_um, ph = float(ro.get("e_um", 0.0)), float(ro.get("phase_deg", 0.0))
        rho = self.flute_offsets(e_um + self.base_runout, ph)
        scale = float(effects.get("force_scale", {}).get("scale", 1.0))
        dx_rev, dy_rev = self.deflection(e_um, ph, scale)

        def surface(row, u):
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
            lag = zc * math.tan(self.helix) / R
            best = np.full(len(pts), np.inf)
            theta_star = (360.0 * t_star / T) % 360.0
            for j in range(Z):
                # spindle angle at which flute j passes φ_C at height zc: φ = −θ − 360 j/Z + lag
                th = np.degrees(-phi_c - 2 * np.pi * j / Z + lag) % 360.0
                dt0 = ((th - theta_star + 180.0) % 360.0 - 180.0) / 360.0 * T
                for m in PASSAGES:
                    t = t_star + dt0 + m * T
                    s_along = u * ln[row] + (t - t_star) * v
                    c, at = self._centre_at(p.s0[row] + s_along)
                    st = self._station_at(at, p.s0[row] + s_along)
                    # the deflection of the pass the tool is on at that passage: a passage a
                    # revolution beyond the end of a short pass is on its neighbour, and after a
                    # pocket corner's 120 µm the next pass's own small deflection there over-cut.
                    # Each pass's revolution is indexed from its own feed direction (θ_rel = Θ +
                    # feed angle, Θ the spindle's machine-frame angle): read the neighbour's at the
                    # same instant, th + its turn (in the own pass's frame, a 94° corner read it
                    # 94° off in the tooth cycle: −5 µm where +4 µm was right)
                    turn = np.degrees(np.arctan2(d[at, 1], d[at, 0]) - feed_ang)
                    fi = ((th + turn) % 360.0) / 360.0 * N_ROT
                    i0 = np.floor(fi).astype(np.int64) % N_ROT
                    w = fi - np.floor(fi)
                    i1 = (i0 + 1) % N_ROT
                    ddx = (1 - w) * dx_rev[st, i0] + w * dx_rev[st, i1]
                    ddy = (1 - w) * dy_rev[st, i0] + w * dy_rev[st, i1]
                    off = np.stack([ddx, ddy, np.zeros_like(ddx)], 1) * 1e-3
                    off += rho[j] * np.stack([np.cos(alpha), np.sin(alpha), np.zeros_like(alpha)], 1)
                    radius = np.full(len(pts), R)
                    off += self._machine_offsets(effects, c, row, s_along / ln[row], t)
                    radius -= self._radius_loss(effects, q, row, s_along, t) * 1e-3
                    cp = c + off - pts
                    a = np.einsum("ij,ij->i", cp, n)
                    perp2 = np.einsum("ij,ij->i", cp, cp) - a * a
                    disc = radius * radius - perp2
                    s_lo = np.where(disc >= 0, a - np.sqrt(np.maximum(disc, 0)), np.inf)
                    best = np.minimum(best, s_lo)
            return best

        # the surface is the deepest cut of the passes whose centres pass nearest (a point between
        # two rows, or at a pass end, may be finished by the neighbour)
        best = np.min(np.stack([surface(rows[:, k], us[:, k]) for k in range(rows.shape[1])]), axis=0)
        err = best * 1e3
        if noise_um > 0:
            rng = rng or np.random.default_rng()
            err = err + rng.normal(0.0, noise_um, len(err))
        return err

    def _near_passes(self, cstar, k_pass: int):
        """The ``k_pass`` distinct passes whose centre segments are nearest each point: (rows, u)."""
        from scipy.spatial import cKDTree
        p = self.path
        ln = p.length
        nsub = np.maximum(1, np.ceil(ln / 0.25).astype(np.int64))
        owner = np.repeat(np.arange(len(ln)), nsub)
        frac = (np.arange(nsub.sum()) - np.repeat(np.cumsum(nsub) - nsub, nsub) + 0.5) / np.repeat(nsub, nsub)
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

    def _centre_at(self, s_glob):
        """Nominal ball centre at path length ``s_glob`` along the cutting moves (continues into the
        neighbouring passes instead of extrapolating a pass beyond its end) and the pass (row) it is on."""
        p = self.path
        i = np.clip(np.searchsorted(p.s0, s_glob, side="right") - 1, 0, len(p.s0) - 1)
        f = np.clip((s_glob - p.s0[i]) / p.length[i], 0.0, 1.0)
        f = np.where((i == len(p.s0) - 1) | (i == 0), (s_glob - p.s0[i]) / p.length[i], f)
        return p.c0[i] + f[:, None] * (p.c1[i] - p.c0[i]), i

    def _radius_loss(self, effects, q_deg, row, s_along, t):
        """Radius smaller than nominal (µm) at contact angle q: measured shape, contour error and wear."""
        out = np.zeros(len(q_deg)) if self.profile is None else np.interp(q_deg, *self.profile)
        if "tool_contour" in effects:
            e = effects["tool_contour"]
            out += e["a_um"] * np.exp(-0.5 * ((q_deg - e["q0_deg"]) / e["width_deg"]) ** 2)
        if "tool_wear" in effects:
            L = self.path.L0[row] + np.clip(s_along, 0, None)
            out += effects["tool_wear"]["rate_um_per_m"] * L * 1e-3
        return out

    def _machine_offsets(self, effects, c, row, frac, t):
        """Tool offset (mm) from the machine: thermal drift, servo lag at corners, axis geometry."""
        off = np.zeros((len(c), 3))
        if "thermal_drift" in effects:
            e = effects["thermal_drift"]
            g = 1 - np.exp(-np.maximum(t, 0) / e["tau_s"])
            off += np.stack([e["ax_um"] * g, e["ay_um"] * g, e["az_um"] * g], 1) * 1e-3
        if "servo_corner" in effects:
            e = effects["servo_corner"]
            # distance along the path from the passage's own position (beyond the pass's end it is
            # on the neighbour: clipping it to the end put every such passage at the corner itself)
            dist, ang, b = corner_features(self.path, row, frac)
            mag = e["a_um"] * np.sin(np.radians(ang) / 2) / math.sin(math.pi / 4) * np.exp(-dist / e["lambda_mm"])
            off += b * mag[:, None] * 1e-3
        if "machine_geometry" in effects:
            e = effects["machine_geometry"]
            tip = c - [0.0, 0.0, self.R]
            x, y, z = tip[:, 0], tip[:, 1], tip[:, 2]
            off += np.stack([e["sx"] * x + e["exy"] * y + e["exz"] * z, e["sy"] * y + e["eyz"] * z, e["sz"] * z], 1) * 1e-3
        return off


def grid_plan(vm: VirtualMachine, spacing_mm: float = 0.5, k: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """Probe points along the cutting passes' contact lines when no plan is given.

    The surface normal is that of the ball-centre surface (the offset surface has the part's
    normals): the smallest principal axis of the ``k`` nearest centre samples (0.1 mm apart along
    the passes, so ``k`` must reach the neighbouring rows: with 12 the samples of one row are
    collinear and the normal is any direction across it), turned up (3-axis ball: the contact is
    on the lower half) and made normal to the pass. Returns (points, normals).
    """
    from scipy.spatial import cKDTree
    p = vm.path
    ln = p.length
    nsub = np.maximum(1, np.floor(ln / spacing_mm).astype(np.int64))
    owner = np.repeat(np.arange(len(ln)), nsub)
    frac = (np.arange(nsub.sum()) - np.repeat(np.cumsum(nsub) - nsub, nsub) + 0.5) / np.repeat(nsub, nsub)
    c = p.c0[owner] + frac[:, None] * (p.c1 - p.c0)[owner]
    dense_n = np.maximum(1, np.ceil(ln / 0.1).astype(np.int64))
    o2 = np.repeat(np.arange(len(ln)), dense_n)
    f2 = (np.arange(dense_n.sum()) - np.repeat(np.cumsum(dense_n) - dense_n, dense_n) + 0.5) / np.repeat(dense_n, dense_n)
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
