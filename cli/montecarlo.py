"""`calib montecarlo -o OUT`: the paper's Monte-Carlo study (or any grid), every method, resumable."""
from __future__ import annotations

import contextlib

import math
from pathlib import Path
from typing import Optional

import typer

from calib.pipeline.formats.io import InputError
from .common import progress_display, user_errors, waiting
from .signals import checked, interrupted


def _floats(text, what):
    try:
        vals = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"--{what}: expected comma-separated numbers, got {text!r}") from None
    if not all(math.isfinite(v) and v >= 0 for v in vals):
        raise InputError(f"--{what}: values must be finite and non-negative, got {text!r}")
    if not vals:
        raise InputError(f"--{what}: no values in {text!r}")
    return vals


def _ints(text, what):
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise InputError(f"--{what}: expected comma-separated integers, got {text!r}") from None


@user_errors
def montecarlo(
    out: Path = typer.Option(..., "-o", "--out", help="output folder (an unfinished or smaller study there is "
                                                      "resumed: runs already written are not recomputed)"),
    runs: Optional[int] = typer.Option(None, help="runs per noise cell and trajectory [default: 200, or the grid "
                                                  "file's]"),
    jobs: int = typer.Option(-1, help="local worker processes (-1: all cores, 1: no worker processes)"),
    methods: Optional[str] = typer.Option(None, help="comma-separated estimators [default: hybrid,wang]"),
    scheduler: Optional[str] = typer.Option(None, help="run on this Dask distributed scheduler "
                                                       "(e.g. tcp://host:8786) instead of local processes"),
    grid: Optional[Path] = typer.Option(None, help="TOML file with the study grid (sigma_tdoa, sigma_doa_deg or "
                                                   "cells, trajectories, runs, methods, sigma_odo, base_seed); "
                                                   "options given on the command line override it"),
    sigma_tdoa: Optional[str] = typer.Option(None, help="comma-separated TDOA noise levels, ms [default: "
                                                        "0.05,0.1,0.5]"),
    sigma_doa: Optional[str] = typer.Option(None, help="comma-separated DOA noise levels, deg [default: 5,10,15]"),
    trajectories: Optional[str] = typer.Option(None, help="comma-separated trajectories among 1,2,3 [default: "
                                                          "all]"),
    seed: Optional[int] = typer.Option(None, help="base seed of the scenes [default: 0]"),
    check_convergence: bool = typer.Option(True, "--check-convergence/--no-check-convergence",
                                           help="also solve from ground truth to tell global convergence"),
    crlb: bool = typer.Option(True, "--crlb/--no-crlb", help="score one draw from the CRLB per run"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress bar and no table"),
    timing_log: Optional[Path] = typer.Option(None, help="also write the study's timeline to this JSON file: "
                                                         "each task's worker, start, end and CPU time, the "
                                                         "parent's phases (benchmarks/bench_scaleout.py reads it)"),
):
    """Run the paper's Monte-Carlo protocol (Zhang et al. 2025, Fig. 3) for every method.

    Default grid: TDOA noise 0.05/0.1/0.5 ms × DOA noise 5/10/15° × trajectories 1-3 × 200 runs, methods
    hybrid and wang (5 arrays, |offset| <= 0.1 s, |drift| <= 1e-4, odometry noise 3 cm). Writes
    OUT/runs.csv (one row per run; every column but time_s is reproducible from the seeds),
    OUT/summary.csv (IQR-means per cell and method, convergence rate, CRLB, the paper's values) and
    OUT/fig3.png. Interrupt it at any time: re-running the same command continues where it stopped.
    """
    from calib.pipeline.montecarlo import paper_grid, read_grid, run_study

    from calib.pipeline.formats import validate as V
    from calib.pipeline.formats.io import dumps_json
    from calib.pipeline.formats.outputs import check_file_replaceable, owned_output, write_file
    from calib.pipeline.montecarlo import COMMAND, check_study_folder

    V.option(runs, "runs", lo=1, hi=10**6, integer=True)
    V.jobs_option(jobs)
    g = read_grid(grid) if grid is not None else paper_grid()
    if sigma_tdoa is not None or sigma_doa is not None:
        st = [v * 1e-3 for v in _floats(sigma_tdoa, "sigma-tdoa")] if sigma_tdoa else sorted({c[0] for c in g["cells"]})
        sd = _floats(sigma_doa, "sigma-doa") if sigma_doa else sorted({c[1] for c in g["cells"]})
        g["cells"] = [(a, b) for b in sd for a in st]
    if trajectories is not None:
        g["trajectories"] = _ints(trajectories, "trajectories")
    if methods is not None:
        g["methods"] = [m.strip() for m in methods.split(",") if m.strip()]
    if runs is not None:
        g["runs"] = runs
    if seed is not None:
        g["base_seed"] = seed
    check_study_folder(out)  # a user's summary.csv (or any file calib did not write) stops it before the work
    if timing_log is not None:
        check_file_replaceable(timing_log, command=COMMAND)
    try:
        # locked, appended to, never replaced as a folder; each file through the output policy
        with owned_output([], [grid], lock=out, check=None, on_wait=waiting), _bar(quiet) as progress:
            res = run_study(out, g["cells"], g["trajectories"], g["runs"], g["methods"], jobs=jobs, scheduler=scheduler,
                            progress=checked(progress), base_seed=g["base_seed"], sigma_odo=g["sigma_odo"],
                            check_convergence=check_convergence, with_crlb=crlb)
    except KeyboardInterrupt as exc:
        raise typer.Exit(interrupted(exc, f"the finished runs are kept in {out}; run the same command again to "
                                          "resume")) from None
    if timing_log is not None:
        write_file(timing_log, dumps_json(res["timing"]) + "\n", command=COMMAND)
    if not quiet:
        _print_summary(res)


@contextlib.contextmanager
def _bar(quiet):
    """Progress on stderr (a bar on a terminal, timestamped lines in a log file), as the ``progress(done, total,
    message)`` callback (None when quiet)."""
    if quiet:
        yield None
        return
    with progress_display("montecarlo", remaining=True) as progress:
        yield progress


def _print_summary(res):
    from rich import box
    from rich.table import Table

    from .tables import out as stdout

    s = res["summary"]
    s = s[s["stage"] == "final"]
    t = Table(title="IQR-means of the final estimates: ours / CRLB / paper", box=box.SIMPLE_HEAD,
              padding=(0, 1), collapse_padding=True)
    for col in ("ms/°", "method", "conv%", "loc cm", "angle °", "off 1e-4s", "drift ppm"):
        t.add_column(col, justify="right")

    def f(v, fmt=".2f"):
        return "—" if v is None or not math.isfinite(v) else format(v, fmt)

    for _, r in s.iterrows():
        t.add_row(f"{r['sigma_tdoa_ms']:g}/{r['sigma_doa_deg']:g}", str(r["method"]), f(r["converged_pct"], ".1f"),
                  " ".join(f(r[k], ".1f") for k in ("loc_cm", "crlb_loc_cm", "paper_loc_cm")),
                  " ".join(f(r[k]) for k in ("ang_deg", "crlb_ang_deg", "paper_ang_deg")),
                  f(r["offset_1e-4s"]), f(r["drift_ppm"]))
    stdout.print(t)
    stdout.print(f"{res['computed']} calibrations run in {res['wall_s']:.0f} s ({res['skipped']} already done); "
                 f"wrote {', '.join(str(p) for p in res['paths'].values())}")
