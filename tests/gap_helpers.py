"""Shared cases of the gap tests: the sample job (``data_samples/gap``), its rigid virtual machine,
this file's own brute-force association, and fresh random seeds.

The closed forms of the tests use this file's own geometry (nearest tool-centre segment, times and
cut lengths summed from the passes table, corners from consecutive move directions), not the code
under test. Tolerances come from the feed-mark cusp of the discrete flutes, f²/(8R), fixed before
running: the virtual machine cuts with tooth passages, not a continuous envelope.

Random cases: every test that draws takes a fresh seed (``fresh_rng``) and prints it in its
assertion messages; ``GAP_TEST_SEED=<n>`` replays one.
"""
from __future__ import annotations

import functools
import math
import os
import secrets
from pathlib import Path

import numpy as np

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


def fresh_rng() -> tuple[int, np.random.Generator]:
    """(seed, generator): a new seed per call unless ``GAP_TEST_SEED`` is set."""
    seed = int(os.environ.get("GAP_TEST_SEED") or secrets.randbits(32))
    return seed, np.random.default_rng(seed)


@functools.lru_cache(maxsize=None)
def sample():
    """The sample program's passes and its measurement plan: (passes, pts (n, 3) mm, nrm (n, 3))."""
    from stages.gap.measurements import points_and_normals, read_measurements
    from stages.nc.moves import split_blocks
    from stages.nc.reader import parse_program
    path = SAMPLE / "gap_t1.nc"
    blocks, _ = parse_program(path.read_bytes(), str(path), "gap_t1")
    passes = split_blocks(blocks, {"split": {"chord_tol_mm": 0.001, "max_pass_mm": 5.0, "merge_max_mm": 0.001},
                                   "machine": {"rapid_mm_min": 30000.0}, "tool": TOOL})
    plan, rej, _ = read_measurements(SAMPLE / "plan.csv", require_deviation=False)
    assert len(rej) == 0
    pts, nrm = points_and_normals(plan)
    return passes, pts, nrm


@functools.lru_cache(maxsize=None)
def rigid_vm():
    """The virtual machine of the sample on a rigid machine (no deflection)."""
    from stages.virtual_machine import VirtualMachine
    return VirtualMachine(sample()[0], TOOL, MAT, RIGID, str(SAMPLE / "stock.stl"))


@functools.lru_cache(maxsize=None)
def effect_free():
    """The rigid machine's probe of the plan with no effect (µm)."""
    _, pts, nrm = sample()
    return rigid_vm().probe(pts, nrm, {})


def signature(effects: dict, noise_um: float = 0.0, rng=None) -> np.ndarray:
    """What ``effects`` change on the rigid machine's plan points (µm, + noise when asked)."""
    _, pts, nrm = sample()
    return rigid_vm().probe(pts, nrm, effects) - effect_free() + (rng.normal(0.0, noise_um, len(pts)) if noise_um else 0.0)


def associated(err_um: np.ndarray, passes=None, pts=None, nrm=None, tool=None) -> dict:
    """The features of the plan points measured with ``err_um`` (no prediction: residual = err)."""
    from stages.gap.associate import associate
    from stages.gap.measurements import measurement_table
    if passes is None:
        passes, pts, nrm = sample()
    F, rej = associate(measurement_table(np.arange(len(pts)), pts, nrm, err_um), passes, None, tool or TOOL)
    assert not rej
    return F


@functools.lru_cache(maxsize=None)
def brute_force_features() -> dict:
    """Brute-force association: nearest ball-centre segment of every cutting pass, and its features."""
    passes, pts, nrm = sample()
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
            "corner_b": bis[j], "n": nrm, "duration_s": float(t1.max()), "cut_len_mm": float(L0[-1] + ln[-1])}


def rms(v) -> float:
    return float(np.sqrt(np.mean(np.square(v))))


def servo_closed_form(f: dict, a_um: float, lam_mm: float) -> np.ndarray:
    """The smooth servo lag at each point's own path position: (b·n)·a·sin(θ/2)/sin 45°·e^(−d/λ) (µm)."""
    return (np.sum(f["corner_b"] * f["n"], 1) * a_um * np.sin(np.radians(f["corner_deg"]) / 2)
            / math.sin(math.pi / 4) * np.exp(-f["corner_d"] / lam_mm))


def repeated_fits(kind: str, truth: dict, noise_um: float, draws: int, rng) -> tuple[dict, dict]:
    """The virtual machine's noise-free signature of ``truth`` on the sample plan, ``draws`` Gaussian
    noise draws, each fitted as the diagnosis fits its final model (the selection's grid fit, then
    ``final_fit``): ({parameter: (draws,) fitted values}, {parameter: (draws,) stated SE})."""
    from stages.gap.effects import catalogue
    from stages.gap.fit import fit_joint, noise_sigma
    from stages.gap.uncertainty import final_fit, param_uncertainty
    F = associated(signature({kind: truth}))
    eff = {e.name: e for e in catalogue(F)}[kind]
    allp = np.ones(len(F["q_deg"]), bool)
    fits, ses = {k: [] for k in truth}, {k: [] for k in truth}
    for _ in range(draws):
        y = F["measured_um"] + rng.normal(0.0, noise_um, len(allp))
        _, th, _ = fit_joint(F, y, allp, [], eff)
        chosen, beta = final_fit(F, y, [(eff, th)])
        p = eff.params(beta, chosen[0][1])
        s = param_uncertainty(F, y, chosen, beta, noise_sigma(F, y))["se"][kind]
        for k in truth:
            fits[k].append(p[k])
            ses[k].append(s[k])
    return {k: np.array(v) for k, v in fits.items()}, {k: np.array(v, float) for k, v in ses.items()}


def cli(*args):
    """``pipeline`` with ``args`` (any path-like or number becomes text), exceptions raised."""
    from click.testing import CliRunner

    from pipeline.cli import main
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


def simulate_runout_then_diagnose(workflow, measured) -> None:
    """The gap job on ``workflow``: a 10 µm runout machined on the virtual machine and probed on the
    sample plan (noise 0.3 µm, seed 3) into ``measured``, then diagnosed (``<out>/gap``)."""
    r = cli("simulate", workflow, "--effect", "runout:e_um=10", "--noise-um", "0.3", "--seed", "3",
            "--plan", SAMPLE / "plan.csv", "--out", measured)
    assert r.exit_code == 0, r.output
    r = cli("diagnose", workflow, "--measurements", measured)
    assert r.exit_code == 0, r.output
