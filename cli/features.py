"""`calib features` (not implemented yet)."""
import typer


def features():
    """Not implemented yet."""
    raise typer.Exit(1)
