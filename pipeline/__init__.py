"""The engine: CLI, workflow config, Dask execution, cache and table I/O (DESIGN §2–§3)."""
