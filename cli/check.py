"""`calib check RECORDINGS`: validate a session without estimating; a table of what is wrong."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .common import user_errors
from .tables import out as stdout

EXIT_PROBLEMS = 2  # as bad input: the session cannot be calibrated as it is


@user_errors
def check(
    recordings: Path = typer.Argument(..., help="recording session folder (session.toml, WAVs, events.csv)"),
    detect: bool = typer.Option(True, "--detect/--no-detect", help="run the chirp detector: is the chirp audible "
                                                                   "in each array?"),
    detect_threshold: Optional[float] = typer.Option(None, show_default=False,
                                                     help="detection threshold: matched-filter peak over local "
                                                          "background [default: 8]"),
):
    """Check a session before a long run: channels vs mics, sample rates, recording length, chirp audible in
    each array, events and odometry plausible; and the set-up consistency stage: dead, clipped, inverted or
    swapped channels, the mic geometry against the inter-mic delays (shape, units), each board's size against
    its delays and the odometry, each array's clock, copied recordings, the speed of sound against the
    odometry, the trajectory. Exit code 0 when nothing FAILs, 2 otherwise."""
    from rich.table import Table

    from calib.pipeline.sessiontools import check_session

    opts = {} if detect_threshold is None else {"threshold": detect_threshold}
    rows = check_session(recordings, detect=detect, **opts)
    style = {"ok": "green", "warn": "yellow", "FAIL": "bold red"}
    t = Table(title=f"calib check {recordings}")
    for col in ("what", "check", "status", "detail"):
        t.add_column(col)
    for _, r in rows.iterrows():
        t.add_row(r["what"], r["check"], f"[{style[r['status']]}]{r['status']}[/]", r["detail"])
    stdout.print(t)
    n_fail = int((rows["status"] == "FAIL").sum())
    stdout.print(f"{n_fail} problem(s), {int((rows['status'] == 'warn').sum())} warning(s)")
    if n_fail:
        raise typer.Exit(EXIT_PROBLEMS)
