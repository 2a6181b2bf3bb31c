"""calib: calibrate a network of asynchronous microphone arrays from real recordings.

Package layout (one import package, folders at the top level of the repository):

- ``calib`` (folder ``core/``): the small core every layer may import: errors, version, JSON helpers.
- ``calib.frontend`` (``frontend/``): WAV → features.
- ``calib.estimator`` (``estimator/``): features → calibration.
- ``calib.pipeline`` (``pipeline/``): file formats, simulators, reports, studies, orchestration.
- ``calib.cli`` (``cli/``): the ``calib`` command.

Imports run one way: cli → pipeline → {frontend, estimator} → core (docs/architecture.md).
"""
__all__ = ["__version__"]


def __getattr__(name):
    """``calib.__version__``, looked up on first use: importlib.metadata costs ~20 ms, and the ``calib`` command
    installs its signal handlers only after this package is imported (cli/entry.py)."""
    if name == "__version__":
        from .version import __version__

        return __version__
    raise AttributeError(f"module 'calib' has no attribute {name!r}")
