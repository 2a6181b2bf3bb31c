"""Shared CLI plumbing: one-line errors with exit code 2, consoles."""
from __future__ import annotations

import functools
import re
import sys
from typing import Annotated

import typer
from rich.console import Console

from calib.estimator import validate_options
from calib.pipeline.io import InputError

EXIT_INPUT = 2
EXIT_FAILED = 3   # the calibration ran but its verdict is "failed" (report.json: verdict); docs/cli.md

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
OutlierThreshold = Annotated[float, typer.Option(help="flag and drop measurements (TDOA, DOA, odometry) whose "
                                                       "normalised residual exceeds this many sigmas (or the "
                                                       "Bonferroni level, if larger)")]
Noise = Annotated[str, typer.Option(help="weights: auto (re-estimate the frontend's own noise figures from the "
                                         "residuals), meta (meta.json's sigmas as they are) or estimate")]
Quiet = Annotated[bool, typer.Option("--quiet", "-q", help="print nothing but errors")]


def estimate_options(method, no_tdoa_s, emission_sigma, loss, outlier_threshold, noise):
    """Validated keyword arguments of ``estimator.calibrate`` from the shared CLI options."""
    for name, value, allowed in (("method", method, ("hybrid", "wang")), ("loss", loss, ("cauchy", "huber", "linear")),
                                 ("noise", noise, ("auto", "meta", "estimate"))):
        if value not in allowed:
            raise ValueError(f"--{name} must be {', '.join(allowed[:-1])} or {allowed[-1]}, not {value!r}")
    opts = {"method": method, "use_tdoa_s": not no_tdoa_s, "emission_sigma": emission_sigma, "loss": loss,
            "outlier_threshold": outlier_threshold, "noise": noise}
    try:
        validate_options(**opts)
    except ValueError as exc:
        msg = str(exc)
        for key in opts:
            msg = re.sub(rf"\b{key}\b", "--" + key.replace("_", "-"), msg)
        raise ValueError(msg) from None
    return opts


def print_verdict(report, console):
    """The verdict, last: status in capitals, then one line per reason (report.json ``verdict``)."""
    v = report.get("verdict") or {}
    status = str(v.get("status", "?"))
    colour = {"ok": "green", "suspect": "yellow", "failed": "bold red"}.get(status, "")
    flagged = v.get("flagged_arrays") or []
    extra = f" (flagged arrays: {', '.join(flagged)})" if flagged else ""
    console.print(f"verdict: [{colour}]{status.upper()}[/{colour}]{extra}" if colour else f"verdict: {status}")
    for r in v.get("reasons") or []:
        console.print(f"  - {r}", highlight=False)


def exit_on_failed(report):
    """Exit with EXIT_FAILED when the verdict is "failed" (after everything has been written and shown)."""
    if (report.get("verdict") or {}).get("status") == "failed":
        raise typer.Exit(EXIT_FAILED)
