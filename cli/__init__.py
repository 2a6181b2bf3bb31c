"""The ``calib`` command: a thin typer layer over the library API (pipeline, frontend, estimator)."""
