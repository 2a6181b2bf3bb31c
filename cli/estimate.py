"""`calib estimate FEATURES -o CALIB`: features/ → calibration/ (arrays.csv, sources.csv, report.json)."""
from __future__ import annotations

from pathlib import Path

import typer

from calib.pipeline.formats.io import write_calibration
from calib.pipeline.formats.outputs import owned_output
from calib.pipeline.run import estimate_features
from .common import (Quiet, console, exit_on_failed, print_verdict, user_errors, waiting,
                     with_estimate_options)
from .tables import print_arrays


@user_errors
@with_estimate_options
def estimate(
    features: Path = typer.Argument(..., help="features/ directory (docs/formats.md section 2)"),
    out: Path = typer.Option(..., "-o", "--out", help="calibration/ directory to write (replaced atomically)"),
    est_opts: dict | None = None,
    quiet: Quiet = False,
):
    """Estimate array poses, clock offsets/drifts and source positions from features.

    Exit code 0 when the verdict is ok or suspect, 3 when it is failed (the calibration is still written),
    2 on bad input.
    """
    with owned_output([out], [features], command="calib estimate", on_wait=waiting):
        calib, feats = estimate_features(features, est_opts, findings=True)  # + the set-up checks features show
        write_calibration(out, calib, features=feats, command="calib estimate")  # + calibration.json
    if not quiet:
        print_arrays(calib)
        rep = calib["report"]
        console.print(f"converged: {rep['converged']} ({rep['reason']}), final cost {rep['cost']['final']:.4g}, "
                      f"{len(rep['outliers'])} outlier(s) → {out}")
        print_verdict(calib["report"], console)
    exit_on_failed(calib["report"])
