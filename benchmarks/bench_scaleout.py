"""Study scale-out (issue 32): `calib montecarlo` on N local processes and on a Dask LocalCluster of N workers,
its parallel efficiency (speed-up / N), and whether every mode writes the same rows.

    python benchmarks/bench_scaleout.py                       # N = 1, 2 and the machine's cores; --runs 4
    python benchmarks/bench_scaleout.py --workers 1 2 4 8 16 --runs 40
    python benchmarks/bench_scaleout.py --modes local          # no Dask

Every study runs as a user runs it: ``calib montecarlo -o OUT --runs R --jobs N -q`` (local) or ``--scheduler
ADDRESS`` (Dask: a ``distributed.LocalCluster(n_workers=N, threads_per_worker=1)`` of worker processes
started by this script first, not timed), each into a fresh folder. Columns: wall time of the command,
CPU time (user + system) of the command and its worker processes (for Dask: the command plus the workers'
own CPU time, read from them), speed-up T(1)/T(N) and efficiency = speed-up / N against the same mode's
N = 1, and cpu_ratio = CPU(N)/CPU(1) (the work parallelism adds: start-up of N workers, their imports,
scheduling). On a shared machine wall times (and so efficiency) depend on the load printed with them;
cpu_ratio does much less.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cliproc import calib_cmd, load, measure  # noqa: E402


def _rows_without_time(path):
    df = pd.read_csv(path, dtype=str, keep_default_na=False)
    return df.drop(columns="time_s").to_csv(index=False)


def _worker_cpu(client):
    """Total CPU seconds (user + system) the cluster's worker processes have used so far."""
    def cpu():
        t = os.times()
        return t.user + t.system

    return sum(client.run(cpu).values())


def local(n, args, out):
    m = measure(calib_cmd("montecarlo", "-o", out, "--runs", args.runs, "--jobs", n, "-q", *args.extra))
    return m, m["cpu_s"]


def dask(n, args, out):
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        c0 = _worker_cpu(client)
        m = measure(calib_cmd("montecarlo", "-o", out, "--runs", args.runs, "--scheduler",
                              cluster.scheduler_address, "-q", *args.extra))
        return m, m["cpu_s"] + _worker_cpu(client) - c0


def amdahl(n, wall):
    """Least-squares (serial, parallel) seconds of T(N) = serial + parallel / N: the serial part is what
    no number of workers removes (start-up, collecting and merging results, summary and figure)."""
    n = np.asarray(n, float)
    (serial, parallel), *_ = np.linalg.lstsq(np.column_stack([np.ones_like(n), 1.0 / n]), np.asarray(wall, float),
                                             rcond=None)
    return float(serial), float(parallel)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, nargs="+", default=sorted({1, 2, os.cpu_count() or 1}))
    ap.add_argument("--runs", type=int, default=4, help="runs per cell and trajectory (the paper's grid)")
    ap.add_argument("--modes", nargs="+", default=["local", "dask"], choices=["local", "dask"])
    ap.add_argument("--extra", nargs=argparse.REMAINDER, default=[], help="more calib montecarlo options")
    args = ap.parse_args()
    rows, reference = [], None
    print(f"calib montecarlo --runs {args.runs} {' '.join(args.extra)}; start: {load()}", flush=True)
    with tempfile.TemporaryDirectory(prefix="calib-bench-scaleout-") as tmp:
        for mode in args.modes:
            for n in args.workers:
                out = Path(tmp) / f"{mode}{n}"
                load0 = os.getloadavg()[0]
                t0 = time.perf_counter()
                m, cpu = (local if mode == "local" else dask)(n, args, out)
                row = {"mode": mode, "N": n, "rc": m["rc"], "wall_s": m["wall_s"], "cpu_s": cpu,
                       "load_before": load0, "load_after": os.getloadavg()[0]}
                if m["rc"] == 0:
                    text = _rows_without_time(out / "runs.csv")
                    reference = text if reference is None else reference
                    row["same_rows"] = text == reference
                else:
                    row["error"] = (m["stderr"].strip().splitlines() or ["?"])[-1]
                rows.append(row)
                print(f"{mode} N={n}: {m['wall_s']:.1f} s wall, {cpu:.1f} s CPU "
                      f"({time.perf_counter() - t0:.0f} s with set-up)", file=sys.stderr, flush=True)
    df = pd.DataFrame(rows)
    for mode, g in df.groupby("mode"):
        one = g[g["N"] == 1]
        if len(one):
            t1, c1 = float(one["wall_s"].iloc[0]), float(one["cpu_s"].iloc[0])
            df.loc[g.index, "speedup"] = t1 / g["wall_s"]
            df.loc[g.index, "efficiency"] = t1 / g["wall_s"] / g["N"]
            df.loc[g.index, "cpu_ratio"] = g["cpu_s"] / c1
    print(df.to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    for mode, g in df[df["rc"] == 0].groupby("mode"):
        if g["N"].nunique() >= 2:
            serial, parallel = amdahl(g["N"], g["wall_s"])
            print(f"{mode}: Amdahl fit T(N) = serial + parallel / N: serial {serial:.1f} s, parallel {parallel:.1f} s"
                  f" (best possible efficiency at N = {g['N'].max()}: "
                  f"{(serial + parallel) / (g['N'].max() * serial + parallel):.2f})")
    print(f"end: {load()}; efficiency = T(1) / (N T(N)) per mode; same_rows: runs.csv (but time_s) equal "
          "to the first study's")
    return 0


if __name__ == "__main__":
    sys.exit(main())
