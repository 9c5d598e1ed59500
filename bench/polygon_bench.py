"""Benchmark: the polygon job (issue 62, seed 004) on a 30 mm part at 0.01 mm and 0.1° (goal ≤ 30 s).

Runs ``workflows/polygon.yaml`` (the seed's Ti-6Al-4V Ø10 blade, feed 0.04 mm per cutter revolution)
and the seed's slowest feed (SUS304 Ø8, 0.01 mm: four times the cutter passages) through the job's
runner at that resolution, into a temporary folder. Prints, as JSON, per case the height map and its
analysis (``simulate_s``), the whole job with the table, STL, pictures and report (``job_s``), and the
figures.

    python bench/polygon_bench.py [--dz 0.01] [--dtheta 0.1] [--length 30]
"""
from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import yaml

from pipeline.polygon_job import run

ROOT = Path(__file__).resolve().parent.parent
CASES = {
    "ti64_d10_f0.04": {},
    "sus304_d8_f0.01": {"workpiece": {"radius_mm": 4.0},
                        "cutter": {"radius_mm": 9.26, "eccentricity_mm": 8.26}, "feed": {"mm": 0.01}},
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dz", type=float, default=0.01)
    ap.add_argument("--dtheta", type=float, default=0.1)
    ap.add_argument("--length", type=float, default=30.0)
    a = ap.parse_args()
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, over in CASES.items():
            over = dict(over, resolution={"dz_mm": a.dz, "dtheta_deg": a.dtheta},
                        workpiece=dict(over.get("workpiece", {}), length_mm=a.length))
            ov = Path(tmp) / f"{name}.yaml"
            ov.write_text(yaml.safe_dump(over))
            t0 = time.perf_counter()
            s = run(ROOT / "workflows" / "polygon.yaml", out=Path(tmp) / name, overlays=[ov], quiet=True)
            out[name] = {"cells": s["rows"] * s["columns"], "simulate_s": s["simulate_s"],
                         "job_s": round(time.perf_counter() - t0, 2), "sides": s["sides"],
                         "twist_deg_per_mm": round(s["twist_deg_per_mm"], 4),
                         "min_thickness_mm": round(s["min_thickness_mm"], 4)}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
