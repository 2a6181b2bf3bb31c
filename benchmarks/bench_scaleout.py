"""Study scale-out (issue 32): `calib montecarlo` on N local processes and on a Dask LocalCluster of N workers,
its parallel efficiency (speed-up / N) measured, and projected for more workers than this machine has.

    python benchmarks/bench_scaleout.py                       # N = 1, 2 and the machine's cores; --runs 4
    python benchmarks/bench_scaleout.py --workers 1 2 16 --runs 40     # issue 32's figure on a 16-core machine
    python benchmarks/bench_scaleout.py --workers 1 2 --runs 40 --save DIR   # here: measure 1, 2; project to 16
    python benchmarks/bench_scaleout.py --analyse DIR --slowdown 1.2        # the saved runs again, a what-if
    python benchmarks/bench_scaleout.py --modes local          # no Dask
    python benchmarks/bench_scaleout.py --probe 16             # the machine's ceiling: 16 busy cores vs one

Every study runs as a user runs it: ``calib montecarlo -o OUT --runs R --jobs N -q --timing-log T`` (local) or
``--scheduler ADDRESS`` (Dask: a ``distributed.LocalCluster(n_workers=N, threads_per_worker=1)`` of worker
processes started by this script first with ``preload=["calib.pipeline.studyrun"]``, not timed), each into a
fresh folder.

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

    # preload: as docs/montecarlo.md advises for a cluster's workers (a long-lived worker imports it once)
    with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                      preload=["calib.pipeline.studyrun"]) as cluster, \
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
    local1 = df[(df["mode"] == "local") & (df["N"] == 1) & (df["rc"] == 0)]
    if len(local1):   # against the plain local study on one core (the stricter baseline for Dask)
        df["eff_vs_local1"] = float(local1["wall_s"].iloc[0]) / df["wall_s"] / df["N"]
    return df


def task_slowdown(df, timelines):
    """The same tasks' own CPU time on N busy workers against the N = 1 run (the mode's own, else local):
    > 1 where a core is slower with the others busy (clock speed, shared caches or memory, a virtual
    machine's neighbours). Per run: the ratio of the sums, and the per-worker median ratios' spread; no
    schedule can have efficiency above about 1 / ratio."""
    def per_task(tl):
        return {tuple(k): (t[2], c["worker"]) for c in tl["chunks"] for k, t in zip(c["keys"], c["tasks"])}

    out = []
    for _, r in df[(df["rc"] == 0) & (df["N"] > 1)].iterrows():
        base = next((timelines[(m, 1)] for m in (r["mode"], "local") if (m, 1) in timelines), None)
        if base is None:
            continue
        one, many = per_task(base), per_task(timelines[(r["mode"], r["N"])])
        keys = [k for k in many if k in one]
        by_worker = {}
        for k in keys:
            by_worker.setdefault(many[k][1], []).append(many[k][0] / one[k][0])
        w = np.array([np.median(v) for v in by_worker.values()])
        ratio = sum(many[k][0] for k in keys) / sum(one[k][0] for k in keys)
        out.append({"mode": r["mode"], "N": r["N"], "task_cpu_ratio": ratio, "worker_min": w.min(),
                    "worker_median": np.median(w), "worker_max": w.max(), "ceiling": 1 / ratio})
    return pd.DataFrame(out)


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


PROBE_TASKS = 12   # the paper grid's first runs: ~1-3 s of one core's work, the same in every probe process


def probe_worker():
    """One probe process (``--probe-worker``): import the study's worker module, then run PROBE_TASKS runs;
    print JSON with the wall and CPU seconds of each part."""
    t0, c0 = time.perf_counter(), time.process_time()
    from calib.pipeline.studyrun import run_chunk

    t1, c1 = time.perf_counter(), time.process_time()
    tasks, _ = mc._pending_tasks(Path(tempfile.gettempdir()) / "calib-no-such-study", {**mc.paper_grid(), "runs": 1})
    settings = {"base_seed": 0, "sigma_odo": mc.SIGMA_ODO, "check_convergence": True, "with_crlb": True}
    run_chunk(tasks[:PROBE_TASKS], settings)
    t2, c2 = time.perf_counter(), time.process_time()
    print(json.dumps({"import_wall_s": t1 - t0, "import_cpu_s": c1 - c0, "task_wall_s": t2 - t1,
                      "task_cpu_s": c2 - c1}))


def probe(n):
    """The machine's own ceiling: ``n`` probe processes started together vs one alone. The ratio of their
    task wall (and CPU) times is the slowdown of the same work when n cores are busy (shared cores of
    hyper-threads, clock speed, memory bandwidth): no study can have efficiency above about 1 / that ratio.
    The import ratio is the same for the workers' start-up (file system and CPU shared by n imports)."""
    import subprocess

    def together(k):
        procs = [subprocess.Popen([sys.executable, __file__, "--probe-worker"], stdout=subprocess.PIPE, text=True)
                 for _ in range(k)]
        return pd.DataFrame([json.loads(p.communicate()[0]) for p in procs])

    alone, busy = together(1).median(), together(n)
    out = pd.DataFrame({"1 process": alone, f"{n} processes (median)": busy.median(),
                        f"{n} processes (max)": busy.max(), "ratio": busy.median() / alone})
    print(f"\nMACHINE PROBE: {PROBE_TASKS} study runs in one process alone, then in {n} processes at once "
          f"({os.cpu_count()} cores)")
    print(out.to_string(float_format=lambda v: f"{v:.3g}"))
    print(f"efficiency ceiling from the task wall ratio alone: {1 / out.loc['task_wall_s', 'ratio']:.2f}", flush=True)


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
    slow = task_slowdown(df, timelines)
    if len(slow):
        print("\nTASK CPU ON N BUSY WORKERS vs N = 1 (the same tasks; per worker: its tasks' median ratio); ceiling = "
              "1 / task_cpu_ratio")
        print(slow.to_string(index=False, float_format=fmt))
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
    ap.add_argument("--probe", type=int, metavar="N", help="measure nothing else: the machine probe with N "
                                                          "processes (see probe())")
    ap.add_argument("--probe-worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--extra", nargs=argparse.REMAINDER, default=[], help="more calib montecarlo options")
    args = ap.parse_args()
    pd.set_option("display.width", 250)
    pd.set_option("display.max_columns", 40)
    if args.probe_worker:
        probe_worker()
        return 0
    if args.probe:
        probe(args.probe)
        return 0
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
