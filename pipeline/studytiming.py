"""Where a study's time goes, and what it would take on N workers (issue 32: parallel efficiency).

A study (:func:`calib.pipeline.montecarlo.run_study`) records a *timeline* (``res["timing"]``,
``calib montecarlo --timing-log FILE``): the parent's phases (set-up before the first task is handed out,
collection, the merge/summary/figure after the last) and, per task (one scene × its methods), the worker
that ran it, its start and end (epoch seconds, ``time.time()`` of the worker's host), its own CPU time
(the thread's) and its process's CPU time over the same interval (what other threads of that process, e.g.
a Dask worker's event loop and profiler, spent meanwhile).

:func:`project` replays such a timeline on N workers: the study's chunks for N workers, each handed in order
to the first free worker (list scheduling, as joblib and Dask do), after the measured worker start-up,
plus the measured serial part (the parent's wall outside the task loop). It is a *projection*: it assumes a
task costs on N workers what it cost in the measured run (shared memory bandwidth or clock speed on a
loaded many-core machine are not in it: compare the CPU time measured at N workers with the one at 1).
"""
from __future__ import annotations

import contextlib
import heapq
import os
import socket
import time

import numpy as np

TASK_FIELDS = ("start", "end", "cpu_s", "process_cpu_s")   # one task's record, in this order


def worker_id():
    """``host:pid`` of this process (one id per worker process, local or on a cluster)."""
    return f"{socket.gethostname()}:{os.getpid()}"


def chunk_timing():
    """A chunk's timing record, opened when a worker starts it: ``worker``, ``cpu_before`` (the process's CPU
    seconds so far: on a worker's first chunk, its start-up and imports) and ``keys``/``tasks`` (filled by
    :func:`task_timer`). The study adds ``import_cpu_s``: the CPU its import of the one-run code took (a
    worker's first chunk; 0 after)."""
    return {"worker": worker_id(), "cpu_before": time.process_time(), "keys": [], "tasks": []}


@contextlib.contextmanager
def task_timer(timing, task):
    """Time the ``with`` body as task ``task`` (sigma_tdoa, sigma_doa_deg, trajectory, run, methods) of chunk
    record ``timing`` (appends its key and TASK_FIELDS)."""
    t0, c0, p0 = time.time(), time.thread_time(), time.process_time()
    yield
    timing["tasks"].append([t0, time.time(), time.thread_time() - c0, time.process_time() - p0])
    timing["keys"].append(list(task_key(task)))


class StudyTimeline:
    """The parent's side: phases (``mark``) and the chunks' records as they arrive (``received``);
    ``process_cpu_s``: the process's CPU time when the study started (a command's start-up and imports)."""

    def __init__(self):
        self._cpu0 = time.process_time()
        self.data = {"start": time.time(), "process_cpu_s": self._cpu0, "phases": {}, "chunks": []}

    def plan(self, mode, n_workers, tasks):
        """The study's execution: ``mode`` (in-process, local, dask), its workers and its tasks, in order."""
        self.data.update(mode=mode, n_workers=int(n_workers), tasks_order=[list(task_key(t)) for t in tasks])

    def mark(self, phase):
        """Record that ``phase`` ends now (wall, epoch s; and the parent's CPU so far)."""
        self.data["phases"][phase] = {"t": time.time(), "parent_cpu_s": time.process_time() - self._cpu0}

    def received(self, timing, handled_s):
        """A chunk's record arrived; ``handled_s``: the parent's wall time to take its rows in (part file, progress)."""
        self.data["chunks"].append({**timing, "received": time.time(), "handled_s": handled_s})


def task_key(task):
    """A task's key in a timeline: (sigma_tdoa, sigma_doa_deg, trajectory, run, number of methods)."""
    st, sd, traj, run, methods = task
    return (float(st), float(sd), int(traj), int(run), len(methods))


# ------------------------------------------------------------------------------------------- analysis
def summary(tl):
    """The measured figures of a timeline (dict of seconds): the parent's phases (wall and its CPU), the
    workers' start-up (wall: hand-out to their first task; CPU: their set-up, see :func:`startup_cpu`), the
    wall per chunk beyond its tasks, the tasks' wall, own CPU and their processes' CPU."""
    ph, t0 = tl["phases"], tl["start"]
    dispatch, collected, end = (ph[k]["t"] for k in ("dispatch", "collected", "end"))
    cpu = {k: ph[k]["parent_cpu_s"] for k in ("dispatch", "collected", "end")}
    tasks = [t for c in tl["chunks"] for t in c["tasks"]]
    firsts = _first_chunks(tl)
    return {"n_workers": tl["n_workers"], "workers_seen": len(firsts), "tasks": len(tasks),
            "cli_start_cpu_s": tl["process_cpu_s"], "before_s": dispatch - t0, "before_cpu_s": cpu["dispatch"],
            "loop_s": collected - dispatch, "after_s": end - collected, "after_cpu_s": cpu["end"] - cpu["collected"],
            "startup_s": float(np.median([c["tasks"][0][0] - dispatch for c in firsts])) if firsts else 0.0,
            "startup_cpu_s": startup_cpu(tl), "chunk_overhead_s": chunk_overhead(tl),
            "task_wall_s": float(sum(t[1] - t[0] for t in tasks)), "task_cpu_s": float(sum(t[2] for t in tasks)),
            "task_process_cpu_s": float(sum(t[3] for t in tasks)),
            "parent_handling_s": float(sum(c["handled_s"] for c in tl["chunks"]))}


def _first_chunks(tl):
    """Each worker's first chunk (by its first task's start)."""
    first = {}
    for c in tl["chunks"]:
        if c["tasks"] and (c["worker"] not in first or c["tasks"][0][0] < first[c["worker"]]["tasks"][0][0]):
            first[c["worker"]] = c
    return list(first.values())


def startup_cpu(tl):
    """Median CPU seconds a worker spends before its first task: a local worker process its whole start
    (interpreter, imports); a Dask worker (already running) or the study's own process its imports of the
    estimator."""
    firsts = _first_chunks(tl)
    key = "cpu_before" if tl["mode"] == "local" else "import_cpu_s"
    return float(np.median([c.get(key, 0.0) for c in firsts])) if firsts else 0.0


def chunk_overhead(tl):
    """Median wall time per chunk that is not in its tasks: on each worker, the gap between one chunk's
    last task end and the next chunk's first task start (hand-out, result transfer, pickling)."""
    by_worker = {}
    for c in tl["chunks"]:
        if c["tasks"]:
            by_worker.setdefault(c["worker"], []).append((c["tasks"][0][0], c["tasks"][-1][1]))
    gaps = [b[0] - a[1] for spans in by_worker.values() for a, b in zip(sorted(spans), sorted(spans)[1:])]
    return float(np.median(gaps)) if gaps else 0.0


def durations(tl, kind="cpu"):
    """Each task's duration (s) in the study's task order: ``cpu`` (the task's own CPU time: its wall on an
    idle core, whatever the load when it was measured) or ``wall`` (as measured, load included)."""
    col = 2 if kind == "cpu" else None
    got = {}
    for c in tl["chunks"]:
        for key, t in zip(c["keys"], c["tasks"]):
            got[tuple(key)] = t[col] if col is not None else t[1] - t[0]
    return [got[tuple(k)] for k in tl["tasks_order"]]


def list_schedule(chunk_durations, n_workers, ready=0.0):
    """Makespan of handing chunks, in order, each to the worker that is free first (all free at ``ready``)."""
    free = [float(ready)] * max(int(n_workers), 1)
    for d in chunk_durations:
        heapq.heappush(free, heapq.heappop(free) + d)
    return max(free)


def project(tl, n_workers, chunker, *, kind="cpu", serial_s=None, startup_s=None, overhead_s=None):
    """Projected wall time (s) of the timeline's study on ``n_workers``: serial + list-scheduled chunks.

    chunker(durations, n_workers) → the study's chunks of the task list for that many workers (lists of
    durations). kind: the tasks' and the workers' start-up durations, ``cpu`` (an idle machine) or ``wall``
    (as measured). serial_s: time outside the task loop (default the timeline's before + after, i.e. inside
    run_study, CPU for ``cpu``; a caller adds the process's own start-up and exit); startup_s: a worker's
    delay to its first task; overhead_s: wall per chunk beyond its tasks (defaults: as measured in ``tl``).
    """
    s = summary(tl)
    idle = kind == "cpu"
    if serial_s is None:
        serial_s = s["before_cpu_s"] + s["after_cpu_s"] if idle else s["before_s"] + s["after_s"]
    startup = (s["startup_cpu_s"] if idle else s["startup_s"]) if startup_s is None else startup_s
    overhead = s["chunk_overhead_s"] if overhead_s is None else overhead_s
    chunks = chunker(durations(tl, kind), n_workers)
    return serial_s + list_schedule([sum(c) + overhead for c in chunks], n_workers, ready=startup)
