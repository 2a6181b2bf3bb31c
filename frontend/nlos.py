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

from typing import NamedTuple

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
    ``shift``: the matched filter's arrival shift for a sweep stretched by 1 + ε (≈ β ε). Also for K tracks at
    once: params (K, 5), t (K, J), s and vel (K, J, 3) → (K, J)."""
    x, tau, delta = params[..., None, :3], params[..., 3:4], params[..., 4:5]
    w = s - x
    d = np.sqrt(np.sum(w * w, axis=-1))
    out = tau + (1.0 + delta) * t + d / c
    if vel is not None and shift is not None:
        out = out + shift(np.sum(vel * w, axis=-1) / np.maximum(d, 1e-9) / c)
    return out


def _jacobian(params, t, s, c):
    """d(model)/d(params) (J, 5) of :func:`range_model` without the (tiny) motion term's derivative
    (K tracks: (K, J, 5))."""
    w = s - params[..., None, :3]
    d = np.maximum(np.sqrt(np.sum(w * w, axis=-1)), 1e-9)
    return np.concatenate([-w / (c * d[..., None]), np.ones(t.shape + (1,)), t[..., None]], axis=-1)


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
    track = Track(arrival, t, s, vel)
    return _fit_many([(track, Fit(np.asarray(q0, float), np.asarray(idx, int), loss == "cauchy"))], c, shift)[0]


class Track(NamedTuple):
    """One array's arrivals along the odometry: arrival (J,) local s, t (J,) emission times − t_emit[0],
    s (J, 3) odometry, vel (J, 3) or None."""
    arrival: np.ndarray
    t: np.ndarray
    s: np.ndarray
    vel: np.ndarray | None = None

    def residuals(self, q, c, shift):
        """measured − :func:`range_model` (J,) of the track parameters q (5,)."""
        return self.arrival - range_model(q, self.t, self.s, c, shift, self.vel)


class Fit(NamedTuple):
    """A track fit to run (:func:`_refine`): start q0 (5,), the indices (K,) int of the arrivals it fits, the
    robust (Cauchy) loss or the plain one, at most ``max_iter`` iterations (None: LM_MAX_ITER)."""
    q0: np.ndarray
    idx: np.ndarray
    robust: bool
    max_iter: int | None = None


def _fit_many(fits, c, shift):
    """The track fits ``fits`` [(Track, Fit), ...] of any arrays, all at once: one :func:`_levenberg_marquardt`
    on the stacked problems (a subset shorter than the longest padded with rows of zero residual and zero
    Jacobian, which change no sum; each fit its own loss). Returns (K, 5)."""
    n = max(len(f.idx) for _, f in fits)
    k = len(fits)
    used = np.arange(n)[None, :] < np.array([len(f.idx) for _, f in fits])[:, None]       # (K, n)
    a, ti, si, v = np.zeros((k, n)), np.zeros((k, n)), np.zeros((k, n, 3)), np.zeros((k, n, 3))
    for i, (tr, f) in enumerate(fits):
        m = len(f.idx)
        a[i, :m], ti[i, :m], si[i, :m] = tr.arrival[f.idx], tr.t[f.idx], tr.s[f.idx]
        if tr.vel is not None:
            v[i, :m] = tr.vel[f.idx]
    v = v if any(tr.vel is not None for tr, _ in fits) else None
    jf = np.zeros((k, n + 1, 5))  # the Jacobian of the data rows (padded rows 0), then the prior row, × X_SCALE
    jf[:, n, 4] = X_SCALE[4] / DRIFT_PRIOR
    scale = used / ROBUST_SCALE_S

    def fun(q):   # q (K, ..., 5): the residuals of each problem's data rows, then its prior row's
        lead = lambda x: x.reshape(x.shape[:1] + (1,) * (q.ndim - 2) + x.shape[1:])
        r = (lead(a) - range_model(q, lead(ti), lead(si), c, shift, None if v is None else lead(v))) * lead(scale)
        return np.concatenate([r, q[..., 4:5] / DRIFT_PRIOR], axis=-1)

    def jac(q):
        np.multiply(_jacobian(q, ti, si, c), (-X_SCALE) * scale[..., None], out=jf[:, :n])
        return jf

    return _levenberg_marquardt(fun, jac, np.array([f.q0 for _, f in fits], float),
                                np.array([f.robust for _, f in fits]),
                                np.array([LM_MAX_ITER if f.max_iter is None else f.max_iter for _, f in fits]))


LM_MAX_ITER = 60        # iterations of the track fit (each one 5 × 5 solve; as scipy's max_nfev before)
LM_STEP_TOL = 1e-9      # a step below this × X_SCALE in every parameter ends the fit (nm, fs, 1e-14 drift)
X_SCALE = np.array([1.0, 1.0, 1.0, 1e-3, 1e-5])   # the parameters' natural sizes (m, m, m, s, 1)
LM_MAX_DAMPING = 1e30   # no step lowers the cost at this damping: the track is at its minimum (to rounding)
LM_LADDER = 3           # trial dampings λ, 10λ, 100λ of one Jacobian evaluated at once (a rejected step: 10λ)


def _levenberg_marquardt(fun, jac, q, robust, max_iter=LM_MAX_ITER):
    """Minimise Σ ρ(f_i(q)²) of K independent problems in the 5 track parameters each: ρ(z) = log(1 + z)
    (Cauchy, ``robust`` (K,) bool) or z. q (K, 5) starts; fun : (K, 5) → (K, n) residuals (a new array);
    jac : (K, 5) → (K, n, 5) their Jacobian times X_SCALE (the parameters' sizes).

    Iteratively reweighted Gauss–Newton (weights ρ'(f²) = 1 / (1 + f²): its fixed point is the cost's
    stationary point) with Levenberg's damping in the parameters scaled by X_SCALE (as scipy's trust
    region with ``x_scale``: a planar trajectory leaves the height of the array nearly free, which a damping
    scaled by the curvature would not hold); a step is taken only when it lowers the cost. A closed 5 × 5
    solve per iteration instead of scipy's trust-region machinery (~4× less CPU, the same minimum: the
    features agree to the fit's tolerance). The K problems advance together, one trial step each per round
    (every array's fits and RANSAC's candidate tracks in one numpy call instead of one per fit), each with
    its own damping and its own end, exactly as K separate fits. max_iter : iterations at most (scalar or (K,)).
    Returns q (K, 5)."""
    q = np.array(q, float)
    k = len(q)
    robust = np.broadcast_to(np.asarray(robust, bool), (k,))
    f = fun(q)
    c0 = _lm_cost(f, robust)
    lam = np.full(k, np.nan)
    iters = np.zeros(k, int)
    active = np.ones(k, bool)
    eye = np.eye(q.shape[1])
    rows, up, tens = np.arange(k), 10.0 ** np.arange(LM_LADDER), np.full((k, LM_LADDER), 10.0)
    while np.any(active):
        J = jac(q)   # (unchanged for a problem whose last step was rejected: the same J, A, g)
        Jw = J * np.where(robust[:, None], 1.0 / (1.0 + f * f), 1.0)[..., None]
        A, g = np.matmul(np.swapaxes(J, 1, 2), Jw), np.einsum("knp,kn->kp", Jw, f)
        lam = np.where(np.isnan(lam), 1e-3 * np.max(np.diagonal(A, axis1=1, axis2=2), axis=1), lam)
        tens[:, 0] = lam
        ladder = np.cumprod(tens, axis=1)   # λ, 10λ, ... each ×10 in turn (as rejected steps raise it)
        steps = -_solve_each(A[:, None] + ladder[..., None, None] * eye, np.repeat(g[:, None], LM_LADDER, 1)) * X_SCALE
        qn = q[:, None] + steps
        fn = fun(qn)
        cn = _lm_cost(fn, robust[:, None])
        # the first trial of the ladder that lowers the cost is the step taken (a trial after one rejected counts
        # only while its damping is below LM_MAX_DAMPING), as if tried one after another
        tried = (cn <= c0[:, None]) & ((ladder < LM_MAX_DAMPING) | (up == 1.0))
        first = np.argmax(tried, axis=1)
        accept = active & np.any(tried, axis=1)
        reject = active & ~accept
        step, qn, fn, cn = steps[rows, first], qn[rows, first], fn[rows, first], cn[rows, first]
        lam = np.where(reject, ladder[:, -1] * 10.0, np.where(accept, ladder[rows, first] / 10.0, lam))
        active &= ~(reject & ~(lam < LM_MAX_DAMPING))   # no step lowers the cost: q is the minimum (to rounding)
        done = np.all(np.abs(step) < LM_STEP_TOL * X_SCALE, axis=1) | (c0 - cn <= 1e-15 * np.maximum(c0, 1e-300))
        q[accept], f[accept], c0[accept] = qn[accept], fn[accept], cn[accept]
        iters += accept
        active &= ~(accept & (done | (iters >= max_iter)))
    return q



def _lm_cost(f, robust):
    """Costs (...) of residuals f (..., n): Σ log(1 + f²) where ``robust`` (...) (Cauchy), else Σ f²; inf where
    a residual is not finite."""
    with np.errstate(over="ignore", invalid="ignore"):
        f2 = f * f
        cost = np.sum(np.where(robust[..., None], np.log1p(f2), f2), axis=-1)
    return np.where(np.isfinite(cost), cost, np.inf)


def _solve_each(a, b):
    """x (..., p) with a[i] x[i] = b[i] for every leading index i; NaN for a singular a[i] (its step is then
    rejected)."""
    try:
        return np.linalg.solve(a, b[..., None])[..., 0]
    except np.linalg.LinAlgError:
        out = np.full(b.shape, np.nan)
        for i in np.ndindex(b.shape[:-1]):
            try:
                out[i] = np.linalg.solve(a[i], b[i])
            except np.linalg.LinAlgError:
                pass
        return out


def fit_range_track(arrival, t, s, c, shift=None, vel=None, delta0=0.0):
    """Fit of :func:`range_model` to one array's arrivals that follows its direct paths, not the majority
    (:func:`_track_search`). arrival (J,) local s; t (J,) emission times − t_emit[0]; s (J, 3) odometry;
    vel (J, 3) or None. Returns (params (5,), residuals (J,) s: measured − model)."""
    return fit_range_tracks([Track(arrival, t, s, vel)], c, shift, delta0)[0]


def fit_range_tracks(tracks, c, shift=None, delta0=0.0):
    """:func:`fit_range_track` of several arrays ([:class:`Track`, ...]) at once: each array's search
    (:func:`_track_search`) is a sequence of fits that depend on the ones before, but the arrays are
    independent, so their searches advance in step and every round's fits of all arrays run as one stacked
    fit (:func:`_fit_many`): the numpy calls per round are those of one fit. Returns [(params, residuals)]."""
    return run_searches([_track_search(tr, c, shift, delta0) for tr in tracks], tracks, c, shift)


def run_searches(searches, tracks, c, shift=None):
    """Drive generators that yield track fits ([:class:`Fit`, ...] on ``tracks[i]``'s arrivals) and are sent
    the fitted tracks ((K, 5)): each round's fits of all of them as one stacked fit (:func:`_fit_many`).
    Returns their return values."""
    out = [None] * len(searches)
    pending = {}
    for i, g in enumerate(searches):
        _advance(g, None, i, pending, out)
    while pending:
        batch = [(tracks[i], f) for i, fits in pending.items() for f in fits]
        q = _fit_many(batch, c, shift)
        sent, k = dict(pending), 0
        pending.clear()
        for i, fits in sent.items():
            _advance(searches[i], q[k : k + len(fits)], i, pending, out)
            k += len(fits)
    return out


def _advance(search, value, i, pending, out):
    """Send ``value`` (the fitted tracks it asked for; None to start it) to search ``i``: its next fits go to
    ``pending[i]``, its result to ``out[i]``."""
    try:
        pending[i] = search.send(value)
    except StopIteration as stop:
        out[i] = stop.value


def _track_search(track, c, shift, delta0):
    """The search of :func:`fit_range_tracks` for one array, as a generator: it yields the fits it needs
    ([:class:`Fit`, ...]), is sent their results ((K, 5)), and returns (params, residuals).

    First a robust (Cauchy) fit to all arrivals from the linear start (:func:`linear_start`) and from above
    the trajectory's centre. When it leaves arrivals EARLY (a direct path is never early: the fit followed
    reflections), the latest arrivals peeled off one by one (:func:`_peel`) and, unless that found the
    direct paths' track (:func:`_enough`), RANSAC: tracks fitted to subsets (:func:`_candidates`, fixed
    seed) and then to their inliers, each scored by its support (:func:`_score`); the best track is kept.
    ``delta0``: a drift guess (0 is better than the association's scale − 1, which carries the trend of
    the propagation delays: up to 7e-4 in the hall, which sent one array's fit to RANSAC).
    """
    arrival, t, s = track.arrival, track.t, track.s
    j, every = len(arrival), np.arange(len(arrival))
    res_of = lambda q: track.residuals(q, c, shift)
    centre = s.mean(axis=0) + [0.0, 0.0, 4.0]
    starts = [linear_start(arrival - delta0 * t, t, s, c),
              np.r_[centre, float(np.median(arrival - t - np.linalg.norm(s - centre, axis=1) / c)), 0.0]]
    best, best_score = None, None
    for q0 in starts:   # the second start only when the first leaves arrivals early
        if best is not None and not np.any(res_of(best) < -NLOS_MIN_S):
            break
        if np.all(np.isfinite(q0)):
            q0[4] = delta0
            q = (yield [Fit(q0, every, True)])[0]
            sc = _score(res_of(q))
            if best_score is None or sc > best_score:
                best, best_score = q, sc
    early = np.flatnonzero(res_of(best) < -NLOS_MIN_S)
    if not early.size:
        return best, res_of(best)
    q, sc = yield from _peel(best, track, c, shift)
    if sc > best_score:
        best, best_score = q, sc
    if _enough(res_of(best)):
        return best, res_of(best)
    # the early group itself (the direct paths when the fit followed the reflections), then the subsets
    subsets = ([early] if early.size >= SUBSET else []) + _candidates(j, np.random.default_rng(0), s)
    for k in range(0, len(subsets), RANSAC_BATCH):
        for q in (yield from _candidate_tracks(subsets[k : k + RANSAC_BATCH], best, track, c, shift, delta0)):
            res = res_of(q)
            sc = _score(res)
            if sc > best_score:
                best, best_score = q, sc
            if _enough(res):
                return best, res_of(best)
    return best, res_of(best)


RANSAC_BATCH = 16   # candidate tracks fitted together (one stacked fit); the search stops after the batch holding the
                    # first track that is enough (:func:`_enough`), so at most this many - 1 are fitted in vain


def _candidate_tracks(subsets, fallback, track, c, shift, delta0):
    """RANSAC's tracks of the index ``subsets`` (a generator step of :func:`_track_search`), in order
    (K, 5): each from its linear start (``fallback`` where that is not finite) fitted to its subset, then, when
    at least MIN_INLIERS arrivals lie within INLIER_S of that, refitted (robust loss) to those inliers."""
    arrival, t, s = track.arrival, track.t, track.s
    fits = []
    for idx in subsets:
        q = linear_start(arrival[idx] - delta0 * t[idx], t[idx], s[idx], c)
        q = q if np.all(np.isfinite(q)) else fallback.copy()
        q[4] = delta0
        fits.append(Fit(q, idx, False))
    q = np.array((yield fits), float)
    inl = [np.flatnonzero(np.abs(track.residuals(qk, c, shift)) < INLIER_S) for qk in q]
    again = [i for i in range(len(q)) if len(inl[i]) >= MIN_INLIERS]
    if again:
        q[again] = yield [Fit(q[i], inl[i], True) for i in again]
    return q


def _enough(res):
    """A track with a third of the arrivals on it and none early: the direct paths' (no need to search on)."""
    return not np.any(res < -NLOS_MIN_S) and np.sum(np.abs(res) < INLIER_S) >= max(MIN_INLIERS, len(res) / 3)


def _peel(q, track, c, shift):
    """The track left when the latest arrivals are taken off one at a time (a reflection is late, never
    early; a generator step of :func:`_track_search`): from the compromise track ``q`` of all arrivals, the
    arrival latest against it is dropped and the track refitted to the rest, down to MIN_INLIERS arrivals;
    the best-scored (:func:`_score`) track on the way. Where the line of sight comes and goes in runs shorter
    than SUBSET (an office's doorways: 8 direct paths of 16 in runs of 2–4), no window and few random subsets
    hold direct paths only, while the reflections, metres late, are peeled off first.
    The fits on the way only score their subsets: each runs PEEL_MAX_ITER iterations at most, and the best
    one's is fitted on to LM_MAX_ITER (its residuals judge the arrivals). Returns (q (5,), score)."""
    keep, best, best_score = np.arange(len(track.arrival)), q, _score(track.residuals(q, c, shift))
    best_keep = None
    while len(keep) > MIN_INLIERS:
        keep = keep[keep != keep[np.argmax(track.residuals(q, c, shift)[keep])]]
        q = (yield [Fit(q, keep, False, PEEL_MAX_ITER)])[0]
        sc = _score(track.residuals(q, c, shift))
        if sc > best_score:
            best, best_score, best_keep = q, sc, keep
    if best_keep is None:
        return best, best_score
    best = (yield [Fit(best, best_keep, False)])[0]
    return best, _score(track.residuals(best, c, shift))


PEEL_MAX_ITER = 15   # iterations of each peeling fit: a least-squares track through reflections metres late crawls
                     # along a flat valley (its cost falling ~0.03 % an iteration, 45 of deploy 350's 52 stacked fits
                     # ended at LM_MAX_ITER), so the cap, not a tolerance, ends them; the peel only ranks the subsets


def _judge(res):
    """(scale, margin) of a fit from the residuals of the arrivals it was fitted to: the std from the
    quartile of |residual| (|N(0, σ²)| has its quartile at Q_ABS σ), which holds while a quarter of the
    arrivals are direct paths (a median-based scale breaks when half of them are reflections)."""
    scale = float(np.quantile(np.abs(res), 0.25)) / Q_ABS
    return scale, max(NLOS_MIN_S, NLOS_SIGMAS * scale)


def late_arrivals(arrival, t, s, c, shift=None, vel=None, delta0=0.0):
    """Per arrival, how late it is against the array's own range track and whether that makes it NLOS
    (:func:`late_arrivals_many` of one array)."""
    return late_arrivals_many([(arrival, t, s, vel)], c, shift, delta0)[0]


def late_arrivals_many(arrays, c, shift=None, delta0=0.0):
    """Per array [(arrival (J,), t (J,), s (J, 3), vel (J, 3) or None), ...], per arrival how late it is
    against the array's own range track and whether that makes it NLOS; the arrays' tracks fitted together
    (:func:`fit_range_tracks`).

    A direct path is never late by metres, and never early: the track (:func:`fit_range_track`) is the
    one with the most support and no early arrivals, so reflections do not take it over even when they are
    the majority (a reflection off one wall follows an image of the array just as smoothly).

    A track whose arrivals scatter about it by more than TRACK_SCALE_MAX is no direct paths' (the odometry
    in other units, or not this session's): nothing is judged (``late`` NaN, ``scale`` says why).

    Returns per array a dict: ``late`` (J,) residual (s; NaN when not judged), ``nlos`` (J,) bool, ``scale``
    (robust std of the residuals, s), ``early`` (arrivals still early by the margin: the track is in doubt),
    ``drift`` (the track's clock drift δ against the emission times; NaN when not judged).
    """
    outs, tracks, judged = [], [], []
    for arrival, t, s, vel in arrays:
        j = len(arrival)
        ok = np.isfinite(arrival)
        outs.append({"late": np.full(j, np.nan), "nlos": np.zeros(j, bool), "scale": np.nan, "early": 0,
                     "drift": np.nan})
        if ok.sum() >= MIN_EVENTS:
            tracks.append(Track(arrival[ok], t[ok], s[ok], None if vel is None else vel[ok]))
            judged.append((outs[-1], ok))
    for (out, ok), (q, res) in zip(judged, fit_range_tracks(tracks, c, shift, delta0) if tracks else []):
        scale, margin = _judge(res)
        out["scale"] = scale
        if not scale <= TRACK_SCALE_MAX:   # no range track along this odometry: nothing to judge against
            continue
        out["late"][ok], out["drift"] = res, float(q[4])
        out["nlos"][ok] = res > margin
        out["early"] = int(np.sum(res < -margin))
    return outs


# ------------------------------------------------------------ no direct path in the arrival's own waveform
# A reflection-only arrival whose detour is short (a path diffracted or reflected round a corner: 0.03-0.5 ms
# late, 1-17 cm of path) stays on its range track, so lateness cannot tell it. Its own waveform can: the
# onset is weak against a later peak (doubt "weak_direct") AND its mics agree with no one plane wave (doubt
# "doa_spread": several paths of like strength, none of them a direct path standing out). Either doubt alone
# is common in line of sight (office/L-shape seeds 50-54, 410-414: 166 and 19 of 1338 clear arrivals); both
# at once marked 3 of the 4 blocked arrivals the range track missed (DOAs 84-103 deg off, an L-shaped room's
# array turned 135 deg by one of them) and 2 clear ones, one of which was timed 0.61 ms early.
NO_DIRECT_DOUBTS = ("weak_direct", "doa_spread")


def no_direct_path(flags):
    """(J,) bool: the arrivals whose doubts ``flags`` [[str, ...], ...] hold every one of NO_DIRECT_DOUBTS."""
    return np.array([all(d in f for d in NO_DIRECT_DOUBTS) for f in flags], bool)


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
    env = lag_grid(c_plain, setup, lo, hi, magnitude=True).mean(axis=1) if env is None else env
    k = np.asarray(dp) - lo
    rows = np.arange(j)
    sub = subtract_path(c_plain, setup, shape, dp, half_width)
    env2 = lag_grid(sub, setup, lo, hi, magnitude=True).mean(axis=1)
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

