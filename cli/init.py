"""`calib init FOLDER --model MODEL`: a session.toml from the WAVs of a folder and an array model."""
from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from calib.errors import InputError
from calib.pipeline.formats.outputs import check_file_replaceable, write_file
from calib.pipeline.sessiontools import MODELS, PER_MIC_NAME, init_session
from .common import Quiet, console, user_errors

COMMAND = "calib init"
# the other writers of a session.toml (a simulated session; "calib": a folder written before the manifest named
# its command, or by a library call): calib's own session descriptions, which --force may replace; only a file
# named session.toml (their events.csv or WAVs are a recording's, never init's to replace)
SESSION_WRITERS = ("calib simulate", "calib")
SESSION_NAME = "session.toml"


@user_errors
def init(
    folder: Path = typer.Argument(..., help="folder with one multichannel WAV per array (named after the array)"),
    model: List[str] = typer.Option(["custom"], "--model", "-m",
                                    help=f"array model ({', '.join(MODELS)}) for every WAV, or NAME=MODEL per "
                                         "WAV (repeat); custom leaves the mics to fill in"),
    reference: Optional[str] = typer.Option(None, show_default=False,
                                            help="reference array [default: the first WAV, by name]"),
    out: Optional[Path] = typer.Option(None, "-o", "--out", show_default=False,
                                       help="file to write [default: FOLDER/session.toml]"),
    layout: str = typer.Option("array", "--layout",
                               help="array: each WAV one array (named after the file); per-mic: one mono WAV per "
                                    "mic, named ARRAY-MIC.wav (e.g. the seed paper's arr1-1.wav ... arr1-4.wav)"),
    force: bool = typer.Option(False, "--force", help="replace a session.toml calib wrote (never a file you wrote or "
                                                      "edited)"),
    quiet: Quiet = False,
):
    """Write a session.toml for the WAVs in FOLDER: each WAV one array, mics from the array model.

    Models: respeaker-6-circular, respeaker-usb-4mic, minidsp-uma8, matrix-voice (geometry of the ODAS
    configurations), respeaker-4-linear (nominal spacing: measure your board) and custom (zeros to fill in).
    A WAV in the board's raw layout (e.g. 8 channels of a ReSpeaker 6-Mic, 6 of a ReSpeaker USB v2.0) gets
    its channel map. Check the result, add events.csv, then run `calib check FOLDER`.
    """
    per = dict(m.split("=", 1) for m in model if "=" in m)
    plain = [m for m in model if "=" not in m]
    if len(plain) > 1:
        raise InputError("give one --model for all WAVs, or NAME=MODEL for each")
    for m in list(per.values()) + plain:
        if m not in MODELS:
            raise InputError(f"--model must be one of {', '.join(MODELS)}, not {m!r}")
    spec = {**dict.fromkeys(_array_names(folder, layout), plain[0] if plain else "custom"), **per} if per else plain[0]
    path = out if out is not None else folder / "session.toml"
    inputs = [folder, *sorted(folder.glob("*.wav"))]
    kin = SESSION_WRITERS if path.name == SESSION_NAME else ()
    # before the work: never a user's file
    check_file_replaceable(path, inputs, replace=force, command=COMMAND, kin=kin)
    text = init_session(folder, spec, reference=reference, layout=layout)
    write_file(path, text, command=COMMAND, inputs=inputs, replace=force, kin=kin)
    if not quiet:
        console.print(f"wrote {path}")


def _array_names(folder, layout):
    """The array names of the WAVs of ``folder`` (the NAME of --model NAME=MODEL)."""
    names = [p.stem for p in folder.glob("*.wav")]
    if layout == "per-mic":
        names = [m["array"] for m in map(PER_MIC_NAME.match, (p.name for p in folder.glob("*.wav"))) if m]
    return names
