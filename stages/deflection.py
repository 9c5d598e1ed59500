"""Stage ``deflection``: tool deflection over one revolution at each predicted pass (DESIGN §7).

The force on the tool (``forces`` table, machine frame, one revolution) is periodic at the spindle
frequency, so D(ω) = G(ω)·F(ω) with the compliance FRF of ``machine.frf`` and an inverse FFT give
dx(θ), dy(θ) at the same spindle angles (seed para 0063). The tool deflects along the force acting
on it (a positive static compliance). ``run(..., method="rk4")`` integrates the modes in time
instead (the check of para 0062; modal FRF only).
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa

from stages import InputError
from stages.cutting.frf import deflection_xy
from stages.tables import list_column, list_values

NAME = "deflection"
VERSION = "1"
INPUTS = ("forces",)
OUTPUTS = ("deflection",)
PARAMS = ("tool", "machine.frf")


def run(inputs: dict, params: dict, method: str = "fft") -> dict:
    forces = inputs["forces"]
    if forces.num_rows == 0:
        from schemas.deflection import SCHEMA
        return {"deflection": SCHEMA.empty_table()}
    machine = params.get("machine") or {}
    frf = machine.get("frf")
    if not frf:
        raise InputError("machine.frf: no compliance given (modes for x and y, or a measured table); "
                         "deflection cannot be predicted")
    theta = list_values(forces.column("rotation_deg"), "forces.rotation_deg")
    n_rot = theta.shape[1]
    if not np.allclose(theta, np.arange(n_rot)[None, :] * (360.0 / n_rot)):
        raise InputError("forces.rotation_deg: expected uniform spindle angles i·360/n from 0")
    fx = list_values(forces.column("fx_n"), "forces.fx_n")
    fy = list_values(forces.column("fy_n"), "forces.fy_n")
    rpm = forces.column("spindle_rpm").to_numpy()
    if np.any(~(rpm > 0)):
        raise InputError(f"forces: pass {forces.column('pass_id')[int(np.argmin(rpm > 0))]} has no spindle speed")
    dx, dy = deflection_xy(fx, fy, rpm, frf, method=method)
    table = pa.table({
        "program_id": forces.column("program_id"),
        "pass_id": forces.column("pass_id"),
        "rotation_deg": forces.column("rotation_deg"),
        "dx_um": list_column(dx),
        "dy_um": list_column(dy),
    })
    return {"deflection": table}
