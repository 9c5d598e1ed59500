"""A stage that runs in shards, for tests/test_shards.py (importable by name on a Dask worker).

Shard i of n returns the rows i, i+n, … of passes 0–9; a shard listed in ``params["fail"]`` raises.
"""
import numpy as np
import pyarrow as pa

NAME = "sharded_test"
VERSION = "1"
INPUTS = ()
OUTPUTS = ("angle_prune",)
PARAMS = ()
SHARDS = 3


def run(inputs, params, shard=None):
    i, n = shard or (0, 1)
    if i in params.get("fail", ()):
        raise ValueError(f"shard {i} broke")
    ids = np.arange(10)[i::n]
    return {"angle_prune": pa.table({"program_id": ["p"] * len(ids), "pass_id": ids.astype(np.int32),
                                     "max_contact_deg": ids * 10.0, "predict": ids % 2 == 0,
                                     "surface_px": ids.astype(np.int32), "source": ["surface"] * len(ids)})}


def combine_shards(parts):
    t = pa.concat_tables([p["angle_prune"] for p in parts])
    return {"angle_prune": t.take(pa.array(np.argsort(t.column("pass_id").to_numpy(), kind="stable")))}
