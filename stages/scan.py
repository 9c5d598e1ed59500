"""Stage ``scan``: the render chain of seed 000 as global ordered scans (claims 1, 4, 5, 6, 7, 8).

Per tile of the part, one ordered scan from below of the stock and every sweep in execution order
(:mod:`stages.surface.ordered`) gives which passes cut and where (claim 7: ``cut_filter``), the
final surface with the pass that left each pixel (claim 8: ``angle_prune``, the largest contact
angle of the surface a pass leaves, against ``prune.min_contact_deg``), and the cut log. For every
predicted pass, at its prediction point: the generating point with φ and q from the tool's strip
between the other sweeps (claims 1, 4, 6: :mod:`stages.surface.strip`) and the cutting region
from the depths its cuts replaced (claim 5: :mod:`stages.surface.engagement`).

The program meets the stock less what the earlier programs of its job cut (``passes@earlier``: their
passes and tools, in machining order; :mod:`stages.surface.chain`).

A large program is scanned in several tasks (``shards``); a pass belongs to one tile, and the
tiles' rows are joined in pass order. Decode an ``engagement`` row with
:func:`stages.surface.engagement.unpack_engagement`.
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa

import schemas
from stages.geometry.cutter import Cutter
from stages.geometry.passes import pass_geometry
from stages.geometry.workpiece import load_design_surface, load_workpiece
from stages.render import make_renderer
from stages.surface.engagement import N_PHI, chip_limit, ramp_deg
from stages.surface.program import CUT_COLUMNS, scan_program
from stages.surface.strip import GEN_COLUMNS
from stages.tables import nullable_list_column, task_count

NAME = "scan"
VERSION = "4"
INPUTS = ("passes", "passes@earlier", "stock", "nominal")
OUTPUTS = ("cut_filter", "angle_prune", "generating", "engagement")
PARAMS = ("tool", "render", "prune", "feed")
MOST_TASKS = 16          # a program's tiles are dealt to at most this many tasks


def used_params(params: dict) -> dict:
    """Of the ``feed:`` section only whether there is one: scheduled feeds need the deflection of
    every cutting pass, so then every cutting pass is predicted (``prune.min_contact_deg`` decides
    which passes' surface errors matter, not which passes load the tool)."""
    return {**params, "feed": bool(params.get("feed"))}


def shards(rows: dict, params: dict) -> int:
    """Tasks a program is scanned in, from its number of passes."""
    per = int((params.get("render") or {}).get("passes_per_task", 4000))
    return task_count(rows.get("passes", 0), per, MOST_TASKS)


def run(inputs: dict, params: dict, shard: tuple[int, int] | None = None) -> dict:
    pg = pass_geometry(inputs["passes"], params["tool"])
    rp = params.get("render") or {}
    i, n = shard or (0, 1)
    earlier = [(pass_geometry(t, p["tool"]), Cutter.from_params(p["tool"])) for t, p in inputs.get("passes@earlier") or ()]
    min_q = -np.inf if params.get("feed") else float((params.get("prune") or {}).get("min_contact_deg", 45.0))
    res = scan_program(pg, Cutter.from_params(params["tool"]), load_workpiece(inputs.get("stock")),
                       make_renderer(rp.get("backend", "auto")), float(rp.get("px_per_mm", 20.0)),
                       min_q,
                       design=load_design_surface(inputs.get("nominal")), strips=n, strip=i, earlier=earlier)
    return tables(pg, res)


def tables(pg, res: dict) -> dict:
    """The stage's four tables from :func:`stages.surface.program.scan_program`'s columns."""
    idx = res["passes"]
    pid = pa.array(pg.pass_id[idx], pa.int32())
    prog = pa.array([pg.program_id] * len(idx), pa.string())
    cf = pa.table({"program_id": prog, "pass_id": pid, **{c: res["cut_filter"][c] for c in CUT_COLUMNS}})
    ap = res["angle_prune"]
    apt = pa.table({"program_id": prog, "pass_id": pid, "max_contact_deg": ap["max_contact_deg"],
                    "predict": ap["predict"], "surface_px": ap["surface_px"],
                    "source": pa.array(list(ap["source"]), pa.string())})
    pred = res["predicted"]
    m = len(pred)
    gprog = pa.array([pg.program_id] * m, pa.string())
    gpid = pa.array(pg.pass_id[pred], pa.int32())
    gen = res["generating"] or {}
    g = pa.table({"program_id": gprog, "pass_id": gpid,
                  **{c: np.asarray(gen.get(c, np.zeros(0)), float) for c in GEN_COLUMNS},
                  **{c: pa.array(np.asarray(gen.get(c, np.zeros(0)), np.int64), pa.int32()) for c in ("n_px", "n2_px")},
                  "view": pa.array(list(gen.get("view", [])), pa.string())})
    feed = np.radians(pg.feed_deg[pred])
    ramp = ramp_deg(pg.p1[pred] - pg.p0[pred])
    limit = chip_limit(res["depth"], ramp)
    e = pa.table({"program_id": gprog, "pass_id": gpid, "dz_mm": np.full(m, res["dz"]),
                  "n_z": pa.array(res["n_z"], pa.int32()), "n_phi": pa.array(np.full(m, N_PHI), pa.int32()),
                  "mask": pa.array(res["masks"], pa.binary()), "feed_dir_x": np.cos(feed), "feed_dir_y": np.sin(feed),
                  "ramp_deg": pa.array(ramp, pa.float64()),
                  "chip_limit_mm": nullable_list_column(limit)})
    out = {"cut_filter": cf, "angle_prune": apt, "generating": g, "engagement": e}
    return {name: schemas.check(name, _sorted(t)) for name, t in out.items()}


def _sorted(t: pa.Table) -> pa.Table:
    return t.take(pa.array(np.argsort(t.column("pass_id").to_numpy(), kind="stable")))


def combine_shards(parts: list[dict]) -> dict:
    """The tables of one program from its shards' tables, in pass order."""
    return {name: _sorted(pa.concat_tables([p[name] for p in parts])) for name in OUTPUTS}
