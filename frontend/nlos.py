"""Is an arrival the direct path? Evidence from the array's own range track along the odometry.

A reflection-only (NLOS) arrival — the line of sight blocked by a wall, only a reflection heard — arrives
LATE: its path is longer than the direct one by metres (5–25 ms in an office). One array's arrivals along
the robot's trajectory follow ``a_j = τ + (1 + δ) t_j + |s_j − x|/c`` (docs/architecture.md, the array's
own clock; ``s_j`` the odometry, in the reference frame up to the gauge, which a range to an unknown ``x``
absorbs). The frontend knows every term but ``x``, ``τ``, ``δ``: a robust fit of those five numbers to the
array's arrivals leaves each arrival's residual, and a reflection is a residual that is large AND positive
(a direct path is never late by metres; an early residual is a detection error of another kind).

With a moving source (events.csv ``vel_x, vel_y, vel_z``) the matched filter shifts each arrival by
``shift(v·(s − x)/(c|s − x|))`` ≈ ``β ṙ/c`` (the range-Doppler coupling, estimator/motion.py); the fit models it, so a
robot that keeps moving does not look like reflections.

Limits: the fit describes the majority; when reflections are the majority the direct arrivals show as
early, and the track is refitted to them if there are at least ``MIN_EARLY``; with fewer, ``early``
counts them (a warning). With fewer than ``MIN_EVENTS`` arrivals nothing is judged.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

MIN_EVENTS = 8          # arrivals needed to fit the 5 unknowns and still judge each one
MIN_EARLY = 6           # early arrivals needed to refit the track to them alone (5 unknowns)
NLOS_MIN_S = 0.5e-3     # late by at least this (17 cm of path) ... a direct path's timing error is ~10-100 µs
NLOS_SIGMAS = 8.0       # ... and by this many robust residual stds (MAD) of the array's own fit
Q_ABS = 0.3186          # quartile of |x| for x ~ N(0, 1)
ROBUST_SCALE_S = 2e-4   # the robust loss's scale in the fit (s): direct-path noise is well inside it


def range_model(params, t, s, c, shift=None, vel=None):
    """Arrival times (J,) of the model ``τ + (1 + δ) t + |s − x|/c [+ shift(ṙ/c)]``; params = (x (3), τ, δ);
    ``shift``: the matched filter's arrival shift for a sweep stretched by 1 + ε (≈ β ε)."""
    x, tau, delta = params[:3], params[3], params[4]
    w = s - x
    d = np.sqrt(np.sum(w * w, axis=1))
    out = tau + (1.0 + delta) * t + d / c
    if vel is not None and shift is not None:
        out = out + shift(np.sum(vel * w, axis=1) / np.maximum(d, 1e-9) / c)
    return out


def _jacobian(params, t, s, c):
    """d(model)/d(params) (J, 5) of :func:`range_model` without the (tiny) motion term's derivative."""
    w = s - params[:3]
    d = np.maximum(np.sqrt(np.sum(w * w, axis=1)), 1e-9)
    return np.column_stack([-w / (c * d[:, None]), np.ones(len(t)), t])


def linear_start(arrival, t, s, c):
    """Initial (x, τ, δ = 0) of the track from the squared ranges, linear in (x, τ, c²τ² − |x|²):
    ``|s_j|² − c² b_j² = 2 s_j·x − 2 c² b_j τ + (c² τ² − |x|²)`` with ``b_j = a_j − t_j`` (least squares,
    minimum norm: a planar trajectory leaves x's height to the refinement)."""
    b = arrival - t
    b0 = float(np.median(b))
    bb = b - b0                       # conditioning: τ relative to the median arrival
    A = np.column_stack([2 * s, -2 * c * c * bb, np.ones(len(t))])
    y = np.sum(s * s, axis=1) - c * c * bb * bb
    sol = np.linalg.lstsq(A, y, rcond=None)[0]
    return np.r_[sol[:3], b0 + sol[3], 0.0]


def fit_range_track(arrival, t, s, c, shift=None, vel=None):
    """Robust fit of :func:`range_model` to one array's arrivals, from the linear start and from the
    trajectory's centre 4 m up (the array may be anywhere; the better fit is kept).

    arrival (J,) local s; t (J,) emission times − t_emit[0]; s (J, 3) odometry; vel (J, 3) or None.
    Returns (params (5,), residuals (J,) s: measured − model).
    """
    centre = s.mean(axis=0) + [0.0, 0.0, 4.0]
    tau_c = float(np.median(arrival - t - np.linalg.norm(s - centre, axis=1) / c))
    best = None
    for q0 in (linear_start(arrival, t, s, c), np.r_[centre, tau_c, 0.0]):
        if not np.all(np.isfinite(q0)):
            continue
        res = least_squares(lambda q: (arrival - range_model(q, t, s, c, shift, vel)) / ROBUST_SCALE_S, q0,
                            jac=lambda q: -_jacobian(q, t, s, c) / ROBUST_SCALE_S, loss="cauchy", f_scale=1.0,
                            x_scale=np.r_[1, 1, 1, 1e-3, 1e-5], max_nfev=100)
        if best is None or res.cost < best.cost:
            best = res
    return best.x, arrival - range_model(best.x, t, s, c, shift, vel)


def _judge(res):
    """(scale, margin) of a fit from the residuals of the arrivals it was fitted to: the std from the
    quartile of |residual| (|N(0, σ²)| has its quartile at Q_ABS σ), which holds while a quarter of the
    arrivals are direct paths (a median-based scale breaks when half of them are reflections)."""
    scale = float(np.quantile(np.abs(res), 0.25)) / Q_ABS
    return scale, max(NLOS_MIN_S, NLOS_SIGMAS * scale)


def late_arrivals(arrival, t, s, c, shift=None, vel=None):
    """Per arrival, how late it is against the array's own range track and whether that makes it NLOS.

    A direct path is never late by metres, and never early: when the robust fit to all arrivals leaves a
    group EARLY by the margin (the reflections were the majority and the fit followed them: a reflection
    off one wall follows an image of the array just as smoothly), the track is refitted to that group
    alone and kept if it leaves fewer arrivals early (its own reflections are then late).

    Returns dict: ``late`` (J,) residual (s; NaN when not judged), ``nlos`` (J,) bool, ``scale`` (robust
    std of the residuals, s), ``early`` (arrivals still early by the margin: the track is in doubt).
    """
    j = len(arrival)
    ok = np.isfinite(arrival)
    out = {"late": np.full(j, np.nan), "nlos": np.zeros(j, bool), "scale": np.nan, "early": 0}
    if ok.sum() < MIN_EVENTS:
        return out
    a, tt, ss, vv = arrival[ok], t[ok], s[ok], None if vel is None else vel[ok]
    _, res = fit_range_track(a, tt, ss, c, shift, vv)
    scale, margin = _judge(res)
    early = res < -margin
    if early.sum() >= MIN_EARLY:
        q, _ = fit_range_track(a[early], tt[early], ss[early], c, shift, None if vv is None else vv[early])
        res2 = a - range_model(q, tt, ss, c, shift, vv)
        scale2, margin2 = _judge(res2[early])
        if np.sum(res2 < -margin2) < early.sum():
            res, scale, margin = res2, scale2, margin2
    out["late"][ok] = res
    out["nlos"][ok] = res > margin
    out["scale"] = scale
    out["early"] = int(np.sum(res < -margin))
    return out
