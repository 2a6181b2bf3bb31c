"""Estimator: measurement factors, deterministic initialisation, IVE, joint NLS, uncertainty and CRLB.

Public API: :func:`calibrate` (features → :class:`CalibrationResult`), :func:`crlb` and :func:`draw_from_crlb` (the
Cramér–Rao bound at a ground truth), :func:`rebuild`, :func:`residuals`, :func:`position_covariances`,
:func:`array_covariance` (a calibration evaluated against its features), :func:`to_frames` / :func:`to_tables` / :func:`state_from_frames`.
"""
# Imported eagerly: ``calibrate`` is both a submodule and the function it exports, so a lazy package would
# hand out the module once anything imported the submodule first.
from .assess import array_covariance, position_covariances, rebuild, residuals
from .calibrate import calibrate, validate_options
from .outputs import CalibrationResult, to_frames, to_tables
from .factors import KINDS, register, unregister
from .init import ObservabilityError
from .problem import LINE_COLUMN
from .uncertainty import crlb, draw_from_crlb, state_from_frames

__all__ = ["CalibrationResult", "KINDS", "LINE_COLUMN", "register", "unregister", "array_covariance", "calibrate", "crlb", "draw_from_crlb",
           "ObservabilityError", "position_covariances", "rebuild", "residuals", "state_from_frames", "to_frames",
           "to_tables", "validate_options"]
