"""Compliance FRF and deflection over one revolution: FFT vs RK4, textbook resonance, tables."""
from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

import schemas
from stages.geometry.cutter import Cutter
from stages import InputError
from stages.cutting import forces as cutting
from stages.cutting import frf
from stages import deflection as deflection_stage
from stages.tables import list_column

MODE = {"fn_hz": 900.0, "zeta": 0.03, "k_n_per_um": 2.0}


def _slot_force(rpm=6000.0, flutes=2, helix=30.0, n_rot=128):
    """A realistic force over one revolution: flat end mill slot, from the kernel."""
    n_z, n_phi, a = 20, 360, 3.0
    phi = (np.arange(n_phi) + 0.5) * 360 / n_phi
    E = np.broadcast_to(np.cos(np.radians(phi)) > 0, (n_z, n_phi))
    tool = Cutter.from_params({"type": "flat", "diameter_mm": 10, "flutes": flutes, "helix_deg": helix, "runout_um": 4.0})
    k = {"ktc": 2000, "krc": 700, "kac": 300, "kte": 20, "kre": 15, "kae": 5}
    return cutting.cutting_forces(E[None], a / n_z, 1000 / (rpm * flutes), tool, k,
                                  rotation_deg=cutting.rotation_grid_deg(n_rot))[0]


def test_single_mode_resonance_amplification():
    """Harmonic force at fn: amplitude / static = 1/(2ζ), phase lag 90°, by FFT and by RK4."""
    n_rot = 64
    theta = cutting.rotation_grid_deg(n_rot)
    f0 = 10.0
    force = f0 * np.cos(np.radians(theta))[None, :]                  # first harmonic only
    rpm = np.array([MODE["fn_hz"] * 60.0])                           # spindle frequency = fn
    static = f0 / MODE["k_n_per_um"]
    for d in (frf.deflection_fft(force, rpm, lambda f: frf.modal_compliance(f, [MODE])),
              frf.deflection_rk4(force, rpm, [MODE])):
        amp = np.abs(d).max()
        assert amp / static == pytest.approx(1 / (2 * MODE["zeta"]), rel=0.01)
        # 90° lag: the response is a sine when the force is a cosine (peak a quarter turn later)
        assert theta[np.argmax(d[0])] == pytest.approx(90.0, abs=360 / n_rot)
    g = frf.modal_compliance(np.array([0.0, MODE["fn_hz"]]), [MODE])
    assert g[0] == pytest.approx(1 / MODE["k_n_per_um"])
    assert abs(g[1]) * MODE["k_n_per_um"] == pytest.approx(1 / (2 * MODE["zeta"]))


@pytest.mark.parametrize("rpm", [3000.0, 8000.0, 13500.0])
def test_fft_matches_rk4_in_steady_state(rpm):
    """Kernel force (slot, runout), two modes per axis: FFT and RK4 within 1 % of the peak."""
    modes = [MODE, {"fn_hz": 2300.0, "zeta": 0.05, "k_n_per_um": 5.0}]
    F = _slot_force(rpm)
    fxy = F[None, :, :2]
    d_fft = frf.tool_deflection(fxy, np.array([rpm]), {"x": modes, "y": modes})
    d_rk4 = frf.tool_deflection(fxy, np.array([rpm]), {"x": modes, "y": modes}, method="rk4")
    peak = np.abs(d_fft).max()
    assert np.abs(d_fft - d_rk4).max() <= 0.01 * peak


def test_static_limit_and_direction():
    """Far below resonance the tool moves along the force by F/k (Σ 1/k over modes)."""
    modes = [{"fn_hz": 5000.0, "zeta": 0.05, "k_n_per_um": 4.0}, {"fn_hz": 8000.0, "zeta": 0.05, "k_n_per_um": 4.0}]
    F = np.full((1, 32), 40.0)                                        # constant force, N
    d = frf.deflection_fft(F, np.array([60.0]), lambda f: frf.modal_compliance(f, modes))
    assert np.allclose(d, 40.0 * (1 / 4.0 + 1 / 4.0))


def _write_table(path, freqs, gx, gy):
    rows = np.column_stack([freqs, gx.real, gx.imag, gy.real, gy.imag])
    np.savetxt(path, rows, delimiter=",", header="freq_hz,xx_re,xx_im,yy_re,yy_im", comments="")


def test_measured_table_matches_modal(tmp_path):
    """A finely sampled table of a modal FRF gives the modal deflection (1 % of peak)."""
    mx, my = [MODE], [{"fn_hz": 1300.0, "zeta": 0.04, "k_n_per_um": 3.0}]
    freqs = np.arange(0.0, 20000.0, 2.0)
    p = tmp_path / "frf.csv"
    _write_table(p, freqs, frf.modal_compliance(freqs, mx), frf.modal_compliance(freqs, my))
    F = _slot_force(7000.0)[None, :, :2]
    rpm = np.array([7000.0])
    d_tab = frf.tool_deflection(F, rpm, {"table": str(p)})
    d_mod = frf.tool_deflection(F, rpm, {"x": mx, "y": my})
    assert np.abs(d_tab - d_mod).max() <= 0.01 * np.abs(d_mod).max()


def test_measured_table_errors(tmp_path):
    p = tmp_path / "bad.csv"
    p.write_text("freq_hz,xx_re,xx_im\n0,1,0\n")
    with pytest.raises(InputError, match="bad.csv:1"):
        frf.read_frf_table(p)
    p.write_text("freq_hz,xx_re,xx_im,yy_re,yy_im\n0,1,0,1,0\n10,1,x,1,0\n")
    with pytest.raises(InputError, match="bad.csv:3"):
        frf.read_frf_table(p)
    with pytest.raises(InputError, match="machine.frf"):
        frf.tool_deflection(np.zeros((1, 8, 2)), np.array([1000.0]), None)


def test_deflection_stage_table():
    F = _slot_force(6000.0)
    n = 3
    forces = pa.table({
        "program_id": ["p"] * n, "pass_id": pa.array([0, 1, 2], pa.int32()),
        "rotation_deg": list_column(np.tile(cutting.rotation_grid_deg(128), (n, 1))),
        "fx_n": list_column(np.tile(F[:, 0], (n, 1))), "fy_n": list_column(np.tile(F[:, 1], (n, 1))),
        "fz_n": list_column(np.tile(F[:, 2], (n, 1))),
        "spindle_rpm": [6000.0, 6000.0, 12000.0], "feed_per_tooth_mm": [0.1] * n})
    forces = schemas.check("forces", forces)
    params = {"tool": {}, "machine": {"rapid_mm_min": 30000, "frf": {"x": [MODE], "y": [MODE], "table": None}}}
    out = schemas.check("deflection", deflection_stage.run({"forces": forces}, params)["deflection"])
    dx = np.array(out.column("dx_um").to_pylist())
    ref = frf.deflection_fft(F[None, :, 0], np.array([6000.0]), lambda f: frf.modal_compliance(f, [MODE]))
    assert np.allclose(dx[0], ref[0]) and np.allclose(dx[1], ref[0])
    assert not np.allclose(dx[2], ref[0])                              # other spindle speed, other response
    rk = deflection_stage.run({"forces": forces}, params, method="rk4")["deflection"]
    assert np.abs(np.array(rk.column("dx_um").to_pylist()) - dx).max() <= 0.01 * np.abs(dx).max()
