"""`calib estimate` (not implemented yet)."""
import typer


def estimate():
    """Not implemented yet."""
    raise typer.Exit(1)
