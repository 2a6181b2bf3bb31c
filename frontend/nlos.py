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

Limits: the track needs about SUBSET direct arrivals that a candidate subset catches (runs along the
trajectory, or random draws); arrivals still early against it are counted (``early``, a warning). With
fewer than ``MIN_EVENTS`` arrivals nothing is judged.
"""
from __future__ import annotations

import numpy as np

from .timing import _path_peaks as path_peaks  # per mic, one path's refined time and amplitude near a lag
from .timing import direct_path_lag, lag_grid, locate, path_model, pulse_envelope, subtract_path

MIN_EVENTS = 8          # arrivals needed to fit the 5 unknowns and still judge each one
NLOS_MIN_S = 2.0e-3     # late by at least this (69 cm of path): a direct path is within ~0.1 ms of its track, a
                        # misfit track (few events, a degenerate trajectory) left 1.2 ms (hall seed 0); walls: 5-25 ms
NLOS_SIGMAS = 8.0       # ... and by this many robust residual stds of the array's own fit (:func:`_judge`)
Q_ABS = 0.3186          # quartile of |x| for x ~ N(0, 1)
SUBSET = 5              # arrivals per candidate track (5 unknowns)
RANDOM_SUBSETS = 20     # random candidate subsets besides the windows (fixed seed: deterministic)
INLIER_S = 3e-4         # s: an arrival this close to a candidate track supports it (10 cm of path)
MIN_INLIERS = 6         # fewer: the refinement uses every arrival
DRIFT_PRIOR = 2e-4      # clock drifts beyond this are rare (200 ppm); a weak prior row in the track fit
ROBUST_SCALE_S = 2e-4   # the robust loss's scale in the fit (s): direct-path noise is well inside it
TRACK_SCALE_MAX = 1e-3  # s: a track whose own arrivals scatter about it by more (robust std, 34 cm of path) follows
                        # no direct paths and judges nothing: direct-path tracks 0.02-0.28 ms (57 arrays, 9 rooms
                        # with walls, moving robots); odometry in cm instead of m: 3.5 ms


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


def _candidates(j, rng, s=None):
    """Index subsets to seed the track: the SUBSET events nearest each event's source position (``s`` (J, 3),
    the odometry: line of sight is a matter of where the source is, and a trajectory that visits one arm of a
    U-shaped room twice has its direct paths there in two runs, each shorter than SUBSET: ushape seed 71, A1,
    7 direct paths of 16 in runs of 3 and 4, had no window of direct paths and no track judged), windows of
    SUBSET consecutive events (line of sight is lost and regained in runs along the trajectory) and
    RANDOM_SUBSETS random ones; each subset once."""
    near = [] if s is None else [np.sort(np.argsort(np.linalg.norm(s - s[k], axis=1), kind="stable")[:SUBSET])
                                 for k in range(j)]
    win = [np.arange(k, k + SUBSET) for k in range(0, j - SUBSET + 1)]
    rand = [np.sort(rng.choice(j, SUBSET, replace=False)) for _ in range(RANDOM_SUBSETS)]
    seen, out = set(), []
    for idx in near + win + rand:
        if len(idx) == SUBSET and (key := tuple(idx)) not in seen:
            seen.add(key)
            out.append(idx)
    return out


def _score(res):
    """A candidate track's support: arrivals within INLIER_S of it, less twice those EARLY by more than
    NLOS_MIN_S (a direct path is never early: a track with early arrivals follows reflections)."""
    return int(np.sum(np.abs(res) < INLIER_S)) - 2 * int(np.sum(res < -NLOS_MIN_S))


def _refine(q0, idx, arrival, t, s, c, shift, vel, loss="cauchy"):
    """:func:`range_model`'s parameters fitted to the arrivals ``idx`` from ``q0`` (analytic Jacobian), with
    a prior row δ / DRIFT_PRIOR: a far array with a fudged drift mimics a track (a plane wave whose delay
    trend the drift absorbs; seen 370 m away with δ = −6e-4 on the L-shaped office). ``loss``: "cauchy"
    (every row, the prior too, as scipy's ``least_squares(loss="cauchy", f_scale=1)``) or "linear"."""
    a, ti, si = arrival[idx], t[idx], s[idx]
    v = None if vel is None else vel[idx]
    prior = np.zeros((1, 5))
    prior[0, 4] = 1.0 / DRIFT_PRIOR
    return _levenberg_marquardt(
        lambda q: np.r_[(a - range_model(q, ti, si, c, shift, v)) / ROBUST_SCALE_S, q[4] / DRIFT_PRIOR],
        lambda q: np.vstack([-_jacobian(q, ti, si, c) / ROBUST_SCALE_S, prior]), q0, loss == "cauchy")


LM_MAX_ITER = 60        # iterations of the track fit (each one 5 × 5 solve; as scipy's max_nfev before)
LM_STEP_TOL = 1e-9      # a step below this × X_SCALE in every parameter ends the fit (nm, fs, 1e-14 drift)
X_SCALE = np.array([1.0, 1.0, 1.0, 1e-3, 1e-5])   # the parameters' natural sizes (m, m, m, s, 1)


def _levenberg_marquardt(fun, jac, q, robust):
    """Minimise Σ ρ(f_i(q)²) of the 5 track parameters: ρ(z) = log(1 + z) (Cauchy, ``robust``) or z.

    Iteratively reweighted Gauss–Newton (weights ρ'(f²) = 1 / (1 + f²): its fixed point is the cost's
    stationary point) with Levenberg's damping in the parameters scaled by X_SCALE (as scipy's trust
    region with ``x_scale``: a planar trajectory leaves the height of the array nearly free, which a damping
    scaled by the curvature would not hold); a step is taken only when it lowers the cost. A closed 5 × 5
    solve per iteration instead of scipy's trust-region machinery (~4× less CPU, the same minimum: the
    features agree to the fit's tolerance). q (5,) start; returns q (5,)."""
    cost = (lambda f: float(np.sum(np.log1p(f * f)))) if robust else (lambda f: float(np.sum(f * f)))
    q = np.asarray(q, float).copy()
    f = fun(q)
    c0, lam = cost(f), None
    for _ in range(LM_MAX_ITER):
        J = jac(q) * X_SCALE
        Jw = J / (1.0 + f * f)[:, None] if robust else J
        A, g = J.T @ Jw, Jw.T @ f
        lam = 1e-3 * float(np.max(np.diag(A))) if lam is None else lam
        while True:
            try:
                step = -np.linalg.solve(A + lam * np.eye(len(q)), g) * X_SCALE
            except np.linalg.LinAlgError:
                step = np.full(len(q), np.nan)
            qn = q + step
            fn = fun(qn)
            cn = cost(fn) if np.all(np.isfinite(fn)) else np.inf
            if cn <= c0:
                break
            lam *= 10.0
            if not lam < 1e30:   # no step lowers the cost: q is the minimum (to rounding)
                return q
        q, f, lam = qn, fn, lam / 10.0
        done = np.all(np.abs(step) < LM_STEP_TOL * X_SCALE) or c0 - cn <= 1e-15 * max(c0, 1e-300)
        c0 = cn
        if done:
            break
    return q


def fit_range_track(arrival, t, s, c, shift=None, vel=None, delta0=0.0):
    """Fit of :func:`range_model` to one array's arrivals that follows its direct paths, not the majority.

    First a robust (Cauchy) fit to all arrivals from the linear start (:func:`linear_start`) and from above
    the trajectory's centre. When it leaves arrivals EARLY (a direct path is never early: the fit followed
    reflections), the latest arrivals peeled off one by one (:func:`_peel`) and, unless that found the
    direct paths' track (:func:`_enough`), RANSAC: tracks fitted to subsets (:func:`_candidates`, fixed
    seed) and then to their inliers, each scored by its support (:func:`_score`); the best track is kept.
    ``delta0``: a drift guess (0 is better than the association's scale − 1, which carries the trend of
    the propagation delays: up to 7e-4 in the hall, which sent one array's fit to RANSAC).
    arrival (J,) local s; t (J,) emission times − t_emit[0]; s (J, 3) odometry; vel (J, 3) or None.
    Returns (params (5,), residuals (J,) s: measured − model).
    """
    j, every = len(arrival), np.arange(len(arrival))
    model = lambda q: range_model(q, t, s, c, shift, vel)
    centre = s.mean(axis=0) + [0.0, 0.0, 4.0]
    starts = [linear_start(arrival - delta0 * t, t, s, c),
              np.r_[centre, float(np.median(arrival - t - np.linalg.norm(s - centre, axis=1) / c)), 0.0]]
    best, best_score = None, None
    for q0 in starts:   # the second start only when the first leaves arrivals early
        if best is not None and not np.any(arrival - model(best) < -NLOS_MIN_S):
            break
        if np.all(np.isfinite(q0)):
            q0[4] = delta0
            q = _refine(q0, every, arrival, t, s, c, shift, vel)
            sc = _score(arrival - model(q))
            if best_score is None or sc > best_score:
                best, best_score = q, sc
    early = np.flatnonzero(arrival - model(best) < -NLOS_MIN_S)
    if not early.size:
        return best, arrival - model(best)
    q, sc = _peel(best, arrival, t, s, c, shift, vel)
    if sc > best_score:
        best, best_score = q, sc
    if _enough(arrival - model(best)):
        return best, arrival - model(best)
    # the early group itself (the direct paths when the fit followed the reflections), then the subsets
    for idx in ([early] if early.size >= SUBSET else []) + _candidates(j, np.random.default_rng(0), s):
        q0 = linear_start(arrival[idx] - delta0 * t[idx], t[idx], s[idx], c)
        q0 = q0 if np.all(np.isfinite(q0)) else best.copy()
        q0[4] = delta0
        q = _refine(q0, idx, arrival, t, s, c, shift, vel, loss="linear")
        inl = np.flatnonzero(np.abs(arrival - model(q)) < INLIER_S)
        if len(inl) >= MIN_INLIERS:
            q = _refine(q, inl, arrival, t, s, c, shift, vel)
        res = arrival - model(q)
        sc = _score(res)
        if sc > best_score:
            best, best_score = q, sc
        if _enough(res):
            break
    return best, arrival - model(best)


def _enough(res):
    """A track with a third of the arrivals on it and none early: the direct paths' (no need to search on)."""
    return not np.any(res < -NLOS_MIN_S) and np.sum(np.abs(res) < INLIER_S) >= max(MIN_INLIERS, len(res) / 3)


def _peel(q, arrival, t, s, c, shift, vel):
    """The track left when the latest arrivals are taken off one at a time (a reflection is late, never
    early): from the compromise track ``q`` of all arrivals, the arrival latest against it is dropped and
    the track refitted to the rest, down to MIN_INLIERS arrivals; the best-scored (:func:`_score`) track on
    the way. Where the line of sight comes and goes in runs shorter than SUBSET (an office's doorways:
    8 direct paths of 16 in runs of 2–4), no window and few random subsets hold direct paths only, while
    the reflections, metres late, are peeled off first. Returns (q (5,), score)."""
    model = lambda qq: range_model(qq, t, s, c, shift, vel)
    keep, best, best_score = np.arange(len(arrival)), q, _score(arrival - model(q))
    while len(keep) > MIN_INLIERS:
        keep = keep[keep != keep[np.argmax((arrival - model(q))[keep])]]
        q = _refine(q, keep, arrival, t, s, c, shift, vel, loss="linear")
        sc = _score(arrival - model(q))
        if sc > best_score:
            best, best_score = q, sc
    return best, best_score


def _judge(res):
    """(scale, margin) of a fit from the residuals of the arrivals it was fitted to: the std from the
    quartile of |residual| (|N(0, σ²)| has its quartile at Q_ABS σ), which holds while a quarter of the
    arrivals are direct paths (a median-based scale breaks when half of them are reflections)."""
    scale = float(np.quantile(np.abs(res), 0.25)) / Q_ABS
    return scale, max(NLOS_MIN_S, NLOS_SIGMAS * scale)


def late_arrivals(arrival, t, s, c, shift=None, vel=None, delta0=0.0):
    """Per arrival, how late it is against the array's own range track and whether that makes it NLOS.

    A direct path is never late by metres, and never early: the track (:func:`fit_range_track`) is the
    one with the most support and no early arrivals, so reflections do not take it over even when they are
    the majority (a reflection off one wall follows an image of the array just as smoothly).

    A track whose arrivals scatter about it by more than TRACK_SCALE_MAX is no direct paths' (the odometry
    in other units, or not this session's): nothing is judged (``late`` NaN, ``scale`` says why).

    Returns dict: ``late`` (J,) residual (s; NaN when not judged), ``nlos`` (J,) bool, ``scale`` (robust
    std of the residuals, s), ``early`` (arrivals still early by the margin: the track is in doubt).
    """
    j = len(arrival)
    ok = np.isfinite(arrival)
    out = {"late": np.full(j, np.nan), "nlos": np.zeros(j, bool), "scale": np.nan, "early": 0}
    if ok.sum() < MIN_EVENTS:
        return out
    _, res = fit_range_track(arrival[ok], t[ok], s[ok], c, shift, None if vel is None else vel[ok], delta0)
    scale, margin = _judge(res)
    out["scale"] = scale
    if not scale <= TRACK_SCALE_MAX:   # no range track along this odometry: nothing to judge against
        return out
    out["late"][ok] = res
    out["nlos"][ok] = res > margin
    out["early"] = int(np.sum(res < -margin))
    return out


# ------------------------------------------------------------ a weak direct path before the timed arrival
# A mount or obstacle that only attenuates the direct path (10-20 dB) leaves it BEFORE a strong reflection
# that arrives within a few pulse widths (a wall 10 cm behind the array: 0.3-0.6 ms). The onset search
# rejects it as a possible sidelobe of that reflection (it sits on its rising flank), so the reflection is
# timed — consistently in every event, so the array fits its image through the wall (20 cm, 55° off) and no
# range track or residual can tell. Subtracting the timed path exactly (the plain matched filter's pulse is
# known) removes its sidelobes: what is left before it is a genuine earlier arrival.
# What is left after subtracting a path is not only other paths: its spectrum is not exactly the template's
# (frequency-dependent walls and mics), and that residue lies within about a pulse width and a half (the
# first sidelobes) on BOTH sides of it (an amplitude error is symmetric): 10 % of the path 1.2 pulses before
# it in a 0.8 s hall. An earlier arrival counts only beyond that, or where nothing as strong mirrors it after.
RESIDUE_PULSES = 1.5      # an earlier path further before the timed one than this many pulse widths is no residue
MIRROR_RATIO = 2.0        # ... nor one this many times above the residual at the mirrored lag after it
EARLIER_MAX_RATIO = 0.35  # an earlier path weaker than this × the timed one (as extract.WEAK_DIRECT) is a weak
                          # direct path; a stronger one the onset search did not take is the other half of a
                          # merged two-path cluster (a clear wall array: 0.5-1.05, seen in occluded-lab 23, 41)
PAIR_ITERS = 2            # alternating refinements of the (earlier, timed) pair of paths per mic


def _pair_fit(c, setup, shape, early, timed, half_width):
    """Per mic the two paths near lags ``early`` and ``timed`` (J,), each refined with the other's model
    subtracted (SAGE): (t0, a0, t1, a1) (J, M) times (s) and complex amplitudes of the earlier and timed."""
    model = lambda t, a: path_model(setup, shape, t, a, c.dtype)
    t1, a1 = path_peaks(c, setup, timed, half_width)
    t0, a0 = path_peaks(c - model(t1, a1), setup, early, half_width)
    for _ in range(PAIR_ITERS):
        t1, a1 = path_peaks(c - model(t0, a0), setup, timed, half_width)
        t0, a0 = path_peaks(c - model(t1, a1), setup, early, half_width)
    return t0, a0, t1, a1


def earlier_paths(c_plain, setup, dp, lo, hi, half_width, snr_factor, min_ratio, sidelobe_margin, env=None):
    """Events whose timed arrival (lag ``dp`` (J,)) has a weak genuine arrival before it.

    The timed path is subtracted from the plain matched filter's spectra ``c_plain`` (J, M, Fb) at every
    mic (:func:`timing.subtract_path`); the onset search (:func:`timing.direct_path_lag`, the same
    thresholds, the noise floor before the timed arrival) runs again on what is left; an arrival it finds
    more than ``half_width`` before the timed one is refitted jointly with it (:func:`_pair_fit`) and kept
    when its amplitude is ``min_ratio`` … EARLIER_MAX_RATIO of the timed path's (median over mics).
    Returns (found (J,) bool, lag (J,) int of the earlier arrival, ratio (J,): its amplitude / the timed
    path's; NaN where none). env : (J, hi − lo) the mic-averaged plain envelope on lags lo..hi when already
    computed (:func:`timing.locate`'s ``onset_env``: the same values), else computed here.
    """
    j = len(dp)
    shape = setup["weights"] * np.abs(setup["tmpl_conj"]) ** 2
    env = np.abs(lag_grid(c_plain, setup, lo, hi)).mean(axis=1) if env is None else env
    k = np.asarray(dp) - lo
    rows = np.arange(j)
    sub = subtract_path(c_plain, setup, shape, dp, half_width)
    env2 = np.abs(lag_grid(sub, setup, lo, hi)).mean(axis=1)
    floor = np.array([np.median(env[i, : max(k[i] - half_width, 16)]) for i in rows])
    d2, q2, s2, _ = direct_path_lag(env2, pulse_envelope(setup, hi - lo, plain=True), snr_factor, min_ratio,
                                    sidelobe_margin, floor=floor, peak=env[rows, k])
    cand = np.flatnonzero((d2 < k - half_width) & (q2 >= min_ratio) & (s2 >= snr_factor))
    found, ratio = np.zeros(j, bool), np.full(j, np.nan)
    if cand.size:
        t0, a0, t1, a1 = _pair_fit(c_plain[cand], setup, shape, lo + d2[cand], dp[cand], half_width)
        r = np.median(np.abs(a0), axis=1) / np.maximum(np.median(np.abs(a1), axis=1), 1e-300)
        ratio[cand] = r
        pulse = setup["fs"] / max(setup["freqs"].max() - setup["freqs"].min(), 1.0)   # samples
        sep = np.median(t1 - t0, axis=1) * setup["fs"]
        found[cand] = (r >= min_ratio) & (r < EARLIER_MAX_RATIO) & (
            (sep > RESIDUE_PULSES * pulse) | (env2[cand, d2[cand]] > MIRROR_RATIO * _mirrored(env2[cand], k[cand], d2[cand], pulse)))
    return found, lo + d2, ratio


def _mirrored(env, k, d, pulse):
    """(J,) the largest of ``env`` (J, T) within half a pulse of lag ``2 k − d``: ``d`` mirrored about ``k``."""
    h = int(np.ceil(pulse / 2))
    lags = (2 * k - d)[:, None] + np.arange(-h, h + 1)
    inside = (lags >= 0) & (lags < env.shape[1])
    vals = np.take_along_axis(env, np.clip(lags, 0, env.shape[1] - 1), axis=1)
    return np.max(np.where(inside, vals, 0.0), axis=1)


def retime_earlier(res, c, c_plain, setup, locate_kw, onset_env=None):
    """:func:`timing.locate`'s result ``res`` for one chunk of events, with the events whose timed arrival
    has a weak direct path before it (:func:`earlier_paths`) timed again on that path: the timed path
    subtracted from both spectra (as :func:`timing.locate`'s own second look does for a shadowed peak) and
    located anew. Their ``ratio`` becomes the direct path's amplitude over the strongest peak's (so the
    arrival is flagged ``weak_direct``, and the array ``occluded`` when that is frequent) and ``strongest``
    stays the first look's. Returns (res, sub): ``sub`` the new location of those events (a dict like
    ``res``, its ``events`` (K,) their indices) or None (``extract.locate_events`` puts it into ``res``).
    onset_env : locate's ``onset_env`` of ``c_plain`` (the plain envelope, not computed twice), or None."""
    kw = {k: v for k, v in locate_kw.items() if k != "c_onset"}
    found, lag, ratio = earlier_paths(c_plain, setup, res["dp"], kw["lo"], kw["hi"], kw["half_width"],
                                      kw.get("snr_factor", 6.0), kw.get("min_ratio", 0.05),
                                      kw.get("sidelobe_margin", 2.0), env=onset_env)
    sel = np.flatnonzero(found)
    if not sel.size:
        return res, None
    # the direct path's amplitude over the strongest peak's: flagged weak_direct even where not timed again
    res = {**res, "ratio": np.where(found, ratio * res["ratio"], res["ratio"])}
    hw = kw["half_width"]
    plain_shape = setup["weights"] * np.abs(setup["tmpl_conj"]) ** 2
    c_sub = subtract_path(c[sel], setup, setup["weights"], res["dp"][sel], hw)
    on_sub = subtract_path(c_plain[sel], setup, plain_shape, res["dp"][sel], hw)
    phase = res["phase"][sel] if np.ndim(res["phase"]) else res["phase"]
    # its level relative to the strongest peak may be below the onset's min_ratio (which holds relative to
    # the path it precedes): the threshold scaled down alike; the lag found is checked against it below
    min_ratio = kw.get("min_ratio", 0.05) * float(np.min(res["ratio"][sel] / ratio[sel]))
    sub = locate(c_sub, setup, **{**kw, "phase": phase, "min_ratio": min_ratio}, c_onset=on_sub)
    sub.pop("onset_env", None)
    ok = np.abs(sub["dp"] - lag[sel]) <= hw   # it timed the earlier arrival found (not something else)
    sub["ratio"] = res["ratio"][sel]
    sub["strongest"] = res["strongest"][sel]
    sub["stretch"] = np.asarray(res.get("stretch", np.zeros(len(res["dp"]))))[sel]
    sub["events"] = sel
    sub = {key: v[ok] if isinstance(v, np.ndarray) and v.ndim >= 1 and len(v) == len(sel) else v
           for key, v in sub.items()}
    return res, (sub if np.any(ok) else None)

