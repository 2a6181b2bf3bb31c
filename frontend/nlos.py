"""Is an arrival the direct path? Evidence from the array's own range track along the odometry.

A reflection-only (NLOS) arrival — the line of sight blocked by a wall, only a reflection heard — arrives
LATE: its path is longer than the direct one by metres (5–25 ms in an office). One array's arrivals along
the robot's trajectory follow ``a_j = τ + (1 + δ) t_j + |s_j − x|/c`` (docs/architecture.md, the array's
own clock; ``s_j`` the odometry, in the reference frame up to the gauge, which a range to an unknown ``x``
absorbs). The frontend knows every term but ``x``, ``τ``, ``δ``: a robust fit of those five numbers to the
array's arrivals leaves each arrival's residual, and a reflection is a residual that is large AND positive
(a direct path is never late by metres; an early residual is a detection error of another kind).

With a moving source (events.csv ``vel_x, vel_y, vel_z``) the matched filter shifts each arrival by
``β (v·(s − x)/|s − x|)/c`` (the range-rate coupling, docs/method.md); the fit models it, so a
robot that keeps moving does not look like reflections.

Limits: the fit describes the majority; an array that hears only reflections in most events fits the
reflections (its direct arrivals then show as early: ``early`` counts them, and the array's
``weak_direct``/``occluded`` doubts remain). With fewer than ``MIN_EVENTS`` arrivals nothing is judged.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares

MIN_EVENTS = 8          # arrivals needed to fit the 5 unknowns and still judge each one
NLOS_MIN_S = 0.5e-3     # late by at least this (17 cm of path) ... a direct path's timing error is ~10-100 µs
NLOS_SIGMAS = 8.0       # ... and by this many robust residual stds (MAD) of the array's own fit
ROBUST_SCALE_S = 2e-4   # the robust loss's scale in the fit (s): direct-path noise is well inside it
START_OFFSETS_M = np.array([[0, 0, 0], [4, 0, 0], [-4, 0, 0], [0, 4, 0], [0, -4, 0], [0, 0, 3], [0, 0, -3]], float)


def range_model(params, t, s, c, beta=0.0, vel=None):
    """Arrival times (J,) of the model ``τ + (1 + δ) t + |s − x|/c [+ β ṙ/c]``; params = (x (3), τ, δ)."""
    x, tau, delta = params[:3], params[3], params[4]
    w = s - x
    d = np.sqrt(np.sum(w * w, axis=1))
    out = tau + (1.0 + delta) * t + d / c
    if vel is not None and beta:
        out = out + beta * np.sum(vel * w, axis=1) / np.maximum(d, 1e-9) / c
    return out


def fit_range_track(arrival, t, s, c, beta=0.0, vel=None):
    """Robust fit of :func:`range_model` to one array's arrivals (multi-start: the array may be anywhere).

    arrival (J,) local s; t (J,) emission times − t_emit[0]; s (J, 3) odometry; vel (J, 3) or None.
    Returns (params (5,), residuals (J,) s: measured − model).
    """
    centre = s.mean(axis=0)
    best = None
    for off in START_OFFSETS_M:
        x0 = centre + off
        d0 = np.linalg.norm(s - x0, axis=1) / c
        tau0 = float(np.median(arrival - t - d0))
        res = least_squares(lambda q: (arrival - range_model(q, t, s, c, beta, vel)) / ROBUST_SCALE_S,
                            np.r_[x0, tau0, 0.0], loss="cauchy", f_scale=1.0, x_scale=np.r_[1, 1, 1, 1e-3, 1e-5],
                            max_nfev=200)
        if best is None or res.cost < best.cost:
            best = res
    return best.x, arrival - range_model(best.x, t, s, c, beta, vel)


def late_arrivals(arrival, t, s, c, beta=0.0, vel=None):
    """Per arrival, how late it is against the array's own range track and whether that makes it NLOS.

    Returns dict: ``late`` (J,) residual (s; NaN when not judged), ``nlos`` (J,) bool, ``scale`` (robust
    std of the residuals, s), ``early`` (number of arrivals early by the NLOS margin: the fit may be on
    reflections).
    """
    j = len(arrival)
    ok = np.isfinite(arrival)
    out = {"late": np.full(j, np.nan), "nlos": np.zeros(j, bool), "scale": np.nan, "early": 0}
    if ok.sum() < MIN_EVENTS:
        return out
    _, res = fit_range_track(arrival[ok], t[ok], s[ok], c, beta, None if vel is None else vel[ok])
    scale = 1.4826 * float(np.median(np.abs(res - np.median(res))))
    margin = max(NLOS_MIN_S, NLOS_SIGMAS * scale)
    out["late"][ok] = res
    out["nlos"][ok] = res > margin
    out["scale"] = scale
    out["early"] = int(np.sum(res < -margin))
    return out
