"""Stage ``forces``: cutting force over one revolution at each predicted pass (DESIGN §7, claim 5).

One row per row of the ``engagement`` table (the predicted passes). The cutting region (engagement
grid) and the pass's feed per tooth fz = feed_mm_min / (spindle_rpm·flutes) drive the micro-edge
model of :mod:`stages.cutting.forces` (the chip no thicker than the material ahead of a descending
pass allows: the engagement's ``chip_limit_mm``); forces are those **acting on the tool**, sampled at spindle
angles θ_i = i·360/n_rot (θ = 0: flute 0's tip end points along the feed; the spindle turns
clockwise), rotated from the feed frame to the machine frame with the engagement row's feed
direction. Ramps (the engagement row's ``ramp_deg``) change the chip.
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa

from stages import InputError
from stages.cutting.forces import (
    COEFF_NAMES, DEFAULT_N_ROT, cutting_forces_packed, feed_per_tooth_mm, rotation_grid_deg)
from stages.geometry.cutter import Cutter
from stages.surface.engagement import effective_feed_per_tooth
from stages.tables import (binary_rows, list_column, match_passes, padded_list_values, pick_entry, program_tool_number,
                           task_count)

NAME = "forces"
VERSION = "3"
INPUTS = ("passes", "generating", "engagement")
OUTPUTS = ("forces",)
PARAMS = ("tool", "material")

N_ROT = DEFAULT_N_ROT
ROWS_PER_TASK = 1000     # predicted passes per task: a large program's forces spread over the workers


def shards(rows: dict, params: dict) -> int:
    """Tasks a program's forces are computed in, from its number of predicted passes."""
    return task_count(rows.get("engagement", 0), ROWS_PER_TASK, 64)


def combine_shards(parts: list[dict]) -> dict:
    """Shard i holds the i-th contiguous block of the engagement rows: joined in that order."""
    return {"forces": pa.concat_tables([p["forces"] for p in parts])}


def _empty():
    from schemas.forces import SCHEMA
    return SCHEMA.empty_table()


def run(inputs: dict, params: dict, shard: tuple[int, int] | None = None) -> dict:
    passes, engagement = inputs["passes"], inputs["engagement"]
    if shard is not None:
        i, n = shard
        a, b = engagement.num_rows * i // n, engagement.num_rows * (i + 1) // n
        engagement = engagement.slice(a, b - a)
    if engagement.num_rows == 0:
        return {"forces": _empty()}
    t_no = program_tool_number(passes)
    cutter = Cutter.from_params(pick_entry(params.get("tool"), t_no, "tool"))
    material = pick_entry(params.get("material"), t_no, "material")
    coeffs = {k: float(material.get(k) or 0.0) for k in COEFF_NAMES}

    pass_ids = engagement.column("pass_id").to_numpy().astype(np.int64)
    rows = match_passes(passes, pass_ids, "engagement")
    feed = passes.column("feed_mm_min").to_numpy()[rows]
    rpm = passes.column("spindle_rpm").to_numpy()[rows]
    line = passes.column("line_no").to_numpy()[rows]
    bad = np.flatnonzero(~(rpm > 0) | ~(feed > 0))
    if bad.size:
        b = bad[0]
        raise InputError(f"line {line[b]}: pass {pass_ids[b]} cuts material with spindle_rpm {rpm[b]:g} "
                         f"and feed {feed[b]:g} mm/min (both must be > 0: the cutting force needs a feed per tooth)")
    fz = feed_per_tooth_mm(feed, rpm, cutter.flutes)

    dz = engagement.column("dz_mm").to_numpy()
    # feed angle above the horizontal (tables written before ramps were modelled: level passes)
    ramp = (engagement.column("ramp_deg").to_numpy(zero_copy_only=False).astype(float)
            if "ramp_deg" in engagement.column_names else np.zeros(len(pass_ids)))
    if not np.all(np.isfinite(ramp)) or np.any(np.abs(ramp) > 90.0):
        b = int(np.argmax(~np.isfinite(ramp) | (np.abs(ramp) > 90.0)))
        raise InputError(f"engagement: pass {pass_ids[b]} has ramp_deg {ramp[b]!r} (needs -90 … 90)")
    # a descent into material thinner than the feed per tooth cuts only that material per tooth
    chip = fz
    if "chip_limit_mm" in engagement.column_names:
        chip = effective_feed_per_tooth(fz, padded_list_values(engagement.column("chip_limit_mm")))
        chip = np.where(chip > 0, chip, fz)          # no material in the footprint: the grid has no chip either
    n_z = engagement.column("n_z").to_numpy()
    n_phi = engagement.column("n_phi").to_numpy()
    packed, lengths = binary_rows(engagement.column("mask"))
    theta = rotation_grid_deg(N_ROT)
    comp = np.zeros((3, len(pass_ids), N_ROT))
    forces_feed = np.moveaxis(comp, 0, -1)
    keys = np.stack([dz, n_z.astype(float), n_phi.astype(float)], axis=1)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    for g, (g_dz, g_nz, g_nphi) in enumerate(uniq):
        sel = np.flatnonzero(inv.ravel() == g)
        n_bytes = (int(g_nz) * int(g_nphi) + 7) // 8
        bad = sel[lengths[sel] != n_bytes]
        if bad.size or not (g_dz > 0) or g_nz < 1 or g_nphi < 1:
            b = bad[0] if bad.size else sel[0]
            raise InputError(f"engagement: pass {pass_ids[b]}: mask of {lengths[b]} bytes, dz_mm {g_dz:g}, "
                             f"grid {int(g_nz)}×{int(g_nphi)} (needs dz_mm > 0 and ceil(n_z·n_phi/8) = {n_bytes} bytes)")
        rows_bytes = packed[sel] if isinstance(packed, np.ndarray) else np.stack([packed[i] for i in sel])
        f_g = cutting_forces_packed(rows_bytes, int(g_nz), int(g_nphi), float(g_dz),
                                    chip[sel], cutter, coeffs, theta, ramp[sel])
        if len(uniq) == 1:
            forces_feed = f_g                   # one grid for the program (the usual case): no copy
        else:
            forces_feed[sel] = f_g
    # feed frame → machine frame, component arrays kept contiguous for the list columns
    c = engagement.column("feed_dir_x").to_numpy().astype(float)
    s = engagement.column("feed_dir_y").to_numpy().astype(float)
    norm = np.hypot(c, s)
    if np.any(~(norm > 0)):
        raise InputError(f"engagement: pass {pass_ids[np.argmin(norm > 0)]} has no feed direction")
    c, s = (c / norm)[:, None], (s / norm)[:, None]
    fxf, fyf = forces_feed[..., 0], forces_feed[..., 1]
    fx, fy, fz_n = c * fxf - s * fyf, s * fxf + c * fyf, forces_feed[..., 2]
    table = pa.table({
        "program_id": engagement.column("program_id"),
        "pass_id": pa.array(pass_ids.astype(np.int32)),
        "rotation_deg": list_column(np.broadcast_to(theta, (len(pass_ids), N_ROT))),
        "fx_n": list_column(fx),
        "fy_n": list_column(fy),
        "fz_n": list_column(fz_n),
        "spindle_rpm": pa.array(rpm.astype(float)),
        "feed_per_tooth_mm": pa.array(fz),
    })
    return {"forces": table}
