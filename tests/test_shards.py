"""Stages run in shards: one program's stage as several Dask tasks, joined into one cache entry."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
import yaml
from distributed import Client

from pipeline.cache import Cache
from pipeline.engine import Run
from pipeline.executor import Executor, shard_key
from pipeline.graph import Stage, mould_graph
from tests import sharded_stage
from tests.test_engine import BOX_PROGRAM, WF, run_cli


@pytest.fixture(scope="module")
def client():
    with Client(processes=False, n_workers=2, threads_per_worker=1, dashboard_address=":0") as c:
        yield c


def test_shards_are_joined_in_pass_order_and_a_failed_shard_fails_only_its_program(tmp_path, client):
    cache = Cache(tmp_path)
    good, bad = SimpleNamespace(program_id="good"), SimpleNamespace(program_id="bad")
    todo = [(good, "k1", {}, {}), (bad, "k2", {"fail": [1]}, {})]
    with Executor(progress=False, client=client) as ex:
        recs = {p.program_id: r for p, _, r in ex.run(Stage.of(sharded_stage), todo, cache)}
    assert recs["good"]["ok"]
    t = cache.read("sharded_test", "k1", "angle_prune")
    assert t.column("pass_id").to_pylist() == list(range(10))           # every row once, in pass order
    assert t.column("max_contact_deg").to_pylist() == [10.0 * i for i in range(10)]
    assert not any(cache.has("sharded_test", shard_key("k1", i, 3)) for i in range(3))   # replaced by the join
    assert not recs["bad"]["ok"] and "shard 1 broke" in recs["bad"]["message"]
    assert not cache.has("sharded_test", "k2")
    # the shards that did finish stay cached: a rerun computes only the broken one
    assert cache.has("sharded_test", shard_key("k2", 0, 3)) and cache.has("sharded_test", shard_key("k2", 2, 3))


def test_scan_in_shards_equals_it_in_one_piece(tmp_path):
    """The engine's sharded scan (its tiles dealt to several tasks) against one unsharded scan.run on
    the same inputs: the same rows in pass order, the same generating points and engagement."""
    from stages import scan
    wf = dict(WF, until="scan", stock={"box": [0, 0, -10, 20, 20, 0]},
              render={"backend": "auto", "px_per_mm": 100, "passes_per_task": 2},
              prune={"min_contact_deg": 0}, split={"max_pass_mm": 3.0})
    (tmp_path / "nc").mkdir()
    (tmp_path / "nc" / "box.nc").write_bytes(BOX_PROGRAM)
    (tmp_path / "wf.yaml").write_text(yaml.safe_dump(wf))
    code, out = run_cli("run", str(tmp_path / "wf.yaml"), "--workers", "2", "-q")
    assert code == 0, out
    run = Run(str(tmp_path / "wf.yaml"), mould_graph())
    part = run.parts[0]
    run.status()                                        # finds the cached tables of the partition
    stage = Stage.of(scan)
    _, params, specs = run.plan(stage, part, 1)
    assert stage.shard_count(specs, params) > 1
    inputs = {n: (pq.read_table(v) if kind == "table" else v) for n, (kind, v) in specs.items()}
    whole = scan.run(inputs, params)
    for name in scan.OUTPUTS:
        sharded = pd.read_parquet(tmp_path / "out" / "tables" / name / "box.parquet")
        one = whole[name].to_pandas()
        assert np.all(np.diff(sharded.pass_id) > 0) and len(sharded) >= (10 if name == "cut_filter" else 1)
        pd.testing.assert_frame_equal(sharded, one, check_dtype=False)


def test_forces_in_shards_equal_them_in_one_piece(tmp_path):
    """forces.run on contiguous blocks of the engagement rows, joined, against one run on all."""
    from stages import forces
    wf = dict(WF, until="forces", stock={"box": [0, 0, -10, 20, 20, 0]},
              render={"backend": "auto", "px_per_mm": 50}, prune={"min_contact_deg": 0}, split={"max_pass_mm": 1.0})
    (tmp_path / "nc").mkdir()
    (tmp_path / "nc" / "box.nc").write_bytes(BOX_PROGRAM)
    (tmp_path / "wf.yaml").write_text(yaml.safe_dump(wf))
    code, out = run_cli("run", str(tmp_path / "wf.yaml"), "--workers", "1", "-q")
    assert code == 0, out
    read = {n: pq.read_table(tmp_path / "out" / "tables" / n / "box.parquet") for n in ("passes", "generating", "engagement")}
    params = {"tool": wf["tool"], "material": wf["material"]}
    n = 3
    assert read["engagement"].num_rows >= n
    joined = forces.combine_shards([forces.run(read, params, shard=(i, n)) for i in range(n)])["forces"]
    pd.testing.assert_frame_equal(joined.to_pandas(), forces.run(read, params)["forces"].to_pandas())
    assert forces.shards({"engagement": 2 * forces.ROWS_PER_TASK + 1}, params) == 3
