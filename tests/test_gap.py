"""Gap diagnosis (issue 7): measurement reader errors, virtual-machine effect signatures against
closed forms, and a small blind check.

The closed forms use this file's own brute-force geometry (nearest tool-centre segment, times and
cut lengths summed from the passes table, corners from consecutive move directions), not the code
under test. Tolerances come from the feed-mark cusp of the discrete flutes, f²/(8R), fixed before
running: the virtual machine cuts with tooth passages, not a continuous envelope.
"""
from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import yaml
from click.testing import CliRunner

from stages import InputError
from stages.measurements import read_measurements
from stages.nc.reader import parse_program
from stages.nc.moves import split_blocks

ROOT = Path(__file__).resolve().parent.parent
SAMPLE = ROOT / "data_samples" / "gap"
TOOL = {"type": "ball", "diameter_mm": 6.0, "flutes": 2, "helix_deg": 30.0, "stickout_mm": 30.0, "runout_um": 0.0,
        "control_point": "tip", "profile": None, "corner_radius_mm": None, "t": None}
MAT = {"ktc": 2000, "krc": 700, "kac": 300, "kte": 20, "kre": 15, "kae": 5}
RIGID = {"frf": {"x": [{"fn_hz": 900, "zeta": 0.03, "k_n_per_um": 1e7}], "y": [{"fn_hz": 950, "zeta": 0.03, "k_n_per_um": 1e7}]}}
SOFT = {"frf": {"x": [{"fn_hz": 900, "zeta": 0.03, "k_n_per_um": 3.0}], "y": [{"fn_hz": 950, "zeta": 0.03, "k_n_per_um": 3.5}]}}
R = 3.0
FZ = 800.0 / (8000.0 * 2)                   # the sample program: F800, S8000, 2 flutes
CUSP_UM = (2 * FZ) ** 2 / (8 * R) * 1e3     # feed-mark cusp of one flute per revolution (runout)
TOL = 2 * CUSP_UM + 0.05


# ------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def sample():
    path = SAMPLE / "gap_t1.nc"
    blocks, _ = parse_program(path.read_bytes(), str(path), "gap_t1")
    passes = split_blocks(blocks, {"split": {"chord_tol_mm": 0.001, "max_pass_mm": 5.0, "merge_max_mm": 0.001},
                                   "machine": {"rapid_mm_min": 30000.0}, "tool": TOOL})
    plan, rej, _ = read_measurements(SAMPLE / "plan.csv", require_deviation=False)
    assert len(rej) == 0
    pts = np.stack([plan.column(c).to_numpy() for c in ("x_mm", "y_mm", "z_mm")], 1)
    nrm = np.stack([plan.column(c).to_numpy() for c in ("nx", "ny", "nz")], 1)
    return passes, pts, nrm


@pytest.fixture(scope="module")
def rigid(sample):
    from stages.virtual_machine import VirtualMachine
    return VirtualMachine(sample[0], TOOL, MAT, RIGID, str(SAMPLE / "stock.stl"))


@pytest.fixture(scope="module")
def ref(sample):
    """Brute-force association: nearest ball-centre segment of every cutting pass, and its features."""
    passes, pts, nrm = sample
    col = lambda c: passes.column(c).to_numpy().astype(float)  # noqa: E731
    cut = passes.column("motion").to_numpy() != 0
    a = np.stack([col("x0_mm"), col("y0_mm"), col("z0_mm") + R], 1)[cut]
    b = np.stack([col("x1_mm"), col("y1_mm"), col("z1_mm") + R], 1)[cut]
    t0, t1 = col("t_start_s")[cut], col("t_end_s")[cut]
    ln = np.linalg.norm(b - a, axis=1)
    keep = ln > 1e-9
    a, b, t0, t1, ln = a[keep], b[keep], t0[keep], t1[keep], ln[keep]
    L0 = np.concatenate([[0.0], np.cumsum(ln)[:-1]])
    c = pts + R * nrm
    ab = b - a
    u = np.clip(np.einsum("pkj,kj->pk", c[:, None, :] - a[None], ab) / np.sum(ab * ab, 1), 0, 1)
    d = np.linalg.norm(a[None] + u[..., None] * ab[None] - c[:, None, :], axis=2)
    k = np.argmin(d, axis=1)
    uk = u[np.arange(len(k)), k]
    s = L0[k] + uk * ln[k]
    # corners: touching consecutive moves turning by more than 20°
    dirs = ab / ln[:, None]
    ang = np.degrees(np.arccos(np.clip(np.sum(dirs[:-1] * dirs[1:], 1), -1, 1)))
    touch = np.linalg.norm(b[:-1] - a[1:], axis=1) < 1e-6
    ci = np.flatnonzero(touch & (ang > 20.0))
    cs = L0[ci + 1]
    bis = dirs[ci + 1] - dirs[ci]
    bis /= np.linalg.norm(bis, axis=1, keepdims=True)
    j = np.argmin(np.abs(s[:, None] - cs[None]), axis=1)
    return {"t": t0[k] + uk * (t1[k] - t0[k]), "L": s, "tip": a[k] + uk[:, None] * ab[k] - [0, 0, R],
            "q": np.degrees(np.arccos(nrm[:, 2])), "corner_d": np.abs(s - cs[j]), "corner_deg": ang[ci][j],
            "corner_b": bis[j], "n": nrm}


# ------------------------------------------------------------------------------------ reader
def _csv(tmp_path, text, name="m.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_reader_mapping_units_nan_and_bad_normal_listed(tmp_path):
    p = _csv(tmp_path, "PT;PX;PY;PZ;VI;VJ;VK;DEVI\n"
                       "1;1.0;2.0;3.0;0;0;1;0.002\n"
                       "2;1.0;2.0;nan;0;0;1;0.001\n"
                       "3;1.0;2.0;3.0;0;0;1.2;0.001\n"
                       "4;0.5;0.5;0.5;0.6;0;0.8;-0.003\n")
    cols = {"point_id": "PT", "x_mm": "PX", "y_mm": "PY", "z_mm": "PZ", "nx": "VI", "ny": "VJ", "nz": "VK",
            "err_um": "DEVI"}
    tab, rej, lines = read_measurements(p, cols, length_unit="inch", deviation_unit="mm")
    assert tab.column("point_id").to_pylist() == [1, 4]
    assert tab.column("x_mm").to_pylist() == pytest.approx([25.4, 12.7])
    assert tab.column("err_um").to_pylist() == pytest.approx([2.0, -3.0])
    reasons = {pid: (line, why) for pid, line, why in rej.rows}
    assert reasons[2][0] == 3 and "NaN" in reasons[2][1]
    assert reasons[3][0] == 4 and "normal length 1.2" in reasons[3][1]


@pytest.mark.parametrize("text, mapping, needle", [
    ("id,x,y,z,i,j,k,dev\n1,0,0,0,0,0,1,1.5\n1,1,0,0,0,0,1,2.0\n", {}, "duplicated point id 1"),
    ("id,x,y,z,i,j,k\n1,0,0,0,0,0,1\n", {}, "no column for ['err_um']"),
    ("id,x,y,z,i,j,k,dev\n1,0,0,0,0,0,1,0.002\n2,0,1,0,0,0,1,-0.001\n", {}, "looks like mm"),
    ("id,x,y,z,i,j,k,dev\n1,0,0,0,0,0,1,abc\n", {}, ":2: column 'dev'"),
    ("id,x,y,z,i,j,k,dev\n1,0,0,0,0,0,1,1\n", {"err_um": "Deviation"}, "measurements.columns.err_um"),
    ("id,x,y,z,i,j,k,dev [mm]\n1,0,0,0,0,0,1,0.001\n", {"deviation_unit": "um"}, "says mm"),
])
def test_reader_errors_name_file_line_and_key(tmp_path, text, mapping, needle):
    p = _csv(tmp_path, text)
    dev_unit = mapping.pop("deviation_unit", None)
    with pytest.raises(InputError) as e:
        read_measurements(p, mapping, deviation_unit=dev_unit)
    assert needle in str(e.value) and str(p) in str(e.value)


def test_reader_parquet_and_off_part_points_rejected(tmp_path, sample):
    from stages.gap import associate
    passes, pts, nrm = sample
    n = 60
    err = np.zeros(n)
    moved = pts[:n].copy()
    moved[5] += 1.0 * nrm[5]                     # 1 mm off the surface along its normal
    moved[7] += [0.0, 0.0, -0.5]                 # inside the part
    tab = pa.table({"point_id": pa.array(np.arange(n), pa.int64()), "x_mm": moved[:, 0], "y_mm": moved[:, 1],
                    "z_mm": moved[:, 2], "nx": nrm[:n, 0], "ny": nrm[:n, 1], "nz": nrm[:n, 2], "err_um": err,
                    "t_s": np.full(n, np.nan)})
    pq.write_table(tab, tmp_path / "m.parquet")
    back, rej, _ = read_measurements(tmp_path / "m.parquet")
    assert back.num_rows == n and len(rej) == 0
    F, rejected = associate(back, passes, None, TOOL)
    assert sorted(i for i, _ in rejected) == [5, 7]
    assert all("off the part" in why for _, why in rejected)
    assert len(F["point_id"]) == n - 2


# ------------------------------------------------------------------------------------ signatures
@pytest.fixture(scope="module")
def own(rigid, sample):
    """Plan points whose surface the nearest pass alone leaves (the closed forms below are that
    pass's; where a neighbouring pass cuts deeper, e.g. between rows, the probe sees both)."""
    _, pts, nrm = sample
    both = rigid.probe(pts, nrm)
    alone = rigid.probe(pts, nrm, probe_passes=1)
    mask = np.abs(both - alone) < 1e-3
    assert mask.mean() > 0.8
    return mask


def _diff(vm, sample, effects):
    _, pts, nrm = sample
    return vm.probe(pts, nrm, effects) - vm.probe(pts, nrm, {})


def test_runout_signature_is_minus_e_sin_q(rigid, sample, ref, own):
    d = _diff(rigid, sample, {"runout": {"e_um": 10.0, "phase_deg": 0.0}})
    expect = -10.0 * np.sin(np.radians(ref["q"]))
    assert np.max(np.abs(d - expect)[own]) <= TOL


def test_tool_contour_signature_is_the_profile_dent(rigid, sample, ref, own):
    e = {"a_um": 6.0, "q0_deg": 30.0, "width_deg": 8.0}
    d = _diff(rigid, sample, {"tool_contour": e})
    expect = 6.0 * np.exp(-0.5 * ((ref["q"] - 30.0) / 8.0) ** 2)
    assert np.max(np.abs(d - expect)[own]) <= TOL


def test_tool_wear_signature_grows_with_cut_length(rigid, sample, ref, own):
    d = _diff(rigid, sample, {"tool_wear": {"rate_um_per_m": 40.0}})
    assert np.max(np.abs(d - 40.0 * ref["L"] * 1e-3)[own]) <= TOL


def test_thermal_drift_signature_is_n_dot_a_exponential(rigid, sample, ref, own):
    a = np.array([3.0, -4.0, -8.0])
    tau = 4.0
    d = _diff(rigid, sample, {"thermal_drift": {"ax_um": a[0], "ay_um": a[1], "az_um": a[2], "tau_s": tau}})
    expect = (ref["n"] @ a) * (1 - np.exp(-ref["t"] / tau))
    assert np.max(np.abs(d - expect)[own]) <= TOL


def test_machine_geometry_signature_is_linear_in_tip_position(rigid, sample, ref, own):
    g = {"sx": 0.8, "sy": -0.5, "sz": 0.3, "exy": 0.4, "exz": -0.6, "eyz": 0.2}
    d = _diff(rigid, sample, {"machine_geometry": g})
    x, y, z = ref["tip"].T
    off = np.stack([g["sx"] * x + g["exy"] * y + g["exz"] * z, g["sy"] * y + g["eyz"] * z, g["sz"] * z], 1)
    assert np.max(np.abs(d - np.sum(off * ref["n"], 1))[own]) <= TOL


def test_servo_corner_signature_decays_from_the_corner(rigid, sample, ref):
    a, lam = 10.0, 0.8
    d = _diff(rigid, sample, {"servo_corner": {"a_um": a, "lambda_mm": lam}})
    expect = (np.sum(ref["corner_b"] * ref["n"], 1) * a * np.sin(np.radians(ref["corner_deg"]) / 2)
              / math.sin(math.pi / 4) * np.exp(-ref["corner_d"] / lam))
    # the tool moves ±1 revolution (2·fz) along the path between tooth passages: exp varies by that
    slack = 0.1 + np.abs(expect) * (math.exp(2 * FZ / lam) - 1)
    assert np.all(np.abs(d - expect) <= TOL + slack)
    assert np.max(np.abs(expect)) > 3.0            # the plan does reach the corners


def _corner_job():
    """A 20 mm move along +x turning 90° into +y (F800, S8000: fz = FZ), ball centres of the first leg
    d mm before the corner, contact points on the outer side of the turn at q = 45°."""
    from pipeline.gap import _meas_table
    from stages.gap import associate
    nc = "%\nG90 G17 G21\nS8000 M3\nG0 X-10. Y0. Z5.\nG1 Z0. F400\nG1 X10. F800\nG1 Y10.\nG0 Z10.\nM30\n%\n"
    blocks, _ = parse_program(nc.encode(), "corner.nc", "corner")
    passes = split_blocks(blocks, {"split": {"chord_tol_mm": 0.001, "max_pass_mm": 5.0, "merge_max_mm": 0.0},
                                   "machine": {"rapid_mm_min": 30000.0}, "tool": TOOL})
    q = math.radians(45.0)
    d = np.concatenate([np.linspace(0.01, 0.5, 25), np.linspace(0.6, 3.0, 13)])
    n = np.tile([0.0, math.sin(q), math.cos(q)], (len(d), 1))
    pts = np.stack([10 - d, np.zeros_like(d), np.full_like(d, R)], 1) - R * n
    F, rej = associate(_meas_table(np.arange(len(d)), pts, n, np.zeros(len(d))), passes, None, TOOL)
    assert not rej
    return F, np.argsort(F["point_id"]), d, pts, n


def _brute_force_lag_surface(d, pts, n, a_um, lam, phases=64, reach_mm=3.0):
    """This test's own surface of the corner job with a servo lag: every tooth passage (one per FZ,
    ±reach_mm along the two legs, lag a·e^(−|s − corner|/λ) towards the inside of the 90° turn)
    is a ball; the surface along n is the lowest entry into any of them, averaged over `phases`
    spindle phases, less the same without the lag (µm)."""
    b = np.array([-1.0, 1.0, 0.0]) / math.sqrt(2)
    k = np.arange(-int(reach_mm / FZ), int(reach_mm / FZ) + 1)
    out = np.zeros(len(d))
    for i in range(len(d)):
        s = 20.0 - d[i] + ((np.arange(phases) + 0.5) / phases - 0.5)[:, None] * FZ + k[None, :] * FZ
        cen = np.where((s <= 20.0)[..., None], np.stack([-10 + s, 0 * s, R + 0 * s], -1),
                       np.stack([10 + 0 * s, s - 20, R + 0 * s], -1))

        def entry(lag_um):
            cp = cen + lag_um[..., None] * b * 1e-3 - pts[i]
            A = cp @ n[i]
            inner = R * R - (np.sum(cp * cp, -1) - A * A)
            return np.where(inner >= 0, A - np.sqrt(np.maximum(inner, 0.0)), np.inf).min(axis=1)
        lag = a_um * np.exp(-np.abs(s - 20.0) / lam)       # sin(90°/2)/sin 45° = 1
        out[i] = np.mean(entry(lag) - entry(0 * lag)) * 1e3
    return out


@pytest.mark.parametrize("a_um,lam", [(25.0, 0.3), (-25.0, 0.3), (-25.0, 0.8), (10.0, 0.3)])
def test_servo_signature_is_the_tooth_passage_envelope(a_um, lam):
    """The diagnosis's servo-lag signature (8 phases, its own passage window) against this file's
    brute force (64 phases, ±3 mm of passages) at a straight 90° corner: within 0.1 µm (a third of
    the smallest probe noise the blind check draws); the smooth form a·(b·n)·e^(−d/λ) is not, at
    λ = 0.3 mm (the passage nearer the corner, with the larger lag, cuts deepest)."""
    from stages.gap import servo_signature, servo_smooth
    F, o, d, pts, n = _corner_job()
    ref = _brute_force_lag_surface(d, pts, n, a_um, lam)
    assert np.abs(ref).max() > 0.4 * abs(a_um)                      # the corner is reached
    assert np.max(np.abs(servo_signature(F, a_um, lam)[o] - ref)) <= 0.1
    if lam < 0.5:
        assert np.max(np.abs(a_um * servo_smooth(F, lam)[o] - ref)) > 0.25


@pytest.mark.parametrize("a_um,lam", [(30.0, 0.3), (-30.0, 0.3)])
def test_servo_fit_recovers_the_virtual_machines_lag(rigid, sample, a_um, lam):
    """Noise-free servo lags of the virtual machine (its own tooth passages at their real phase) on
    the sample plan: the fitted a and λ within 3 % (the smooth form alone read 30 → 27.7 µm and −30 → −34.5 µm)."""
    from pipeline.gap import _meas_table
    from stages.gap import associate, catalogue, fit_effects, refine_servo
    passes, pts, nrm = sample
    y = _diff(rigid, sample, {"servo_corner": {"a_um": a_um, "lambda_mm": lam}})
    F, _ = associate(_meas_table(np.arange(len(pts)), pts, nrm, y), passes, None, TOOL)
    eff = {e.name: e for e in catalogue(F)}["servo_corner"]
    allp = np.ones(len(F["q_deg"]), bool)
    th, beta = fit_effects(F, F["measured_um"], allp, [], eff)
    ch, beta = refine_servo(F, F["measured_um"], allp, [(eff, th)], beta)
    p = eff.params(beta, ch[0][1])
    assert p["a_um"] == pytest.approx(a_um, rel=0.03) and p["lambda_mm"] == pytest.approx(lam, rel=0.03)


def test_corner_floor_taken_from_a_reference_part_leaves_the_other_effects(rigid, sample):
    """A reference part whose residual near corners is a lag (the virtual machine's, +25 µm with
    λ 0.3 mm, noise-free): ``corner_floor`` reads it back within 3 %, and as part of the baseline
    it leaves of a part with that floor and a tool wear the wear alone (within 5 % of the floor's
    RMS; the two are not exactly additive: the deepest tooth passage takes both)."""
    from pipeline.gap import _meas_table
    from stages.gap import apply_baseline, associate, corner_floor
    passes, pts, nrm = sample
    lag = {"servo_corner": {"a_um": 25.0, "lambda_mm": 0.3}}
    wear = {"tool_wear": {"rate_um_per_m": 40.0}}
    y0 = _diff(rigid, sample, lag)
    F0, _ = associate(_meas_table(np.arange(len(pts)), pts, nrm, y0), passes, None, TOOL)
    a, lam = corner_floor(F0)
    assert a == pytest.approx(25.0, rel=0.03) and lam == pytest.approx(0.3, rel=0.03)
    y = _diff(rigid, sample, dict(lag, **wear))
    F, _ = associate(_meas_table(np.arange(len(pts)), pts, nrm, y), passes, None, TOOL)
    left = apply_baseline(F, 1.0, (a, lam))["residual_um"]
    only_wear = _diff(rigid, sample, wear)
    assert np.sqrt(np.mean((left - only_wear) ** 2)) < 0.05 * np.sqrt(np.mean(y0 ** 2))


def test_detection_limit_of_wear_next_to_a_drift_is_the_collinear_remainder(sample):
    """The stated detection limit of tool wear next to a chosen thermal drift, against this test's
    own least squares: the part of the wear signature (∝ L) a drift n·A·(1 − e^(−t/τ)) cannot
    reproduce, 1 − ρ², must carry the χ² test, and its own size where it acts must reach ½σ; on
    this raster (cut length grows with time, normals near z) ρ > 0.99 and the χ² test sets the
    limit, above the noise."""
    from scipy.stats import chi2
    from pipeline.gap import _meas_table
    from stages.gap import ALPHA, associate, catalogue, detection_limits
    passes, pts, nrm = sample
    F, _ = associate(_meas_table(np.arange(len(pts)), pts, nrm, np.zeros(len(pts))), passes, None, TOOL)
    cat = catalogue(F)
    drift = next(e for e in cat if e.name == "thermal_drift")
    tau = 0.8 * float(F["t_s"].max())
    lim = detection_limits(F, [(drift, (tau,))], cat, 0.5, 0.0)["tool_wear"]
    n = np.stack([F["nx"], F["ny"], F["nz"]], 1)
    D = n * (1 - np.exp(-F["t_s"] / tau))[:, None]
    L = F["cut_len_mm"]
    fit = D @ np.linalg.lstsq(D, L, rcond=None)[0]
    rho2 = 1 - np.sum((L - fit) ** 2) / np.sum(L ** 2)
    frac = np.mean(np.abs(L) > 0.1 * np.abs(L).max())
    N = len(L)
    ref = max(0.5 * math.sqrt(chi2.ppf(1 - ALPHA, 1) / (N * (1 - rho2))), 0.25 * math.sqrt(frac))
    assert lim["correlation"] == pytest.approx(math.sqrt(rho2), abs=1e-9)
    assert lim["hidden_up_to_um"] == pytest.approx(ref, rel=1e-6)
    # the χ² part sets it: a wear larger than the noise σ = 0.5 µm hides in the drift
    assert lim["masked_by"] == "thermal_drift" and lim["correlation"] > 0.99 and lim["hidden_up_to_um"] > 0.5


def test_wear_inside_a_drift_is_reported_as_ambiguous(rigid, sample):
    """A drift with a wear below its stated detection limit: the diagnosis names the drift, says
    the wear cannot be told from it (``ambiguous_with``) and that more wear than was machined could
    hide there; three times the limit is named."""
    from pipeline.gap import _meas_table
    from stages.gap import AMBIGUOUS_RHO, associate, diagnose
    passes, pts, nrm = sample
    T = float(rigid.path.t1.max())
    drift = {"ax_um": 6.0, "ay_um": -4.0, "az_um": -12.0, "tau_s": 0.8 * T}
    base = rigid.probe(pts, nrm, {})
    unit = rigid.probe(pts, nrm, {"tool_wear": {"rate_um_per_m": 1.0}}) - base
    unit_rms = float(np.sqrt(np.mean(unit ** 2)))

    def run(wear_rms, seed):
        eff = {"thermal_drift": drift}
        if wear_rms:
            eff["tool_wear"] = {"rate_um_per_m": wear_rms / unit_rms}
        y = rigid.probe(pts, nrm, eff, 0.5, np.random.default_rng(seed))
        F, _ = associate(_meas_table(np.arange(len(pts)), pts, nrm, y), passes, None, TOOL)
        return diagnose(F)
    lim = run(0.0, 1)["detection_limits"]["tool_wear"]["hidden_up_to_um"]
    assert lim > 0.5                     # above the noise σ
    low = run(0.5 * lim, 2)
    assert low["effects"] == ["thermal_drift"]
    amb = {a["effect"]: a for a in low["ambiguous_with"]["thermal_drift"]}
    assert "tool_wear" in amb and amb["tool_wear"]["correlation"] >= AMBIGUOUS_RHO
    assert low["detection_limits"]["tool_wear"]["hidden_up_to_um"] >= 0.5 * lim
    high = run(3.0 * lim, 3)
    assert set(high["effects"]) == {"thermal_drift", "tool_wear"}


# ------------------------------------------------------------------------------------ standard errors
@pytest.mark.parametrize("kind,truth,noise,draws", [
    ("thermal_drift", {"ax_um": 3.0, "ay_um": -4.0, "az_um": -8.0, "tau_frac": 0.4}, 0.7, 200),
    ("tool_contour", {"a_um": 5.0, "q0_deg": 25.0, "width_deg": 8.0}, 0.5, 200),
    ("servo_corner", {"a_um": 15.0, "lambda_mm": 0.6}, 0.7, 150),
])
def test_stated_standard_errors_match_the_spread_of_repeated_fits(rigid, sample, kind, truth, noise, draws):
    """Monte Carlo: one noise-free signature of the virtual machine on the sample plan, ``draws``
    Gaussian noise draws, each fitted as the diagnosis fits its final model (the selection's grid
    fit, then ``final_fit``). The empirical standard deviation of every parameter over the draws
    — this test's own reference, from repeated fitting — against the median standard error the
    diagnosis states (``param_uncertainty``): within 25 % (the reference's own sampling error is
    1/√(2·draws) ≈ 5–6 %). Linear amplitudes (the drift's A, the contour's a) and nonlinear values
    (τ, q0, width, the servo lag's a and λ, both read from the tooth-passage envelope)."""
    from pipeline.gap import _meas_table
    from stages.gap import associate, catalogue, final_fit, fit_joint, noise_sigma, param_uncertainty
    passes, pts, nrm = sample
    truth = dict(truth)
    if kind == "thermal_drift":
        truth["tau_s"] = truth.pop("tau_frac") * float(rigid.path.t1.max())
    sig = _diff(rigid, sample, {kind: truth})
    F, _ = associate(_meas_table(np.arange(len(pts)), pts, nrm, sig), passes, None, TOOL)
    eff = {e.name: e for e in catalogue(F)}[kind]
    allp = np.ones(len(F["q_deg"]), bool)
    rng = np.random.default_rng(1)
    fits, ses = [], []
    for _ in range(draws):
        y = F["measured_um"] + rng.normal(0.0, noise, len(allp))
        _, th, _ = fit_joint(F, y, allp, [], eff)
        chosen, beta = final_fit(F, y, [(eff, th)])
        fits.append(eff.params(beta, chosen[0][1]))
        ses.append(param_uncertainty(F, y, chosen, beta, noise_sigma(F, y))["se"][kind])
    for k in truth:
        v = np.array([f[k] for f in fits])
        se = float(np.median([s[k] for s in ses]))
        assert np.std(v, ddof=1) == pytest.approx(se, rel=0.25), (k, np.std(v, ddof=1), se)
        assert abs(v.mean() - truth[k]) <= 0.5 * se, (k, v.mean(), truth[k], se)


def test_standard_errors_of_parameters_the_points_cannot_tell_apart_are_null_with_a_reason():
    """Degenerate cases: a machine geometry on points all at z = 0 (its z terms sz, exz, eyz are
    zero on them) and, separately, a wear whose signature L equals the predicted deflection (force
    scale): those parameters get no standard error and a reason; the others stay finite and agree
    with this test's own (XᵀX)⁻¹ on the identifiable columns."""
    from stages.gap import Effect, param_uncertainty
    g = np.random.default_rng(2)
    n = 300
    nrm = g.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    F = {"q_deg": np.zeros(n), "nx": nrm[:, 0], "ny": nrm[:, 1], "nz": nrm[:, 2], "tip_x_mm": g.uniform(-5, 5, n),
         "tip_y_mm": g.uniform(-5, 5, n), "tip_z_mm": np.zeros(n), "cut_len_mm": g.uniform(0, 1000, n)}
    F["pred_deflection_um"] = F["cut_len_mm"] * 1e-3
    geo = Effect("machine_geometry", [()], 6)
    y = geo.basis(F, ()) @ np.array([1.0, -0.5, 0.0, 0.3, 0.0, 0.0]) + g.normal(0, 0.5, n)
    u = param_uncertainty(F, y, [(geo, ())], np.array([1.0, -0.5, 0.0, 0.3, 0.0, 0.0]), 0.5)
    se = u["se"]["machine_geometry"]
    assert se["sz"] is None and se["exz"] is None and se["eyz"] is None
    assert all("not identifiable" in u["not_identifiable"][f"machine_geometry.{k}"] for k in ("sz", "exz", "eyz"))
    X = geo.basis(F, ())[:, [0, 1, 3]]
    ref = u["sigma_um"] * np.sqrt(np.diag(np.linalg.inv(X.T @ X)))
    assert [se["sx"], se["sy"], se["exy"]] == pytest.approx(ref, rel=1e-6)
    wear, fs = Effect("tool_wear", [()], 1), Effect("force_scale", [()], 1)
    u = param_uncertainty(F, y, [(wear, ()), (fs, ())], np.array([1.0, 0.0]), 0.5)
    assert u["se"] == {"tool_wear": {"rate_um_per_m": None}, "force_scale": {"scale": None}}
    assert "force_scale.scale" in u["not_identifiable"]["tool_wear.rate_um_per_m"]


def test_fits_beyond_a_real_machines_limits_are_flagged():
    """Limits: 4 × the largest the seeds measured (seed 003: 50 µm of drift after 3 h, 50 µm over
    ±20 mm of position error, 10 µm of holder runout); the drift is the one reached by the run's end."""
    from stages.gap import LIMITS, Effect, beyond_limits
    assert LIMITS == {"thermal_drift": 200.0, "machine_geometry": 10.0, "runout": 40.0, "tool_contour": 40.0}
    T = 100.0
    F = {"t_s": np.linspace(0.0, T, 11)}
    drift, geo = Effect("thermal_drift", [(1.0,)], 3), Effect("machine_geometry", [()], 6)
    reached = lambda a, tau: a * (1 - math.exp(-T / tau))  # noqa: E731
    assert reached(201.0, T / 10) > 200 and beyond_limits(F, [(drift, (T / 10,))], np.array([0, 201.0, 0])) == ["thermal_drift"]
    assert beyond_limits(F, [(drift, (T / 10,))], np.array([0, 199.0, 0])) == []
    # a 1 mm asymptote with τ = 10 T has reached 95 µm by the end: a slow linear drift, plausible
    assert reached(1000.0, 10 * T) < 100 and beyond_limits(F, [(drift, (10 * T,))], np.array([600.0, 0, 800.0])) == []
    # the linear parameters are read in the effects' order
    assert beyond_limits(F, [(geo, ()), (drift, (T,))], np.r_[0, 0, 0, 0, -10.5, 0, 1, 2, 3]) == ["machine_geometry"]
    assert beyond_limits(F, [(drift, (T,)), (geo, ())], np.r_[1, 2, 3, 0, 0, 0, 0, -9.5, 0]) == []


def test_force_scale_scales_the_deflection_part(sample):
    from stages.geometry.paths import nearest_pass
    from stages.virtual_machine import VirtualMachine
    passes, pts, nrm = sample
    passes = passes.slice(0, 120)                  # the first rows: two machines built in seconds
    soft = VirtualMachine(passes, TOOL, MAT, SOFT, str(SAMPLE / "stock.stl"))
    stiff = VirtualMachine(passes, TOOL, MAT, RIGID, str(SAMPLE / "stock.stl"))
    row, u, dist = nearest_pass(soft.path, pts + R * nrm)
    # the deflection scales exactly where the tooth passages that cut a point (±1 revolution) are
    # all on its own pass; beyond a pass's end they carry the neighbour's deflection, and which of
    # them cuts deepest may change with the scale
    p = soft.path
    rev = p.feed[row] / p.rpm[row] * 1.5
    mine = (dist < 0.05) & (u * p.length[row] >= rev) & ((1 - u) * p.length[row] >= rev)
    pts, nrm = pts[mine], nrm[mine]
    assert len(pts) >= 50
    dfl = soft.probe(pts, nrm) - stiff.probe(pts, nrm)
    assert np.percentile(np.abs(dfl), 90) > 1.0    # deflection matters on this part
    d = soft.probe(pts, nrm, {"force_scale": {"scale": 1.6}}) - soft.probe(pts, nrm)
    assert np.max(np.abs(d - 0.6 * dfl)) <= 2 * TOL


def _wall_program(offset_um):
    """Ball Ø10 along +x at y = 0, the wall on its −y side at y = −5 (n = +y, q = 90°): a long pass
    A (x 0–10), a 0.05 mm pass B, a long pass C (x 10.05–20, moved away from the wall by
    ``offset_um``). F1000 S10000: 0.1 mm of feed per revolution, B shorter than it."""
    off = offset_um * 1e-3
    src = (f"%\nO1\nT1 M6\nS10000 M3\nG0 X0 Y0 Z5\nG1 Z0 F1000\nX10\nX10.05\nX10.05 Y{off:.4f}\n"
           f"X20 Y{off:.4f}\nG0 Z5\nM30\n%\n").encode()
    blocks, _ = parse_program(src, "wall.nc", "w")
    split = {"split": {"chord_tol_mm": 0.001, "max_pass_mm": 50.0, "merge_max_mm": 0.0},
             "machine": {"rapid_mm_min": 30000.0}, "tool": {"type": "ball", "diameter_mm": 10.0}}
    return split_blocks(blocks, split)


@pytest.mark.parametrize("offset_um", [0.0, 3.0, 8.0])
def test_predicted_error_is_the_deepest_tooth_passage_of_the_neighbouring_passes(offset_um):
    """Deflection pushes A, B, C away from the wall by a constant 10, 30, 5 µm. A point swept by
    the tooth passages of neighbouring passes (within 1.5 revolutions = 0.15 mm of feed along the
    path) is left by the deepest of them: its own pass's error or a neighbour's error plus the
    neighbour's nominal stand-off from it, here the distance from the point to the ball at the
    neighbour's nearest end, hypot(δ, 5 mm + offset) − 5 mm (δ along the wall). Points farther than
    0.15 mm from another pass keep their own pass's error. Re-predicted with the deflection × 2 on
    a subset of the points, every error and stand-off term follows; the deflection part is the
    winning passage's error without its stand-off (the stand-off does not scale with the forces).

    Every neighbour here reaches the points only from one of its ends (the path is straight): the
    deflection cannot change at a vertex, so every point keeps its own pass's error."""
    from stages.gap import associate, predicted_at_points
    R10 = 5.0
    off = offset_um * 1e-3
    passes = _wall_program(offset_um)
    pid = passes.column("pass_id").to_numpy()
    x0, x1 = passes.column("x0_mm").to_numpy(), passes.column("x1_mm").to_numpy()
    cut = (passes.column("motion").to_numpy() == 1) & (passes.column("z0_mm").to_numpy() == 0) \
        & (passes.column("z1_mm").to_numpy() == 0)
    a = int(pid[cut & (x0 == 0) & (x1 == 10)][0])
    b = int(pid[cut & (x0 == 10) & (x1 == 10.05)][0])
    c = int(pid[cut & (x0 == 10.05) & (x1 == 20)][0])
    n_rot = 64

    def defl(k):
        return pa.table({"program_id": ["w"] * 3, "pass_id": pa.array([a, b, c], pa.int32()),
                         "rotation_deg": [list(np.arange(n_rot) * 360.0 / n_rot)] * 3,
                         "dx_um": [[0.0] * n_rot] * 3,
                         "dy_um": [[10.0 * k] * n_rot, [30.0 * k] * n_rot, [5.0 * k] * n_rot]})

    def want(k):
        """(error, deflection part) per point, from the construction."""
        ea, eb, ec = 10.0 * k, 30.0 * k, 5.0 * k
        return [(ea, ea)] * 7 + [(eb, eb)] + [(ec, ec)] * 6

    # on the wall at the ball's equator: six points mid A, one 0.01 mm before A's end, mid B, six mid C
    x = np.array([2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 9.99, 10.025, 13.0, 14.0, 15.0, 16.0, 17.0, 18.0])
    y = np.where(x > 10.05, -R10 + off, -R10)
    n = len(x)
    meas = pa.table({"point_id": pa.array(np.arange(n), pa.int64()), "x_mm": x, "y_mm": y,
                     "z_mm": np.full(n, R10), "nx": np.zeros(n), "ny": np.ones(n), "nz": np.zeros(n),
                     "err_um": np.zeros(n), "t_s": np.full(n, np.nan)})
    tool = {"type": "ball", "diameter_mm": 10.0, "flutes": 2, "helix_deg": 0.0, "stickout_mm": 20.0,
            "runout_um": 0.0, "control_point": "tip"}
    F, rej = associate(meas, passes, None, tool, 0.05, defl(1.0))
    assert not rej
    got = dict(zip(F["point_id"].tolist(), F["predicted_um"].tolist()))
    got_d = dict(zip(F["point_id"].tolist(), F["pred_deflection_um"].tolist()))
    for i, (e, d) in enumerate(want(1.0)):
        assert got[i] == pytest.approx(e, abs=1e-6), i
        assert got_d[i] == pytest.approx(d, abs=1e-9), i
    np.testing.assert_allclose(F["residual_um"], -F["predicted_um"])
    # re-predicted with another deflection table on a subset of the points
    rows = np.zeros(n, bool)
    rows[np.isin(F["point_id"], [0, 6, 7, 13])] = True
    e2, d2, s2 = predicted_at_points(F, lambda prog: defl(2.0), tool, rows)
    w2 = want(2.0)
    np.testing.assert_allclose(e2, [w2[i][0] for i in F["point_id"][rows]], atol=1e-6)
    np.testing.assert_allclose(d2, [w2[i][1] for i in F["point_id"][rows]], atol=1e-9)
    np.testing.assert_allclose(s2, 0.0)
    # a runout e moves the largest flute out by e on every pass: every passage cuts e deeper (q = 90°)
    r3 = predicted_at_points(F, lambda prog: defl(1.0), dict(tool, runout_um=2.0), runout_part=True)[0]
    np.testing.assert_allclose(r3, -2.0, atol=1e-9)


def test_simulated_deflection_matches_static_compliance_for_constant_force():
    from stages.virtual_machine import simulate_deflection
    f = np.full((2, 96), 12.0)                      # N, constant over the revolution
    d = simulate_deflection(f, np.array([6000.0, 9000.0]), [(900.0, 0.03, 3.0), (2000.0, 0.05, 6.0)])
    assert np.allclose(d, 12.0 / 3.0 + 12.0 / 6.0, atol=1e-6)


# ------------------------------------------------------------------------------------ blind check
def test_small_blind_check_names_effects_and_none(rigid, sample):
    """14 single cases (2 per effect, 2 none; force_scale needs a predicted deflection, absent on the
    rigid machine) and 2 two-effect cases, prediction = the rigid machine's (zero)."""
    from pipeline.gap import blind_cases
    passes, pts, nrm = sample
    kinds = ["none", "runout", "tool_contour", "tool_wear", "thermal_drift", "servo_corner", "machine_geometry"]
    s = blind_cases(rigid, passes, None, TOOL, pts, nrm, cases=14, seed=20261123, pairs=2, kinds=kinds)
    assert s["top1_accuracy"] >= 12 / 14
    assert s["none_correct"] == 1.0
    assert s["median_shrink"] >= 0.7
    assert s["param_error"]["median"] <= 0.2
    # both effects of each pair are named; their order of size is measured by the full blind check
    # (README), not asserted on two cases
    pairs = [c for c in s["cases_detail"] if len(c["truth"]) == 2]
    assert len(pairs) == 2 and all(set(c["truth"]) <= set(c["found"]) for c in pairs)
    # every found true effect's parameters against the truth in stated standard errors
    ps = s["param_se"]
    assert ps["n_params"] >= 12 and ps["coverage_2se"] is not None
    for c in s["cases_detail"]:
        assert set(c["param_z"]) == set(c["truth"]) & set(c["found"])
        if c.get("param_error", 0) > 0.2:
            assert c["param_miss"] and all(t["rel_error"] > 0.2 for t in c["param_miss"])
    # a true effect not named is listed with the detection limit the diagnosis stated for it
    assert set(s["misses_within_stated_limit"]) == {"single", "pair"}
    for c in s["cases_detail"]:
        for m in c.get("missed", []):
            assert m["effect"] in c["truth"] and m["hidden_up_to_um"] is not None and m["true_rms_um"] > 0



@pytest.fixture(scope="module")
def sample_vm(tmp_path_factory):
    """The sample gap job with its own prediction and the virtual machine on its plan: (measured
    (truth, σ, seed) → associated points, calibration on an effect-free reference, predictor)."""
    from pipeline.gap import _meas_table, _spec, _tool, calibrate, make_predictor, run_tables
    from pipeline.config import load_workflow
    from stages.gap import associate
    from stages.virtual_machine import VirtualMachine
    tmp_path = tmp_path_factory.mktemp("sample_vm")
    wf_text = (ROOT / "workflows" / "gap.yaml").read_text().replace("data_samples/", f"{ROOT}/data_samples/")
    wf_path = tmp_path / "gap.yaml"
    wf_path.write_text(wf_text.replace("output: runs/gap", f"output: {tmp_path / 'out'}"))
    wf, base = load_workflow(str(wf_path))
    spec = _spec(wf, base)
    tabs, _, run = run_tables(str(wf_path), "errors")
    passes = tabs["passes"]
    tool = _tool(wf, passes)
    vm = VirtualMachine(passes, tool, wf.material.model_dump(), wf.machine.model_dump(), run._static["stock"][0])
    plan, _, _ = read_measurements(SAMPLE / "plan.csv", require_deviation=False)
    pts = np.stack([plan.column(c).to_numpy() for c in ("x_mm", "y_mm", "z_mm")], 1)
    nrm = np.stack([plan.column(c).to_numpy() for c in ("nx", "ny", "nz")], 1)
    ids = np.arange(len(pts))
    predictor = make_predictor(tabs, wf, tool, workdir=tmp_path / "profiles")

    def measured(truth, sigma, seed):
        err = vm.probe(pts, nrm, truth, sigma, np.random.default_rng(seed))
        return associate(_meas_table(ids, pts, nrm, err), passes, tabs["errors"], tool, spec.off_part_mm,
                         tabs["deflection"])[0]
    return measured, calibrate(measured({}, 0.65, 1795569132 + 7919), predictor), predictor


def _diagnosed(sample_vm, truth, sigma, seed):
    from pipeline.gap import diagnose_points
    from stages.gap import apply_baseline
    measured, cal, predictor = sample_vm
    F = apply_baseline(measured(truth, sigma, seed), cal["force_scale_s0"], cal["corner_floor"])
    return diagnose_points(F, None, cal["floor_um"], predictor)


def test_wear_next_to_a_force_scale_is_not_read_as_a_drift(sample_vm):
    """A blind-check pair the diagnosis got wrong (seed 1795569132, case 81), re-run on the sample
    job with its own prediction: a tool wear of 30.3 µm/m (3.5 µm RMS) and a force scale of 2.82
    (1.8 µm RMS) at σ 0.64 µm. Forward selection chose a machine-geometry error, the force scale,
    then a thermal drift 25 σ² better than the wear next to the geometry error; the backward check
    then dropped the geometry error and the drift stayed. Judging the swaps again without it
    (``stages.gap.settle``) names the truth, in its order of size."""
    truth = {"tool_wear": {"rate_um_per_m": 30.341115229078135}, "force_scale": {"scale": 2.8222396060741275}}
    res = _diagnosed(sample_vm, truth, 0.64, 1001)
    assert res["effects"] == ["tool_wear", "force_scale"]
    assert res["params"]["tool_wear"]["rate_um_per_m"] == pytest.approx(30.34, rel=0.2)
    assert res["params"]["force_scale"]["scale"] == pytest.approx(2.822, rel=0.2)


def test_wear_next_to_a_contour_error_is_not_read_as_a_drift(sample_vm):
    """A blind-check pair the diagnosis got wrong (seed 1795578753, case 102): a tool wear of
    44.8 µm/m (5.2 µm RMS) and a 12 µm tool-contour error at q 16.9°, width 6.8° (3.0 µm RMS), σ
    0.84 µm. On the held-out blocks a thermal drift beat the wear by 200 σ² (the block holding the
    contour's peak: the contour refitted next to the wear slid to another centre on the remaining
    flanks), while on all points the wear fits better by 20 σ² with three parameters fewer; the
    pick now requires both to favour the richer effect (``stages.gap._pick``). The truth, in its
    order of size, with parameters within 20 %; noise-free the wear alone fits the VM's wear to
    0.001 µm RMS, the drift leaves 0.29 µm."""
    truth = {"tool_wear": {"rate_um_per_m": 44.762}, "tool_contour": {"a_um": 12.0, "q0_deg": 16.858, "width_deg": 6.806}}
    res = _diagnosed(sample_vm, truth, 0.84, 1000)
    assert res["effects"] == ["tool_wear", "tool_contour"]
    assert res["params"]["tool_wear"]["rate_um_per_m"] == pytest.approx(44.76, rel=0.2)
    for k, v in truth["tool_contour"].items():
        assert res["params"]["tool_contour"][k] == pytest.approx(v, rel=0.2), k


def test_wear_next_to_a_drift_is_named_with_it(sample_vm):
    """A blind-check pair the diagnosis got wrong (seed 1795581749, case 87): a tool wear of 30.8
    µm/m (3.5 µm RMS) and a thermal drift (−7.9, −1.5, −0.7) µm, τ 10.2 s (1.7 µm RMS), σ 0.85 µm.
    On this plan's normals the wear lies along a drift at correlation 0.998: the drift alone
    stretched its τ to 150 s to mimic the wear's ramp, and the wear then explained only 0.3 µm
    beyond it (held-out gain 87 σ², significant). Fitted together they come out at the truth; for
    a candidate this collinear the size test takes its own contribution
    (``stages.gap.collinear_size``)."""
    truth = {"tool_wear": {"rate_um_per_m": 30.765},
             "thermal_drift": {"ax_um": -7.908, "ay_um": -1.459, "az_um": -0.742, "tau_s": 10.176}}
    res = _diagnosed(sample_vm, truth, 0.847, 1000)
    assert res["effects"] == ["tool_wear", "thermal_drift"]
    assert res["params"]["tool_wear"]["rate_um_per_m"] == pytest.approx(30.77, rel=0.2)
    assert res["params"]["thermal_drift"]["ax_um"] == pytest.approx(-7.908, rel=0.2)
    assert res["params"]["thermal_drift"]["tau_s"] == pytest.approx(10.18, rel=0.2)


class _LinearVM:
    """Stand-in for the virtual machine whose effects add known patterns (for the pair generator)."""
    def __init__(self, n=200):
        g = np.random.default_rng(5)
        self.pat = {"runout": g.normal(size=n), "force_scale": g.normal(size=n), "servo_corner": g.normal(size=n)}

    def probe(self, pts, nrm, eff, noise=0.0, rng=None):
        out = np.zeros(len(pts))
        for k, v in eff.items():
            amp = v["scale"] - 1.0 if k == "force_scale" else v["e_um"] if k == "runout" else v["a_um"]
            out += amp * self.pat[k]
        return out


@pytest.mark.parametrize("truth", [
    {"runout": {"e_um": 10.0, "phase_deg": 0.0}, "force_scale": {"scale": 0.5}},      # second must grow: a
    {"force_scale": {"scale": 0.4}, "servo_corner": {"a_um": 10.0, "lambda_mm": 1.0}},  # scale < 0 before
    {"runout": {"e_um": 2.0, "phase_deg": 0.0}, "servo_corner": {"a_um": 20.0, "lambda_mm": 1.0}},
])
def test_pair_sizes_are_in_order_and_physical(truth):
    """Pairs: the second effect's RMS is `ratio` × the first's, with the force scale within the
    drawn range [1/3.5, 3.5] and no other amplitude beyond its drawn value (without the part's
    context the others may not grow: the first is made smaller instead)."""
    from pipeline.gap import _distinct_sizes, _true_order
    vm = _LinearVM()
    pts = np.zeros((200, 3))
    out = _distinct_sizes(truth, vm, pts, pts, 0.6)
    rms = {k: float(np.sqrt(np.mean(vm.probe(pts, pts, {k: v}) ** 2))) for k, v in out.items()}
    first, second = list(truth)
    assert rms[second] == pytest.approx(0.6 * rms[first], rel=1e-9)
    assert _true_order(out, vm, pts, pts) == [first, second]
    for k, v in out.items():
        if k == "force_scale":
            assert 1 / 3.5 - 1e-9 <= v["scale"] <= 3.5 + 1e-9
        else:
            amp = "e_um" if k == "runout" else "a_um"
            assert abs(v[amp]) <= abs(truth[k][amp]) + 1e-12


def test_pair_second_effect_stays_within_its_drawn_range():
    """With the part's context, a second effect is never scaled below the range the single-effect
    cases draw from (runout ≥ 4 µm): the first grows instead, within its own range; when it cannot,
    there is no such pair (None: the blind check draws again)."""
    from pipeline.gap import _RANGES, _distinct_sizes
    vm = _LinearVM()
    pts = np.zeros((200, 3))
    ctx = {"tips": pts, "cut_len_mm": 1000.0}
    rms = lambda k, v: float(np.sqrt(np.mean(vm.probe(pts, pts, {k: v}) ** 2)))  # noqa: E731
    truth = {"servo_corner": {"a_um": 10.0, "lambda_mm": 1.0}, "runout": {"e_um": 15.0, "phase_deg": 0.0}}
    out = _distinct_sizes(truth, vm, pts, pts, 0.2, ctx)
    # the plain rescale would make the runout 0.2·10·|servo|/|runout| ≈ 2 µm, below its 4 µm
    assert 0.2 * 10.0 * rms("servo_corner", {"a_um": 1.0}) / rms("runout", {"e_um": 1.0}) < _RANGES["runout"][0]
    assert out["runout"]["e_um"] == pytest.approx(_RANGES["runout"][0])
    assert rms("runout", out["runout"]) == pytest.approx(0.2 * rms("servo_corner", out["servo_corner"]), rel=1e-9)
    assert abs(out["servo_corner"]["a_um"]) <= _RANGES["servo_corner"][1]
    # a force scale of 3 can grow only to 3.5 (amplitude × 1.25), too little for a 30 µm servo lag
    # that may shrink only to 10 µm
    assert _distinct_sizes({"force_scale": {"scale": 3.0}, "servo_corner": {"a_um": 30.0, "lambda_mm": 1.0}},
                           vm, pts, pts, 0.5, ctx) is None


# ------------------------------------------------------------------------------------ CLI
def test_cli_simulate_writes_a_measurement_file_the_reader_accepts(tmp_path):
    from pipeline.cli import main
    for f in ("stock.stl", "plan.csv"):
        shutil.copy(SAMPLE / f, tmp_path / f)
    lines = (SAMPLE / "gap_t1.nc").read_text().splitlines()      # the first rows of the sample
    (tmp_path / "rows.nc").write_text("\n".join(lines[:120] + ["G0 Z10.", "M5", "M30", "%"]) + "\n")
    wf = {"name": "g", "programs": "rows.nc", "stock": "stock.stl", "tool": {k: v for k, v in TOOL.items()
                                                                              if k not in ("t", "corner_radius_mm", "profile")},
          "material": dict(MAT, name="FCD550"), "machine": RIGID, "measurements": "plan.csv", "output": "out",
          "until": "split"}
    (tmp_path / "wf.yaml").write_text(yaml.safe_dump(wf))
    r = CliRunner().invoke(main, ["simulate", str(tmp_path / "wf.yaml"), "--effect", "runout:e_um=8",
                                  "--noise-um", "0", "--out", str(tmp_path / "m.csv")], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    tab, rej, _ = read_measurements(tmp_path / "m.csv")
    n = np.stack([tab.column(c).to_numpy() for c in ("nx", "ny", "nz")], 1)
    expect = -8.0 * np.sqrt(1 - n[:, 2] ** 2)
    assert tab.num_rows >= 50
    assert len(rej) == 0 and np.max(np.abs(tab.column("err_um").to_numpy() - expect)) <= TOL
    r = CliRunner().invoke(main, ["simulate", str(tmp_path / "wf.yaml"), "--effect", "spindle:x=1",
                                  "--out", str(tmp_path / "m2.csv")])
    assert r.exit_code == 2 and "unknown effect 'spindle'" in r.output


def test_cli_run_simulate_diagnose_end_to_end_on_two_rows(tmp_path):
    """The whole job on the first two rows of the sample: prediction through the render chain, a
    runout of 10 µm on the virtual machine, the diagnosis with its tables, summary and report."""
    import json
    from pipeline.cli import main
    lines = (SAMPLE / "gap_t1.nc").read_text().splitlines()
    (tmp_path / "two.nc").write_text("\n".join(lines[:7] + lines[7:49] + ["G0 Z10.", "M5", "M30", "%"]) + "\n")
    shutil.copy(SAMPLE / "stock.stl", tmp_path / "stock.stl")
    wf = {"name": "two", "programs": "two.nc", "stock": "stock.stl",
          "tool": {"type": "ball", "diameter_mm": 6.0, "flutes": 2, "helix_deg": 30.0, "stickout_mm": 30.0},
          "material": dict(MAT, name="FCD550"),
          "machine": {"frf": {"x": [{"fn_hz": 900, "zeta": 0.03, "k_n_per_um": 8.0}],
                              "y": [{"fn_hz": 950, "zeta": 0.03, "k_n_per_um": 9.0}]}},
          "prune": {"min_contact_deg": 0}, "split": {"merge_max_mm": 0.001}, "output": "out"}
    (tmp_path / "wf.yaml").write_text(yaml.safe_dump(wf))
    run = lambda *a: CliRunner().invoke(main, [str(x) for x in a], catch_exceptions=False)  # noqa: E731
    r = run("simulate", tmp_path / "wf.yaml", "--effect", "runout:e_um=10", "--noise-um", "0.3", "--seed", "3",
            "--plan", SAMPLE / "plan.csv", "--out", tmp_path / "m.csv")
    assert r.exit_code == 0, r.output
    r = run("diagnose", tmp_path / "wf.yaml", "--measurements", tmp_path / "m.csv")
    assert r.exit_code == 0, r.output
    g = tmp_path / "out" / "gap"
    s = json.loads((g / "summary.json").read_text())
    assert s["effect"] == "runout" and abs(s["params"]["runout"]["e_um"] - 10.0) <= 2.0
    # on these two rows a thermal drift and a machine geometry fit far beyond any real machine's
    # (hundreds of µm, cancelling each other): that combination is listed, not chosen. What may
    # be named next to the runout on 123 points is one small effect within the limits (a −2 µm
    # lag before the pass-end passages were dropped, a 2–3 µm/mm geometry error since)
    from stages.gap import LIMITS
    assert "thermal_drift" not in s["effects"] and len(s["effects"]) <= 2
    if "machine_geometry" in s["effects"]:
        assert max(abs(v) for v in s["params"]["machine_geometry"].values()) <= LIMITS["machine_geometry"]
    # how far: the runout was added to the simulation itself (tool.runout_um) and the errors stage
    # re-run: its runout part at every generating point is ±e·sin q of the flute left (e: the fit)
    assert s["how_added"]["runout"].startswith("re-predicted")
    upd = pq.read_table(g / "errors_updated.parquet")
    e_fit = s["params"]["runout"]["e_um"]
    q = np.radians(upd.column("contact_deg").to_numpy())
    assert np.allclose(np.abs(upd.column("err_runout_um").to_numpy()), e_fit * np.sin(q), atol=1e-6)
    assert np.mean(upd.column("err_runout_um").to_numpy() < 0) > 0.9    # mostly the long flute
    assert s["rms_after_um"] < 0.5 * s["rms_before_um"] and s["shrink"] == pytest.approx(1 - s["rms_after_um"] / s["rms_before_um"])
    assert s["where"] and all(k in s["where"][0] for k in ("bbox_mm", "pass_range", "contact_deg", "time_s", "mean_residual_um"))
    assert "residual_map.png" in (g / "index.html").read_text() and (g / "residual_map.png").stat().st_size > 10_000
    assert "runout" not in s["detection_limits"] and s["detection_limits"]["tool_wear"]["hidden_up_to_um"] > 0
    assert "Not seen" in (g / "index.html").read_text()
    # every fitted parameter has a stated standard error (summary, gap_effects, report)
    se = s["params_se"]["runout"]
    assert set(se) == set(s["params"]["runout"]) and 0 < se["e_um"] < 1.0
    assert s["params_se_info"]["sigma_um"] >= s["sigma_um"] and not s["params_se_info"]["not_identifiable"]
    assert "standard errors" in (g / "index.html").read_text()
    pts = pq.read_table(tmp_path / "out" / "tables" / "gap_points" / "m.parquet")
    eff = pq.read_table(tmp_path / "out" / "tables" / "gap_effects" / "m.parquet")
    assert pts.num_rows == s["n_points"] and eff.column("effect").to_pylist()[0] == "runout"
    assert json.loads(eff.column("params_se").to_pylist()[0]) == pytest.approx(se)
    # with a reference part (no effect, another noise draw) the same calibration as the blind check's
    r = run("simulate", tmp_path / "wf.yaml", "--noise-um", "0.3", "--seed", "4", "--plan", SAMPLE / "plan.csv",
            "--out", tmp_path / "ref.csv")
    assert r.exit_code == 0, r.output
    r = run("diagnose", tmp_path / "wf.yaml", "--measurements", tmp_path / "m.csv", "--reference", tmp_path / "ref.csv",
            "--out", tmp_path / "cal")
    assert r.exit_code == 0, r.output
    c = json.loads((tmp_path / "cal" / "gap" / "summary.json").read_text())
    cal = c["calibration"]
    assert cal["file"].endswith("ref.csv") and cal["n_points"] == s["n_points"] and 0.5 < cal["force_scale_s0"] < 2.0
    # the truth first and closer; the prediction's floor near the two rows' corners is not pinned by
    # one reference at σ 0.3 µm (``corner_floor``: below 3 standard errors), so it is not taken
    # into the baseline; as without the reference, one small effect may be named next to the runout
    assert c["effect"] == "runout" and abs(c["params"]["runout"]["e_um"] - 10.0) <= 1.0
    assert len(c["effects"]) <= 2 and "thermal_drift" not in c["effects"]
    assert c["calibration"]["corner_floor"] is None
    # held out, the calibrated diagnosis leaves the noise and little more (0.87 µm at σ 0.3 µm; the
    # uncalibrated one 0.79 µm: the reference's s0 = 1.10 is itself read through the probe noise)
    assert c["rms_after_um"] < 0.5 * c["rms_before_um"] and c["rms_after_um"] <= s["rms_after_um"] * 1.25
    bad = (tmp_path / "m.csv").read_text().splitlines()
    (tmp_path / "dup.csv").write_text("\n".join(bad + [bad[1]]) + "\n")
    r = CliRunner().invoke(main, ["diagnose", str(tmp_path / "wf.yaml"), "--measurements", str(tmp_path / "dup.csv")])
    assert r.exit_code == 2 and "duplicated point id" in r.output
