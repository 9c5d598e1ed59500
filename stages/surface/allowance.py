"""The stock a predicted pass meets, measured along the surface normal from its generating point.

The engagement grid marks the tool's envelope points inside the material before the cut (claim 5).
Against the finished surface through the generating point G with outward normal n, the material
reaches t = max over engaged points p of (p − G)·n: where the stock's top is parallel to the surface
this is the stock's thickness over it (the tool sphere's engaged cap has height t); where they are
inclined by α (a scallop flank under a flat stock) the cap's far side adds up to its radius × sin α
(0.3 mm of stock read as 0.42–0.48 mm at α ≈ 6.5°, tests/test_feed.py); next to a wall it is how far
up the wall the tool is in material. A finishing pass is meant to meet a small, even allowance; much more
is rest material no path offset can handle.
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa

from stages.cutting.forces import unpack_engagement
from stages.geometry.cutter import Cutter
from stages.tables import col, xyz

ROWS_PER_CHUNK = 256


def stock_along_normal(engagement: pa.Table, generating: pa.Table, cut_filter: pa.Table,
                       cutter: Cutter) -> tuple[np.ndarray, np.ndarray]:
    """(pass ids, stock mm) of the engagement rows with a generating point; NaN where nothing is
    engaged.

    Envelope point (k, i): height z_k = (k + 0.5)·dz above the tip, radius r(z_k), at the angle
    φ_i = (i + 0.5)·360/n_phi counter-clockwise from the feed direction; the tip is the pass's
    prediction point (``cut_filter.pred_*``).
    """
    if engagement.num_rows == 0:
        return np.zeros(0, np.int64), np.zeros(0)
    eid = col(engagement, "pass_id", np.int64)
    gid, cid = col(generating, "pass_id", np.int64), col(cut_filter, "pass_id", np.int64)
    g_rows = np.searchsorted(gid, eid)
    c_rows = np.searchsorted(cid, eid)
    ok = (g_rows < gid.size) & (gid[np.minimum(g_rows, gid.size - 1)] == eid)
    G = xyz(generating, ("gen_x_mm", "gen_y_mm", "gen_z_mm"))[np.minimum(g_rows, gid.size - 1)]
    n = xyz(generating, ("nx", "ny", "nz"))[np.minimum(g_rows, gid.size - 1)]
    tip = xyz(cut_filter, ("pred_x_mm", "pred_y_mm", "pred_z_mm"))[np.minimum(c_rows, cid.size - 1)]
    ok &= np.isfinite(G).all(1) & np.isfinite(n).all(1) & np.isfinite(tip).all(1)
    feed = np.arctan2(col(engagement, "feed_dir_y"), col(engagement, "feed_dir_x"))
    n_z, n_phi, dz = col(engagement, "n_z", np.int64), col(engagement, "n_phi", np.int64), col(engagement, "dz_mm")
    masks = engagement.column("mask").to_pylist()
    out = np.full(eid.size, np.nan)
    keys = np.stack([n_z, n_phi, dz], 1)
    for key in np.unique(keys, axis=0):
        rows = np.flatnonzero((keys == key).all(1) & ok)
        nz, nphi, d = int(key[0]), int(key[1]), float(key[2])
        z = (np.arange(nz) + 0.5) * d
        r = cutter.immersion(z)[0]
        for a in range(0, rows.size, ROWS_PER_CHUNK):       # bounds the (rows, levels, angles) arrays
            sel = rows[a:a + ROWS_PER_CHUNK]
            E = unpack_engagement([masks[i] for i in sel], nz, nphi)
            ang = feed[sel, None] + np.radians((np.arange(nphi) + 0.5) * 360.0 / nphi)[None, :]
            # (p − G)·n = (tip − G)·n + r cos(a) nx + r sin(a) ny + z nz, per (pass, level, angle)
            base = np.einsum("ij,ij->i", tip[sel] - G[sel], n[sel])
            lateral = (np.cos(ang) * n[sel, 0, None] + np.sin(ang) * n[sel, 1, None]).astype(np.float32)
            h = r.astype(np.float32)[None, :, None] * lateral[:, None, :] + (z[None, :] * n[sel, 2, None]).astype(np.float32)[:, :, None]
            t = np.where(E, h, -np.inf).max((1, 2)) + base
            out[sel] = np.where(np.isfinite(t), t, np.nan)
    return eid, out
