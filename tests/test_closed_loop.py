"""The closed loop: predict, correct, machine again, on machines written here (not the prediction chain).

The closed loop runs on an independent virtual machine written here (not the pipeline's
prediction chain): a ball end mill whose tool is pushed away from the material by a compliance ×
a load that grows with the local penetration of the (actual, deflected) tool into the stock and
depends on the feed direction, so the error changes when the path moves and iteration is needed.
The finished surface is the brute-force lower envelope of the (deflected) ball positions on a grid;
the target is the lower envelope of the same program on an ideal (rigid) machine. Per-pass errors
for the correction are read off the simulated surface (the grid points each pass generates).
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from stages.correction.rounds import correct_iteratively
from stages.nc.moves import split_blocks
from stages.nc.reader import parse_program
from stages.nc.writer import reverse_check, write_program
from tests.correct_cases import SAMPLES, SPLIT, errors_table


class VirtualMachine:
    """Independent brute-force simulation of ball-end finishing with a compliant machine.

    ``centre_surface(x, y) -> (F, dF/dx, dF/dy)``: the nominal ball-centre surface the program was
    made for (an offset of the part). The load at a tool position is proportional to its penetration
    into the stock, ``allow + (F(x, y) − z_c)·n_z`` along the normal of F (so a path moved into the
    part cuts deeper and deflects more), the tool is pushed out of the material horizontally by
    ``gain·load`` along the horizontal normal (stiffness differing in x and y) plus ``side·load``
    to the left of the feed direction (up/down milling), solved for the deflected position.
    """

    def __init__(self, centre_surface, radius, allow_um, gain_xy=(0.5, 0.35), side=0.08, step=0.1):
        self.F, self.R, self.allow = centre_surface, radius, allow_um / 1000.0
        self.gain, self.side, self.step = np.array(gain_xy), side, step

    def samples(self, passes, deflect=True, box=None):
        """Ball centres along the cutting passes (mm) and the pass index of each.

        ``box`` = (x0, x1, y0, y1): only passes that come within the tool radius of it.
        """
        g = lambda c: passes.column(c).to_numpy().astype(float)  # noqa: E731
        p0 = np.stack([g("x0_mm"), g("y0_mm"), g("z0_mm")], 1)
        p1 = np.stack([g("x1_mm"), g("y1_mm"), g("z1_mm")], 1)
        cut = passes.column("motion").to_numpy() != 0
        if box is not None:
            lo, hi = np.minimum(p0, p1), np.maximum(p0, p1)
            r = self.R + 0.1
            cut &= (hi[:, 0] > box[0] - r) & (lo[:, 0] < box[1] + r) & (hi[:, 1] > box[2] - r) & (lo[:, 1] < box[3] + r)
        idx = np.flatnonzero(cut)
        length = np.linalg.norm(p1[idx] - p0[idx], axis=1)
        k = np.maximum(1, np.ceil(length / self.step)).astype(int) + 1
        owner = np.repeat(idx, k)
        first = np.concatenate(([0], np.cumsum(k)[:-1]))
        t = (np.arange(owner.size) - np.repeat(first, k)) / np.repeat(k - 1, k)
        c = p0[owner] + (p1[owner] - p0[owner]) * t[:, None]
        c[:, 2] += self.R
        if deflect:
            feed = (p1 - p0)[owner]
            feed /= np.maximum(np.linalg.norm(feed, axis=1), 1e-12)[:, None]
            c = c + self.deflection(c, feed)
        return c, owner

    def deflection(self, c, feed):
        d = np.zeros_like(c)
        for _ in range(6):                      # the load is that of the deflected position
            f, fx, fy = self.F(c[:, 0] + d[:, 0], c[:, 1] + d[:, 1])
            nz = 1 / np.sqrt(1 + fx ** 2 + fy ** 2)
            nx, ny = -fx * nz, -fy * nz
            load = np.maximum(self.allow + (f - c[:, 2]) * nz, 0.0)
            d = np.zeros_like(c)
            d[:, 0] = load * (self.gain[0] * nx - self.side * feed[:, 1])
            d[:, 1] = load * (self.gain[1] * ny + self.side * feed[:, 0])
        return d

    def surface(self, passes, xs, ys, deflect=True):
        """Lower envelope of the balls on the grid: height, generating pass, generating centre."""
        c, owner = self.samples(passes, deflect, box=(xs[0], xs[-1], ys[0], ys[-1]))
        sel = (c[:, 0] > xs[0] - self.R) & (c[:, 0] < xs[-1] + self.R) & (c[:, 1] > ys[0] - self.R) & (c[:, 1] < ys[-1] + self.R)
        c, owner = c[sel], owner[sel]
        o = np.argsort(c[:, 1], kind="stable")
        c, owner = c[o], owner[o]
        z = np.full((ys.size, xs.size), np.inf)
        gen = np.full((ys.size, xs.size), -1)
        cen = np.zeros((ys.size, xs.size, 3))
        for j, y in enumerate(ys):
            lo, hi = np.searchsorted(c[:, 1], [y - self.R, y + self.R])
            w = c[lo:hi]
            rho2 = self.R ** 2 - (w[:, 1] - y) ** 2
            dx2 = (xs[:, None] - w[None, :, 0]) ** 2
            h = np.where(dx2 < rho2, w[None, :, 2] - np.sqrt(np.maximum(rho2 - dx2, 0)), np.inf)
            a = np.argmin(h, axis=1)
            z[j] = h[np.arange(xs.size), a]
            gen[j] = owner[lo:hi][a]
            cen[j] = w[a]
        return z, gen, cen


def _closed_loop(text, vm, xs, ys, params, max_iter=4):
    """Correct ``text`` on the virtual machine; RMS machining error before and after, per round."""
    blocks0, _ = parse_program(text, "vm", "p")
    passes0 = split_blocks(blocks0, SPLIT)
    target, _, cen0 = vm.surface(passes0, xs, ys, deflect=False)
    gx, gy = np.meshgrid(xs, ys)
    normal = cen0 - np.stack([gx, gy, target], -1)           # from the contact to the ball centre
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)

    def machined_error(passes):
        z, gen, _ = vm.surface(passes, xs, ys, deflect=True)
        return (z - target) * normal[..., 2] * 1000.0, gen    # µm along the normal, + = left

    def predict(blocks):
        passes = split_blocks(blocks, SPLIT)
        err, gen = machined_error(passes)
        rms.append(float(np.sqrt(np.mean(err ** 2))))
        ids = gen.ravel()
        n = passes.num_rows
        cnt = np.bincount(ids, minlength=n)
        e = np.bincount(ids, err.ravel(), n) / np.maximum(cnt, 1)
        nn = np.stack([np.bincount(ids, normal[..., i].ravel(), n) for i in range(3)], 1)
        have = cnt >= 3
        nn[have] /= np.linalg.norm(nn[have], axis=1)[:, None]
        tab = errors_table(passes, e, nn).filter(pa.array(have))
        return passes, tab

    rms = []                          # machining error of the path each round predicted on
    corrected = correct_iteratively(blocks0, predict, {"correct": dict(params, max_iter=max_iter)})
    out = write_program(text, blocks0, corrected)
    assert reverse_check(out, blocks0, corrected)["ok"]
    written, _ = parse_program(out, "vm-corrected", "p")
    final = float(np.sqrt(np.mean(machined_error(split_blocks(written, SPLIT))[0] ** 2)))
    return rms, final, corrected


def _program(rows):
    """Fanuc-style text from rows of (x, y, z) tip points per pass line, zigzag joined by G1 links."""
    lines = ["%", "O2001 (VIRTUAL MACHINE CASE)", "G90 G17 G21", "T1 M6", "S10000 M3"]
    n = 10
    x, y, z = rows[0][0]
    lines += [f"N{n} G0 X{x:.3f} Y{y:.3f}", f"N{n + 10} Z{z + 5:.3f}", f"N{n + 20} G1 Z{z:.3f} F2000"]
    n += 30
    for r in rows:
        for x, y, z in r:
            lines.append(f"N{n} X{x:.3f} Y{y:.3f} Z{z:.3f}")
            n += 10
    lines += [f"N{n} G0 Z50.000", f"N{n + 10} M30", "%", ""]
    return "\n".join(lines).encode()


def test_closed_loop_cylinder_contour():
    """Seed 000 Fig. 16/20 style: z-level passes along a cylinder (axis along Y), q from 0 to 60°."""
    rc, R = 12.0, 3.0
    pitch = 0.4
    qs = np.arange(-8, 68, np.degrees(pitch / rc)) * np.pi / 180

    def centre_surface(x, y):
        rr = rc + R
        xx = np.clip(x, -rr + 1e-6, rr - 1e-6)
        f = np.sqrt(rr ** 2 - xx ** 2)
        return f, -xx / f, np.zeros_like(f)

    ys = np.arange(-3.0, 3.01, 0.25)
    rows = []
    for k, q in enumerate(qs):
        yy = np.linspace(-7.0, 7.0, 15) * (1 if k % 2 == 0 else -1)
        cx, cz = (rc + R) * np.sin(q), (rc + R) * np.cos(q) - R
        rows.append([(cx, y, cz) for y in yy])
    text = _program(rows)
    vm = VirtualMachine(centre_surface, R, allow_um=60.0)
    xs = np.arange(0.0, rc * np.sin(np.radians(60)), 0.05)
    rms, final, corrected = _closed_loop(text, vm, xs, ys, {"max_move_um": 100.0, "tol_um": 0.2})
    print(f"\ncylinder contour: RMS error {rms[0]:.2f} µm before, rounds {['%.2f' % r for r in rms[1:]]},"
          f" written program {final:.2f} µm = {100 * final / rms[0]:.1f} % of before")
    assert rms[0] > 5.0
    assert final <= 0.2 * rms[0]
    assert corrected.column("iteration").to_numpy()[0] >= 2


def test_closed_loop_freeform_raster():
    """Zigzag raster along X over a free-form surface (bump on a saddle)."""
    R = 3.0

    def centre_surface(x, y):
        b = np.exp(-((x - 5) ** 2 + (y - 4) ** 2) / 12.0)
        f = 2.0 * b + 0.04 * (x - 5) * (y - 4) + 0.1 * x
        fx = 2.0 * b * (-(x - 5) / 6.0) + 0.04 * (y - 4) + 0.1
        fy = 2.0 * b * (-(y - 4) / 6.0) + 0.04 * (x - 5)
        return f, fx, fy

    xs = np.arange(0.0, 10.0, 0.1)
    ys = np.arange(0.0, 8.0, 0.1)
    rows = []
    for k, y in enumerate(np.arange(-3.5, 11.6, 0.5)):
        xx = np.arange(-3.5, 13.6, 0.5)[:: 1 if k % 2 == 0 else -1]
        f, _, _ = centre_surface(xx, np.full_like(xx, y))
        rows.append(list(zip(xx, np.full_like(xx, y), f - R)))
    text = _program(rows)
    vm = VirtualMachine(centre_surface, R, allow_um=60.0)
    rms, final, _ = _closed_loop(text, vm, xs, ys, {"max_move_um": 100.0, "tol_um": 0.2})
    print(f"\nfree-form raster: RMS error {rms[0]:.2f} µm before, rounds {['%.2f' % r for r in rms[1:]]},"
          f" written program {final:.2f} µm = {100 * final / rms[0]:.1f} % of before")
    assert rms[0] > 3.0
    assert final <= 0.2 * rms[0]


def _sample_centre_surface(passes, radius, x_range, y_range, step=0.05):
    """Ball-centre surface of a raster program along X: rows interpolated linearly along X (the CL
    polyline) and by cubic splines across rows; returns (F, dF/dx, dF/dy) as a function of x, y."""
    from scipy.interpolate import CubicSpline, RegularGridInterpolator
    g = lambda c: passes.column(c).to_numpy()  # noqa: E731
    row = (g("motion") != 0) & (np.abs(g("y1_mm") - g("y0_mm")) < 1e-9)
    x0, x1, y, z0, z1 = (g(c)[row] for c in ("x0_mm", "x1_mm", "y0_mm", "z0_mm", "z1_mm"))
    rows_y = np.unique(np.round(y, 3))
    gx = np.arange(x_range[0] - radius - 2, x_range[1] + radius + 2, step)
    zr = np.empty((rows_y.size, gx.size))
    for i, yy in enumerate(rows_y):
        s = np.abs(y - yy) < 1e-6
        xx, zz = np.concatenate([x0[s], x1[s]]), np.concatenate([z0[s], z1[s]])
        o = np.argsort(xx, kind="stable")
        zr[i] = np.interp(gx, xx[o], zz[o]) + radius
    spl = CubicSpline(rows_y, zr, axis=0)
    gy = np.arange(max(y_range[0] - radius - 2, rows_y[0]), min(y_range[1] + radius + 2, rows_y[-1]), step)
    f, fy = spl(gy), spl(gy, 1)
    fx = np.gradient(f, gx, axis=1)
    interp = [RegularGridInterpolator((gy, gx), a) for a in (f, fx, fy)]

    def centre_surface(x, y):
        q = np.stack([np.clip(y, gy[0], gy[-1]), np.clip(x, gx[0], gx[-1])], -1)
        return tuple(i(q) for i in interp)
    return centre_surface


@pytest.mark.parametrize("window", [(14.0, 24.0, 34.0, 44.0), (60.0, 72.0, 36.0, 44.0)])
def test_closed_loop_sample_finishing_program(window):
    """The sample finishing program (OpenCAMLib raster, Ø10 ball) on the virtual machine, in a window.

    The second window holds the foot of the pocket wall at x ≈ 73.2: every row's corner ball (two or
    three vertices 25–40 µm apart) leaves a fan of its own sphere 2–3 mm wide on the floor, with
    normals spread over ~40°, and the virtual machine pushes it sideways by up to 30 µm. The passes
    meeting at those vertices have clearly different normals; the para 0084 move along E'i + E'j
    with one magnitude cannot realise both errors there, and the iteration only slowly recovered
    the rest (27.5 % after 4 rounds; 78 % of the remaining mean square in the 20 % of the window
    covered by the fans). The least-squares refinement in the plane of the two normals
    (stages.correct.vertex_moves) realises both. The bound is the issue's 20 %.
    """
    data = open(SAMPLES[1], "rb").read()
    blocks, _ = parse_program(data, SAMPLES[1], "p")
    passes = split_blocks(blocks, SPLIT)
    x0, x1, y0, y1 = window
    vm = VirtualMachine(_sample_centre_surface(passes, 5.0, (x0, x1), (y0, y1)), 5.0, allow_um=60.0)
    rms, final, _ = _closed_loop(data, vm, np.arange(x0, x1, 0.1), np.arange(y0, y1, 0.1),
                                 {"max_move_um": 100.0, "tol_um": 0.2})
    print(f"\nsample {SAMPLES[1]} window x{x0:g}-{x1:g} y{y0:g}-{y1:g}: RMS error {rms[0]:.2f} µm before, rounds "
          f"{['%.2f' % r for r in rms[1:]]}, written program {final:.2f} µm = {100 * final / rms[0]:.1f} % of before")
    assert final <= 0.2 * rms[0]


class CylinderMachine:
    """Independent simulation of the seed's cylinder benchmark (seed 000 Fig. 16/20, paras 0091–0092).

    Cylinder of radius ``rc`` about the Y axis, Ø20 ball, z-level passes along Y from the top
    (q = 0°) down the +X side to q = 89°. The finished surface is the envelope of the (deflected)
    balls seen from the cylinder axis: at angle θ (from +Z toward +X) and height y it is the nearest
    ball surface along the ray, so steep walls up to the equator are exact (no height field). The
    load is the radial penetration of the deflected ball into the stock (radius rc + allow); the
    tool bends sideways (XY) by ``gain``·load along the horizontal normal, plus ``side``·load to the
    left of the feed (up- and down-milling levels differ).
    """

    def __init__(self, rc, radius, allow_um, gain=0.5, side=0.1, step=0.2):
        self.rc, self.R, self.allow, self.gain, self.side, self.step = rc, radius, allow_um / 1000, gain, side, step

    def load(self, c):
        return np.maximum(self.allow + self.rc + self.R - np.hypot(c[:, 0], c[:, 2]), 0.0)

    def samples(self, passes, deflect=True):
        vm = VirtualMachine(None, self.R, 0.0, step=self.step)
        c, owner = vm.samples(passes, deflect=False)
        if deflect:
            g = lambda k: passes.column(k).to_numpy().astype(float)  # noqa: E731
            feed = np.stack([g("x1_mm") - g("x0_mm"), g("y1_mm") - g("y0_mm")], 1)[owner]
            feed /= np.maximum(np.linalg.norm(feed, axis=1), 1e-12)[:, None]
            d = np.zeros_like(c)
            for _ in range(6):
                p = c + d
                rho = np.hypot(p[:, 0], p[:, 2])
                nx = p[:, 0] / rho
                load = self.load(p)
                d = np.zeros_like(c)
                d[:, 0] = load * (self.gain * nx - self.side * feed[:, 1])
                d[:, 1] = load * self.side * feed[:, 0]
            c = c + d
        return c, owner

    def surface(self, passes, thetas, ys, deflect=True):
        """Finished radius at (y, θ) and the generating pass."""
        c, owner = self.samples(passes, deflect)
        rho = np.hypot(c[:, 0], c[:, 2])
        th = np.arctan2(c[:, 0], c[:, 2])
        r = np.full((ys.size, thetas.size), np.inf)
        gen = np.full((ys.size, thetas.size), -1)
        for j, y in enumerate(ys):
            near = np.abs(c[:, 1] - y) < self.R
            rr2 = self.R ** 2 - (c[near, 1] - y) ** 2
            dth = thetas[:, None] - th[near][None, :]
            along = rho[near] * np.cos(dth)
            disc = rr2 - (rho[near] * np.sin(dth)) ** 2
            t = np.where((disc >= 0) & (along > 0), along - np.sqrt(np.maximum(disc, 0)), np.inf)
            a = np.argmin(t, axis=1)
            r[j] = t[np.arange(thetas.size), a]
            gen[j] = owner[near][a]
        return r, gen


def test_closed_loop_cylinder_benchmark():
    """Seed Fig. 16 geometry (Ø20 ball, 0.63 mm pitch, 50 levels to q = 89°), closed loop."""
    R, pitch, n_levels, q_max = 10.0, 0.63, 50, 89.0
    dq = np.radians(q_max / n_levels)
    rc = pitch / dq
    qs = np.arange(-1, n_levels + 2) * dq
    rows = []
    for k, q in enumerate(qs):
        yy = np.arange(-14.0, 14.01, 2.0)[:: 1 if k % 2 == 0 else -1]
        cx, cz = (rc + R) * np.sin(q), (rc + R) * np.cos(q) - R
        rows.append([(cx, y, cz) for y in yy])
    text = _program(rows)
    vm = CylinderMachine(rc, R, allow_um=60.0)
    thetas = np.radians(np.arange(0.0, q_max + 1e-9, 0.1))
    ys = np.array([-2.0, 0.0, 2.0])
    blocks0, _ = parse_program(text, "cyl", "p")
    passes0 = split_blocks(blocks0, SPLIT)
    target, _ = vm.surface(passes0, thetas, ys, deflect=False)
    normal = np.stack([np.sin(thetas), np.zeros_like(thetas), np.cos(thetas)], 1)
    rms, q_err = [], []

    def predict(blocks):
        passes = split_blocks(blocks, SPLIT)
        r, gen = vm.surface(passes, thetas, ys)
        err = (r - target) * 1000.0                     # radial = along the normal, + = material left
        rms.append(float(np.sqrt(np.mean(err ** 2))))
        q_err.append(err[1])
        n = passes.num_rows
        ids = gen.ravel()
        cnt = np.bincount(ids, minlength=n)
        e = np.bincount(ids, err.ravel(), n) / np.maximum(cnt, 1)
        nn = np.stack([np.bincount(ids, np.broadcast_to(normal[:, i], gen.shape).ravel(), n) for i in range(3)], 1)
        have = cnt >= 3
        nn[have] /= np.linalg.norm(nn[have], axis=1)[:, None]
        return passes, errors_table(passes, e, nn).filter(pa.array(have))

    corrected = correct_iteratively(blocks0, predict, {"correct": {"max_move_um": 100.0, "tol_um": 0.2, "max_iter": 4}})
    out = write_program(text, blocks0, corrected)
    assert reverse_check(out, blocks0, corrected)["ok"]
    written, _ = parse_program(out, "cyl-corrected", "p")
    predict(written)
    final = rms[-1]
    q = np.degrees(thetas)
    band = lambda e, a, b: float(np.abs(e[(q >= a) & (q < b)]).max())  # noqa: E731
    print(f"\ncylinder benchmark (Ø20, rc {rc:.2f} mm, q 0–89°): RMS error {rms[0]:.2f} µm before, rounds "
          f"{['%.2f' % r for r in rms[1:-1]]}, written program {final:.2f} µm = {100 * final / rms[0]:.1f} % of before; "
          f"max |error| at q 80–89°: {band(q_err[0], 80, 90):.1f} → {band(q_err[-1], 80, 90):.1f} µm")
    assert rms[0] > 10.0
    assert final <= 0.2 * rms[0]


def _gap_vm_closed_loop(src: bytes, stock, tool, material, k, pts, nrm, split, level_of, max_iter=4):
    """Correct ``src`` from errors measured on stages/virtual_machine/ (issue 7; shares no prediction
    code) and machine the written program there again. Errors are against the original program cut
    on a rigid machine; per pass, the mean over the probe points that ``level_of`` assigns to it."""
    from stages.virtual_machine import VirtualMachine

    def probe(blocks, stiff):
        machine = {"frf": {a: [{"fn_hz": 900, "zeta": 0.03, "k_n_per_um": stiff}] for a in "xy"}, "table": None}
        passes = split_blocks(blocks, split)
        return VirtualMachine(passes, tool, material, machine, stock).probe(pts, nrm), passes

    blocks0, _ = parse_program(src, "vm", "p")
    ideal, _ = probe(blocks0, 1e9)
    rms = []

    def predict(blocks):
        e, passes = probe(blocks, k)
        e = e - ideal
        rms.append(float(np.sqrt(np.mean(e ** 2))))
        ids = level_of(passes)
        n = passes.num_rows
        ok = ids >= 0
        cnt = np.bincount(ids[ok], minlength=n)
        em = np.bincount(ids[ok], e[ok], n) / np.maximum(cnt, 1)
        nn = np.stack([np.bincount(ids[ok], nrm[ok, i], n) for i in range(3)], 1)
        have = cnt >= 3
        nn[have] /= np.linalg.norm(nn[have], axis=1)[:, None]
        return passes, errors_table(passes, em, nn).filter(pa.array(have))

    corrected = correct_iteratively(blocks0, predict, {"correct": {"max_move_um": 100.0, "tol_um": 0.2, "max_iter": max_iter}})
    out = write_program(src, blocks0, corrected)
    assert reverse_check(out, blocks0, corrected)["ok"]
    e, _ = probe(parse_program(out, "vm-corrected", "p")[0], k)
    return rms, float(np.sqrt(np.mean((e - ideal) ** 2)))


def test_closed_loop_cylinder_benchmark_on_the_gap_virtual_machine(tmp_path):
    """Seed Fig. 16 cylinder (Ø20, 0.63 mm pitch, 51 levels q 0–89°, 6 mm stock) machined on the gap
    issue's virtual machine (discrete flutes, time-domain dynamics), corrected from its measured
    error, machined again: ≤ 20 % of the error before (issue 5)."""
    import trimesh
    R, pitch, n_levels, q_max, length = 10.0, 0.63, 50, 89.0, 6.0
    dq = np.radians(q_max / n_levels)
    rc = pitch / dq
    y_end = length / 2 + R + 2.0
    lines = ["%", "O3002 (CYLINDER)", "G90 G17 G21", "T1 M6", "S6000 M3"]
    for i, kq in enumerate(range(-1, n_levels + 2)):
        x, z = (rc + R) * np.sin(kq * dq), (rc + R) * np.cos(kq * dq) - R
        ys = (-y_end, y_end) if i % 2 == 0 else (y_end, -y_end)
        lines += ([f"G0 X{x:.4f} Y{ys[0]:.4f} Z{z + 30:.4f}", f"G1 Z{z:.4f} F4800"] if i == 0
                  else [f"X{x:.4f} Y{ys[0]:.4f} Z{z:.4f}"]) + [f"Y{ys[1]:.4f}"]
    src = "\n".join(lines + ["G0 Z60.0000", "M30", "%", ""]).encode()
    stock = trimesh.creation.cylinder(radius=rc + 0.2, height=length, sections=720)
    stock.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    stock.export(tmp_path / "stock.stl")
    tool = {"type": "ball", "diameter_mm": 20.0, "flutes": 2, "helix_deg": 30.0, "runout_um": 0.0, "control_point": "tip"}
    material = {"ktc": 2000, "krc": 700, "kac": 300, "kte": 20, "kre": 15, "kae": 5}
    split = {"split": {"chord_tol_mm": 0.001, "max_pass_mm": 40.0, "merge_max_mm": 0.5},
             "machine": {"rapid_mm_min": 30000.0}, "tool": tool}
    qq, yy = np.meshgrid(np.radians(np.linspace(0.0, q_max, 716)), np.linspace(-2.5, 2.5, 11))
    nrm = np.stack([np.sin(qq.ravel()), np.zeros(qq.size), np.cos(qq.ravel())], 1)
    pts = rc * nrm + np.stack([np.zeros(qq.size), yy.ravel(), np.zeros(qq.size)], 1)

    def level_of(passes):
        """Each probe point to the level pass whose ball centre is nearest in angle about the axis."""
        g = lambda c: passes.column(c).to_numpy()  # noqa: E731
        lvl = np.flatnonzero((g("motion") != 0) & (np.abs(g("y1_mm") - g("y0_mm")) > 20))
        ang = np.arctan2(g("x0_mm")[lvl], g("z0_mm")[lvl] + R)
        qp = np.arctan2(pts[:, 0], pts[:, 2])
        return lvl[np.argmin(np.abs(qp[:, None] - ang[None, :]), axis=1)]

    rms, final = _gap_vm_closed_loop(src, str(tmp_path / "stock.stl"), tool, material, 2.0, pts, nrm, split, level_of)
    print(f"\ncylinder benchmark on the gap virtual machine: RMS error {rms[0]:.2f} um before, rounds "
          f"{['%.2f' % r for r in rms[1:]]}, written program {final:.2f} um = {100 * final / rms[0]:.1f} % of before")
    assert rms[0] > 5.0
    assert final <= 0.2 * rms[0]
