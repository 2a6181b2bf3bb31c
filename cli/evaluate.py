"""`calib evaluate` (not implemented yet)."""
import typer


def evaluate():
    """Not implemented yet."""
    raise typer.Exit(1)
