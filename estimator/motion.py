"""A source that moves during the sweep: the matched filter's range–Doppler coupling (docs/method.md).

The event's time and source position are those of the sweep's START (docs/architecture.md: ``t_emit`` and
``s_j``). A source moving with velocity ``v`` changes its range to array ``i`` at the rate
``ṙ_ij = v_j · (s_j − x_i)/|s_j − x_i|`` (> 0 moving away), so the array receives the sweep time-stretched
by ``1 + ṙ/c`` about its start — the same stretch as a clock running ``ṙ/c`` fast. Matched filtering then
shifts the arrival by ``β ṙ_ij / c`` (β = meta ``chirp_drift_bias``, the coupling the frontend measures for
the clock drift; ≈ f1·T/(f1 − f0): 0.57 s for a 0.5 s 0.5–4 kHz sweep, so 0.5 m/s moves an arrival by
0.8 ms = 28 cm of path). With ``u`` the unit vector from the source to the array this is ``−β (v·u)/c``.

The estimator models the shift in TDOA-M (``shift_i − shift_ref``) and TDOA-S (``shift_to − shift_from``)
at the state each factor is evaluated at, its derivative in the Jacobian (``factors.arrival_shifts``;
``problem.SourceMotion``): the derivative with respect to the geometry is ``β|v|/(c r)`` of the range's,
0.07 on test_motion_noise's scene (1 m/s), which the earlier fixed-point passes with the shifts held between
solves missed — two passes left shift errors of a few σ_TDOA there and arrays named inconsistent without any
fault. Only the DOAs turned from ``doa_time_s`` are still turned at a state between passes (second order).

Velocities: events.csv ``vel_x, vel_y, vel_z`` when present (used as given), else central differences of
the odometry over the emission times — which are also nonzero for a robot that stops for every chirp, so
then the correction is kept only if it lowers the cost of the same rows under the same sigmas
(:func:`motion_gain`: does the static solve leave the shift pattern in its residuals?).

The velocity the correction uses is not the source's: the odometry's own noise and the cubic Hermite curve
between events (seconds apart) miss it by σ_v per axis (:func:`velocity_sigma`). An error δv_j moves every
corrected arrival of event j by β (δv_j · w_ij)/c (w_ij the unit vector from array i to the source): exactly
what moving the source by β δv_j does to the times of flight, so it is shared by all the arrays of the event
and no row's own sigma can hold it. The solve takes it as an event-level nuisance parameter (``State.dv``,
prior factor ``velocity`` N(0, σ_v²) per axis): the arrivals of event j see the source at s_j + β δv_j, the
DOAs turned from ``doa_time_s`` to the start at s_j + doa_time_s δv_j, the odometry at s_j; so the solve's χ²,
its array and outlier tests, its covariance and the clock selection's scans all hold it (before, only the
error bars did, :class:`MotionNoise`, ``uncertainty.velocity_rows``, and the solve's array test named fault-free
arrays inconsistent on 7 of 8 sessions of that scene).
"""
from __future__ import annotations

import dataclasses

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
from scipy.interpolate import CubicHermiteSpline

from calib.geometry import mirror, yaw_rotate
from calib.tables import event_velocities

from .factors import active_kinds
from .problem import SourceMotion
from .odoframe import yaw_decision
from .solver import linearise
from .uncertainty import whiten

MOTION_ITERATIONS = 2    # passes turning the DOAs (doa_time_s > 0) at a state (each a warm joint solve)
MIN_SPEED = 0.05         # m/s: slower odometry (median over the intervals) is not tested for motion
MIN_GAIN = 0.5           # odometry velocities are used when the residuals hold at least half the shift pattern


@dataclasses.dataclass(frozen=True)
class MotionNoise:
    """The error of the velocity a moving source's correction used, as the error bars see it: ``sigma``
    (m/s, per axis and event, :func:`velocity_sigma`); an error δv moves the corrected arrivals as a source
    shift of ``beta`` δv (s: β, the arrival shift per unit stretch) and the turned DOAs as one of
    ``t_doa`` δv (s: meta ``doa_time_s``)."""
    sigma: float
    beta: float
    t_doa: float


def velocity_sigma(t, odom, vel, t_star, sigma_odo):
    """Per-axis std (m/s) of the velocity :func:`sweep_middle` gives ``t_star`` after each sweep start,
    from the odometry itself (no fitted constant): the cubic Hermite curve through the events' positions
    and velocities carries the acceleration only as well as its second derivative, which jumps at every
    interior event where the curves of the two intervals disagree; with independent errors on both sides
    the acceleration's error is rms(jump)/√2 and the velocity's at t* that × t*. The reported velocity's own
    noise is taken as what the odometry's positions (``sigma_odo`` m each) give a velocity over the median
    event interval h: √2 σ_odo / h. On the rendered robot/moving sessions (0.35-0.6 m/s, 13 sessions) the
    true errors at t* (0.008-0.020 m/s per axis, against the simulator's trajectory) are 0.65-1.07 of it
    (RMS of error / σ_v per session)."""
    t = np.asarray(t, float)
    if len(t) < 3:
        return float(np.sqrt(2.0) * sigma_odo / max(float(np.ptp(t)) if len(t) > 1 else 1.0, 1e-3))
    c = CubicHermiteSpline(t, odom, vel, axis=0).c          # (4, K-1, 3): interval k's cubic in (x - t_k)
    dt = np.diff(t)[:-1, None]
    jump = 2.0 * c[1, 1:] - (6.0 * c[0, :-1] * dt + 2.0 * c[1, :-1])   # right piece's a − left piece's a
    sigma_a = float(np.sqrt(np.mean(jump ** 2) / 2.0))
    sigma_odo_v = float(np.sqrt(2.0) * sigma_odo / max(float(np.median(np.diff(t))), 1e-3))
    return float(np.hypot(sigma_a * float(t_star), sigma_odo_v))


def odometry_velocities(t, odom):
    """(K, 3) velocity at each event from the odometry: central differences (one-sided at the ends)."""
    if len(t) < 2:
        return np.zeros_like(odom)
    return np.gradient(odom, t, axis=0)


def source_velocities(events, t, odom):
    """(velocities (K, 3) in odometry axes, source "events" | "odometry") or (None, None) when the odometry
    does not move at MIN_SPEED (the test would only cost time)."""
    v = event_velocities(events)
    if v is not None:
        return v, "events"
    if len(t) < 3:
        return None, None
    speed = np.linalg.norm(np.diff(odom, axis=0), axis=1) / np.maximum(np.diff(t), 1e-9)
    if np.median(speed) < MIN_SPEED:
        return None, None
    return odometry_velocities(t, odom), "odometry"


def sweep_middle(t, odom, vel, t_mid):
    """(displacement (K, 3), velocity (K, 3)) of the source ``t_mid`` after each sweep start, in odometry
    axes: the cubic Hermite curve through the odometry positions and velocities at the sweep starts ``t``
    (it carries the acceleration between events; a constant velocity leaves β (a·u) t_mid / c, 40-120 µs
    at 0.1-0.3 m/s² for a 0.5 s sweep, and fitted the moving preset's arrivals no better than the start's)."""
    if not t_mid or len(t) < 2:
        return vel * t_mid, vel
    h = CubicHermiteSpline(t, odom, vel, axis=0)
    return h(t + t_mid) - odom, h(t + t_mid, 1)


def range_rates(p, st, vel, mid=None):
    """(N, K) range rate ṙ_ij (m/s, > 0 moving away) of every array and event at state ``st``, at the sweep
    start or, with ``mid`` = (displacement, velocity) of :func:`sweep_middle`, from the source there."""
    yaw = float(st.odo_yaw[0]) if len(st.odo_yaw) else 0.0
    if mid is not None:
        v, s = yaw_rotate(mid[1], yaw), st.s + yaw_rotate(mid[0], yaw)
    else:
        v, s = yaw_rotate(vel, yaw), st.s
    w = s[None, :, :] - st.x[:, None, :]                      # (N, K, 3) array → source
    d = np.linalg.norm(w, axis=2)
    return np.einsum("kc,nkc->nk", v, w) / np.maximum(d, 1e-9)


def arrival_shifts(p, st, vel, curve=None, mid=None):
    """(N, K) matched-filter arrival shift of every array and event at state ``st``: β ṙ_ij / c, or the
    frontend's measured curve (meta ``chirp_stretch_shift``: {stretch, shift_s}) at ε = ṙ_ij / c.
    mid : (displacement, velocity) of :func:`sweep_middle`: ṙ is then taken at the sweep's middle, from the
    source there — the stretch a linear sweep's matched filter sees is the mean over the sweep (equal time
    per Hz), so the path's curvature and the robot's acceleration shift the arrival by β r̈ T / (2c)
    (on the moving preset's arrivals: 77 → 11 µs RMS against simulator truth, anechoic); None: at the start."""
    eps = range_rates(p, st, vel, mid) / p.c
    if curve:
        return np.interp(eps, np.asarray(curve["stretch"], float), np.asarray(curve["shift_s"], float))
    return p.beta * eps


def predicted_stretches(p, st, events, t_stretch):
    """(N, K) stretch ε_ij each array records event j's sweep with, at state ``st``: ``ṙ_ij / c`` at
    ``t_stretch`` after the sweep start (meta ``stretch_time_s``, the instant whose stretch the timing
    follows) plus the array's clock drift (its samples run ``1 + drift`` fast: the same stretch); None when
    the source does not move (no velocities, :func:`source_velocities`)."""
    vel, _ = source_velocities(events, p.t, p.odom)
    if vel is None:
        return None
    mid = sweep_middle(p.t, p.odom, vel, float(t_stretch)) if t_stretch else None
    return range_rates(p, st, vel, mid) / p.c + np.asarray(st.drift, float)[:, None]


def doa_moves(p, st, disp, arr, ev, u):
    """(m, 3) change of the direction (array frame) from the source at its DOA time (``s + disp``, disp the
    displacement since the sweep start in odometry axes, :func:`sweep_middle`) to the source at the sweep
    start ``s``, at state ``st``, for DOA rows (arr, ev, measured u). A mirror-ambiguous array's change is
    mirrored where its measurement is."""
    d_s = yaw_rotate(disp, float(st.odo_yaw[0]) if len(st.odo_yaw) else 0.0)
    a = st.s[ev] - st.x[arr]
    b = a + d_s[ev]
    d = a / np.linalg.norm(a, axis=1, keepdims=True) - b / np.linalg.norm(b, axis=1, keepdims=True)
    R = st.R[arr]
    d_arr = np.einsum("kba,kb->ka", R, d)                      # R_iᵀ d
    pred = np.einsum("kba,kb->ka", R, a)
    n = p.fold[arr]
    flip = np.any(n != 0, axis=1) & (np.einsum("ka,ka->k", u, n) * np.einsum("ka,ka->k", pred, n) < 0)
    d_arr[flip] = mirror(d_arr[flip], n[flip])
    return d_arr


def corrected(p, st, vel, curve=None, t_doa=0.0, t_stretch=None, sigma_v=0.0):
    """``p`` modelling the motion: its TDOA factors take the arrival shifts at the state they are evaluated
    at (``problem.SourceMotion``, ``factors.arrival_shifts``; the rows as read), its DOAs turned from the source
    at ``t_doa`` after the sweep start to the source at the start at ``st`` (a copy; measured rows as read),
    and with ``sigma_v`` > 0 the velocity error as a nuisance per event (``State.dv``, prior factor
    ``velocity``). The
    range rates of the shifts are taken ``t_stretch`` after the start (meta ``stretch_time_s``, the instant
    whose stretch the frontend's timing follows); None: ``t_doa``."""
    t_stretch = t_doa if t_stretch is None else float(t_stretch)
    disp, v = sweep_middle(p.t, p.odom, vel, t_stretch) if t_stretch else (np.zeros_like(vel), vel)
    shape = None if not curve else (np.asarray(curve["stretch"], float), np.asarray(curve["shift_s"], float))
    out = {"motion": SourceMotion(np.asarray(v, float), np.asarray(disp, float), shape, float(p.beta),
                                  float(sigma_v or 0.0), float(t_doa or 0.0))}
    if sigma_v and sigma_v > 0:
        out["sigma"] = {**p.sigma, "velocity": float(sigma_v)}
    if t_doa and len(p.doa.u):
        disp = sweep_middle(p.t, p.odom, vel, t_doa)[0]
        u = p.doa.u + doa_moves(p, st, disp, p.doa.arr, p.doa.ev, p.doa.u)
        out["doa"] = dataclasses.replace(p.doa, u=u / np.linalg.norm(u, axis=1, keepdims=True))
    if t_doa and len(p.cone.cos):
        k = p.cone
        d = doa_moves(p, st, sweep_middle(p.t, p.odom, vel, t_doa)[0], k.arr, k.ev, np.zeros((len(k.cos), 3)))
        out["cone"] = dataclasses.replace(k, cos=np.clip(k.cos + np.einsum("ka,ka->k", p.cone_axis[k.arr], d), -1, 1))
    return p.replace(**out)


def _shifted(p, st, vel):
    """``p`` with its TDOAs freed of the arrival shifts at ``st`` (at the sweep start, β ε): the pattern
    :func:`motion_gain` tests the static solve's residuals for."""
    sh = arrival_shifts(p, st, vel)
    tm, ts = p.tdoa_m, p.tdoa_s
    return p.replace(tdoa_m=dataclasses.replace(tm, val=tm.val - (sh[tm.arr, tm.ev] - sh[p.ref, tm.ev])),
                     tdoa_s=dataclasses.replace(ts, val=ts.val - (sh[ts.arr, ts.b] - sh[ts.arr, ts.a])))


def motion_gain(p, st, lay, mask, vel, kinds):
    """How much of the motion's arrival-shift pattern the residuals of the static solve hold: γ̂ of
    ``r + γ P⊥ δr`` (r the whitened residuals at the solution, δr their change when the shifts are removed,
    P⊥ the projector off the Jacobian's range: what a re-solve cannot absorb). γ̂ ≈ 1: the arrivals carry
    the shifts (a moving source), ≈ 0: they do not (the robot stopped for the chirps). One linearisation and
    one least-squares solve, not a second calibration. ``lay``, ``mask``: the solve's layout and kept
    residuals. Returns (γ̂, its std)."""
    lin = linearise(p, st, lay, kinds, mask=mask)
    dr = linearise(_shifted(p, st, vel), st, lay, kinds, mask=mask).r - lin.r
    sw = np.sqrt(lin.w)
    A = scipy.sparse.diags(sw) @ scipy.sparse.csr_matrix(lin.J) if not scipy.sparse.issparse(lin.J) else \
        scipy.sparse.diags(sw) @ lin.J
    g = sw * dr
    g_perp = g - A @ scipy.sparse.linalg.lsqr(A, g, atol=1e-10, btol=1e-10)[0]
    gg = float(g_perp @ g_perp)
    if gg <= 0:
        return 0.0, np.inf
    return float(-(sw * lin.r) @ g_perp / gg), float(1.0 / np.sqrt(gg))


def velocity_in_sigma(meta):
    """Whether the features' σ_TDOA already holds a moving source's velocity error: a frontend's own estimate
    (meta ``sigmas_estimated`` lists ``sigma_tdoa``) adds the shift model's error to it as row noise
    (``frontend.extract.motion_sd``, 0.1-0.2 of the RMS shift). A nuisance parameter on top counts it twice: on
    the rendered moving sessions 503, 505, 507 (dev) it left the arrays 1.93 / 2.46 / 2.65 cm off, without it
    1.25 / 2.27 / 2.68 cm."""
    return "sigma_tdoa" in (meta.get("sigmas_estimated") or [])


def motion_noise(record, p, t_doa=0.0):
    """The :class:`MotionNoise` of a corrected moving source from :func:`motion_solve`'s ``record`` (None
    when no correction was applied); ``p`` the problem (its β), ``t_doa`` meta ``doa_time_s``."""
    if not (record or {}).get("applied") or not record.get("velocity_sigma_m_s"):
        return None
    return MotionNoise(float(record["velocity_sigma_m_s"]), float(p.beta), float(t_doa or 0.0))


def retest_yaw(res, kinds):
    """The odometry yaw tested again (``odoframe.yaw_decision``) at the motion-corrected solution ``res`` (a
    ``joint.JointResult``) when IVE kept it: IVE decides on the arrivals before the shifts are removed, and a
    source moving during the sweep shifts them in a pattern a turned odometry frame partly mimics (moving 4:
    −5.7 ± 0.5° there, 0.4 ± 0.5° once corrected, and a verdict 'suspect' for a frame that is not turned).
    Returns None (not kept before, or not free), else (test {yaw_deg, std_deg, kept}, the state with the yaw
    at 0 when it is not kept)."""
    p, lay = res.problem, res.layout
    if not p.odo_yaw_free or not (p.odo_yaw_test or {}).get("kept") or lay.odo_yaw[0] < 0:
        return None
    lin = linearise(p, res.state, lay, kinds, mask=res.mask)
    _, st, test = yaw_decision(p, res.state, whiten(lin.J, lin.w), int(lay.odo_yaw[0]))
    return test, st


def motion_solve(p_raw, events, first, solve, *, kinds, curve=None, t_doa=0.0, t_stretch=None, nuisance=True):
    """The joint solve with the moving source's arrival shifts removed, when the source moves.

    p_raw : the problem as built (before a solve changed its sigmas); first : ``solve``'s result (a
    ``joint.JointResult``) on ``p_raw``; solve(problem, state) → the same type; curve: meta
    ``chirp_stretch_shift`` (the frontend's measured shift for large stretches) or None (β ε); t_doa: meta
    ``doa_time_s``, when after the sweep start the DOAs look (0: not corrected); t_stretch: meta
    ``stretch_time_s``, when the range rate of the arrival shift is taken (None: t_doa).
    Odometry velocities are used only when the static solve's residuals hold the shift pattern
    (:func:`motion_gain` ≥ MIN_GAIN). ``nuisance``: the velocity error a parameter of the solve (``State.dv``,
    :func:`corrected`'s ``sigma_v``); False where the rows' σ already holds it (:func:`velocity_in_sigma`): then
    only the error bars take it (:class:`MotionNoise`). Returns (the result kept, record for report.json
    ``motion``; ``velocity_nuisance``: whether it was a parameter; the joint solve to start again from another
    state: (problem, solve) for ``solve(problem, state)``, the correction made at that state when one was
    applied — ``ambiguity.retry_dropped``'s rejoin).
    """
    vel, source = source_velocities(events, p_raw.t, p_raw.odom)
    if vel is None or not p_raw.beta:   # β = 0: the features state no coupling (a frontend that has none)
        return first, {"source": None, "applied": False}, (p_raw, solve)
    rec = {"source": source, "median_speed_m_s": float(np.median(np.linalg.norm(vel, axis=1)))}
    if source == "odometry":
        gain, sd = motion_gain(first.problem, first.state, first.layout, first.mask, vel, kinds)
        rec.update(gain=gain, gain_std=sd)
        if not gain >= MIN_GAIN:
            return first, {**rec, "applied": False}, (p_raw, solve)
    t_star = float(t_stretch if t_stretch is not None else t_doa)
    rec["velocity_sigma_m_s"] = velocity_sigma(p_raw.t, p_raw.odom, vel, t_star, p_raw.sigma["odometry"])
    rec["velocity_nuisance"] = bool(nuisance)
    sigma_v = rec["velocity_sigma_m_s"] if nuisance else 0.0
    cur = first
    for _ in range(MOTION_ITERATIONS if t_doa else 1):   # (the shifts are in the factors; the DOAs turn at a state)
        cur = solve(corrected(p_raw, cur.state, vel, curve, t_doa, t_stretch, sigma_v), cur.state)
    yaw = retest_yaw(cur, active_kinds(cur.problem))
    if yaw is not None:
        rec["odometry_yaw_retest"] = yaw[0]
        if not yaw[0]["kept"]:   # IVE's yaw was the uncorrected shifts: solved again with the yaw fixed at 0
            p_raw = p_raw.replace(odo_yaw_free=False, odo_yaw_test=yaw[0])
            cur = solve(corrected(p_raw, yaw[1], vel, curve, t_doa, t_stretch, sigma_v), yaw[1])

    def corrected_solve(p_, st):   # (the shifts in the factors; the DOAs turned at the start state, as above)
        return solve(corrected(p_, st, vel, curve, t_doa, t_stretch, sigma_v), st)

    return cur, {**rec, "applied": True, "curve": bool(curve),
                 "max_shift_s": float(np.max(np.abs(arrival_shifts(
                     p_raw, cur.state, vel, curve, sweep_middle(p_raw.t, p_raw.odom, vel, t_stretch or t_doa)))))}, \
        (p_raw, corrected_solve)
