"""Estimator: measurement factors, deterministic initialisation, IVE, joint NLS, uncertainty and CRLB."""
from .calibrate import calibrate
from .init import ObservabilityError

__all__ = ["calibrate", "ObservabilityError"]
