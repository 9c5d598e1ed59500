"""Stage ``forces``: cutting force over one revolution at each predicted pass (DESIGN §7, claim 5).

One row per row of the ``engagement`` table (the predicted passes). The cutting region (engagement
grid) and the pass's feed per tooth fz = feed_mm_min / (spindle_rpm·flutes) drive the micro-edge
model of ``stages.cutting``; forces are those **acting on the tool**, sampled at spindle angles
θ_i = i·360/n_rot (θ = 0: flute 0's tip end points along the feed; the spindle turns clockwise,
see ``stages.cutting``), rotated from the feed frame to the machine frame with the engagement row's
feed direction. Ramps (the engagement row's ``ramp_deg``) change the chip, see ``stages.cutting``.
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa

from stages import InputError
from stages import cutting

NAME = "forces"
VERSION = "2"
INPUTS = ("passes", "generating", "engagement")
OUTPUTS = ("forces",)
PARAMS = ("tool", "material")

N_ROT = cutting.DEFAULT_N_ROT


# ---- list-column helpers shared by the physics stages ------------------------------------------
def list_column(values: np.ndarray) -> pa.ListArray:
    """(P, n) float array → Arrow list<double> column with n values per row."""
    values = np.ascontiguousarray(values, dtype=np.float64)
    n_rows, n = values.shape
    offsets = pa.array(np.arange(n_rows + 1, dtype=np.int32) * n)
    return pa.ListArray.from_arrays(offsets, pa.array(values.ravel()))


def list_values(column, what: str) -> np.ndarray:
    """Arrow list<double> column with equally long rows → (P, n) float array."""
    arr = column.combine_chunks() if isinstance(column, pa.ChunkedArray) else column
    n_rows = len(arr)
    if n_rows == 0:
        return np.zeros((0, 0))
    if arr.null_count:
        raise InputError(f"{what}: null list")
    offsets = np.asarray(arr.offsets)
    lengths = np.diff(offsets)
    if np.any(lengths != lengths[0]):
        raise InputError(f"{what}: rows have different lengths {sorted(set(lengths.tolist()))[:5]}")
    flat = np.asarray(arr.values.to_numpy(zero_copy_only=False), dtype=float)
    return flat[offsets[0]:offsets[-1]].reshape(n_rows, int(lengths[0]))


def pick_entry(entry, tool_t, key: str) -> dict:
    """The workflow entry (tool/material) for T number ``tool_t`` when the workflow gives a list."""
    if isinstance(entry, (list, tuple)):
        for e in entry:
            if e.get("t") == tool_t:
                return e
        raise InputError(f"{key}: no entry for T{tool_t}")
    if entry is None:
        raise InputError(f"{key}: missing")
    return entry


def program_tool_number(passes: pa.Table):
    if "tool" not in passes.column_names or passes.num_rows == 0:
        return None
    tools = [t for t in passes.column("tool").to_pylist() if t is not None]
    return tools[0] if tools else None


def match_passes(passes: pa.Table, pass_ids: np.ndarray, table_name: str) -> np.ndarray:
    """Row index into ``passes`` of every pass id (InputError naming the first missing one)."""
    ids = passes.column("pass_id").to_numpy()
    order = np.argsort(ids, kind="stable")
    pos = np.searchsorted(ids[order], pass_ids)
    pos = np.minimum(pos, len(ids) - 1) if len(ids) else pos
    ok = (len(ids) > 0) & (ids[order][pos] == pass_ids) if len(ids) else np.zeros(len(pass_ids), bool)
    if not np.all(ok):
        bad = pass_ids[~ok][0]
        raise InputError(f"{table_name}: pass_id {bad} is not in the passes table")
    return order[pos]


def _mask_bytes(column):
    """Binary column → ((P, L) uint8 when all rows are L bytes long, else a list of arrays), lengths."""
    arr = column.combine_chunks() if isinstance(column, pa.ChunkedArray) else column
    if arr.null_count:
        raise InputError("engagement.mask: null mask")
    n = len(arr)
    bufs = arr.buffers()
    offsets = np.frombuffer(bufs[1], dtype=np.int32)[arr.offset:arr.offset + n + 1]
    data = np.frombuffer(bufs[2], dtype=np.uint8) if bufs[2] is not None else np.zeros(0, np.uint8)
    lengths = np.diff(offsets)
    if n and np.all(lengths == lengths[0]):
        return data[offsets[0]:offsets[-1]].reshape(n, int(lengths[0])), lengths
    return [data[offsets[i]:offsets[i + 1]] for i in range(n)], lengths


def _empty():
    from schemas.forces import SCHEMA
    return SCHEMA.empty_table()


def run(inputs: dict, params: dict) -> dict:
    passes, engagement = inputs["passes"], inputs["engagement"]
    if engagement.num_rows == 0:
        return {"forces": _empty()}
    t_no = program_tool_number(passes)
    tool = pick_entry(params.get("tool"), t_no, "tool")
    material = pick_entry(params.get("material"), t_no, "material")
    coeffs = {k: float(material.get(k) or 0.0) for k in cutting.COEFF_NAMES}

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
    fz = cutting.feed_per_tooth_mm(feed, rpm, int(tool["flutes"]))

    dz = engagement.column("dz_mm").to_numpy()
    # feed angle above the horizontal (tables written before ramps were modelled: level passes)
    ramp = (engagement.column("ramp_deg").to_numpy(zero_copy_only=False).astype(float)
            if "ramp_deg" in engagement.column_names else np.zeros(len(pass_ids)))
    if not np.all(np.isfinite(ramp)) or np.any(np.abs(ramp) > 90.0):
        b = int(np.argmax(~np.isfinite(ramp) | (np.abs(ramp) > 90.0)))
        raise InputError(f"engagement: pass {pass_ids[b]} has ramp_deg {ramp[b]!r} (needs -90 … 90)")
    n_z = engagement.column("n_z").to_numpy()
    n_phi = engagement.column("n_phi").to_numpy()
    packed, lengths = _mask_bytes(engagement.column("mask"))
    theta = cutting.rotation_grid_deg(N_ROT)
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
        f_g = cutting.cutting_forces_packed(rows_bytes, int(g_nz), int(g_nphi), float(g_dz),
                                            fz[sel], tool, coeffs, theta, ramp[sel])
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
