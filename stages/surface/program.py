"""A program's passes through the scans: every tile's claims 7 and 8, then the generating point and
the cutting region of each predicted pass (see ``stages/scan.py``)."""
from __future__ import annotations

import numpy as np

from stages.geometry.cutter import Cutter
from stages.geometry.envelope import envelope_mesh
from stages.geometry.passes import PassGeometry
from stages.geometry.workpiece import Workpiece
from stages.surface.chain import ChainedStock, Earlier
from stages.surface.cut_passes import cut_columns
from stages.surface.engagement import DEPTH_QUANTILES, DZ_PER_RADIUS, N_PHI, TRAIL_TURN_DEG, engagement, snapshot_from
from stages.surface.ordered import scan_tile, surface_stats
from stages.surface.strip import GEN_COLUMNS, STEEP_DEG, generating_points
from stages.surface.tiles import cutting_candidates, fine_tolerance, tiles

CUT_COLUMNS = ("is_cutting", "cut_px", "pred_x_mm", "pred_y_mm", "pred_z_mm", "pred_t", "cut_max_contact_deg",
               "surface_px", "surface_max_contact_deg")
PRUNE_COLUMNS = ("max_contact_deg", "predict", "surface_px", "source")


def scan_program(pg: PassGeometry, cutter: Cutter, wp: Workpiece, renderer, px_per_mm: float,
                 min_contact_deg: float = 45.0, design=None, strips: int = 1, strip: int | None = None,
                 at: dict | None = None, steep_deg: float = STEEP_DEG,
                 earlier: list[tuple[PassGeometry, Cutter]] = ()) -> dict:
    """Scan the program's tiles (those of shard ``strip`` of ``strips``) and predict its passes.

    Parameters
    ----------
    min_contact_deg : passes whose surface's largest contact angle is below this are not predicted
        (claim 8)
    design : the nominal model (:class:`stages.geometry.workpiece.DesignSurface`) or None
    at : {pass index: tip (3,)} to predict exactly these passes at these points (the test of a
        kernel against a closed form), instead of the pruned cutting passes at their scan's points
    steep_deg : strip points steeper than this are tested against the sweeps (claim 6)
    earlier : the passes and cutters of the programs machined before this one on the same stock, in
        order: the program meets the stock less their sweeps

    Returns
    -------
    dict of numpy columns: ``passes`` (the pass indices reported), ``cut_filter`` and
    ``angle_prune`` (one row per pass), ``predicted`` (pass indices predicted), ``generating``
    (one row per predicted pass), ``n_z`` and ``masks`` (their engagement grids, packed).
    """
    mesh = envelope_mesh(cutter, fine_tolerance(px_per_mm))
    before = Earlier(list(earlier), wp, mesh.tol_mm) if len(earlier) else None
    stock = ChainedStock(wp.top, before) if before else wp.top
    dz = cutter.radius_mm * DZ_PER_RADIUS
    out = {"passes": [], "cut_filter": [], "angle_prune": [], "predicted": [], "generating": [], "n_z": [],
           "masks": [], "depth": []}
    for tile in tiles(pg, cutter, wp, px_per_mm, strips=strips, strip=strip):
        ts = scan_tile(tile, pg, wp, mesh, renderer, earlier=before)
        px, sq = surface_stats(ts, len(pg.pass_id))
        cols = cut_columns(pg, ts.counts, ts.b_max, px, sq)
        k = tile.owned
        cf = {c: v[k] for c, v in cols.items()}
        visible = cf["surface_px"] > 0
        max_q = np.where(visible, cf["surface_max_contact_deg"],
                         np.where(cf["is_cutting"], cf["cut_max_contact_deg"], np.nan))
        predict = cf["is_cutting"] & (np.nan_to_num(max_q, nan=-1.0) >= min_contact_deg)
        ap = {"max_contact_deg": max_q, "predict": predict, "surface_px": cf["surface_px"],
              "source": np.where(visible, "surface", np.where(cf["is_cutting"], "cut", "none"))}
        if at is None:
            pred = k[predict]
            tips = np.stack([cf["pred_x_mm"], cf["pred_y_mm"], cf["pred_z_mm"]], 1)[predict]
        else:
            pred = np.intersect1d(np.fromiter(at, np.int64, len(at)), k)
            tips = np.array([at[p] for p in pred], float).reshape(-1, 3)
        s_tip = pg.s0[pred] + np.linalg.norm(tips - pg.p0[pred], axis=1)
        gen = generating_points(ts, pg, cutter, pred, tips, mesh.tol_mm, design, steep_deg)
        snap = snapshot_from(pg, pred, s_tip, cutter.radius_mm, TRAIL_TURN_DEG)
        n_z, masks, depth = engagement(ts, pg, cutter, pred, tips, snap, dz, N_PHI, margin=mesh.tol_mm, stock_top=stock)
        for key, v in (("passes", k), ("cut_filter", cf), ("angle_prune", ap), ("predicted", pred),
                       ("generating", gen), ("n_z", n_z), ("masks", masks), ("depth", depth)):
            out[key].append(v)
    if strip in (None, 0):                # the passes no tile owns (rapids, moves off the stock) do not cut
        rest = np.setdiff1d(np.arange(len(pg.pass_id)), cutting_candidates(pg, cutter, wp))
        m = len(rest)
        nan = np.full(m, np.nan)
        out["passes"].append(rest)
        out["cut_filter"].append(dict(is_cutting=np.zeros(m, bool), cut_px=np.zeros(m, np.int64), pred_x_mm=nan,
                                      pred_y_mm=nan, pred_z_mm=nan, pred_t=nan, cut_max_contact_deg=nan,
                                      surface_px=np.zeros(m, np.int64), surface_max_contact_deg=nan))
        out["angle_prune"].append({"max_contact_deg": nan, "predict": np.zeros(m, bool),
                                   "surface_px": np.zeros(m, np.int64), "source": np.array(["none"] * m, dtype=object)})
    return {"passes": _cat(out["passes"]).astype(np.int64),
            "cut_filter": {c: _cat([d[c] for d in out["cut_filter"]]) for c in CUT_COLUMNS},
            "angle_prune": {c: _cat([d[c] for d in out["angle_prune"]]) for c in PRUNE_COLUMNS},
            "predicted": _cat(out["predicted"]).astype(np.int64),
            "generating": {c: _cat([d[c] for d in out["generating"]]) for c in
                           (*GEN_COLUMNS, "n_px", "n2_px", "view")} if out["generating"] else None,
            "n_z": _cat(out["n_z"]).astype(np.int64), "masks": [b for m in out["masks"] for b in m], "dz": dz,
            "depth": np.concatenate(out["depth"]) if out["depth"] else np.zeros((0, DEPTH_QUANTILES))}


def _cat(parts):
    return np.concatenate(parts) if parts else np.zeros(0)
