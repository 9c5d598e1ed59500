"""Cutting-coefficient calibration: fit ktc, krc, kac, kte, kre, kae to measured forces (seed para 0047).

The micro-edge model (``stages.cutting``) is linear in the six coefficients once the cut geometry
(cutting region, feed per tooth, runout) is fixed: F(θ) = Σ_c K_c·B_c(θ), where B_c is the force the
model gives with K_c = 1 and the others 0. Stacking Fx, Fy, Fz of every sample of every record gives
an ordinary linear least-squares problem; several records at different feeds separate the cutting
(∝ h) from the edge (∝ length) terms best, but one record already does because h varies with the
immersion angle.

Measured force record (CSV, one revolution or several, one line per sample)::

    rotation_deg,fx_n,fy_n,fz_n
    0.0,12.1,-30.5,4.2
    2.8125,14.0,-33.1,4.4
    ...

``rotation_deg`` is the spindle angle θ of ``stages.cutting`` (θ = 0 when flute 0's tip end points
along the feed; synchronise the dynamometer with a once-per-revolution spindle mark), forces in N in
the machine frame. A table dynamometer measures the force on the **workpiece**: pass
``forces_on="workpiece"`` and the record is negated to the force on the tool used by the model.

The cut geometry of a calibration cut is the usual one: a straight cut along ``feed_dir`` at axial
depth a with radial width ae on one side (``engagement_for_cut``), or any engagement grid.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stages import InputError
from stages.cutting.forces import (
    COEFF_NAMES,
    cutting_forces,
    feed_per_tooth_mm,
    to_machine_frame,
)
from stages.geometry.cutter import Cutter
from stages.tables import read_numeric_csv


@dataclass
class ForceRecord:
    """One measured cut: samples and the geometry that produced them."""

    rotation_deg: np.ndarray            # (n,)
    force_n: np.ndarray                 # (n, 3) machine frame
    engaged: np.ndarray                 # (n_z, n_phi) bool cutting region
    dz_mm: float
    fz_mm: float                        # feed per tooth
    feed_dir: tuple = (1.0, 0.0)
    name: str = ""
    forces_on: str = "tool"             # 'tool' or 'workpiece' (table dynamometer)
    extra: dict = field(default_factory=dict)


def read_force_csv(path) -> tuple[np.ndarray, np.ndarray]:
    """Read ``rotation_deg,fx_n,fy_n,fz_n`` → (rotation_deg (n,), force_n (n, 3))."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{path}: no such force record")
    a = read_numeric_csv(p, ("rotation_deg", "fx_n", "fy_n", "fz_n"), "force record")
    if len(a) < 6:
        raise InputError(f"{path}: {len(a)} samples; at least 6 are needed to fit 6 coefficients")
    return a[:, 0], a[:, 1:4]


def engagement_for_cut(cutter: Cutter, axial_depth_mm: float, radial_width_mm: float | None = None,
                       side: str = "right", n_z: int = 64, n_phi: int = 720) -> tuple[np.ndarray, float]:
    """Cutting region of a straight calibration cut into a block (slot when the width ≥ diameter).

    The block's top is ``axial_depth_mm`` above the tool tip; the material occupies the strip of
    width ``radial_width_mm`` on the ``side`` of the feed ('right': y_f < −(R − ae), down milling
    with M3; 'left': y_f > R − ae, up milling); only the front half (cos φ > 0) cuts.

    Returns
    -------
    engaged : bool (n_z, n_phi), dz_mm : float
    """
    radius = cutter.radius_mm
    dz = axial_depth_mm / n_z
    z = (np.arange(n_z) + 0.5) * dz
    r, _ = cutter.immersion(z)
    phi = np.radians((np.arange(n_phi) + 0.5) * 360.0 / n_phi)
    y = r[:, None] * np.sin(phi)[None, :]
    front = np.cos(phi)[None, :] > 0
    ae = 2 * radius if radial_width_mm is None else float(radial_width_mm)
    if ae >= 2 * radius:
        inside = np.ones_like(y, dtype=bool)
    elif side == "right":
        inside = y < -(radius - ae)
    elif side == "left":
        inside = y > radius - ae
    else:
        raise ValueError("side: 'right' or 'left'")
    return inside & front, dz


def basis_forces(record: ForceRecord, cutter: Cutter) -> np.ndarray:
    """Model force with each coefficient = 1 in turn: (6, n, 3), machine frame, on the tool."""
    out = []
    for name in COEFF_NAMES:
        coeffs = {k: (1.0 if k == name else 0.0) for k in COEFF_NAMES}
        f = cutting_forces(record.engaged[None], record.dz_mm, record.fz_mm, cutter, coeffs,
                           rotation_deg=record.rotation_deg)
        f = to_machine_frame(f, np.array([record.feed_dir[0]]), np.array([record.feed_dir[1]]))
        out.append(f[0])
    return np.stack(out)


def fit_coefficients(records: list[ForceRecord], cutter: Cutter) -> dict:
    """Least-squares fit of the six coefficients to the records.

    Returns
    -------
    dict
        ``ktc … kae`` (N/mm², N/mm), ``r2`` (coefficient of determination over all samples and
        components, each component about its own mean), ``rms_n`` (RMS residual, N), ``n_samples``,
        ``per_record`` (name, r2, rms_n) and ``rank`` of the design matrix (< 6: the records cannot
        separate some coefficients; those are then the minimum-norm solution).
    """
    if not records:
        raise ValueError("no force records to fit")
    blocks, rhs, spans = [], [], []
    for rec in records:
        b = basis_forces(rec, cutter)                                        # (6, n, 3)
        meas = np.asarray(rec.force_n, dtype=float)
        if rec.forces_on == "workpiece":
            meas = -meas
        elif rec.forces_on != "tool":
            raise ValueError("forces_on: 'tool' or 'workpiece'")
        start = sum(len(x) for x in rhs)
        blocks.append(b.reshape(6, -1).T)                                   # (3n, 6)
        rhs.append(meas.reshape(-1))
        spans.append((rec.name, start, start + meas.size, meas))
    a = np.concatenate(blocks)
    y = np.concatenate(rhs)
    sol, _, rank, _ = np.linalg.lstsq(a, y, rcond=None)
    res = y - a @ sol

    def quality(measured, residual):
        comp = measured.reshape(-1, 3)
        ss_tot = float(((comp - comp.mean(axis=0)) ** 2).sum())
        ss_res = float((residual ** 2).sum())
        return (1.0 - ss_res / ss_tot if ss_tot > 0 else float("nan")), float(np.sqrt(np.mean(residual ** 2)))

    per = []
    all_meas = []
    for name, s, e, meas in spans:
        r2, rms = quality(meas, res[s:e])
        per.append({"name": name, "r2": r2, "rms_n": rms})
        all_meas.append(meas.reshape(-1, 3) - meas.reshape(-1, 3).mean(axis=0))
    ss_tot = float(sum((m ** 2).sum() for m in all_meas))
    out = {k: float(v) for k, v in zip(COEFF_NAMES, sol)}
    out.update({"r2": 1.0 - float((res ** 2).sum()) / ss_tot if ss_tot > 0 else float("nan"),
                "rms_n": float(np.sqrt(np.mean(res ** 2))), "n_samples": int(len(y) // 3),
                "rank": int(rank), "per_record": per})
    return out


def calibrate_from_csv(paths, cuts: list[dict], cutter: Cutter, forces_on: str = "tool") -> dict:
    """Fit coefficients to force CSVs, one cut description per file.

    Each cut is a dict: ``axial_depth_mm``, ``radial_width_mm`` (None = slot), ``side``,
    ``feed_mm_min``, ``spindle_rpm``, optional ``feed_dir`` (machine x, y; default (1, 0)).
    """
    records = []
    for path, cut in zip(paths, cuts):
        theta, force = read_force_csv(path)
        engaged, dz = engagement_for_cut(cutter, cut["axial_depth_mm"], cut.get("radial_width_mm"),
                                         cut.get("side", "right"))
        fz = float(feed_per_tooth_mm(cut["feed_mm_min"], cut["spindle_rpm"], cutter.flutes))
        records.append(ForceRecord(theta, force, engaged, dz, fz, tuple(cut.get("feed_dir", (1.0, 0.0))),
                                   name=str(path), forces_on=forces_on))
    return fit_coefficients(records, cutter)
