"""The standard deviation each fused arrival claims (docs/frontend.md, "Noise estimates").

An arrival's error has three parts, each estimated from the session's own data:

1. differential: the mean of the mics' independent timing errors, ``s / √n`` with ``s`` the residual spread
   of the array-model fit (:func:`near_field_fit`: constant + wavefront curvature, ``n − 2`` dof);
2. later paths: reflections shift all mics of a few-cm array alike, which no spread between mics shows;
   its size is taken as one mic's residual ``s`` (the mics' own disagreement comes from the same paths);
3. near-field bias: the mic times are referred to the origin with a plane wave, so their mean carries the
   wavefront curvature ``mean_m(|m|² − (u·m)²) / (2 d c)`` (≈ 1 µs at 2 m for a 3.5 cm circle); a per-array
   constant is a clock offset, but it varies with the range ``d``. The range per event comes from the
   array's clock track (:func:`range_track`); the claim is the bias's deviation from its mean.

The three add in quadrature. The plane-wave spread used before (one mic's spread about the fused arrival)
contains the curvature pattern itself: on 10 cm arrays it claimed 1.6–2× the measured error, while on
3.5 cm arrays it matched only because it did (CHANGELOG.md, issue 9).
"""
from __future__ import annotations

import numpy as np

RESOLVED_SIGMAS = 3.0     # an event's curvature counts for the range track when κ̂ > this × its std error
TRACK_MIN_EVENTS = 4      # ... and at least this many events do (2 parameters of the track)
TRACK_MAX_SCATTER = 2.0   # robust normalised scatter of the resolved κ̂ about the track; above: no track
TRACK_ITERATIONS = 3      # reweighting passes (events beyond 3 robust sd dropped)
MIN_RANGE_SD = 1e-6       # m: floor of a range's standard error in the track's weights (noise-free fits)


def near_field_fit(res, u, mics, c):
    """Per event, the mic residuals ``res`` (J, M) (times referred to the origin minus the fused arrival,
    NaN = unused) fitted by ``a + κ q_m`` with ``q_m = (|m|² − (u·m)²) / (2c)`` (the curvature delay of a
    source at range ``1/κ``). Returns (kappa, kappa_sd, s, qbar, n), each (J,): the curvature (1/m) and its
    standard error (NaN with < 4 mics or no curvature lever), the residual spread of the fit (s; the plain
    spread where κ is NaN), the mics' mean ``q`` (s·m) and the mic count."""
    ok = np.isfinite(res)
    w = ok.astype(float)
    y = np.where(ok, res, 0.0)
    q = (np.sum(mics**2, axis=1)[None] - (u @ mics.T) ** 2) / (2 * c)
    n = w.sum(axis=1)
    s1, s2 = (w * q).sum(axis=1), (w * q * q).sum(axis=1)
    sy, sqy = y.sum(axis=1), (w * q * y).sum(axis=1)
    det = n * s2 - s1**2
    fit = (n >= 4) & (det > 1e-9 * np.maximum(n * s2, 1e-300))
    det_ = np.where(fit, det, 1.0)
    kappa = np.where(fit, (n * sqy - s1 * sy) / det_, np.nan)
    a = np.where(fit, (s2 * sy - s1 * sqy) / det_, sy / np.maximum(n, 1))
    r = np.where(ok, y - a[:, None] - np.nan_to_num(kappa)[:, None] * q, 0.0)
    dof = np.where(fit, n - 2, n - 1)
    s = np.where(dof > 0, np.sqrt((r**2).sum(axis=1) / np.maximum(dof, 1)), np.nan)
    kappa_sd = np.where(fit, s * np.sqrt(n / det_), np.nan)
    qbar = (w * q).sum(axis=1) / np.maximum(n, 1)
    return kappa, kappa_sd, s, qbar, n


def range_track(kappa, kappa_sd, lag, e):
    """Source range per event (m) from the array's clock track, or None where the data do not support one.

    ``lag`` (J,) = c × (arrival − the association's clock line) is the range up to ``A + B e`` (``e`` (J,)
    the emission times: the line's offset, and the propagation trend its slope absorbed). ``A``, ``B`` are
    fitted to the events whose curvature is resolved (``1/κ̂`` with std ``σ_κ / κ̂²``), iteratively
    reweighted; no track when those events scatter about it by more than ``TRACK_MAX_SCATTER`` of their own
    errors or when a range comes out ≤ 0.
    """
    use = np.isfinite(kappa) & np.isfinite(lag) & (kappa > RESOLVED_SIGMAS * kappa_sd)
    if use.sum() < TRACK_MIN_EVENTS:
        return None
    y = np.where(use, 1.0 / np.where(use, kappa, 1.0), 0.0)
    sy = np.maximum(np.where(use, kappa_sd / np.where(use, kappa, 1.0) ** 2, 1.0), MIN_RANGE_SD)
    for _ in range(TRACK_ITERATIONS):
        x = np.c_[np.ones(use.sum()), e[use]] / sy[use, None]
        beta = np.linalg.lstsq(x, (y[use] - lag[use]) / sy[use], rcond=None)[0]
        z = (y - lag - beta[0] - beta[1] * e) / sy
        scatter = 1.4826 * np.median(np.abs(z[use]))
        use = use & (np.abs(z) < 3 * max(scatter, 1.0))
        if use.sum() < TRACK_MIN_EVENTS:
            return None
    d = lag + beta[0] + beta[1] * e
    return d if scatter <= TRACK_MAX_SCATTER and not np.any(d <= 0) else None


def arrival_sd(res, u, mics, c, lag, e, clean, single=None):
    """Claimed standard deviation (s) of each fused arrival (module docstring).

    res : (J, M) mic times referred to the origin minus the fused arrival (NaN = unused); u : (J, 3) DOAs;
    lag : (J,) c × (arrival − clock line) (m); e : (J,) emission times (s); clean : (J,) bool arrivals
    without doubts (the near-field bias's mean is taken over them); single : (J,) the claim where a fit has
    no residual (one mic), e.g. :func:`calib.frontend.timing.interference_sd`. Returns (sd (J,), details).
    """
    kappa, kappa_sd, s, qbar, n = near_field_fit(res, u, mics, c)
    d = range_track(kappa, kappa_sd, lag, e)
    bias = np.zeros(len(s)) if d is None else qbar / d
    ref = clean if np.sum(clean) >= 2 else np.ones(len(s), bool)
    near = bias - np.nanmean(bias[ref]) if np.any(np.isfinite(bias[ref])) else bias
    sd = np.sqrt(s**2 * (1 + 1 / np.maximum(n, 1)) + near**2)
    if single is not None:
        sd = np.where(np.isfinite(sd), sd, single)
    return sd, {"kappa": kappa, "kappa_sd": kappa_sd, "fit_sd": s, "range": d, "near_field": near}
