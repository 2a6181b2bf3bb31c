"""`calib import-bag BAG -o REC/events.csv`: the robot's log (a ROS 1 or ROS 2 bag) as events.csv."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from calib.errors import InputError
from calib.pipeline.formats import validate as V
from calib.pipeline.formats.io import EVENTS_COLS, read_table, write_table
from calib.pipeline.formats.rosbag import bag_events
from .common import Quiet, console, user_errors

MAX_LATENCY = 10.0  # s: a playback latency beyond this is a unit mistake (ms for s)


@user_errors
def import_bag(
    bag: Path = typer.Argument(..., help="ROS 1 .bag file or ROS 2 bag folder (no ROS install needed)"),
    out: Path = typer.Option(..., "-o", "--out", help="events.csv to write (into the session folder)"),
    odom_topic: str = typer.Option("/odom", "--odom-topic", help="nav_msgs/Odometry topic of the robot base"),
    emit_topic: Optional[str] = typer.Option(None, "--emit-topic", show_default=False,
                                             help="topic with one message per chirp played (its header stamp, "
                                                  "else its record time, is the emission time)"),
    schedule: Optional[Path] = typer.Option(None, "--schedule", show_default=False,
                                            help="or the emission schedule (calib chirp's schedule.csv: event,t_emit)"),
    start: Optional[float] = typer.Option(None, "--start", show_default=False,
                                          help="bag time (s) of the schedule's zero"),
    start_topic: Optional[str] = typer.Option(None, "--start-topic", show_default=False,
                                              help="or a topic whose first message marks the schedule's zero"),
    latency: float = typer.Option(0.0, "--latency",
                                  help="playback latency, s: the sound leaves the speaker this long after the logged "
                                       "time (emission time and pose are taken then)"),
    force: bool = typer.Option(False, "--force", help="replace an existing events.csv"),
    quiet: Quiet = False,
):
    """Write events.csv from a robot's bag: the emission times (a topic, or the chirp schedule and its start)
    and the robot base's odometry (nav_msgs/Odometry) interpolated to each emission, with its heading
    (odom_yaw). Put the speaker's offset from the robot base into session.toml ([robot] speaker_offset =
    [x, y, z], m, robot frame): calib turns the base's pose into the speaker's position with it.
    """
    V.number(latency, "--latency", lo=-MAX_LATENCY, hi=MAX_LATENCY)
    if out.exists() and not force:
        raise InputError(f"{out}: exists (use --force to replace it)")
    sched = None
    if schedule is not None:
        sched = read_table(schedule, ["event", "t_emit"], int_cols=("event",)).sort_values("event")["t_emit"]
    ev = bag_events(bag, odom_topic, emit_topic=emit_topic, schedule=sched, start=start, start_topic=start_topic,
                    latency=latency)
    write_table(ev, out, EVENTS_COLS, float_format="%.9f")
    if not quiet:
        dist = float(((ev[["odom_x", "odom_y"]].diff() ** 2).sum(axis=1) ** 0.5).sum())
        console.print(f"{len(ev)} emissions, {dist:.2f} m of odometry → {out}")
