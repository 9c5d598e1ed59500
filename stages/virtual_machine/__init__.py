"""Virtual machine: an independent, higher-fidelity simulation of machining that writes "measured" data.

It exists to test the gap diagnosis (DESIGN §8.5, issue 7): it machines the programs' passes with
its own models and probes the finished surface at the points of a measurement plan, optionally with
unmodelled effects switched on. It shares nothing with the prediction path (``cutting``, ``scan``,
``errors``, ``correction``, ``render``, ``gap``); it imports only ``stages.geometry`` (the cutter
and the path geometry) and ``stages.tables``, and reads parsed passes only.

Model (all vectorised over passes / points), one module each:

- ``stock``: the stock as a height field (a box, or rasterised from the stock mesh);
- ``engagement``: micro-edges of the ball and the side up to the stick-out, in the material below
  the stock and outside the tool swept along every earlier pass, at stations along the passes;
- ``cutting``: discrete flutes with helix lag and runout, Lee–Altintas forces on the chip;
- ``dynamics``: modes of the compliance (given or fitted to a measured FRF), time-domain
  integration to the periodic deflection of each station;
- ``probe``: discrete tooth passages cut every plan point; the deviation along its normal;
- ``effects``: the unmodelled effects (runout, tool contour, wear, thermal drift, force scale,
  servo lag at corners, machine geometry) and their parameters;
- ``machine``: :class:`VirtualMachine`, one program loaded on the machine.
"""
from stages.virtual_machine.cutting import N_ROT, flute_offsets, station_forces
from stages.virtual_machine.dynamics import fit_modes, machine_modes, modal_frf, simulate_deflection
from stages.virtual_machine.effects import DEFAULTS, EFFECTS, machine_offsets, parse_effect, radius_loss
from stages.virtual_machine.engagement import (K_NEAR, N_PHI, N_Z, SHANK_DZ_MM, STEP_SLACK, Stations, edge_grid,
                                               engagement, make_stations)
from stages.virtual_machine.removal import inside_tool
from stages.virtual_machine.machine import VirtualMachine
from stages.virtual_machine.probe import PASSAGES, PROBE_PASSES, grid_plan, machined_deviation, near_passes
from stages.virtual_machine.stock import stock_height_fn

__all__ = [
    "DEFAULTS", "EFFECTS", "K_NEAR", "N_PHI", "N_ROT", "N_Z", "PASSAGES", "PROBE_PASSES", "SHANK_DZ_MM",
    "STEP_SLACK", "Stations", "VirtualMachine", "edge_grid", "engagement", "fit_modes", "flute_offsets",
    "grid_plan", "inside_tool", "machine_modes", "machine_offsets", "machined_deviation", "make_stations",
    "modal_frf", "near_passes", "parse_effect", "radius_loss", "simulate_deflection", "station_forces",
    "stock_height_fn",
]
