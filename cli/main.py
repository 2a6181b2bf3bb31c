"""Entry point of the ``calib`` command. Each command lives in its own module of this package."""
from __future__ import annotations

import typer

from . import estimate, evaluate, features, montecarlo, run, simulate

app = typer.Typer(
    name="calib",
    help="Calibrate asynchronous microphone arrays (positions, orientations, clock offsets, drifts).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
app.command("run")(run.run)
app.command("simulate")(simulate.simulate)
app.command("features")(features.features)
app.command("estimate")(estimate.estimate)
app.command("evaluate")(evaluate.evaluate)
app.command("montecarlo")(montecarlo.montecarlo)


def main():
    app()


if __name__ == "__main__":
    main()
