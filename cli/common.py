"""Shared CLI plumbing: one-line errors with exit code 2, consoles."""
from __future__ import annotations

import functools
import sys
from typing import Annotated

import typer
from rich.console import Console

from calib.pipeline.io import InputError

EXIT_INPUT = 2

console = Console(stderr=True)


def user_errors(func):
    """Turn expected user-facing failures into ``error: <one line>`` on stderr and exit code 2."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        try:
            return func(*args, **kwargs)
        except (InputError, ValueError) as exc:  # library errors for bad input are ValueErrors
            msg = " ".join(str(exc).split())
            print(f"error: {msg}", file=sys.stderr)
            raise typer.Exit(EXIT_INPUT) from None

    return wrapper


# Estimator options shared by `calib estimate` and `calib run` (one declaration, one help text).
Method = Annotated[str, typer.Option(help="estimator: hybrid (ours) or wang (baseline, no TDOA-S)")]
NoTdoaS = Annotated[bool, typer.Option("--no-tdoa-s", help="ignore TDOA-S (Wang et al.'s measurement set)")]
EmissionSigma = Annotated[float, typer.Option(help="prior std (s) of emission-interval errors to estimate; 0 = off")]
Loss = Annotated[str, typer.Option(help="robust loss on TDOA residuals: cauchy, huber or linear")]
OutlierThreshold = Annotated[float, typer.Option(help="flag and drop TDOA residuals beyond this many sigmas")]
Noise = Annotated[str, typer.Option(help="weights: auto (re-estimate the frontend's own noise figures from the "
                                         "residuals), meta (meta.json's sigmas as they are) or estimate")]
Quiet = Annotated[bool, typer.Option("--quiet", "-q", help="print nothing but errors")]


def estimate_options(method, no_tdoa_s, emission_sigma, loss, outlier_threshold, noise):
    """Validated keyword arguments of ``estimator.calibrate`` from the shared CLI options."""
    for name, value, allowed in (("method", method, ("hybrid", "wang")), ("loss", loss, ("cauchy", "huber", "linear")),
                                 ("noise", noise, ("auto", "meta", "estimate"))):
        if value not in allowed:
            raise ValueError(f"--{name} must be {', '.join(allowed[:-1])} or {allowed[-1]}, not {value!r}")
    return {"method": method, "use_tdoa_s": not no_tdoa_s, "emission_sigma": emission_sigma, "loss": loss,
            "outlier_threshold": outlier_threshold, "noise": noise}
