"""One program machined on the virtual machine: the tool, the machine, the stations and their deflection.

The machine reads parsed passes only; it shares the cutter type and the path geometry
(``stages.geometry``) with the prediction and nothing else. Effects are applied per call of
:meth:`VirtualMachine.probe`.
"""
from __future__ import annotations

import math
from functools import cached_property
from typing import Optional

import numpy as np
import pyarrow as pa

from stages import InputError
from stages.geometry.cutter import Cutter
from stages.geometry.paths import program_paths
from stages.tables import read_numeric_csv
from stages.virtual_machine.cutting import COEFFS, flute_offsets, station_forces
from stages.virtual_machine.dynamics import machine_modes, simulate_deflection
from stages.virtual_machine.engagement import K_NEAR, STEP_SLACK, edge_grid, engagement, make_stations
from stages.virtual_machine.probe import PROBE_PASSES, machined_deviation
from stages.virtual_machine.stock import stock_height_fn


class VirtualMachine:
    """One program machined on the virtual machine.

    Parameters
    ----------
    passes : pyarrow Table
        The passes table of one program (DESIGN §6).
    tool : dict or Cutter
        The workflow's ``tool`` entry (a ball end mill): diameter, flutes, helix, stick-out, runout,
        control point and the measured shape error table ``profile`` (contact_deg, error_um).
    material : dict
        Cutting coefficients ktc, krc, kac, kte, kre, kae.
    machine : dict
        The workflow's ``machine`` entry; its ``frf`` gives the modes (``dynamics.machine_modes``).
    stock : dict or path
        ``{"box": [...]}`` or a stock mesh (``stock.stock_height_fn``).
    deflection_step_mm : float, optional
        One engagement and deflection per piece of at most this length (``engagement.make_stations``);
        None: one per pass.
    step_slack : float
        See ``engagement.make_stations``.
    k_near : int
        See ``engagement.engagement`` (a speed-up only).
    earlier : sequence of (passes, tool)
        The programs machined before this one on the same stock, in order (their passes tables and
        ``tool`` entries): the stock this program meets is what they left.

    Attributes
    ----------
    cutter : Cutter
    R, flutes, helix, stickout, base_runout : the tool's radius (mm), flutes, helix (rad),
        stick-out (mm) and runout (µm)
    profile : (contact_deg, error_um) or None
    path : Path3
    stations : engagement.Stations
    engaged : (S, levels, N_PHI // 8) uint8, packed engaged micro-edges of each station (computed
        on first use: a probe with a prescribed deflection, e.g. a rigid machine's, needs none)
    stock_h : callable z_top(x, y)
    """

    def __init__(self, passes: pa.Table, tool, material: dict, machine: dict, stock,
                 deflection_step_mm: Optional[float] = None, *, step_slack: float = STEP_SLACK,
                 k_near: int = K_NEAR, earlier=()):
        cutter = Cutter.from_params(tool)
        if cutter.kind != "ball":
            raise InputError(f"tool.type {cutter.kind!r}: the virtual machine models ball-nose tools only")
        self.cutter = cutter
        self.R = cutter.radius_mm
        self.flutes = cutter.flutes
        self.helix = math.radians(cutter.helix_deg)
        # the flutes run up the side to the stick-out (the same tool the prediction describes)
        self.stickout = cutter.stickout_mm
        self.base_runout = cutter.runout_um
        # the real tool's shape (claim 2 table: contact_deg, error_um; + = tool smaller there)
        self.profile = None
        if cutter.profile:
            tab = read_numeric_csv(cutter.profile, ["contact_deg", "error_um"], "tool.profile")
            o = np.argsort(tab[:, 0])
            self.profile = (tab[o, 0], tab[o, 1])
        self.coeffs = {k: float(material.get(k) or 0.0) for k in COEFFS}
        frf = (machine or {}).get("frf")
        self.modes = {"x": machine_modes(frf, "x"), "y": machine_modes(frf, "y")}
        paths = program_paths(passes, self.R, cutter.control_point)
        if len(paths) != 1:
            raise InputError(f"virtual machine: one program at a time, got {len(paths)}")
        self.path = paths[0]
        if len(self.path.pass_id) == 0:
            raise InputError(f"{self.path.program_id}: no cutting moves to machine")
        self.stock_h = stock_height_fn(stock)
        self.stations = make_stations(self.path, deflection_step_mm, step_slack)
        self._k_near = k_near
        self._earlier = []
        for e_passes, e_tool in earlier:
            c = Cutter.from_params(e_tool)
            self._earlier += [(q, c.radius_mm, c.stickout_mm) for q in program_paths(e_passes, c.radius_mm, c.control_point)]
        self._defl_cache: dict = {}

    @cached_property
    def engaged(self) -> np.ndarray:
        return engagement(self.path, self.stations, self.stock_h, self.R, self.stickout, self._k_near,
                          earlier=self._earlier)

    def flute_offsets(self, e_um: float, phase_deg: float) -> np.ndarray:
        """Radial offset of each flute (mm) for a runout ``e_um`` at ``phase_deg``."""
        return flute_offsets(self.flutes, e_um, phase_deg)

    def forces(self, e_um: float = 0.0, phase_deg: float = 0.0):
        """Machine-frame (fx, fy) in N on the tool over one revolution per station, at spindle
        angles θ_i = i·360/N_ROT, with a runout ``e_um`` at ``phase_deg`` besides the tool's own."""
        rho = self.flute_offsets(e_um + self.base_runout, phase_deg)
        return station_forces(self.path, self.stations.pass_row, self.engaged, edge_grid(self.R, self.stickout),
                              self.R, self.flutes, self.helix, self.coeffs, rho)

    def deflection(self, runout_e_um: float = 0.0, runout_phase_deg: float = 0.0, scale: float = 1.0):
        """(dx, dy) µm over one revolution per station (per pass without a deflection step), at
        spindle angles θ_i = i·360/N_ROT; computed once per runout and scaled by ``scale``."""
        key = (round(runout_e_um, 6), round(runout_phase_deg, 6))
        if key not in self._defl_cache:
            fx, fy = self.forces(runout_e_um, runout_phase_deg)
            rpm = self.path.rpm[self.stations.pass_row]
            self._defl_cache[key] = (simulate_deflection(fx, rpm, self.modes["x"]),
                                     simulate_deflection(fy, rpm, self.modes["y"]))
        dx, dy = self._defl_cache[key]
        return dx * scale, dy * scale

    def probe(self, pts: np.ndarray, normals: np.ndarray, effects: dict | None = None,
              noise_um: float = 0.0, rng: Optional[np.random.Generator] = None, *,
              probe_passes: int = PROBE_PASSES, deflection=None) -> np.ndarray:
        """Deviation (µm, + = material left) of the machined surface at each plan point along its
        normal; see ``probe.machined_deviation`` for the parameters."""
        return machined_deviation(self, pts, normals, effects, noise_um, rng, probe_passes, deflection)
