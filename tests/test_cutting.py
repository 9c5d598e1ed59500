"""Cutting-force kernels against closed forms and an independent brute-force integration.

Reference numbers come from Altintas' mean-force formulas (derived below from the integrals, not
taken from the code), from an independent κ-integration of the Lee–Altintas ball-end model written
here in the immersion angle ψ, and from exact chip-load arithmetic for runout.
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from stages.geometry.cutter import Cutter
from stages.cutting import calibrate
from stages.cutting import forces as cutting
from stages import forces as forces_stage

KC = {"ktc": 2000.0, "krc": 700.0, "kac": 300.0, "kte": 0.0, "kre": 0.0, "kae": 0.0}
KE = {"ktc": 2000.0, "krc": 700.0, "kac": 300.0, "kte": 20.0, "kre": 15.0, "kae": 5.0}


# ------------------------------------------------------------------------------------------------
# analytic cutting regions (independent of stages.cutting)
# ------------------------------------------------------------------------------------------------
def _radius_at(kind, R, rc, z):
    if kind == "flat":
        return np.full_like(z, R)
    zc = np.minimum(z, rc)
    return R - rc + np.sqrt(rc ** 2 - (rc - zc) ** 2)


def engagement_from_geometry(kind, diameter, depth, n_z, n_phi, width=None, side="right", rc=None):
    """Straight cut into a block whose top is ``depth`` above the tip; material strip of ``width``
    on ``side`` of the feed (None = slot). Only the front half (ahead of the tool) cuts.
    Returns (E (n_z, n_phi) bool, dz)."""
    R = diameter / 2
    rc = {"ball": R, "flat": 0.0}.get(kind, rc)
    dz = depth / n_z
    z = (np.arange(n_z) + 0.5) * dz
    r = _radius_at(kind, R, rc, z)
    phi = np.radians((np.arange(n_phi) + 0.5) * 360.0 / n_phi)
    x, y = r[:, None] * np.cos(phi), r[:, None] * np.sin(phi)
    E = x > 0
    if width is not None:
        E &= (y < -(R - width)) if side == "right" else (y > R - width)
    return E, dz


def textbook_mean(N, a, c, k, psi_st, psi_ex):
    """Altintas' mean forces per revolution on the tool for a flat end mill, h = c·sinψ, db = dz.

    With Ft = Ktc·h + Kte, Fr = Krc·h + Kre, Fa = Kac·h + Kae and on the tool
    Fx = −Ft cosψ − Fr sinψ, Fy = Ft sinψ − Fr cosψ, Fz = −Fa (right-hand helix pulls the tool
    down), F̄ = N·a/(2π)·∫ F dψ over [ψst, ψex]:
      F̄x = Nac/(8π)[Ktc cos2ψ − Krc(2ψ − sin2ψ)] + Na/(2π)[−Kte sinψ + Kre cosψ]
      F̄y = Nac/(8π)[Ktc(2ψ − sin2ψ) + Krc cos2ψ] + Na/(2π)[−Kte cosψ − Kre sinψ]
      F̄z = −Na/(2π)[−Kac c cosψ + Kae ψ]
    """
    def fx(p):
        return N * a * c / (8 * np.pi) * (k["ktc"] * np.cos(2 * p) - k["krc"] * (2 * p - np.sin(2 * p))) \
            + N * a / (2 * np.pi) * (-k["kte"] * np.sin(p) + k["kre"] * np.cos(p))

    def fy(p):
        return N * a * c / (8 * np.pi) * (k["ktc"] * (2 * p - np.sin(2 * p)) + k["krc"] * np.cos(2 * p)) \
            + N * a / (2 * np.pi) * (-k["kte"] * np.cos(p) - k["kre"] * np.sin(p))

    def fz(p):
        return -N * a / (2 * np.pi) * (-k["kac"] * c * np.cos(p) + k["kae"] * p)

    return np.array([f(psi_ex) - f(psi_st) for f in (fx, fy, fz)])


def _tool(kind, flutes=3, helix=30.0, diameter=10.0, runout=0.0, rc=None):
    return Cutter.from_params({"type": kind, "diameter_mm": diameter, "flutes": flutes, "helix_deg": helix,
                               "corner_radius_mm": rc, "runout_um": runout})


# ------------------------------------------------------------------------------------------------
# closed forms: slotting, partial immersion, edge coefficients
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("helix", [0.0, 30.0, 45.0])
@pytest.mark.parametrize("flutes", [2, 3, 4])
def test_slot_mean_force_closed_form(helix, flutes):
    """Issue formula |F̄xy| = N·a·c·√(Ktc²+Krc²)/4, |F̄z| = N·a·c·Kac/π: holds for any helix (the
    mean over a revolution of each axial slice is the same) with db = dz, h = c·sinψ."""
    a, c = 3.0, 0.05
    E, dz = engagement_from_geometry("flat", 10.0, a, 30, 360)
    F = cutting.cutting_forces(E[None], dz, c, _tool("flat", flutes, helix), KC)[0]
    m = F.mean(axis=0)
    want_xy = flutes * a * c * np.hypot(KC["ktc"], KC["krc"]) / 4
    want_z = flutes * a * c * KC["kac"] / np.pi
    assert abs(np.hypot(m[0], m[1]) / want_xy - 1) < 0.01
    assert abs(abs(m[2]) / want_z - 1) < 0.01
    # directions, forces on the tool: radial pushes it back against the feed (−x), tangential to
    # the left of the feed (+y, the clockwise spindle drags the work to the right), axial down.
    assert m[0] < 0 and m[1] > 0 and m[2] < 0
    assert np.allclose(m, [-flutes * a * c * KC["krc"] / 4, flutes * a * c * KC["ktc"] / 4, -want_z], rtol=0.01)


@pytest.mark.parametrize("side,width", [("right", 2.5), ("left", 2.5), ("right", 2.0), ("left", 1.3)])
@pytest.mark.parametrize("helix", [0.0, 30.0])
def test_partial_immersion_with_edge_forces_textbook(side, width, helix):
    """Down milling (material right of the feed: ψ from π − acos(1 − ae/R) to π) and up milling
    (left: 0 to acos(1 − ae/R)), edge coefficients on: all three mean components within 1 %."""
    N, a, c, R = 3, 2.0, 0.08, 5.0
    E, dz = engagement_from_geometry("flat", 2 * R, a, 20, 1440, width=width, side=side)
    F = cutting.cutting_forces(E[None], dz, c, _tool("flat", N, helix), KE,
                               rotation_deg=np.arange(512) * 360 / 512)[0]
    m = F.mean(axis=0)
    arc = np.arccos(1 - width / R)
    st, ex = (np.pi - arc, np.pi) if side == "right" else (0.0, arc)
    want = textbook_mean(N, a, c, KE, st, ex)
    # components can be small differences of large terms (F̄y here): compare as vectors, and the
    # big components one by one; the grid quantises an unaligned entry/exit angle to its bins
    # (0.25° here; with 0.5° bins and no helix to smooth it, ae = 1.3 is off by 1.04 %)
    assert np.linalg.norm(m - want) <= 0.01 * np.linalg.norm(want), (m, want)
    big = np.abs(want) > 0.2 * np.linalg.norm(want)
    assert np.all(np.abs(m - want)[big] <= 0.01 * np.abs(want)[big]), (m, want)


def test_slot_edge_forces_textbook():
    N, a, c = 2, 4.0, 0.1
    E, dz = engagement_from_geometry("flat", 10.0, a, 40, 360)
    m = cutting.cutting_forces(E[None], dz, c, _tool("flat", N, 30.0), KE)[0].mean(axis=0)
    want = textbook_mean(N, a, c, KE, 0.0, np.pi)
    assert np.allclose(m, want, rtol=0.01)


@pytest.mark.parametrize("kind,rc", [("ball", None), ("bull", 1.5), ("flat", None)])
def test_slot_mean_feed_normal_force_is_shape_independent(kind, rc):
    """Slotting: F̄y = N·a·c·Ktc/4 whatever the profile (∫ sinκ dS = a), edge terms 0."""
    N, a, c = 2, 2.4, 0.06
    E, dz = engagement_from_geometry(kind, 10.0, a, 48, 360, rc=rc)
    m = cutting.cutting_forces(E[None], dz, c, _tool(kind, N, 30.0, rc=rc), KC)[0].mean(axis=0)
    assert abs(m[1] / (N * a * c * KC["ktc"] / 4) - 1) < 0.01


# ------------------------------------------------------------------------------------------------
# ball end mill vs brute force
# ------------------------------------------------------------------------------------------------
def brute_force_ball_slot(theta_deg, R, depth, N, helix_deg, c, k, n_kappa=6000):
    """Lee & Altintas ball-end model integrated over κ (midpoint rule), written in ψ.

    ψ_j(κ) = θ + 90° + 360·j/N − z·tanβ/R (clockwise spindle, immersion from +y, edge above the tip
    trails); slot: cutting where 0 < ψ < 180°, z = R(1 − cos κ) < depth. db = dS = R·dκ."""
    kap_a = np.arccos(1 - depth / R)
    dk = kap_a / n_kappa
    kap = (np.arange(n_kappa) + 0.5) * dk
    z = R * (1 - np.cos(kap))
    ds = R * dk
    out = np.zeros((len(theta_deg), 3))
    for i, th in enumerate(theta_deg):
        for j in range(N):
            psi = np.radians(th + 90 + 360.0 * j / N) - z * np.tan(np.radians(helix_deg)) / R
            psi = np.mod(psi, 2 * np.pi)
            cut = (psi > 0) & (psi < np.pi)
            h = c * np.sin(psi) * np.sin(kap)
            dft = (k["ktc"] * h + k["kte"]) * ds * cut
            dfr = (k["krc"] * h + k["kre"]) * ds * cut
            dfa = (k["kac"] * h + k["kae"]) * ds * cut
            sk, ck, sp, cp = np.sin(kap), np.cos(kap), np.sin(psi), np.cos(psi)
            out[i, 0] += np.sum(-dfr * sk * sp - dft * cp - dfa * ck * sp)
            out[i, 1] += np.sum(-dfr * sk * cp + dft * sp - dfa * ck * cp)
            out[i, 2] += np.sum(dfr * ck - dfa * sk)
    return out


@pytest.mark.parametrize("depth,helix,k", [(1.0, 30.0, KC), (2.5, 30.0, KE), (4.0, 45.0, KE)])
def test_ball_end_mill_against_brute_force(depth, helix, k):
    R, N, c = 5.0, 2, 0.07
    theta = np.arange(128) * 360 / 128
    E, dz = engagement_from_geometry("ball", 2 * R, depth, 40, 720)
    got = cutting.cutting_forces(E[None], dz, c, _tool("ball", N, helix), k, rotation_deg=theta)[0]
    ref = brute_force_ball_slot(theta, R, depth, N, helix, c, k)
    peak = np.abs(ref).max()
    assert np.abs(got - ref).max() <= 0.02 * peak
    assert np.allclose(got.mean(axis=0), ref.mean(axis=0), atol=0.02 * np.abs(ref.mean(axis=0)).max())


# ------------------------------------------------------------------------------------------------
# conventions: rotation ↔ φ, machine frame, runout
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("helix", [0.0, 30.0])
def test_spindle_angle_convention(helix):
    """A single cell at φ0 (level k) is hit when θ = −φ0 + z_k·tanβ/R (clockwise spindle)."""
    n_z, n_phi, dz, R = 10, 360, 0.5, 5.0
    E = np.zeros((n_z, n_phi), bool)
    k_level, j_bin = 6, 30                                    # φ0 = 30.5°, ahead-left of the tool
    E[k_level, j_bin] = True
    theta = np.arange(3600) * 0.1
    F = cutting.cutting_forces(E[None], dz, 0.1, _tool("flat", 1, helix), KC, rotation_deg=theta)[0]
    hit = theta[np.abs(F).sum(axis=1) > 0]
    z = (k_level + 0.5) * dz
    expect = np.mod(-(j_bin + 0.5) + np.degrees(z * np.tan(np.radians(helix)) / R), 360)
    assert hit.size > 0 and np.all(np.abs((hit - expect + 180) % 360 - 180) <= 0.5 + 1e-9)
    # and the helper that inverts it (used by the errors stage)
    assert np.isclose(cutting.spindle_angle_at(j_bin + 0.5, z, 0, _tool("flat", 1, helix, diameter=2 * R)), expect)


def test_machine_frame_rotation():
    """Feed along +y: the left of the feed is −x, so the slot's tangential mean (+y_f) is −x."""
    N, a, c = 2, 2.0, 0.05
    E, dz = engagement_from_geometry("flat", 10.0, a, 20, 360)
    Ff = cutting.cutting_forces(E[None], dz, c, _tool("flat", N, 30.0), KC)
    Fm = cutting.to_machine_frame(Ff, np.array([0.0]), np.array([1.0]))[0].mean(axis=0)
    assert np.allclose(Fm, [-N * a * c * KC["ktc"] / 4, -N * a * c * KC["krc"] / 4,
                            -N * a * c * KC["kac"] / np.pi], rtol=0.01)


def test_runout_chip_load():
    """Two flutes, eccentricity e toward flute 0: radii R ± e, chips fz·sinψ ± 2e (fz > 2e)."""
    a, c, e_um = 2.0, 0.05, 10.0
    E, dz = engagement_from_geometry("flat", 10.0, a, 10, 360)
    tool = _tool("flat", 2, 0.0, runout=e_um)
    F = cutting.cutting_forces(E[None], dz, c, tool, KC, rotation_deg=np.array([0.0, 180.0]))[0]
    # θ = 0: flute 0 straight ahead (ψ = 90°) alone in the cut; θ = 180°: flute 1 there
    e = e_um * 1e-3
    assert np.isclose(F[0, 1], KC["ktc"] * a * (c + 2 * e), rtol=1e-6)
    assert np.isclose(F[1, 1], KC["ktc"] * a * (c - 2 * e), rtol=1e-6)
    assert np.isclose(F[0, 0], -KC["krc"] * a * (c + 2 * e), rtol=1e-6)
    # large runout: flute 1 misses entirely, flute 0 takes both teeth's chip (2·fz)
    big = _tool("flat", 2, 0.0, runout=40.0)
    F = cutting.cutting_forces(E[None], dz, c, big, KC, rotation_deg=np.array([0.0, 180.0]))[0]
    assert np.isclose(F[0, 1], KC["ktc"] * a * 2 * c, rtol=1e-6) and abs(F[1, 1]) < 1e-9


def test_runout_three_flutes_order():
    """Three flutes, radii R + e·cos(2πj/3) = R + e, R − e/2, R − e/2. The clockwise spindle brings
    flute 1 to any angle before flute 0, flute 2 before flute 1, flute 0 before flute 2, so the
    chips are fz + 1.5e (flute 0), fz (flute 1), fz − 1.5e (flute 2)."""
    a, c, e_um = 2.0, 0.05, 10.0
    E, dz = engagement_from_geometry("flat", 10.0, a, 10, 360)
    tool = _tool("flat", 3, 0.0, runout=e_um)
    # flute j points along the feed (ψ = 90°, alone in the cut) at θ = −120°·j
    F = cutting.cutting_forces(E[None], dz, c, tool, KC, rotation_deg=np.array([0.0, 240.0, 120.0]))[0]
    e = e_um * 1e-3
    assert F[:, 1] == pytest.approx(KC["ktc"] * a * np.array([c + 1.5 * e, c, c - 1.5 * e]), rel=1e-6)


def test_runout_keeps_mean_force_of_slot():
    """Material removed per revolution is unchanged by runout (no flute misses): same mean force."""
    E, dz = engagement_from_geometry("flat", 10.0, 2.0, 20, 360)
    m0 = cutting.cutting_forces(E[None], dz, 0.05, _tool("flat", 3, 30.0), KC)[0].mean(axis=0)
    m1 = cutting.cutting_forces(E[None], dz, 0.05, _tool("flat", 3, 30.0, runout=8.0), KC)[0].mean(axis=0)
    assert np.allclose(m0, m1, rtol=0.01)


def test_unpack_engagement_roundtrip():
    rng = np.random.default_rng(1)
    grids = rng.random((5, 7, 13)) > 0.5
    masks = [cutting.pack_engagement(g) for g in grids]
    assert np.array_equal(cutting.unpack_engagement(masks, 7, 13), grids)


def test_batch_equals_single_and_zero_engagement():
    E1, dz = engagement_from_geometry("ball", 10.0, 1.5, 30, 360)
    E2, _ = engagement_from_geometry("ball", 10.0, 1.5, 30, 360, width=2.0, side="left")
    E = np.stack([E1, E2, np.zeros_like(E1)])
    fz = np.array([0.05, 0.08, 0.05])
    for runout in (0.0, 5.0):
        tool = _tool("ball", 2, 30.0, runout=runout)
        Fb = cutting.cutting_forces(E, dz, fz, tool, KE)
        for p in range(3):
            Fs = cutting.cutting_forces(E[p:p + 1], dz, fz[p], tool, KE)
            assert np.allclose(Fb[p], Fs[0], atol=1e-4)
        assert np.all(Fb[2] == 0)


# ------------------------------------------------------------------------------------------------
# forces stage on tables
# ------------------------------------------------------------------------------------------------
def _passes_table(n, feed=1200.0, rpm=8000.0):
    z = np.zeros(n)
    return pa.table({
        "program_id": ["p"] * n, "pass_id": pa.array(np.arange(n), pa.int32()),
        "block_no": pa.array(np.arange(n), pa.int32()), "line_no": pa.array(np.arange(n) + 10, pa.int32()),
        "motion": pa.array(np.ones(n), pa.int8()), "x0_mm": z, "y0_mm": z, "z0_mm": z,
        "x1_mm": z + 1, "y1_mm": z, "z1_mm": z, "feed_mm_min": np.full(n, feed),
        "spindle_rpm": np.full(n, rpm), "tool": pa.array([1] * n, pa.int32()),
        "t_start_s": z, "t_end_s": z + 1})


def test_forces_stage_table():
    import schemas
    E, dz = engagement_from_geometry("flat", 10.0, 2.0, 20, 360)
    n = 4
    eng = pa.table({"program_id": ["p"] * n, "pass_id": pa.array([3, 1, 0, 2], pa.int32()),
                    "dz_mm": np.full(n, dz), "n_z": pa.array([20] * n, pa.int32()),
                    "n_phi": pa.array([360] * n, pa.int32()),
                    "mask": pa.array([cutting.pack_engagement(E)] * n, pa.binary()),
                    "feed_dir_x": [1.0, 0.0, -1.0, np.sqrt(0.5)], "feed_dir_y": [0.0, 1.0, 0.0, np.sqrt(0.5)]})
    tool = _tool("flat", 2, 30.0)
    out = forces_stage.run({"passes": _passes_table(5), "generating": None, "engagement": eng},
                           {"tool": tool, "material": {"name": "m", **KC}})["forces"]
    out = schemas.check("forces", out)
    fx = np.array(out.column("fx_n").to_pylist())
    fy = np.array(out.column("fy_n").to_pylist())
    c = 1200.0 / (8000.0 * 2)
    tang, rad = 2 * 2.0 * c * KC["ktc"] / 4, 2 * 2.0 * c * KC["krc"] / 4
    # mean force in the feed frame (−rad, +tang) rotated by each row's feed direction
    for row, (dx, dy) in enumerate(zip(eng.column("feed_dir_x").to_pylist(), eng.column("feed_dir_y").to_pylist())):
        want = (dx * -rad - dy * tang, dy * -rad + dx * tang)
        assert np.allclose([fx[row].mean(), fy[row].mean()], want, rtol=0.01)
    assert out.column("feed_per_tooth_mm").to_pylist() == pytest.approx([c] * n)


def test_forces_stage_rejects_zero_spindle():
    from stages import InputError
    E, dz = engagement_from_geometry("flat", 10.0, 2.0, 4, 36)
    eng = pa.table({"program_id": ["p"], "pass_id": pa.array([0], pa.int32()), "dz_mm": [dz],
                    "n_z": pa.array([4], pa.int32()), "n_phi": pa.array([36], pa.int32()),
                    "mask": pa.array([cutting.pack_engagement(E)], pa.binary()),
                    "feed_dir_x": [1.0], "feed_dir_y": [0.0]})
    with pytest.raises(InputError, match="line 10"):
        forces_stage.run({"passes": _passes_table(1, rpm=0.0), "generating": None, "engagement": eng},
                         {"tool": _tool("flat", 2), "material": {"name": "m", **KC}})


# ------------------------------------------------------------------------------------------------
# calibration
# ------------------------------------------------------------------------------------------------
def analytic_flat_forces(theta_deg, N, a, c, k, psi_st, psi_ex):
    """Zero-helix flat end mill: closed-form force on the tool at each spindle angle."""
    out = np.zeros((len(theta_deg), 3))
    for j in range(N):
        psi = np.mod(np.radians(np.asarray(theta_deg) + 90 + 360.0 * j / N), 2 * np.pi)
        cut = (psi > psi_st) & (psi < psi_ex)
        h = c * np.sin(psi)
        ft, fr, fa = [(k[kc] * h + k[ke]) * a * cut for kc, ke in (("ktc", "kte"), ("krc", "kre"), ("kac", "kae"))]
        out[:, 0] += -ft * np.cos(psi) - fr * np.sin(psi)
        out[:, 1] += ft * np.sin(psi) - fr * np.cos(psi)
        out[:, 2] += -fa
    return out


def test_calibration_recovers_coefficients(tmp_path):
    """Records from the closed-form zero-helix model (+ 1 N noise) at two feeds, slot and half
    immersion: the fit returns the six coefficients within 2 % and R² > 0.99."""
    rng = np.random.default_rng(0)
    N, a = 3, 2.0
    tool = _tool("flat", N, 0.0)
    theta = (np.arange(720) + 0.5) * 0.5                        # off the bin edges
    paths, cuts = [], []
    for i, (feed, width) in enumerate([(900.0, None), (2400.0, None), (1500.0, 2.5)]):
        c = feed / (6000.0 * N)
        st, ex = (0.0, np.pi) if width is None else (np.pi - np.arccos(1 - width / 5.0), np.pi)
        f = analytic_flat_forces(theta, N, a, c, KE, st, ex) + rng.normal(0, 1.0, (len(theta), 3))
        p = tmp_path / f"rec{i}.csv"
        # a table dynamometer sees the force on the workpiece: the negative
        np.savetxt(p, np.column_stack([theta, -f]), delimiter=",", header="rotation_deg,fx_n,fy_n,fz_n",
                   comments="")
        paths.append(p)
        cuts.append({"axial_depth_mm": a, "radial_width_mm": width, "side": "right",
                     "feed_mm_min": feed, "spindle_rpm": 6000.0})
    fit = calibrate.calibrate_from_csv(paths, cuts, tool, forces_on="workpiece")
    for name in cutting.COEFF_NAMES:
        assert fit[name] == pytest.approx(KE[name], rel=0.02), name
    assert fit["r2"] > 0.99 and fit["rms_n"] < 1.2 and fit["rank"] == 6


def test_force_record_errors(tmp_path):
    from stages import InputError
    p = tmp_path / "rec.csv"
    p.write_text("angle,fx_n,fy_n,fz_n\n0,1,2,3\n")
    with pytest.raises(InputError, match="rec.csv:1"):
        calibrate.read_force_csv(p)
    p.write_text("rotation_deg,fx_n,fy_n,fz_n\n" + "0,1,2,3\n" * 6 + "7,1,x,3\n")
    with pytest.raises(InputError, match="rec.csv:8"):
        calibrate.read_force_csv(p)


# ------------------------------------------------------------------------------------------------
# ramps: the chip is the feed per tooth along the edge's envelope normal
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("ramp", [-90.0, -30.0, 0.0, 20.0, 75.0])
def test_chip_on_a_ramp_is_the_gap_between_consecutive_tooth_spheres(ramp):
    """Exact geometry: the sphere of the previous tooth, centred fz back along the 3-D feed; the
    chip at an edge point is how far inside that sphere's surface the point lies along its normal."""
    R, fz = 5.0, 0.01
    kap = np.radians(np.linspace(2.0, 90.0, 23))
    phi = np.radians(np.linspace(0.0, 359.0, 37))
    K, P = np.meshgrid(kap, phi, indexing="ij")
    u = np.stack([np.sin(K) * np.cos(P), np.sin(K) * np.sin(P), -np.cos(K)], -1)
    a = np.radians(ramp)
    v = np.array([np.cos(a), 0.0, np.sin(a)])
    # point p = R·u (centre at 0); previous centre −fz·v; distance t from p inward along u to that
    # sphere: |(R − t)·u + fz·v| = R  →  t = R + fz·v·u − sqrt(R² − fz²·(1 − (v·u)²))
    vu = u @ v
    t = R + fz * vu - np.sqrt(R * R - fz * fz * (1 - vu * vu))
    want = np.maximum(t, 0.0)
    got = cutting.chip_thickness_mm(fz, np.cos(P), np.sin(K), None, ramp)
    assert np.allclose(got, want, rtol=0, atol=fz * fz / R)      # first order in fz/R
    assert want.max() > 0.2 * fz                                  # not a vacuous all-zero case


def test_plunging_ball_force_matches_closed_form():
    """Ball plunging straight down (ramp −90°), whole lower hemisphere in the material: every edge
    cuts h = fz·cos κ; with two flutes 180° apart the horizontal forces cancel at every angle and
    Fz = N·R·(Krc·fz·π/4 + Kre − Kac·fz/2 − Kae) (∫cos²κ, ∫cos κ, ∫sin κ cos κ, ∫sin κ over 0…π/2)."""
    R, fz, N = 5.0, 0.05, 2
    n_z, n_phi = 400, 360
    E = np.ones((1, n_z, n_phi), bool)
    F = cutting.cutting_forces(E, R / n_z, fz, _tool("ball", N, 30.0), KE, ramp_deg=-90.0)[0]
    want = N * R * (KE["krc"] * fz * np.pi / 4 + KE["kre"] - KE["kac"] * fz / 2 - KE["kae"])
    assert np.allclose(F[:, 2], want, rtol=2e-3)
    assert np.abs(F[:, :2]).max() < 1e-6 * abs(want)
    # the same tool climbing (ramp +90°) cuts nothing with its underside
    assert np.abs(cutting.cutting_forces(E, R / n_z, fz, _tool("ball", N, 30.0), KE, ramp_deg=90.0)).max() == 0


def test_forces_stage_groups_passes_by_ramp():
    """Rows with different ramps in one table get each their own chip (the stage groups by ramp)."""
    E, dz = engagement_from_geometry("ball", 10.0, 5.0, 60, 360)
    ramps = [0.0, -90.0, 30.0]
    single = [cutting.cutting_forces(E[None], dz, 1200.0 / (8000.0 * 2), _tool("ball", 2, 30.0), KC,
                                     ramp_deg=r)[0] for r in ramps]
    eng = pa.table({"program_id": ["p"] * 3, "pass_id": pa.array([0, 1, 2], pa.int32()),
                    "dz_mm": np.full(3, dz), "n_z": pa.array([60] * 3, pa.int32()),
                    "n_phi": pa.array([360] * 3, pa.int32()),
                    "mask": pa.array([cutting.pack_engagement(E)] * 3, pa.binary()),
                    "feed_dir_x": [1.0] * 3, "feed_dir_y": [0.0] * 3, "ramp_deg": ramps})
    out = forces_stage.run({"passes": _passes_table(3), "generating": None, "engagement": eng},
                           {"tool": _tool("ball", 2, 30.0), "material": {"name": "m", **KC}})["forces"]
    for row, ref in enumerate(single):
        assert np.allclose(out.column("fz_n")[row].as_py(), ref[:, 2], rtol=1e-5, atol=1e-9)
    assert not np.allclose(single[0][:, 2], single[1][:, 2])
