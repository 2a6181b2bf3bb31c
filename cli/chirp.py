"""`calib chirp -o DIR`: the chirp to play from the robot and an emission schedule."""
from __future__ import annotations

from pathlib import Path

import typer

from calib.pipeline import sessiontools as st
from calib.pipeline.formats import validate as V
from .common import Quiet, console, user_errors


@user_errors
def chirp(
    out: Path = typer.Option(..., "-o", "--out", help="folder to write chirp.wav, schedule.csv and chirp.toml into (a file there that calib did not write is never replaced)"),
    fs: float = typer.Option(48000, help="sample rate of chirp.wav, Hz, 1 kHz … 1 MHz (any rate: the frontend "
                                         "resamples it)"),
    n_events: int = typer.Option(30, help="chirps in the schedule (≥ 3; 20-40 stops give a well-posed "
                                          "calibration)"),
    interval: float = typer.Option(st.INTERVAL, help="mean time between chirps, s: longer than the chirp + RT60 + "
                                                     "the largest propagation delay, so chirps never overlap"),
    jitter: float = typer.Option(st.JITTER, help="± fraction of the interval: irregular intervals make matching "
                                                 "detections to events unambiguous"),
    seed: int = typer.Option(0, help="seed of the jitter"),
    f0: float = typer.Option(st.CHIRP_F0, help="start frequency, Hz: above room modes, hum and footsteps"),
    f1: float = typer.Option(st.CHIRP_F1, help="end frequency, Hz: below spatial aliasing of ~4 cm mic spacings"),
    duration: float = typer.Option(st.CHIRP_DURATION, help="chirp length, s: time-bandwidth (f1-f0)·T sets the "
                                                          "matched-filter gain (1750 ≈ 32 dB)"),
    fade: float = typer.Option(st.CHIRP_FADE, help="raised-cosine fade in/out, s (no click)"),
    kind: str = typer.Option("linear", help="sweep: linear or exponential"),
    quiet: Quiet = False,
):
    """Write the sweep to play (chirp.wav), an emission schedule (schedule.csv: event,t_emit in s from the start
    of playback) and the [chirp] table for session.toml (chirp.toml).

    Play chirp.wav at the schedule's times, stopping the robot for each chirp, and log each emission time on the
    robot's clock with its odometry into events.csv. Copy chirp.wav into the session folder: the frontend then
    matches against the exact emitted signal.
    """
    paths = st.chirp_files(out, fs=V.option(fs, "fs", lo=V.SAMPLE_RATE[0], hi=V.SAMPLE_RATE[1], integer=True), n_events=n_events, interval=interval, jitter=jitter, seed=seed, f0=f0, f1=f1,
                           duration=duration, fade=fade, kind=kind)
    if not quiet:
        console.print(f"{kind} sweep {f0:g}-{f1:g} Hz, {duration:g} s at {fs:g} Hz; {n_events} chirps every "
                      f"{interval:g} s ± {100 * jitter:.0f} % → {', '.join(str(p) for p in paths.values())}")
