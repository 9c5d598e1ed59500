"""Content-keyed partition cache (DESIGN §3).

A partition's output tables live in ``<root>/<stage>/<key[:2]>/<key>/<table>.parquet``, where the
key hashes the stage name and version, the parameters the stage declares, and the keys (or file
hashes) of everything it reads. An entry is written into a temporary directory and renamed into
place in one step, so a run killed at any moment leaves either a complete entry or none; a rerun
recomputes exactly the missing entries.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import time
import uuid
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq


def digest(obj) -> str:
    """Stable sha256 of a JSON-able object (keys sorted, floats by repr)."""
    blob = json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str).encode()
    return hashlib.sha256(blob).hexdigest()


def file_sha256(path: str | os.PathLike, _chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(_chunk), b""):
            h.update(block)
    return h.hexdigest()


class Cache:
    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)

    def entry(self, stage: str, key: str) -> Path:
        return self.root / stage / key[:2] / key

    def table_path(self, stage: str, key: str, table: str) -> Path:
        return self.entry(stage, key) / f"{table}.parquet"

    def has(self, stage: str, key: str) -> bool:
        return self.entry(stage, key).is_dir()

    def read(self, stage: str, key: str, table: str) -> pa.Table:
        return pq.read_table(self.table_path(stage, key, table))

    def write(self, stage: str, key: str, tables: dict[str, pa.Table]) -> Path:
        """Write all tables of one partition atomically (directory rename)."""
        final = self.entry(stage, key)
        final.parent.mkdir(parents=True, exist_ok=True)
        tmp = final.parent / f".{key}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        tmp.mkdir()
        try:
            for name, table in tables.items():
                pq.write_table(table, tmp / f"{name}.parquet", compression="zstd")
            try:
                os.rename(tmp, final)
            except OSError:
                # another worker finished the same partition first: same key, same content
                if not final.is_dir():
                    raise
                shutil.rmtree(tmp, ignore_errors=True)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return final

    def sweep_temp(self, older_than_s: float = 0.0) -> int:
        """Remove temporary directories left by killed runs. Returns how many."""
        n = 0
        if not self.root.is_dir():
            return 0
        now = time.time()
        for p in self.root.glob("*/*/.*.tmp-*"):
            try:
                if now - p.stat().st_mtime >= older_than_s:
                    shutil.rmtree(p, ignore_errors=True)
                    n += 1
            except OSError:
                pass
        return n
