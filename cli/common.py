"""Shared CLI plumbing: one-line errors with exit code 2, consoles."""
from __future__ import annotations

import functools
import sys

import typer
from rich.console import Console

from pipeline.io import InputError

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
