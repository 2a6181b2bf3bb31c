"""Study scale-out (issue 32): `calib montecarlo` on N local processes and on a Dask LocalCluster of N workers,
its parallel efficiency (speed-up / N) measured, and projected for more workers than this machine has.

    python benchmarks/bench_scaleout.py                       # N = 1, 2 and the machine's cores; --runs 4
    python benchmarks/bench_scaleout.py --workers 1 2 16 --runs 40     # issue 32's figure on a 16-core machine
    python benchmarks/bench_scaleout.py --workers 1 2 --runs 40 --save DIR   # here: measure 1, 2; project to 16
    python benchmarks/bench_scaleout.py --analyse DIR --slowdown 1.2        # the saved runs again, a what-if
    python benchmarks/bench_scaleout.py --modes local          # no Dask

Every study runs as a user runs it: ``calib montecarlo -o OUT --runs R --jobs N -q --timing-log T`` (local) or
``--scheduler ADDRESS`` (Dask: a ``distributed.LocalCluster(n_workers=N, threads_per_worker=1)`` of worker
processes started by this script first, not timed), each into a fresh folder.

Measured, per mode and N: wall time of the command, CPU time (user + system) of the command and its
worker processes (for Dask: the command plus the workers' own CPU time, read from them), speed-up and
efficiency = T(1) / (N T(N)) against the same mode's N = 1, cpu_ratio = CPU(N)/CPU(1), and whether runs.csv
(but time_s) is the same as the first study's. From the study's timeline (``--timing-log``,
:mod:`calib.pipeline.studytiming`): the *serial* part, i.e. the process's wall outside the task loop (its
start-up and imports, the set-up before the first task, the merge/summary/figure after the last, its exit),
the workers' start-up (hand-out to their first task), the wall per chunk beyond its tasks, and the tasks'
own CPU time.

**Projection** (printed as such, never as a measurement): T(N) = serial + the study's chunks for N workers
list-scheduled (in order, each to the first free worker, after the measured worker start-up) with the
tasks' durations and chunk overhead measured in one run. Task durations are their CPU time (what a task
takes on a core of its own, whatever the load here), so the projection is for an idle machine with as
many cores as workers, each as fast per task as in the measured run: memory bandwidth or clock speed
shared by many busy cores are not in it (compare cpu_ratio measured there). It is validated here: the
measured runs replayed with their *wall* durations (the load included) against their measured wall, and
the projected efficiency from 1 to 2 workers against the measured one (``--repeat`` interleaves the runs).
T(1) and T(N) of a projected efficiency share the tasks' CPU times (of the run with the most workers); T(1)
has the serial part, worker start-up and chunk overhead of the N = 1 run.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cliproc import calib_cmd, load, measure  # noqa: E402

from calib.pipeline import montecarlo as mc  # noqa: E402
from calib.pipeline import studytiming as st  # noqa: E402


def _rows_without_time(path):
    """sha256 of runs.csv without its time_s column (every other column is a function of the seeds)."""
    df = pd.read_csv(path, dtype=str, keep_default_na=False)
    return hashlib.sha256(df.drop(columns="time_s").to_csv(index=False).encode()).hexdigest()


def _worker_cpu(client):
    """Total CPU seconds (user + system) the cluster's worker processes have used so far."""
    def cpu():
        t = os.times()
        return t.user + t.system

    return sum(client.run(cpu).values())


def timed(cmd):
    """:func:`cliproc.measure` of ``cmd``, with ``launched``: the epoch second it was started."""
    launched = time.time()
    return {**measure(cmd), "launched": launched}


def local(n, args, out, log):
    m = timed(calib_cmd("montecarlo", "-o", out, "--runs", args.runs, "--jobs", n, "-q", "--timing-log", log,
                          *args.extra))
    return m, m["cpu_s"]


def dask(n, args, out, log):
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None) as cluster, \
            Client(cluster) as client:
        c0 = _worker_cpu(client)
        m = timed(calib_cmd("montecarlo", "-o", out, "--runs", args.runs, "--scheduler",
                              cluster.scheduler_address, "-q", "--timing-log", log, *args.extra))
        return m, m["cpu_s"] + _worker_cpu(client) - c0


def chunker(durations, n):
    """The study's own chunking of its tasks (here: their durations) for n workers."""
    return mc._chunks(durations, n)


def serial_parts(tl, launched, exited):
    """The process's time outside the task loop (s), by part: as measured (wall) and for an idle machine
    (``*_idle``: the parent's CPU in each part; its exit, whose CPU is not separable from the workers', as
    the wall scaled by the CPU share the process got while it started)."""
    s = st.summary(tl)
    wall = {"cli_start_s": tl["start"] - launched, "before_s": s["before_s"], "after_s": s["after_s"],
            "cli_exit_s": exited - tl["phases"]["end"]["t"]}
    share = min(1.0, s["cli_start_cpu_s"] / max(wall["cli_start_s"], 1e-9))
    idle = {"cli_start_idle": s["cli_start_cpu_s"], "before_idle": s["before_cpu_s"], "after_idle": s["after_cpu_s"],
            "cli_exit_idle": wall["cli_exit_s"] * share}
    return {**wall, "serial_s": sum(wall.values()), **idle, "serial_idle_s": sum(idle.values())}


def run_one(mode, n, args, tmp, rep=0):
    out, log = Path(tmp) / f"{mode}{n}-{rep}", Path(tmp) / f"{mode}{n}-{rep}.json"   # a fresh study each time
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    m, cpu = (local if mode == "local" else dask)(n, args, out, log)
    launched = m["launched"]
    row = {"mode": mode, "N": n, "rc": m["rc"], "wall_s": m["wall_s"], "cpu_s": cpu, "load_before": load0,
           "load_after": os.getloadavg()[0]}
    tl = None
    if m["rc"] == 0:
        tl = json.loads(log.read_text())
        s = st.summary(tl)
        parts = serial_parts(tl, launched, launched + m["wall_s"])
        row.update(**parts, startup_s=s["startup_s"],
                   startup_cpu_s=s["startup_cpu_s"], chunk_ovh_ms=1e3 * s["chunk_overhead_s"],
                   task_cpu_s=s["task_cpu_s"],
                   task_wall_s=s["task_wall_s"], other_thread_cpu_s=s["task_process_cpu_s"] - s["task_cpu_s"],
                   rows=_rows_without_time(out / "runs.csv"))
    else:
        row["error"] = (m["stderr"].strip().splitlines() or ["?"])[-1]
    print(f"{mode} N={n}: {m['wall_s']:.1f} s wall, {cpu:.1f} s CPU ({time.perf_counter() - t0:.0f} s with set-up; "
          f"load {load0:.2f})", file=sys.stderr, flush=True)
    return row, tl


def measured_table(rows):
    df = pd.DataFrame(rows)
    ref = next((r for r in df["rows"] if isinstance(r, str)), None) if "rows" in df else None
    df["same_rows"] = [isinstance(r, str) and r == ref for r in df.get("rows", [None] * len(df))]
    df = df.drop(columns=[c for c in ("rows",) if c in df])
    for mode, g in df.groupby("mode"):
        one = g[g["N"] == 1]
        if len(one):
            t1, c1 = float(one["wall_s"].iloc[0]), float(one["cpu_s"].iloc[0])
            df.loc[g.index, "speedup"] = t1 / g["wall_s"]
            df.loc[g.index, "efficiency"] = t1 / g["wall_s"] / g["N"]
            df.loc[g.index, "cpu_ratio"] = g["cpu_s"] / c1
    return df


def validation(df, timelines):
    """Each measured run replayed: its tasks with their measured wall durations list-scheduled on its N
    workers, its measured serial part and worker start-up, against its measured wall time; for N > 2, also
    what the mode's 2-worker run projects for that N (the check of the projection on a machine with the cores:
    on an idle machine it should be close to measured_wall_s)."""
    out = []
    for _, r in df[df["rc"] == 0].iterrows():
        tl = timelines[(r["mode"], r["N"])]
        replay = st.project(tl, r["N"], chunker, kind="wall", serial_s=float(r["serial_s"]))
        row = {"mode": r["mode"], "N": r["N"], "measured_wall_s": r["wall_s"], "replay_wall_s": replay,
               "error_pct": 100 * (replay / r["wall_s"] - 1),
               "idle_wall_s": st.project(tl, r["N"], chunker, kind="cpu", serial_s=float(r["serial_idle_s"]))}
        two = df[(df["mode"] == r["mode"]) & (df["N"] == 2) & (df["rc"] == 0)]
        if r["N"] > 2 and len(two):   # what a 2-worker run projected for this N (on an idle machine)
            row["projected_from_2_s"] = st.project(timelines[(r["mode"], 2)], r["N"], chunker, kind="cpu",
                                                   serial_s=float(two["serial_idle_s"].iloc[0]))
        out.append(row)
    return pd.DataFrame(out)


def projections(df, timelines, project_n, slowdown=1.0):
    """Per mode, from its run with the most workers: the projected wall time on N workers and efficiency =
    T(1) / (N T(N)). Both use that run's task CPU times (on a shared machine a task's CPU time drifts with the
    load, ±10 % between runs minutes apart: comparing two runs' tasks would measure the load, not the
    scaling); T(N) its chunk overhead, worker start-up and serial part, T(1) those of the mode's N = 1 run.
    Also the parts of T(N): serial, worker start-up, tasks' CPU / N and the rest (the tail: workers idle
    at the end, chunk overhead). ``slowdown``: every task of T(N > 1) that much longer (a what-if for
    clock speed or memory bandwidth shared by N busy cores, which this machine cannot show)."""
    out = []

    def slowed(durations, n):
        return chunker([d * (slowdown if n > 1 else 1.0) for d in durations], n)

    for mode, g in df[df["rc"] == 0].groupby("mode"):
        one, top = g[g["N"] == 1], g.loc[g["N"].idxmax()]
        tl = timelines[(mode, top["N"])]
        s = st.summary(tl)
        t1 = None
        if len(one):
            s1 = st.summary(timelines[(mode, 1)])
            t1 = st.project(tl, 1, chunker, kind="cpu", serial_s=float(one["serial_idle_s"].iloc[0]),
                            startup_s=s1["startup_cpu_s"], overhead_s=s1["chunk_overhead_s"])
        for n in project_n:
            p = st.project(tl, n, slowed, kind="cpu", serial_s=float(top["serial_idle_s"]))
            work = s["task_cpu_s"] * (slowdown if n > 1 else 1.0) / n
            out.append({"mode": mode, "from_N": top["N"], "N": n, "PROJECTED_wall_s": p,
                        "efficiency": t1 / (n * p) if t1 else np.nan, "serial_s": top["serial_idle_s"],
                        "startup_s": s["startup_cpu_s"], "work_per_worker_s": work,
                        "tail_s": p - top["serial_idle_s"] - s["startup_cpu_s"] - work})
    return pd.DataFrame(out)


def measure_all(args):
    """Run every (mode, N), ``--repeat`` times interleaved; keep each one's fastest. Returns (rows, timelines)."""
    best, timelines = {}, {}
    with tempfile.TemporaryDirectory(prefix="calib-bench-scaleout-") as tmp:
        for rep in range(args.repeat):
            for mode in args.modes:
                for n in args.workers:
                    row, tl = run_one(mode, n, args, tmp, rep)
                    key = (mode, n)
                    if key not in best or (row["rc"] == 0 and row["wall_s"] < best[key]["wall_s"]):
                        best[key], timelines[key] = row, tl
    return list(best.values()), timelines


def save(folder, rows, timelines):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "measured.json").write_text(json.dumps(rows))
    for (mode, n), tl in timelines.items():
        if tl is not None:
            (folder / f"timeline-{mode}-{n}.json").write_text(json.dumps(tl))


def load_saved(folder):
    rows = json.loads((folder / "measured.json").read_text())
    timelines = {(r["mode"], r["N"]): json.loads((folder / f"timeline-{r['mode']}-{r['N']}.json").read_text())
                 for r in rows if r["rc"] == 0}
    return rows, timelines


def report(rows, timelines, project_n, slowdown=1.0):
    fmt = lambda v: f"{v:.3g}"  # noqa: E731
    df = measured_table(rows)
    print("MEASURED")
    print(df.drop(columns=["task_wall_s"], errors="ignore").to_string(index=False, float_format=fmt))
    val = validation(df, timelines)
    if len(val):
        print("\nVALIDATION: each run replayed (its tasks' measured wall durations list-scheduled, its measured serial "
              "part and worker start-up) vs its measured wall; idle_wall_s: the same with CPU durations (no load)")
        print(val.to_string(index=False, float_format=fmt))
    proj = projections(df, timelines, project_n, slowdown)
    if len(proj):
        print("\nPROJECTION (not a measurement): an idle machine with N cores, each as fast per task as here"
              + (f" but {slowdown:g}x slower per task for N > 1" if slowdown != 1 else
                 "; shared memory bandwidth and clock speed under N busy cores are not in it"))
        print(proj.to_string(index=False, float_format=fmt))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, nargs="+", default=sorted({1, 2, os.cpu_count() or 1}))
    ap.add_argument("--project", type=int, nargs="*", default=[1, 2, 4, 8, 16],
                    help="numbers of workers to project to from each measured run")
    ap.add_argument("--runs", type=int, default=4, help="runs per cell and trajectory (the paper's grid)")
    ap.add_argument("--modes", nargs="+", default=["local", "dask"], choices=["local", "dask"])
    ap.add_argument("--repeat", type=int, default=1, help="measure each (mode, N) this many times, interleaved; "
                                                          "the table keeps the fastest")
    ap.add_argument("--slowdown", type=float, default=1.0,
                    help="projection what-if: tasks on N > 1 workers this much slower (e.g. 1.2)")
    ap.add_argument("--save", type=Path, help="also write the measurements and timelines into this folder")
    ap.add_argument("--analyse", type=Path, help="measure nothing: report the measurements saved in this folder")
    ap.add_argument("--extra", nargs=argparse.REMAINDER, default=[], help="more calib montecarlo options")
    args = ap.parse_args()
    pd.set_option("display.width", 250)
    pd.set_option("display.max_columns", 40)
    if args.analyse:
        report(*load_saved(args.analyse), args.project, args.slowdown)
        return 0
    print(f"calib montecarlo --runs {args.runs} {' '.join(args.extra)}; start: {load()}", flush=True)
    rows, timelines = measure_all(args)
    if args.save:
        save(args.save, rows, timelines)
    report(rows, timelines, args.project, args.slowdown)
    print(f"end: {load()}; efficiency = T(1) / (N T(N)) per mode; same_rows: runs.csv (but time_s) equal "
          "to the first study's; serial_s = cli_start + before + after + cli_exit (outside the task loop)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
