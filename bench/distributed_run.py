"""The same job on a Dask cluster of separate processes, with a worker killed mid-run.

Starts ``dask scheduler`` and ``--workers`` ``dask worker`` processes on loopback, runs the
workflow on them (``pipeline run --scheduler``), kills one worker with SIGKILL ``--kill-after``
seconds into the run (its tasks go to the others), and compares every table with a run of the
same workflow on a LocalCluster (``scripts/compare_runs.py``). Prints both wall times and the
comparison; exits 1 on a failed run or a difference.

    python bench/distributed_run.py [WORKFLOW] [--workers 2] [--kill-after 20] [--dir runs/distributed]
"""
from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def start(cmd: list[str], log: Path) -> subprocess.Popen:
    return subprocess.Popen(cmd, stdout=log.open("w"), stderr=subprocess.STDOUT, cwd=ROOT)


def pipeline(*args: str) -> list[str]:
    return [sys.executable, "-m", "pipeline", *args]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workflow", nargs="?", default=str(ROOT / "workflows" / "mould.yaml"))
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--kill-after", type=float, default=20.0, help="seconds into the run")
    ap.add_argument("--dir", default=str(ROOT / "runs" / "distributed"))
    a = ap.parse_args()
    out = Path(a.dir)
    out.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    local = subprocess.run(pipeline("run", a.workflow, "--out", str(out / "local"), "--fresh", "-q",
                                    "--workers", str(a.workers)), cwd=ROOT)
    local_s = time.perf_counter() - t
    sched_file = Path(tempfile.mkdtemp()) / "scheduler.json"
    dask = [sys.executable, "-m", "distributed.cli.dask_scheduler"]
    procs = [start([*dask, "--host", "127.0.0.1", "--port", "0", "--scheduler-file", str(sched_file),
                    "--dashboard-address", ":0"], out / "scheduler.log")]
    while not sched_file.exists():
        time.sleep(0.2)
    address = json.loads(sched_file.read_text())["address"]
    worker = [sys.executable, "-m", "distributed.cli.dask_worker", address, "--nworkers", "1", "--nthreads", "1",
              "--host", "127.0.0.1", "--no-nanny"]
    workers = [start(worker, out / f"worker{i}.log") for i in range(a.workers)]
    procs += workers
    try:
        time.sleep(3.0)
        t = time.perf_counter()
        run = start(pipeline("run", a.workflow, "--out", str(out / "cluster"), "--fresh", "-q", "--scheduler", address),
                    out / "cluster.log")
        killed = False
        while run.poll() is None:
            if not killed and time.perf_counter() - t > a.kill_after:
                workers[0].send_signal(signal.SIGKILL)
                killed = True
                print(f"killed worker 0 (pid {workers[0].pid}) {a.kill_after:.0f} s into the run")
            time.sleep(0.5)
        cluster_s = time.perf_counter() - t
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
    print(f"LocalCluster run: {local_s:.1f} s (exit {local.returncode}); scheduler + {a.workers} worker processes, "
          f"one killed: {cluster_s:.1f} s (exit {run.returncode}; log {out / 'cluster.log'})")
    same = subprocess.run([sys.executable, str(ROOT / "scripts" / "compare_runs.py"), str(out / "local"),
                           str(out / "cluster")], cwd=ROOT)
    return int(local.returncode != 0 or run.returncode != 0 or same.returncode != 0 or not killed)


if __name__ == "__main__":
    sys.exit(main())
