"""`calib run` (not implemented yet)."""
import typer


def run():
    """Not implemented yet."""
    raise typer.Exit(1)
