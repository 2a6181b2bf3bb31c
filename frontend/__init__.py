"""WAV → features: chirp detection, association with the robot's events, GCC-PHAT TDOA-M/TDOA-S, SRP-PHAT DOA.

``extract_features(session, progress=None, **options) -> (features, diagnostics)`` works on an in-memory
session (``calib.pipeline.formats.session.read_session``); ``plot_detections(path, diagnostics)`` draws the
detection timeline; ``retime_arrivals(session, diagnostics, stretches)`` times a moving source's arrivals again
against given stretches. Reading folders and writing files is the pipeline's job (``calib.pipeline.features``).
"""
from calib.lazy import lazy_exports

EXPORTS = {"extract_features": "extract", "retime_arrivals": "extract", "DEFAULTS": "extract", "plot_detections": "diagnostics"}
__getattr__, __dir__ = lazy_exports(__name__, EXPORTS)

__all__ = sorted(EXPORTS)
