"""Estimator: measurement factors, deterministic initialisation, IVE, joint NLS, uncertainty and CRLB.

Public API: :func:`calibrate` (features → calibration), :func:`crlb` and :func:`draw_from_crlb` (the
Cramér–Rao bound at a ground truth), :func:`rebuild`, :func:`residuals`, :func:`position_covariances`,
:func:`array_covariance` (a calibration evaluated against its features), :func:`to_frames` / :func:`state_from_frames`.
"""
from calib.lazy import lazy_exports

EXPORTS = {"array_covariance": "assess", "position_covariances": "assess", "rebuild": "assess",
           "residuals": "assess", "calibrate": "calibrate", "to_frames": "calibrate",
           "validate_options": "calibrate", "KINDS": "factors", "MeasurementKind": "factors",
           "ObservabilityError": "init", "LINE_COLUMN": "problem", "crlb": "uncertainty",
           "draw_from_crlb": "uncertainty", "state_from_frames": "uncertainty"}
__getattr__, __dir__ = lazy_exports(__name__, EXPORTS)
__all__ = sorted(EXPORTS)
