"""Measurements made on the virtual machine: a program's plan points probed with chosen effects."""
from __future__ import annotations

from typing import Optional

import numpy as np
import pyarrow as pa

from stages.gap.measurements import measurement_table, points_and_normals
from stages.geometry.paths import nearest_pass
from stages.virtual_machine import grid_plan

PLAN_TOL_MM = 0.05    # a plan point belongs to a program when one of its ball centres passes this near


def probe_program(vm, plan: Optional[pa.Table], effects: dict, noise_um: float, rng: np.random.Generator,
                  grid_mm: float = 0.5, first_id: int = 0) -> pa.Table:
    """Probe one program machined on the virtual machine.

    With a plan, the plan points the program machined (their ideal ball centre p + R·n on one of its
    centre segments; the others belong to other programs or were not machined); without one, a grid
    over the machined surface (``stages.virtual_machine.grid_plan``). Each point's time stamp is
    when the nearest pass passed it.

    Parameters
    ----------
    vm : VirtualMachine
        The program (``stages.virtual_machine``).
    plan : pa.Table or None
        Measurement plan (``point_id``, points, normals).
    effects : dict
        {effect: parameters} switched on.
    noise_um : float
        Probe noise σ (µm).
    rng : numpy.random.Generator
    grid_mm : float
        Grid spacing without a plan (mm).
    first_id : int
        Id of the first grid point (without a plan).

    Returns
    -------
    pa.Table
        ``measurements`` table of the probed points (err_um µm, t_s s).
    """
    if plan is not None:
        pts, nrm = points_and_normals(plan)
        ids = plan.column("point_id").to_numpy()
        _, _, d = nearest_pass(vm.path, pts + vm.R * nrm)
        mine = d < PLAN_TOL_MM
        pts, nrm, ids = pts[mine], nrm[mine], ids[mine]
    else:
        pts, nrm = grid_plan(vm, grid_mm)
        ids = np.arange(len(pts)) + first_id
    err = vm.probe(pts, nrm, effects, noise_um, rng)
    row, u, _ = nearest_pass(vm.path, pts + vm.R * nrm)
    t = vm.path.t0[row] + u * (vm.path.t1[row] - vm.path.t0[row])
    return measurement_table(ids, pts, nrm, err, t)
