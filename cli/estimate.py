"""`calib estimate FEATURES -o CALIB`: features/ → calibration/ (arrays.csv, sources.csv, report.json)."""
from __future__ import annotations

from pathlib import Path

import typer

from calib.pipeline.io import write_calibration
from calib.pipeline.outputs import owned_output
from calib.pipeline.run import estimate_features
from .common import (EmissionSigma, Loss, Method, Noise, NoTdoaS, OutlierThreshold, Quiet, console,
                     estimate_options, exit_on_failed, print_verdict, user_errors, waiting)
from .tables import print_arrays


@user_errors
def estimate(
    features: Path = typer.Argument(..., help="features/ directory (docs/formats.md section 2)"),
    out: Path = typer.Option(..., "-o", "--out", help="calibration/ directory to write (replaced atomically)"),
    method: Method = "hybrid",
    no_tdoa_s: NoTdoaS = False,
    emission_sigma: EmissionSigma = 0.0,
    loss: Loss = "cauchy",
    outlier_threshold: OutlierThreshold = 5.0,
    noise: Noise = "auto",
    quiet: Quiet = False,
):
    """Estimate array poses, clock offsets/drifts and source positions from features.

    Exit code 0 when the verdict is ok or suspect, 3 when it is failed (the calibration is still written),
    2 on bad input.
    """
    opts = estimate_options(method, no_tdoa_s, emission_sigma, loss, outlier_threshold, noise)
    with owned_output([out], [features], command="calib estimate", on_wait=waiting):
        calib, feats = estimate_features(features, opts)
        write_calibration(out, calib, features=feats, command="calib estimate")  # + calibration.json
    if not quiet:
        print_arrays(calib)
        rep = calib["report"]
        console.print(f"converged: {rep['converged']} ({rep['reason']}), final cost {rep['cost']['final']:.4g}, "
                      f"{len(rep['outliers'])} outlier(s) → {out}")
        print_verdict(calib["report"], console)
    exit_on_failed(calib["report"])
