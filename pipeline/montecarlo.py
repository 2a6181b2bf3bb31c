"""Monte-Carlo study of the paper's protocol (Zhang et al. 2025, Sec. IV-A, Fig. 3): ``calib montecarlo``.

One *run* = one scene from ``pipeline.simulate.featsim`` (a cell ``(sigma_tdoa, sigma_doa_deg)``, a trajectory, a
run number → a seed) calibrated by one method, scored against truth, next to the same solve started from
ground truth (the convergence check) and to one draw from the CRLB.

A *study* (:func:`run_study`) runs a grid of runs for several methods and writes into ``out_dir``:

``runs.csv``     one row per run and stage (``final``, plus the estimator's intermediate stages when it
                 exposes them), sorted; every column but ``time_s`` is a deterministic function of the seeds
``summary.csv``  per cell × method × stage: IQR-means (the paper's statistic) of the errors, convergence
                 rate, the CRLB draws' IQR-means and the paper's published values
``fig3.png``     the paper's Fig. 3 layout: one panel per metric, boxes per cell and method, CRLB and paper
``study.json``   the settings every row depends on (a resumed study must use the same)
``parts/``       while running: the finished runs as CSV files (written atomically, one per PART_EVERY_S), so
                 a killed study loses at most the chunks in flight and the last seconds' runs; a rerun skips
                 every run already in a part or in runs.csv, then merges them into runs.csv and removes parts/.
"""
from __future__ import annotations

import contextlib
import itertools
import json
import math
import multiprocessing
import os
import signal
import sys
import threading
import time
import warnings
from concurrent.futures import ProcessPoolExecutor, as_completed
from calib.tomlcompat import tomllib
from pathlib import Path

import numpy as np
import pandas as pd

from calib.pipeline import studytiming
from calib.pipeline.formats.io import InputError, dumps_json
from calib.pipeline.formats.outputs import (check_file_replaceable, is_own_temp, remove_owned_file, remove_temp,
                                            write_file)
from calib.pipeline.formats.validate import read_text

SIGMA_TDOA = (5e-5, 1e-4, 5e-4)
SIGMA_DOA_DEG = (5.0, 10.0, 15.0)
TRAJECTORIES = (1, 2, 3)
METHODS = ("hybrid", "wang")
RUNS = 200            # per cell and trajectory (the paper: 9 cells × 3 trajectories × 200)
SIGMA_ODO = 0.03      # m per axis and step (the paper's odometry noise)
# Published IQR-means of the paper's final estimates (Zhang et al. 2025): location cm / angle deg.
PAPER_FINAL = {
    (5e-5, 5.0): (5.22, 1.80), (1e-4, 5.0): (6.99, 1.81), (5e-4, 5.0): (15.4, 2.15),
    (5e-5, 10.0): (5.87, 3.40), (1e-4, 10.0): (8.52, 3.47), (5e-4, 10.0): (21.9, 3.74),
    (5e-5, 15.0): (6.13, 4.98), (1e-4, 15.0): (9.30, 5.09), (5e-4, 15.0): (27.5, 5.39),
}
METRICS = ("position_rmse_m", "orientation_paper_deg", "orientation_geodesic_deg", "offset_rmse_s",
           "relative_drift_rmse", "source_rmse_m")
KEY = ["sigma_tdoa", "sigma_doa_deg", "trajectory", "run", "method"]
RUN_COLUMNS = (KEY + ["stage", "seed", "ok", "error", "converged", "solver_converged", "cost", "cost_truth_start",
                      "n_outliers"] + list(METRICS) + [f"crlb_{m}" for m in METRICS] + ["time_s"])
STAGE_ORDER = {"init": 0, "ive": 1, "final": 9}
# summary column → (runs.csv metric, scale): the paper's units (offset in 1e-4 s, drift "µs" = ppm).
SUMMARY_METRICS = {"loc_cm": ("position_rmse_m", 100.0), "ang_deg": ("orientation_paper_deg", 1.0),
                   "geo_deg": ("orientation_geodesic_deg", 1.0), "offset_1e-4s": ("offset_rmse_s", 1e4),
                   "drift_ppm": ("relative_drift_rmse", 1e6), "src_cm": ("source_rmse_m", 100.0)}
SETTINGS = ("base_seed", "sigma_odo", "check_convergence", "with_crlb")
# Chunks of runs per worker task (:func:`_chunks`): each takes 1/GUIDED_SHARE of what is left per worker, at most
# MAX_CHUNK runs (what an interrupted study loses per worker).
GUIDED_SHARE = 2
MAX_CHUNK = 40
PART_EVERY_S = 5.0   # s: the parent writes the finished runs as a part file at most this often (and at the end)
ONE_RUN = ("run_seed", "truth_state", "run_methods", "run_one")   # in calib.pipeline.studyrun (the workers' side)


def paper_values(sigma_tdoa, sigma_doa_deg):
    """The paper's published (location cm, angle deg) for a cell, or None if it is not one of its cells."""
    for (st, sd), v in PAPER_FINAL.items():
        if np.isclose(st, sigma_tdoa, rtol=1e-6, atol=0) and np.isclose(sd, sigma_doa_deg, rtol=1e-6, atol=0):
            return v
    return None


def iqr_mean(x):
    """Mean of the values between the 25th and 75th percentiles (the paper's statistic)."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if not x.size:
        return float("nan")
    q1, q3 = np.percentile(x, [25, 75])
    inner = x[(x >= q1) & (x <= q3)]
    return float(np.mean(inner)) if inner.size else float(np.median(x))  # n = 2: nothing strictly inside


# ------------------------------------------------------------------------------------------------ grid
def paper_grid():
    """The paper's protocol: 3 TDOA × 3 DOA noise cells, 3 trajectories, 200 runs each, both methods."""
    return {"cells": [(st, sd) for sd in SIGMA_DOA_DEG for st in SIGMA_TDOA], "trajectories": list(TRAJECTORIES),
            "runs": RUNS, "methods": list(METHODS), "sigma_odo": SIGMA_ODO, "base_seed": 0}


def check_grid(grid, where="grid"):
    """Validate a grid dict (keys of :func:`paper_grid`); returns a cleaned copy. Raises InputError."""
    g = dict(grid)

    def pos_num(v, what):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
            raise InputError(f"{where}: {what} must be a non-negative number, got {v!r}")
        return float(v)

    cells = g.get("cells")
    if not cells:
        raise InputError(f"{where}: no noise cells")
    try:
        g["cells"] = [(pos_num(c[0], "sigma_tdoa"), pos_num(c[1], "sigma_doa_deg")) for c in cells]
    except (TypeError, IndexError, KeyError):
        raise InputError(f"{where}: cells must be pairs [sigma_tdoa (s), sigma_doa_deg]") from None
    if any(st > 0.01 for st, _ in g["cells"]):
        raise InputError(f"{where}: sigma_tdoa is in seconds; {max(st for st, _ in g['cells'])!r} s is not plausible")
    trajs = g.get("trajectories")
    if not trajs or any(isinstance(t, bool) or t not in TRAJECTORIES for t in trajs):
        raise InputError(f"{where}: trajectories must be a non-empty list of {list(TRAJECTORIES)}, got {trajs!r}")
    g["trajectories"] = [int(t) for t in dict.fromkeys(trajs)]
    runs = g.get("runs")
    if isinstance(runs, bool) or not isinstance(runs, int) or runs < 1:
        raise InputError(f"{where}: runs must be a positive integer, got {runs!r}")
    methods = g.get("methods")
    if not methods or any(m not in METHODS for m in methods):
        raise InputError(f"{where}: methods must be a non-empty list of {list(METHODS)}, got {methods!r}")
    g["methods"] = list(dict.fromkeys(methods))
    g["sigma_odo"] = pos_num(g.get("sigma_odo", SIGMA_ODO), "sigma_odo")
    seed = g.get("base_seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise InputError(f"{where}: base_seed must be a non-negative integer, got {seed!r}")
    g["cells"] = list(dict.fromkeys(g["cells"]))
    return g


def read_grid(path):
    """A grid from a TOML file, over the paper's defaults. Keys (all optional)::

        sigma_tdoa = [5e-5, 1e-4, 5e-4]   # s      } the cells are their product ...
        sigma_doa_deg = [5, 10, 15]       # deg    }
        cells = [[5e-5, 5.0], [5e-4, 15.0]]        # ... or an explicit list of (s, deg) pairs
        trajectories = [1, 2, 3]
        runs = 200                        # per cell and trajectory
        methods = ["hybrid", "wang"]
        sigma_odo = 0.03                  # m
        base_seed = 0
    """
    path = Path(path)
    try:
        cfg = tomllib.loads(read_text(path))
    except (tomllib.TOMLDecodeError, RecursionError) as exc:
        raise InputError(f"{path}: invalid TOML ({exc})") from None
    known = {"sigma_tdoa", "sigma_doa_deg", "cells", "trajectories", "runs", "methods", "sigma_odo", "base_seed"}
    unknown = sorted(set(cfg) - known)
    if unknown:
        raise InputError(f"{path}: unknown key {unknown[0]!r} (known: {', '.join(sorted(known))})")
    g = paper_grid()
    if "cells" in cfg and ("sigma_tdoa" in cfg or "sigma_doa_deg" in cfg):
        raise InputError(f"{path}: give either 'cells' or 'sigma_tdoa'/'sigma_doa_deg', not both")
    if "cells" in cfg:
        g["cells"] = cfg["cells"]
    elif "sigma_tdoa" in cfg or "sigma_doa_deg" in cfg:
        st = cfg.get("sigma_tdoa", list(SIGMA_TDOA))
        sd = cfg.get("sigma_doa_deg", list(SIGMA_DOA_DEG))
        if not isinstance(st, list) or not isinstance(sd, list):
            raise InputError(f"{path}: sigma_tdoa and sigma_doa_deg must be lists")
        g["cells"] = [(a, b) for b in sd for a in st]
    for k in ("trajectories", "runs", "methods", "sigma_odo", "base_seed"):
        if k in cfg:
            g[k] = cfg[k]
    return check_grid(g, str(path))


# ----------------------------------------------------------------------------------------------- study
def _key(sigma_tdoa, sigma_doa_deg, trajectory, run, method):
    # Same 6-digit rounding as run_seed: cells closer than that are the same scenes.
    return (f"{float(sigma_tdoa):.6g}", f"{float(sigma_doa_deg):.6g}", int(trajectory), int(run), str(method))


def _run_chunk(tasks, settings):
    """Worker entry point (:func:`calib.pipeline.studyrun.run_chunk`, imported here: a study's parent process
    never loads the estimator, 0.45 s of its start-up that no number of workers shortens)."""
    cpu0 = time.process_time()
    from calib.pipeline.studyrun import run_chunk   # a worker's first chunk: its imports of the estimator

    res = run_chunk(tasks, settings)
    res["timing"]["import_cpu_s"] = res["timing"]["cpu_before"] - cpu0
    return res


def __getattr__(name):
    """The one-run functions, formerly defined here (``from calib.pipeline.montecarlo import truth_state``)."""
    if name in ONE_RUN:
        from calib.pipeline import studyrun

        return getattr(studyrun, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")



def _rows_to_csv(rows):
    df = pd.DataFrame(rows)
    for c in RUN_COLUMNS:
        if c not in df:
            df[c] = np.nan
    return df[RUN_COLUMNS].to_csv(index=False, float_format="%.10g")


def _read_text_table(path):
    """A runs CSV as strings (no type inference), so merging never re-formats a value."""
    return pd.read_csv(path, dtype=str, keep_default_na=False)


def _sorted_runs(df):
    order = pd.DataFrame({"a": df["sigma_tdoa"].astype(float), "b": df["sigma_doa_deg"].astype(float),
                          "c": df["trajectory"].astype(int), "d": df["run"].astype(int), "e": df["method"],
                          "f": df["stage"].map(lambda s: (STAGE_ORDER.get(s, 5), s))})
    idx = order.sort_values(list("abcdef"), kind="stable").index
    return df.loc[idx].reset_index(drop=True)


COMMAND = "calib montecarlo"
STUDY_FILES = ("study.json", "runs.csv", "summary.csv", "fig3.png")  # written into the study folder


def check_study_folder(out):
    """InputError unless every file the study writes into ``out`` is absent or calib's own (before any work)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"{out}: exists and is not a directory")
    for name in STUDY_FILES:
        check_file_replaceable(out / name, command=COMMAND)


def _existing(out):
    """Rows already computed in ``out`` (runs.csv and any part files), as a string table, deduplicated."""
    tables = []
    if (out / "runs.csv").is_file():
        tables.append(_read_text_table(out / "runs.csv"))
    tables += [_read_text_table(f) for f in sorted((out / "parts").glob("part-*.csv"))]
    if not tables:
        return pd.DataFrame(columns=RUN_COLUMNS)
    df = pd.concat(tables, ignore_index=True)
    missing = [c for c in KEY + ["stage"] if c not in df]
    if missing:
        raise InputError(f"{out / 'runs.csv'}: not a runs table of calib montecarlo (no column {missing[0]!r})")
    return df.drop_duplicates(subset=KEY + ["stage"], keep="first").reset_index(drop=True)


def _check_settings(out, settings):
    path = out / "study.json"
    if path.is_file():
        try:
            old = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError):
            raise InputError(f"{path}: not valid JSON; remove the study directory or use another one") from None
        for k in SETTINGS:
            if k in old and old[k] != settings[k]:
                raise InputError(f"{path}: this study was run with {k}={old[k]!r}, not {settings[k]!r}; "
                                 "use the same settings to resume or another output directory")


def _chunks(tasks, n_workers, size=None):
    """Split tasks into contiguous chunks (a chunk = one worker task).

    ``size`` given: chunks of that many tasks. Else guided self-scheduling: each chunk takes
    1/GUIDED_SHARE of the remaining tasks per worker (at most MAX_CHUNK), so the first chunks are long (the
    per-chunk hand-out and result transfer are amortised) and the last ones short (the workers finish together: the
    study's tail is one short chunk, not one of average length).
    """
    out, k = [], 0
    while k < len(tasks):
        n = size or int(np.clip(math.ceil((len(tasks) - k) / (GUIDED_SHARE * max(n_workers, 1))), 1, MAX_CHUNK))
        out.append(tasks[k:k + n])
        k += n
    return out


def _connect(scheduler):
    """A ``distributed.Client`` for an address (or the given client). Raises InputError if unreachable."""
    try:
        from distributed import Client
    except ImportError:
        raise InputError("--scheduler needs dask.distributed: pip install 'calib[dask]'") from None
    if isinstance(scheduler, Client):
        return scheduler
    try:
        return Client(str(scheduler), timeout="20s")
    except (OSError, TimeoutError, ValueError) as exc:
        raise InputError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None


def _kill_workers():
    """Stop joblib's worker processes now (they would otherwise finish their chunks after the parent stops, or
    take their time to exit with it)."""
    from joblib.externals.loky import reusable_executor

    executor = getattr(reusable_executor, "_executor", None)  # None: no pool was started
    if executor is not None:
        executor.shutdown(wait=False, kill_workers=True)


def _can_fork():
    """Whether local workers can be forked from this process: on Linux (fork is unsafe on macOS, absent on
    Windows) with no other Python thread running (a lock another thread holds at the fork stays held in every
    worker: a notebook kernel's threads; the ``calib`` command has none then)."""
    return (sys.platform.startswith("linux") and "fork" in multiprocessing.get_all_start_methods()
            and threading.active_count() == 1)


def _execute(chunks, settings, jobs, client):
    """Yield each chunk's rows as it finishes (local processes, or a Dask cluster)."""
    if client is None:
        if jobs == 1:
            for c in chunks:
                yield _run_chunk(c, settings)
        elif _can_fork():
            yield from _execute_forked(chunks, settings, jobs)
        else:
            yield from _execute_joblib(chunks, settings, jobs)
        return
    import distributed

    futures = client.map(_run_chunk, chunks, settings=settings, pure=False)
    try:
        for fut in distributed.as_completed(futures):
            yield fut.result()
    finally:
        client.cancel(futures)


def _execute_forked(chunks, settings, jobs):
    """Local workers forked from this process once it has imported the one-run code: each starts in
    milliseconds with the estimator loaded, where a fresh interpreter per worker imports numpy, scipy and the
    estimator itself (0.6 s CPU each; 1.8 s wall for 16 at once on a 16-core machine, all of it serial time
    of the study)."""
    import calib.pipeline.studyrun  # noqa: F401 (the workers inherit it)

    n = min((os.cpu_count() or 1) if jobs == -1 else jobs, len(chunks))
    before = set(multiprocessing.active_children())
    pool = ProcessPoolExecutor(max_workers=n, mp_context=multiprocessing.get_context("fork"),
                               initializer=_worker_init, initargs=(os.getpid(),))
    done, workers = False, set()
    try:
        with warnings.catch_warnings():  # Python >= 3.12 warns of fork beside BLAS's idle threads (safe: OpenBLAS
            warnings.simplefilter("ignore", DeprecationWarning)  # stops them over a fork)
            futures = [pool.submit(_run_chunk, c, settings) for c in chunks]   # starts all n workers
        workers = set(multiprocessing.active_children()) - before
        for fut in as_completed(futures):
            yield fut.result()
        done = True
    finally:
        pool.shutdown(wait=done, cancel_futures=True)
        if not done:  # interrupted or failed: the workers must not compute on
            for w in workers:
                w.terminate()


PARENT_POLL_S = 1.0   # how often a forked worker checks that the study's process is still there


def _worker_init(parent):
    """A forked worker leaves interrupts to the study (the parent stops it) and dies of SIGTERM: it inherits the
    command's handlers, which raise an exception the pool would catch and carry on after. It also ends when
    the study's process (pid ``parent``, taken before the fork: it may be gone before this runs) dies
    (killed outright), instead of waiting forever for work."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    threading.Thread(target=_exit_with_parent, args=(parent,), daemon=True).start()


def _exit_with_parent(parent):
    while os.getppid() == parent:
        time.sleep(PARENT_POLL_S)
    os._exit(1)


def _execute_joblib(chunks, settings, jobs):
    """Local workers as joblib's processes (fresh interpreters): where this process cannot fork."""
    from joblib import Parallel, delayed

    try:
        # batch_size=1: a chunk is already a batch (joblib's automatic batching would merge the short
        # last chunks again)
        yield from Parallel(n_jobs=jobs, return_as="generator_unordered", batch_size=1)(
            delayed(_run_chunk)(c, settings) for c in chunks)
    finally:  # done: the workers stop with the study (an idle worker's own clean exit takes the parent ~0.5 s
        _kill_workers()  # to wait for); interrupted or failed: they must not compute on


def run_study(out_dir, cells=None, trajectories=None, runs=RUNS, methods=METHODS, jobs=-1, scheduler=None,
              progress=None, *, base_seed=0, sigma_odo=SIGMA_ODO, check_convergence=True, with_crlb=True,
              chunk_size=None, figure=True):
    """Run (or resume) a Monte-Carlo study and write runs.csv, summary.csv and fig3.png into ``out_dir``.

    Parameters
    ----------
    out_dir : output directory (created; an existing study there is resumed).
    cells : list of (sigma_tdoa s, sigma_doa_deg) pairs; default the paper's 3 × 3.
    trajectories : subset of (1, 2, 3); default all. ``runs`` : runs per cell and trajectory.
    methods : estimator methods ("hybrid", "wang").
    jobs : local worker processes (joblib; -1 = all cores, 1 = in this process).
    scheduler : address of a Dask distributed scheduler (or a ``distributed.Client``): run there instead.
    progress : optional callable ``progress(done, total, message)``, called as chunks finish (the CLI draws
        a bar with it; the library prints nothing).
    base_seed, sigma_odo : scene generation (``run_seed``, odometry noise m); check_convergence: also solve
        from ground truth (``converged`` column); with_crlb: score one CRLB draw per run. These four must
        match the ones of a study being resumed (``study.json``).
    chunk_size : runs per worker task (default: shrinking chunks, :func:`_chunks`).

    Returns
    -------
    dict: ``runs`` (DataFrame of the requested grid's rows), ``summary`` (DataFrame), ``computed`` and
    ``skipped`` (numbers of runs × methods), ``wall_s``, ``paths`` (dict of written files).
    """
    timeline = studytiming.StudyTimeline()
    g = paper_grid()
    grid = check_grid({**g, "cells": g["cells"] if cells is None else cells,
                       "trajectories": g["trajectories"] if trajectories is None else trajectories,
                       "runs": runs, "methods": list(methods), "sigma_odo": sigma_odo, "base_seed": base_seed})
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs == 0 or jobs < -1:
        raise InputError(f"jobs must be a positive integer or -1 (all cores), got {jobs!r}")
    out = Path(out_dir)
    check_study_folder(out)
    settings = {"base_seed": grid["base_seed"], "sigma_odo": grid["sigma_odo"],
                "check_convergence": bool(check_convergence), "with_crlb": bool(with_crlb)}
    if out.is_dir():
        _check_settings(out, settings)
    tasks, skipped = _pending_tasks(out, grid)
    client = _connect(scheduler) if scheduler is not None and tasks else None  # before writing anything
    out.mkdir(parents=True, exist_ok=True)
    write_file(out / "study.json", dumps_json({**settings, "grid": grid}, indent=2) + "\n", command=COMMAND)
    if client is not None:
        n_workers = sum(client.nthreads().values())
    else:
        n_workers = (os.cpu_count() or 1) if jobs == -1 else jobs
    chunks = _chunks(tasks, n_workers, chunk_size)
    total = sum(len(t[4]) for t in tasks)
    timeline.plan("dask" if client else "local" if jobs != 1 else "in-process", n_workers, tasks)
    timeline.mark("dispatch")
    t0 = time.perf_counter()
    try:
        if chunks:
            _run_chunks(out, chunks, settings, jobs, client, timeline, progress, total, skipped,
                        first_result=_import_plotting_meanwhile if figure else None)
    finally:
        if client is not None and client is not scheduler:
            client.close()
    timeline.mark("collected")
    wall = time.perf_counter() - t0
    paths = finish_study(out, grid, figure=figure)
    all_runs = pd.read_csv(paths["runs"])
    sel = _select(all_runs, grid)
    timeline.mark("end")
    return {"runs": sel, "summary": pd.read_csv(paths["summary"]), "computed": total, "skipped": skipped,
            "wall_s": wall, "paths": paths, "timing": timeline.data}


def _import_plotting_meanwhile():
    """Import what :func:`plot_study` needs (0.5-0.8 s CPU) in a thread, while the runs are computed (started
    once the work is out: a thread importing holds the interpreter lock the hand-out needs)."""
    threading.Thread(target=_import_plotting, daemon=True).start()


def _import_plotting():
    with contextlib.suppress(Exception):  # plot_study imports (and reports) for itself
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.collections  # noqa: F401
        import matplotlib.pyplot  # noqa: F401


def _run_chunks(out, chunks, settings, jobs, client, timeline, progress, total, skipped, first_result=None):
    """Run the chunks; write the rows that arrived as a part file every PART_EVERY_S and when the loop ends
    (done, interrupted or failed); record the timeline; call ``first_result()`` when the first chunk is in."""
    (out / "parts").mkdir(exist_ok=True)
    parts = _PartWriter(out / "parts")
    done_runs = 0
    message = f"{skipped} already done"
    if progress is not None:
        progress(0, total, message)
    try:
        for k, res in enumerate(_execute(chunks, settings, jobs, client)):
            t = time.perf_counter()
            if k == 0 and first_result is not None:
                first_result()
            parts.add(res["rows"])
            done_runs += sum(r["stage"] == "final" for r in res["rows"])
            if progress is not None:
                progress(done_runs, total, message)
            timeline.received(res["timing"], time.perf_counter() - t)
    finally:
        parts.flush()


class _PartWriter:
    """Rows → part files (``part-<stamp>-<k>.csv``, each written atomically): one file per PART_EVERY_S, not per
    chunk. Each part costs the parent a write, a read and a removal when the study is merged (~20 ms; 130
    chunks at 16 workers); a study killed outright loses at most the last PART_EVERY_S of finished runs."""

    def __init__(self, folder):
        self.folder, self.stamp, self.k = folder, f"{time.time_ns():x}", 0
        self.rows, self.last = [], time.perf_counter()

    def add(self, rows):
        self.rows += rows
        if time.perf_counter() - self.last >= PART_EVERY_S:
            self.flush()

    def flush(self):
        if self.rows:
            write_file(self.folder / f"part-{self.stamp}-{self.k:05d}.csv", _rows_to_csv(self.rows), command=COMMAND)
            self.k += 1
        self.rows, self.last = [], time.perf_counter()


def _pending_tasks(out, grid):
    """The (sigma_tdoa, sigma_doa_deg, trajectory, run, methods to do) of ``grid`` not yet in ``out``'s
    part files, and how many runs × methods are already done."""
    done = _existing(out) if out.is_dir() else pd.DataFrame(columns=RUN_COLUMNS)
    done_keys = {_key(*k) for k in zip(done["sigma_tdoa"].astype(float), done["sigma_doa_deg"].astype(float),
                                       done["trajectory"].astype(int), done["run"].astype(int), done["method"])}
    tasks, skipped = [], 0
    for (st, sd), traj, r in itertools.product(grid["cells"], grid["trajectories"], range(grid["runs"])):
        todo = [m for m in grid["methods"] if _key(st, sd, traj, r, m) not in done_keys]
        skipped += len(grid["methods"]) - len(todo)
        if todo:
            tasks.append((st, sd, traj, r, todo))
    return tasks, skipped


def _select(df, grid):
    """The rows of ``df`` (numeric runs table) that belong to ``grid``."""
    keys = {_key(st, sd, t, r, m) for (st, sd), t, r, m in
            itertools.product(grid["cells"], grid["trajectories"], range(grid["runs"]), grid["methods"])}
    mask = [_key(*k) in keys for k in zip(df["sigma_tdoa"], df["sigma_doa_deg"], df["trajectory"], df["run"],
                                           df["method"])]
    return df[np.asarray(mask, bool)].reset_index(drop=True)


def finish_study(out, grid, figure=True):
    """Merge the part files into runs.csv (sorted), then write summary.csv and the figure."""
    out = Path(out)
    merged = _sorted_runs(_existing(out))
    cols = RUN_COLUMNS + [c for c in merged.columns if c not in RUN_COLUMNS]
    for c in cols:
        if c not in merged:
            merged[c] = ""
    write_file(out / "runs.csv", merged[cols].to_csv(index=False), command=COMMAND)
    parts = out / "parts"
    if parts.is_dir():
        for f in parts.iterdir():  # calib's part files (merged above) and temporaries of killed writes
            if is_own_temp(f):
                remove_temp(f)
            elif f.name.startswith("part-"):
                remove_owned_file(f)
        with contextlib.suppress(OSError):
            parts.rmdir()  # unless a file calib did not write is left there
    runs = _select(pd.read_csv(out / "runs.csv"), grid)
    summary = summarise(runs)
    write_file(out / "summary.csv", summary.to_csv(index=False, float_format="%.6g"), command=COMMAND)
    paths = {"runs": out / "runs.csv", "summary": out / "summary.csv"}
    if figure and len(runs):
        paths["figure"] = plot_study(runs, summary, out / "fig3.png")
    return paths


def summarise(runs):
    """Per cell × method × stage: IQR-means (paper units), convergence rate, CRLB IQR-means, paper values.

    runs : numeric runs table (runs.csv). Failed runs (``ok`` false) count in ``failed`` and are left out
    of the statistics; the convergence rate is over all runs (a failure is not converged).
    """
    out = []
    if not len(runs):
        return pd.DataFrame()
    ok_all = runs["ok"].astype(str).str.lower() == "true"
    for (st, sd, method, stage), g in runs.groupby(["sigma_tdoa", "sigma_doa_deg", "method", "stage"], sort=False):
        ok = g[ok_all.loc[g.index]]
        row = {"sigma_tdoa_ms": st * 1e3, "sigma_doa_deg": sd, "method": method, "stage": stage, "runs": len(g),
               "failed": int(len(g) - len(ok))}
        if stage == "final" and "converged" in g and g["converged"].notna().any():
            row["converged_pct"] = 100.0 * float((g["converged"].astype(str).str.lower() == "true").mean())
        else:
            row["converged_pct"] = np.nan
        for name, (col, scale) in SUMMARY_METRICS.items():
            row[name] = scale * iqr_mean(ok[col]) if col in ok else np.nan
        for name, (col, scale) in SUMMARY_METRICS.items():
            c = f"crlb_{col}"
            row[f"crlb_{name}"] = scale * iqr_mean(ok[c]) if stage == "final" and c in ok else np.nan
        paper = paper_values(st, sd) if method == "hybrid" and stage == "final" else None
        row["paper_loc_cm"], row["paper_ang_deg"] = paper if paper else (np.nan, np.nan)
        t = ok["time_s"] if "time_s" in ok else pd.Series(dtype=float)
        row["median_ms"] = 1e3 * float(t.median()) if stage == "final" and t.notna().any() else np.nan
        out.append(row)
    df = pd.DataFrame(out)
    order = df["stage"].map(lambda s: (STAGE_ORDER.get(s, 5), s))
    df = df.assign(_o=order).sort_values(["sigma_doa_deg", "sigma_tdoa_ms", "method", "_o"], kind="stable")
    return df.drop(columns="_o").reset_index(drop=True)


# ---------------------------------------------------------------------------------------------- figure
def _plot_references(ax, summary, method, name, cells, pos):
    """The CRLB IQR-mean (bars) and the paper's values (stars) of one method's final estimates, one line
    artist each (markers at ``pos``, one per cell)."""
    sm = summary[(summary["method"] == method) & (summary["stage"] == "final")]
    crlb, paper = [], []
    for i, (st, sd) in enumerate(cells):
        r = sm[np.isclose(sm["sigma_tdoa_ms"], st * 1e3) & np.isclose(sm["sigma_doa_deg"], sd)]
        if not len(r):
            continue
        crlb.append((pos[i], r[f"crlb_{name}"].iloc[0]))
        if name in ("loc_cm", "ang_deg"):
            paper.append((pos[i], r["paper_loc_cm" if name == "loc_cm" else "paper_ang_deg"].iloc[0]))
    for pts, style, label in ((crlb, dict(marker="_", color="k", ms=14, mew=2),
                               "CRLB of the method's measurements (IQR-mean of draws)"),
                              (paper, dict(marker="*", color="gold", mec="k", ms=11),
                               "published, Zhang et al. 2025 (IQR-mean)")):
        pts = [(x, y) for x, y in pts if np.isfinite(y)]
        if pts:
            ax.plot(*np.transpose(pts), ls="none", label=label, **style)


def _boxes(ax, data, pos, width, color):
    """Box plots of the arrays ``data`` at x ``pos``: quartile boxes, medians, whiskers to the data within the
    5th-95th percentiles (matplotlib's ``boxplot_stats``), drawn as two collections: one artist per box part
    (``Axes.boxplot``) made the study's figure 2-4 s, the slowest step after the last run."""
    from matplotlib.cbook import boxplot_stats
    from matplotlib.collections import LineCollection, PolyCollection

    boxes, lines = [], []
    for st, x in zip(boxplot_stats(data, whis=(5, 95)), pos):
        lo, hi, cap = x - width / 2, x + width / 2, width / 4
        boxes.append([(lo, st["q1"]), (hi, st["q1"]), (hi, st["q3"]), (lo, st["q3"])])
        lines += [[(lo, st["med"]), (hi, st["med"])], [(x, st["q1"]), (x, st["whislo"])],
                  [(x, st["q3"]), (x, st["whishi"])], [(x - cap, st["whislo"]), (x + cap, st["whislo"])],
                  [(x - cap, st["whishi"]), (x + cap, st["whishi"])]]
    ax.add_collection(PolyCollection(boxes, facecolors=color, edgecolors="k", linewidths=1.0, alpha=0.85))
    ax.add_collection(LineCollection(lines, colors="k", linewidths=1.0))


# Fig. 3's margins (inches): the y label and "%g" log ticks on the left, two-line cell labels below, the title
# and legend above (what tight_layout chose for 1-9 cells, plus room for wider tick labels)
MARGIN_IN = {"left": 0.8, "right": 0.15, "bottom": 0.55, "top": 0.9}


def plot_study(runs, summary, path):
    """The paper's Fig. 3 layout: per metric a panel; per cell, one box per method/stage (whiskers at the
    5th/95th percentiles), the CRLB draws' IQR-mean (bar) and the paper's published value (star)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FormatStrFormatter, LogLocator, NullFormatter

    ok = runs[runs["ok"].astype(str).str.lower() == "true"]
    cells = sorted({(st, sd) for st, sd in zip(ok["sigma_tdoa"], ok["sigma_doa_deg"])}, key=lambda c: (c[1], c[0]))
    series = sorted({(m, s) for m, s in zip(ok["method"], ok["stage"])},
                    key=lambda x: (x[0] != "hybrid", x[0], STAGE_ORDER.get(x[1], 5)))
    colors = {("hybrid", "final"): "#1f77b4", ("wang", "final"): "#d62728", ("hybrid", "ive"): "#9ecae1",
              ("wang", "init"): "#f4a6a6", ("hybrid", "init"): "#c6dbef"}
    panels = [("loc_cm", "location error (cm)"), ("ang_deg", "orientation error (deg)"),
              ("offset_1e-4s", "time offset error (1e-4 s)"), ("drift_ppm", "clock drift error (ppm = paper's µs)")]
    fig, axes = plt.subplots(len(panels), 1, figsize=(max(8.0, 1.25 * len(cells) + 3), 3.2 * len(panels)),
                             sharex=True)
    width = 0.8 / max(len(series), 1)
    groups = {k: g for k, g in ok.groupby(["sigma_tdoa", "sigma_doa_deg", "method", "stage"], sort=False)}
    for ax, (name, label) in zip(np.atleast_1d(axes), panels):
        col, scale = SUMMARY_METRICS[name]
        for k, (m, s) in enumerate(series):
            pos = np.arange(len(cells)) + (k - (len(series) - 1) / 2) * width
            empty = pd.DataFrame({col: []})
            data = [scale * groups.get((st, sd, m, s), empty)[col].dropna().to_numpy() for st, sd in cells]
            keep = [i for i, d in enumerate(data) if len(d)]
            if not keep:
                continue
            _boxes(ax, [data[i] for i in keep], pos[keep], 0.85 * width, colors.get((m, s), "#bbbbbb"))
            ax.plot([], [], "s", color=colors.get((m, s), "#bbbbbb"), label=f"{m} ({s})")
            if s == "final":
                _plot_references(ax, summary, m, name, cells, pos)
        ax.set_yscale("log")
        ax.autoscale_view()
        ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 1.5, 2.0, 3.0, 5.0, 7.0)))
        ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
        ax.yaxis.set_minor_formatter(NullFormatter())
        ax.set_ylabel(label, fontsize=9)
        ax.grid(True, axis="y", which="both", alpha=0.3)
        for i in range(1, len(cells)):
            ax.axvline(i - 0.5, color="0.85", lw=0.8)
    seen = {}
    for ax in np.atleast_1d(axes):
        for h, lab in zip(*ax.get_legend_handles_labels()):
            seen.setdefault(lab, h)
    last = np.atleast_1d(axes)[-1]
    last.set_xticks(np.arange(len(cells)))
    last.set_xticklabels([f"TDOA {st * 1e3:g} ms\nDOA {sd:g}°" for st, sd in cells], fontsize=8)
    n_runs = ok.groupby(["sigma_tdoa", "sigma_doa_deg", "method", "stage"]).size()
    H = fig.get_figheight()  # header laid out in inches: title, then the legend, then the panels
    fig.suptitle(f"Monte-Carlo study: {len(cells)} noise cells, {int(n_runs.median()) if len(n_runs) else 0} runs "
                 "per cell and method\nboxes: quartiles and median; whiskers: 5th-95th percentiles", fontsize=10,
                 y=1 - 0.05 / H, va="top")
    fig.legend(seen.values(), seen.keys(), loc="upper center", bbox_to_anchor=(0.5, 1 - 0.45 / H), ncol=4,
               fontsize=8, frameon=False)
    W = fig.get_figwidth()  # margins in inches, fixed: tight_layout drew the figure once more (0.3 s, serial)
    fig.subplots_adjust(left=MARGIN_IN["left"] / W, right=1 - MARGIN_IN["right"] / W,
                        bottom=MARGIN_IN["bottom"] / H, top=1 - MARGIN_IN["top"] / H, hspace=0.09)
    try:
        return write_file(Path(path), lambda tmp: fig.savefig(tmp, dpi=110, format="png"), command=COMMAND)
    finally:
        plt.close(fig)
