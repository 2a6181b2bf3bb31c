"""Entry point of the ``calib`` command. Each command lives in its own module of this package."""
from __future__ import annotations

from typing import Optional

import typer

from calib import __version__

from . import chirp, check, estimate, evaluate, export, features, import_bag, init, montecarlo, run, simulate

app = typer.Typer(
    name="calib",
    help="Calibrate asynchronous microphone arrays (positions, orientations, clock offsets, drifts).",
    no_args_is_help=True,
    add_completion=True,  # --install-completion / --show-completion (bash, zsh, fish, PowerShell)
    pretty_exceptions_enable=False,
    rich_markup_mode=None,  # plain help: '[default: …]' in a help text stays visible, flags show no '<bool>'
    context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 110},
)


def _version(value: bool):
    if value:
        print(f"calib {__version__}")
        raise typer.Exit()


@app.callback()
def _main(version: Optional[bool] = typer.Option(None, "--version", "-V", callback=_version, is_eager=True,
                                                 help="print the version and exit")):
    """Calibrate asynchronous microphone arrays (positions, orientations, clock offsets, drifts)."""


app.command("run")(run.run)
app.command("simulate")(simulate.simulate)
app.command("features")(features.features)
app.command("estimate")(estimate.estimate)
app.command("evaluate")(evaluate.evaluate)
app.command("export")(export.export)
app.command("chirp")(chirp.chirp)
app.command("init")(init.init)
app.command("check")(check.check)
app.command("import-bag")(import_bag.import_bag)
app.command("montecarlo")(montecarlo.montecarlo)


def main():
    app()


if __name__ == "__main__":
    main()
