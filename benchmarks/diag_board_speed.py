"""A 3-D board's own speed of sound against the declared one and the odometry's (issue 27): for each rendered
session folder and each edit (``c=V``: session.toml declares V m/s; ``odo=S``: events.csv's odometry x, y, z scaled
by S, a wheel-diameter error), the session is hard-linked into a scratch folder with that one file rewritten, its
set-up findings computed (``setupcheck.folder_findings``: features extracted here) and the speed-of-sound finding
classified: which cause it names (``sound``: the declared speed; ``odometry``: the odometry's scale; ``board``: the
boards alone, the odometry's test silent), ``both`` (no board decides: the finding offers both), or none.

    python benchmarks/diag_board_speed.py SESSION_DIR ... [--edits c=349,c=338,odo=1.02,odo=0.98] [--old]
        [--scratch /tmp/x]

--old: the boards' c withheld (the findings as before board_speed). Prints one line per session and edit: the
boards' c ± std (their names), the finding's class and status. Scratch folders are rebuilt each run.
"""
from __future__ import annotations

import argparse
import os
import shutil
import tempfile
from pathlib import Path

import pandas as pd

from calib.pipeline import setupcheck as S

SOUND_CHECKS = ("speed of sound", "odometry scale")


def edited(src, edit, scratch):
    """A hard-linked copy of ``src`` with the one edited file written anew (the source is never written)."""
    kind, value = edit.split("=")
    dst = Path(scratch) / f"{Path(src).name}_{kind}{value}"
    shutil.rmtree(dst, ignore_errors=True)
    shutil.copytree(src, dst, copy_function=os.link)
    if kind == "c":
        text = (dst / "session.toml").read_text().splitlines()
        (dst / "session.toml").unlink()
        (dst / "session.toml").write_text("\n".join(f"speed_of_sound = {float(value)}" if ln.startswith(
            "speed_of_sound") else ln for ln in text) + "\n")
    else:
        ev = pd.read_csv(dst / "events.csv")
        ev[["odom_x", "odom_y", "odom_z"]] *= float(value)
        (dst / "events.csv").unlink()
        ev.to_csv(dst / "events.csv", index=False, float_format="%.9f")
    return dst


def classify(found):
    """(class, status) of the speed-of-sound findings ``found``."""
    for f in found:
        if f.check == "odometry scale":
            return "odometry", f.status
        if f.check == "speed of sound":
            return ("sound" if " is off: " in f.text else "board" if "but the mic delays" in f.text else "both"), \
                f.status
    return "-", "-"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("sessions", nargs="+")
    ap.add_argument("--edits", default="c=349,c=338,odo=1.02,odo=0.98")
    ap.add_argument("--old", action="store_true")
    ap.add_argument("--scratch", default=None)
    args = ap.parse_args()
    seen = {}
    orig = S.board_sound
    S.board_sound = (lambda boards: None) if args.old else (lambda boards: seen.setdefault("b", orig(boards)))
    scratch = args.scratch or tempfile.mkdtemp(prefix="board_speed_")
    for src in args.sessions:
        for edit in [e for e in args.edits.split(",") if e] or ["c=none"]:
            seen.clear()
            folder = edited(src, edit, scratch) if edit != "c=none" else src
            cls, status = classify(S.folder_findings(folder))
            b = seen.get("b")
            said = "-" if b is None else f"{b[0]:.1f} ± {b[1]:.1f} ({','.join(b[2])})"
            print(f"{Path(src).name} {edit:9s} board {said:28s} {cls:9s} {status}", flush=True)


if __name__ == "__main__":
    main()
