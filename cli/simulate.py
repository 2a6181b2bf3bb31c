"""`calib simulate` (not implemented yet)."""
import typer


def simulate():
    """Not implemented yet."""
    raise typer.Exit(1)
