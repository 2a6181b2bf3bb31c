"""`calib features RECORDINGS -o FEATURES`: recordings → features/ (docs/formats.md section 2) + diagnostics."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from .common import Jobs, console, progress_display, user_errors, waiting
from .signals import checked


@user_errors
def features(
    recordings: Path = typer.Argument(..., help="recording session folder (session.toml, WAVs, events.csv)"),
    out: Path = typer.Option(..., "-o", "--out", help="features folder to write (replaced atomically)"),
    diagnostics: Optional[Path] = typer.Option(
        None, "--diagnostics", help="where to write diagnostics.json and detections.png "
                                    "[default: 'diagnostics' beside the features folder] (written with the "
                                    "features: both or neither)"),
    detect_threshold: float = typer.Option(8.0, help="chirp detection threshold: matched-filter peak over local "
                                                     "background"),
    max_drift: float = typer.Option(1e-3, help="largest clock drift |δ| the association allows"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="no progress bar or summary"),
    jobs: Jobs = -1,
):
    """Detect the chirps, match them to the robot's events, measure TDOA-M, TDOA-S and DOA."""
    from calib.pipeline.features import write_feature_outputs
    from calib.pipeline.formats.outputs import check_separate, owned_output
    from calib.pipeline.formats.session import read_session
    from calib.pipeline.formats.validate import features_options, jobs_option

    diag_dir = diagnostics if diagnostics is not None else out.resolve().parent / "diagnostics"
    opts = {**features_options({"threshold": detect_threshold, "max_drift": max_drift}), "jobs": jobs_option(jobs)}
    check_separate([out, diag_dir], [recordings])
    session = read_session(recordings)  # every input checked before any output is touched
    inputs = [recordings, *(f for a in session["arrays"] for f in a["files"]), session["chirp"].get("reference")]
    with owned_output([out, diag_dir], inputs, command="calib features", on_wait=waiting):
        feats, diag = _extract(session, opts, quiet)
        write_feature_outputs(out, diag_dir, feats, diag)
    if not quiet:
        _summary(feats, diag, out, diag_dir)


def _extract(recordings, opts, quiet):
    """Features and diagnostics of a session (folder or read session), with a progress bar unless ``quiet``."""
    from calib.pipeline.features import session_features

    if quiet:
        feats, diag = session_features(recordings, progress=checked(), **opts)
    else:
        with progress_display("features") as progress:
            feats, diag = session_features(recordings, progress=checked(progress), **opts)
    return feats, diag


def _summary(feats, diag, out, diag_dir):
    from rich.table import Table

    t = Table(title=f"features of {len(feats['events'])} events in {diag['elapsed_s']:.2f} s "
                    f"({100 * diag['elapsed_s'] / diag['recording_duration_s']:.1f} % of the recording)")
    for col in ("array", "fs", "matched", "missed", "spurious", "TDOA-S", "DOA", "notes"):
        t.add_column(col)
    ts = feats["tdoa_s"]
    for name, a in diag["arrays"].items():
        n_m = sum(d["event"] is not None for d in a["detections"])
        t.add_row(name, f"{a['fs']}", str(n_m), ", ".join(map(str, a["missed_events"])) or "-",
                  str(len(a["spurious"])), str(int((ts["array"] == name).sum())),
                  str(int((feats["doa"]["array"] == name).sum())), "; ".join(a["warnings"]))
    console.print(t)
    console.print(f"TDOA-M: {len(feats['tdoa_m'])}; chirp drift bias β = {diag['chirp_drift_bias']:.4g} s "
                  f"→ {out}  (diagnostics: {diag_dir})")
