"""WAV → features: chirp detection, association with the robot's events, GCC-PHAT TDOA-M/TDOA-S, SRP-PHAT DOA.

``extract_features(session_dir, progress=None, **options) -> (features, diagnostics)``;
``write_diagnostics(directory, diagnostics)`` writes diagnostics.json and detections.png.
"""
from .diagnostics import write_diagnostics
from .extract import DEFAULTS, extract_features

__all__ = ["extract_features", "write_diagnostics", "DEFAULTS"]
