"""Entry point of the ``calib`` command. Each command lives in its own module of this package.

``app`` is the command with all its subcommands; :func:`app_for` builds it for one command line with only the
subcommand it names, so ``calib montecarlo`` does not import the frontend and the estimator (0.3 s of CPU on
every start; a study's parent process needs neither).
"""
from __future__ import annotations

import importlib
from typing import Optional

import typer

from calib import __version__

# command name → its module in this package (the function has the module's name, '-' read as '_')
COMMANDS = ("run", "simulate", "features", "estimate", "evaluate", "export", "chirp", "init", "check",
            "import-bag", "montecarlo")


def _typer():
    return typer.Typer(
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


def _main(version: Optional[bool] = typer.Option(None, "--version", "-V", callback=_version, is_eager=True,
                                                 help="print the version and exit")):
    """Calibrate asynchronous microphone arrays (positions, orientations, clock offsets, drifts)."""


def build(names=COMMANDS):
    """The ``calib`` Typer app with the subcommands ``names`` (in COMMANDS' order)."""
    app = _typer()
    app.callback()(_main)   # a callback keeps a one-command app a group: `calib NAME ...` as with all of them
    for name in COMMANDS:
        if name in names:
            module = name.replace("-", "_")
            app.command(name)(getattr(importlib.import_module(f"{__package__}.{module}"), module))
    return app


def app_for(argv):
    """The app for command-line arguments ``argv`` (without the program): only the subcommand ``argv[0]``
    names, else (help, --version, a misspelled command, completion) all of them."""
    return build((argv[0],)) if argv and argv[0] in COMMANDS else build()


def __getattr__(name):
    if name == "app":   # `from calib.cli.main import app` (tests, notebooks): every subcommand, built once
        globals()["app"] = built = build()
        return built
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def main():
    import sys

    app_for(sys.argv[1:])()


if __name__ == "__main__":
    main()
