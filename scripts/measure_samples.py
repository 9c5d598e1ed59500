"""The stock the sample finishing programs meet, measured on the files (independent of the pipeline).

For every G1 end point of each program: the contact point of its ball on the nominal model (the
closest point to the ball's centre, over every triangle near it) and the stock's thickness from
there along the model's normal to the stock mesh (the first crossing of that ray with a triangle).

    python scripts/measure_samples.py [--samples data_samples] [--json FILE]

Prints per program and for all: contact points, median, 5th and 95th percentile and maximum (mm).
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

import numpy as np
import trimesh

from samples_geom import Grid  # noqa: E402 (scripts/ is on sys.path when run as a script)
from samples_measure import allowance_met, program_points, summary  # noqa: E402


def ball_radius(text: str) -> float:
    """The ball's radius from the program header's ``(T… BALL D… R… …)`` comment."""
    m = re.search(r"\(T\d+ BALL D[\d.]+ R([\d.]+)", text)
    if not m:
        raise SystemExit("no '(T.. BALL D.. R..)' comment in the program header")
    return float(m.group(1))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=Path, default=Path("data_samples"))
    ap.add_argument("--json", type=Path, help="also write the figures here")
    a = ap.parse_args(argv)
    nominal = trimesh.load(str(a.samples / "models" / "mould.stl"), force="mesh")
    stock = trimesh.load(str(a.samples / "models" / "semi.stl"), force="mesh")
    gn, gs = Grid(np.asarray(nominal.triangles, float), 2.0), Grid(np.asarray(stock.triangles, float), 0.1, dims=2)
    out, every = {}, []
    for path in sorted((a.samples / "nc").glob("*.nc")):
        text = path.read_text()
        tips, _ = program_points(text)
        t = allowance_met(gn, gs, tips, ball_radius(text))["thickness"]
        out[path.stem] = summary(t)
        every.append(t)
        print(f"{path.name}: {out[path.stem]}")
    out["all"] = summary(np.concatenate(every))
    print(f"all: {out['all']}")
    if a.json:
        a.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
