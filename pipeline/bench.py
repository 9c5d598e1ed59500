"""``pipeline bench``: the whole nightly chain on a generated finishing job of a given size.

The job is a zigzag raster finish of the sample mould insert (``data_samples/models/mould.stl``:
the cavity of a real injection mould from OpenCAMLib's examples, 101.6 × 84.1 mm): a Ø6 ball, the cutter
locations dropped onto the model by OpenCAMLib's drop-cutter (independent CAM code) every
``SAMPLE_MM`` along each row, one G1 per location as CAM chord output is, and the step-over chosen
so the program has the asked number of passes. The stock is the model raised by the finishing
allowance. The job runs through the engine as ``pipeline run`` does (one correction round), and
the figures are written as JSON: passes, wall seconds, passes/s, the peak memory of the process
and its workers, and each stage's seconds.
"""
from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path

import numpy as np

SAMPLES = Path(__file__).resolve().parents[1] / "data_samples"
TOOL_D_MM = 6.0
SAMPLE_MM = 0.1           # cutter locations along a row
ALLOWANCE_MM = 0.15       # finishing stock over the model
CLEARANCE_MM = 5.0        # rapid plane above the model


def design_mesh():
    """The sample insert (machine frame: its top at z = 0)."""
    import trimesh
    return trimesh.load(SAMPLES / "models" / "mould.stl", force="mesh")


def raster(mesh, n_passes: int, radius_mm: float):
    """Cutter-location rows (tips) of a zigzag along x with the step-over that gives about
    ``n_passes`` moves; drop-cutter onto ``mesh`` by OpenCAMLib."""
    from opencamlib import ocl
    lo, hi = mesh.bounds
    x = np.arange(lo[0], hi[0] + 1e-9, SAMPLE_MM)
    n_rows = max(2, int(round(n_passes / len(x))))
    ys = np.linspace(lo[1], hi[1], n_rows)
    surf = ocl.STLSurf()
    for t in mesh.triangles:
        surf.addTriangle(ocl.Triangle(*(ocl.Point(*map(float, p)) for p in t)))
    cutter = ocl.BallCutter(2.0 * radius_mm, 50.0)
    dc = ocl.BatchDropCutter()
    dc.setSTL(surf)
    dc.setCutter(cutter)
    for y in ys:
        for xi in x:
            dc.appendPoint(ocl.CLPoint(float(xi), float(y), float(lo[2] - 10.0)))
    dc.run()
    z = np.array([p.z for p in dc.getCLPoints()]).reshape(n_rows, len(x))
    rows = []
    for i, y in enumerate(ys):
        pts = np.stack([x, np.full_like(x, y), z[i]], 1)
        rows.append(pts if i % 2 == 0 else pts[::-1])
    return rows


def write_program(path: Path, rows) -> int:
    """The rows as an ISO program (G1 between the locations, step-overs in the cut); its moves."""
    lines = ["%", "O1000 (BENCH RASTER FINISH)", "G90 G17 G21", "T1 M6", "S12000 M3"]
    first = rows[0][0]
    lines += [f"G0 X{first[0]:.4f} Y{first[1]:.4f} Z{CLEARANCE_MM:.4f}", f"G1 Z{first[2]:.4f} F1000"]
    moves = 1
    for k, pts in enumerate(rows):
        body = pts if k else pts[1:]
        lines.append(f"G1 X{body[0, 0]:.4f} Y{body[0, 1]:.4f} Z{body[0, 2]:.4f} F3000")
        lines += [f"X{p[0]:.4f} Y{p[1]:.4f} Z{p[2]:.4f}" for p in body[1:]]
        moves += len(body)
    lines += [f"G0 Z{CLEARANCE_MM:.4f}", "M5", "M30", "%"]
    path.write_text("\n".join(lines) + "\n")
    return moves + 1


def make_job(root: Path, n_passes: int, n_programs: int = 1) -> Path:
    """Write the bench job (programs, models, workflow) under ``root``; returns the workflow.

    With ``n_programs`` > 1 the rows are dealt to that many programs, bands of consecutive rows (a
    mould finished region by region), each on the same stock."""
    root.mkdir(parents=True, exist_ok=True)
    (root / "nc").mkdir(exist_ok=True)
    design = design_mesh()
    design.export(root / "design.stl")
    stock = design.copy()
    stock.apply_translation([0.0, 0.0, ALLOWANCE_MM])
    stock.export(root / "stock.stl")
    rows = raster(design, n_passes, TOOL_D_MM / 2)
    if n_programs <= 1:
        write_program(root / "nc" / "raster.nc", rows)
    else:
        for k, band in enumerate(np.array_split(np.arange(len(rows)), n_programs)):
            write_program(root / "nc" / f"raster_{k:02d}.nc", [rows[i] for i in band])
    wf = {
        "name": "bench", "programs": "nc/*.nc", "stock": "stock.stl", "nominal": "design.stl",
        "tool": {"type": "ball", "diameter_mm": TOOL_D_MM, "flutes": 2, "helix_deg": 30, "stickout_mm": 30},
        "material": {"name": "FCD550", "ktc": 2000, "krc": 700, "kac": 300, "kte": 20, "kre": 15, "kae": 5},
        "machine": {"rapid_mm_min": 30000, "frf": {"table": str(SAMPLES / "machine" / "frf_xy.csv")}},
        "render": {"backend": "auto", "px_per_mm": 20},
        "prune": {"min_contact_deg": 45},
        "split": {"chord_tol_mm": 0.001, "max_pass_mm": 5.0, "merge_max_mm": 0.0},
        "correct": {"max_move_um": 50, "tol_um": 0.1, "max_iter": 1},
        "output": "out",
    }
    import yaml
    path = root / "bench.yaml"
    path.write_text(yaml.safe_dump(wf, sort_keys=False))
    return path


class PeakMemory:
    """Peak resident memory of this process and its children (the Dask workers), sampled."""

    def __init__(self, every_s: float = 0.2):
        import psutil
        self._proc, self._every, self.peak_mb = psutil.Process(), every_s, 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def _loop(self):
        import psutil
        while not self._stop.is_set():
            total = 0
            for p in [self._proc, *self._proc.children(recursive=True)]:
                try:
                    total += p.memory_info().rss
                except psutil.Error:
                    pass
            self.peak_mb = max(self.peak_mb, total / 2 ** 20)
            self._stop.wait(self._every)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()


def run_job(workflow: Path, workers: int | None, scheduler: str | None, fresh: bool) -> dict:
    from pipeline.engine import Run
    from pipeline.graph import mould_graph
    with PeakMemory() as mem:
        t = time.perf_counter()
        summary = Run(str(workflow), mould_graph(), fresh=fresh).execute(scheduler=scheduler, workers=workers,
                                                                         progress=False)
        wall = time.perf_counter() - t
    stages: dict = {}
    for s in summary.get("stages", []):
        name = s["name"].partition("@")[0]
        stages[name] = round(stages.get(name, 0.0) + s.get("wall_s", 0.0), 3)
    return {"wall_s": round(wall, 3), "peak_rss_mb": round(mem.peak_mb, 1), "stage_s": stages,
            "failures": summary.get("failures", [])}


def bench(n_passes: int, root: Path, workers: int | None = None, scheduler: str | None = None,
          rerun: bool = False, n_programs: int = 1) -> dict:
    """Make the job (once per size under ``root``), run it from a cold cache, and optionally again."""
    job = root / (f"passes-{n_passes}" + (f"-programs-{n_programs}" if n_programs > 1 else ""))
    workflow = job / "bench.yaml"
    if not workflow.exists():
        make_job(job, n_passes, n_programs)
    import pyarrow.parquet as pq
    cold = run_job(workflow, workers, scheduler, fresh=True)
    passes = sum(pq.ParquetFile(f).metadata.num_rows for f in (job / "out" / "tables" / "passes").glob("*.parquet"))
    out = {"passes": passes, "wall_s": cold["wall_s"], "passes_per_s": round(passes / cold["wall_s"], 1),
           "peak_rss_mb": cold["peak_rss_mb"], "stage_s": cold["stage_s"], "workers": workers, "programs": n_programs,
           "backend": _backend(), "failures": cold["failures"]}
    if rerun:
        out["rerun_s"] = run_job(workflow, workers, scheduler, fresh=False)["wall_s"]
    return out


def _backend() -> str:
    from stages.render import make_renderer
    return make_renderer("auto").name


def write_json(result: dict, path: str | None) -> str:
    text = json.dumps(result, indent=2)
    if path:
        Path(path).write_text(text + "\n")
    return text


def default_root() -> Path:
    return Path(os.environ.get("PIPELINE_BENCH_DIR", Path.cwd() / "runs" / "bench"))
