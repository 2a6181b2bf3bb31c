"""`calib estimate FEATURES -o CALIB`: features/ → calibration/ (arrays.csv, sources.csv, report.json)."""
from __future__ import annotations

from pathlib import Path

import typer

from estimator import calibrate
from pipeline.io import read_features, write_calibration
from .common import console, user_errors
from .tables import print_arrays


@user_errors
def estimate(
    features: Path = typer.Argument(..., help="features/ directory (FORMATS.md section 2)"),
    out: Path = typer.Option(..., "-o", "--out", help="calibration/ directory to write (replaced atomically)"),
    method: str = typer.Option("hybrid", help="hybrid (ours) or wang (baseline, no TDOA-S)"),
    no_tdoa_s: bool = typer.Option(False, "--no-tdoa-s", help="ignore TDOA-S (Wang et al.'s measurement set)"),
    emission_sigma: float = typer.Option(0.0, help="prior std (s) of emission-interval errors to estimate; 0 = off"),
    loss: str = typer.Option("cauchy", help="robust loss on TDOA residuals: cauchy, huber or linear"),
    outlier_threshold: float = typer.Option(5.0, help="flag and drop TDOA residuals beyond this many sigmas"),
    noise: str = typer.Option("auto", help="weights: meta (the sigmas of meta.json), estimate (re-estimated per "
                                           "measurement type from the residuals) or auto (estimate when meta.json "
                                           "lists sigmas_estimated by the frontend)"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="print nothing but errors"),
):
    """Estimate array poses, clock offsets/drifts and source positions from features."""
    if method not in ("hybrid", "wang"):
        raise ValueError(f"--method must be hybrid or wang, not {method!r}")
    if noise not in ("auto", "meta", "estimate"):
        raise ValueError(f"--noise must be auto, meta or estimate, not {noise!r}")
    if loss not in ("cauchy", "huber", "linear"):
        raise ValueError(f"--loss must be cauchy, huber or linear, not {loss!r}")
    feats = read_features(features)
    calib = calibrate(feats, method=method, use_tdoa_s=not no_tdoa_s, emission_sigma=emission_sigma,
                      loss=None if loss == "linear" else loss, outlier_threshold=outlier_threshold, noise=noise)
    write_calibration(out, calib)
    if not quiet:
        print_arrays(calib)
        rep = calib["report"]
        console.print(f"converged: {rep['converged']} ({rep['reason']}), final cost {rep['cost']['final']:.4g}, "
                      f"{len(rep['outliers'])} outlier(s) → {out}")
