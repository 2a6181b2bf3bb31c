"""`calib export CALIBRATION_DIR --format FORMAT -o PATH`: calibration.json in the formats other tools read."""
from __future__ import annotations

from pathlib import Path

import typer

from calib.pipeline.formats.export import FORMATS, export as export_calibration
from calib.pipeline.formats.results import load_calibration
from .common import Quiet, console, user_errors
from calib.errors import InputError


@user_errors
def export(
    calibration: Path = typer.Argument(..., help="calibration/ folder (or its calibration.json)"),
    fmt: str = typer.Option(..., "--format", "-f", help=f"output format: {', '.join(FORMATS)}"),
    out: Path = typer.Option(..., "-o", "--out", help="file to write (usual suffixes: .json, .yaml, .npy, .urdf, "
                                                      ".sh); odas: a folder of <array>.cfg"),
    quiet: Quiet = False,
):
    """Export a calibration: json, yaml (Kalibr-style), pyroomacoustics (.npy of mic positions, shape (3, all
    mics)), odas (one complete ODAS configuration per array), urdf, tf (ROS 2 static transforms). Formats:
    docs/formats.md."""
    if fmt not in FORMATS:
        raise InputError(f"--format must be one of {', '.join(FORMATS)}, not {fmt!r}")
    cal = load_calibration(calibration)
    path = export_calibration(cal, fmt, out)
    if not quiet:
        console.print(f"{fmt}: {len(cal.arrays)} arrays → {path}")
