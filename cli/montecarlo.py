"""`calib montecarlo` (not implemented yet)."""
import typer


def montecarlo():
    """Not implemented yet."""
    raise typer.Exit(1)
