"""WAV → features: chirp detection, association with the robot's events, GCC-PHAT TDOA-M/TDOA-S, SRP-PHAT DOA.

``extract_features(session, progress=None, **options) -> (features, diagnostics)`` works on an in-memory
session (``calib.pipeline.formats.session.read_session``); ``plot_detections(path, diagnostics)`` draws the
detection timeline. Reading folders and writing files is the pipeline's job (``calib.pipeline.features``).
"""
from .diagnostics import plot_detections
from .extract import DEFAULTS, extract_features

__all__ = ["extract_features", "plot_detections", "DEFAULTS"]
