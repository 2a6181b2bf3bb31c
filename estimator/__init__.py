"""Estimator: measurement factors, deterministic initialisation, IVE, joint NLS, uncertainty and CRLB."""
from .calibrate import calibrate
from .init import ObservabilityError
from .uncertainty import crlb

__all__ = ["calibrate", "crlb", "ObservabilityError"]
