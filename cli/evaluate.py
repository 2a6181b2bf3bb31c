"""`calib evaluate CALIB TRUTH`: the metrics of docs/formats.md section 4 as a table, or one JSON line."""
from __future__ import annotations

from pathlib import Path

import typer

from calib.pipeline.formats.io import dumps_json, read_calibration, read_truth
from .common import user_errors
from .tables import print_metrics


@user_errors
def evaluate(
    calib: Path = typer.Argument(..., help="calibration/ directory"),
    truth: Path = typer.Argument(..., help="truth/ directory"),
    json_out: bool = typer.Option(False, "--json", help="print one JSON line instead of a table"),
):
    """Compare a calibration with ground truth."""
    # imported here: scoring loads scipy.spatial (~0.1 s), which every other command would pay at start
    from calib.pipeline.report.evaluate import evaluate as evaluate_metrics

    metrics = evaluate_metrics(read_calibration(calib), read_truth(truth))
    if json_out:
        print(dumps_json(metrics))
    else:
        print_metrics(metrics)
