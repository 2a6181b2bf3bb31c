"""calib: calibrate a network of asynchronous microphone arrays from real recordings.

Package layout (one import package, folders at the top level of the repository):

- ``calib`` (folder ``core/``): the small core every layer may import: errors, version, JSON helpers.
- ``calib.frontend`` (``frontend/``): WAV → features.
- ``calib.estimator`` (``estimator/``): features → calibration.
- ``calib.pipeline`` (``pipeline/``): file formats, simulators, reports, studies, orchestration.
- ``calib.cli`` (``cli/``): the ``calib`` command.

Imports run one way: cli → pipeline → {frontend, estimator} → core (docs/architecture.md).
"""
from .version import __version__

__all__ = ["__version__"]
