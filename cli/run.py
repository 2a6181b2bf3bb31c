"""`calib run RECORDINGS [-o OUT]`: features → estimate → report, skipping stages whose inputs are unchanged."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from calib.pipeline.formats.io import dumps_json
from .common import Jobs, Quiet, console, exit_on_failed, print_verdict, user_errors, waiting, with_estimate_options
from .signals import checked, interrupted
from .tables import out as stdout, print_arrays, print_metrics


class _Display:
    """Rich progress: one line per stage (a bar for the frontend and the report, a spinner for the estimate)."""

    def __init__(self, enabled):
        self.enabled = enabled
        self.tasks = {}
        self.progress = None
        if enabled:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn, \
                TimeElapsedColumn

            self.progress = Progress(SpinnerColumn(), TextColumn("{task.description:<10}"), BarColumn(),
                                     MofNCompleteColumn(), TextColumn("{task.fields[msg]}"), TimeElapsedColumn(),
                                     console=console, transient=False)

    def __enter__(self):
        self.started = False  # the display starts with the first stage, after the inputs are validated
        return self

    def __exit__(self, *exc):
        if self.started:
            self.progress.__exit__(*exc)

    def log(self, stage, status, detail):
        if not self.enabled:
            return
        if status == "skipped":
            console.print(f"[dim]{stage:<10} skipped ({detail})[/dim]")
        elif status == "run":
            if not self.started:
                self.progress.__enter__()
                self.started = True
            self.tasks[stage] = self.progress.add_task(stage, total=None, msg=f"[dim]{detail}[/dim]")
        elif status == "done":
            t = self.tasks[stage]
            total = self.progress.tasks[t].total or 1
            self.progress.update(t, total=total, completed=total, msg=f"done in {detail:.1f} s")
            self.progress.stop_task(t)

    def update(self, stage, done, total, msg):
        if self.enabled and stage in self.tasks:
            self.progress.update(self.tasks[stage], total=total, completed=done, msg=msg)


@user_errors
@with_estimate_options
def run(
    recordings: Path = typer.Argument(..., help="recording session folder (session.toml, WAVs, events.csv, "
                                                "optional truth/)"),
    out: Optional[Path] = typer.Option(None, "-o", "--out",
                                       help="output folder (default: ./<session folder name>-calib)"),
    force: bool = typer.Option(False, "--force", help="recompute every stage even if its inputs are unchanged"),
    est_opts: dict | None = None,
    detect_threshold: Optional[float] = typer.Option(
        None, show_default=False,
        help="chirp detection threshold: matched-filter peak over local background [default: 8]"),
    max_drift: Optional[float] = typer.Option(None, show_default=False,
                                              help="largest clock drift |δ| the association allows [default: 1e-3]"),
    quiet: Quiet = False,
    jobs: Jobs = -1,
    json_out: bool = typer.Option(False, "--json", help="print one JSON line (stages, timings, metrics, paths)"),
):
    """Calibrate from recordings: features → estimate → report (+ evaluation when RECORDINGS/truth exists).

    Writes OUT/features, OUT/diagnostics, OUT/calibration and OUT/report. Re-running skips every stage whose
    inputs (file contents), settings and software are unchanged; edit OUT/features/*.csv by hand and re-run
    to re-estimate from your edits.

    Exit code 0 when the verdict is ok or suspect, 3 when it is failed (everything is still written), 2 on
    bad input, 130 when interrupted.
    """
    from calib.pipeline.run import run as run_pipeline

    out = out if out is not None else Path(f"{recordings.resolve().name}-calib")
    feat_opts = {k: v for k, v in {"threshold": detect_threshold, "max_drift": max_drift}.items() if v is not None}
    show = not quiet and not json_out
    try:
        with _Display(show) as disp:
            res = run_pipeline(recordings, out, force=force, features_options=feat_opts, estimate_options=est_opts,
                               progress=checked(disp.update), log=checked(disp.log), on_wait=waiting,
                               jobs=jobs)
    except KeyboardInterrupt as exc:
        raise typer.Exit(interrupted(exc, "the stage in progress kept no output; re-run to resume")) from None

    stages = res["stages"]
    if json_out:
        rep = res["calibration"]["report"]
        print(dumps_json({
            "out": str(res["out"]),
            "ran": [s for s, v in stages.items() if v["status"] == "run"],
            "skipped": [s for s, v in stages.items() if v["status"] == "skipped"],
            "stages": stages,
            "seconds": res["seconds"],
            "converged": rep.get("converged"),
            "verdict": rep.get("verdict"),
            "metrics": res["metrics"],
            "outputs": {"features": str(res["out"] / "features"), "diagnostics": str(res["out"] / "diagnostics"),
                        "calibration": str(res["out"] / "calibration"), "report": str(res["report"])},
        }))
        exit_on_failed(rep)
        return
    if quiet:
        exit_on_failed(res["calibration"]["report"])
        return
    print_arrays(res["calibration"])
    if res["metrics"] is not None:
        print_metrics(res["metrics"])
    skipped = [s for s, v in stages.items() if v["status"] == "skipped"]
    note = f"; skipped (unchanged): {', '.join(skipped)}" if skipped else ""
    stdout.print(f"report: {res['report']}  ({res['seconds']:.1f} s{note})")
    print_verdict(res["calibration"]["report"], stdout)
    exit_on_failed(res["calibration"]["report"])
