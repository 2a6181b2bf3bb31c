"""Leave-one-array-out consistency: does leaving array a's rows out move the other arrays more than the
noise allows? (A Hausman test; docs/method.md "Verdict".)

The residual tests (``estimator.robust``) see rows that do not fit. An array whose rows are biased *with the
geometry* — an unmodelled clock drift, a warm-up, a wrong mic geometry — does not show there: the solve
absorbs the bias by moving the sources and the other arrays, so every residual stays small and the result
looks right while another, clean array is centimetres off. What does show is that the solution depends on
that array's rows more than the noise allows.

Maths. Let θ̂ be the least-squares solution with every row and θ̃_a the one without array a's rows (a's
parameters fixed, its rows out), warm-started from θ̂ (one or two Gauss-Newton steps). Compare them on the
positions of the other free arrays, d_a = θ̃_a − θ̂ (3 m values). To first order both are linear maps of the
whitened row errors e, θ̂ − θ = G e with G = (JᵀJ)⁻¹Jᵀ over the kept rows (θ̃_a likewise with a's rows out),
so d_a ≈ (G_a − G) e and, with C = Cov(e),

    S_a = Cov(d_a) = P_aᵀ C P_a,    P_a = (G_a − G)ᵀ restricted to those positions  (M × 3m)
    T_a = d_aᵀ S_a⁺ d_a  ~  χ²(r),   r = rank(S_a)                                   (Hausman 1978)

When the rows are independent with their stated sigmas (C = I) this is Hausman's S_a = V_a − V (the full
solution is efficient). C is the one the ``*_std`` columns are computed with
(``uncertainty.sandwich_covariance``: each (type, array)'s σ² factor from its residuals, TDOA rows sharing
arrivals, planar arrays' DOA errors), so sigmas stated too small or errors shared between rows do not turn
into false alarms. The pseudo-inverse is taken in the generalised eigenbasis of (S_a, V), V the full
solution's plain covariance of those positions: directions whose variance grows by less than MIN_GROWTH
when a is left out carry almost no information from a (d_a there is linearisation error, not evidence) and
are left out of T_a and of r.

Under the alternative — a's rows biased with the geometry (an unmodelled clock drift) — θ̂ is pulled and
θ̃_a is not: T_a is large although every residual is small.

Each tested array is one test; the family-wise false-alarm rate over a calibration is FAMILY_ALPHA
(Bonferroni: p_a < FAMILY_ALPHA / m for m arrays tested). The reference array is not tested (it fixes the
frame: leaving it out leaves nothing to compare).

What follows (:func:`settle`, at the end of ``calibrate``): an inconsistent array is named. The others are solved
without its rows (it is refitted alone, unreliable) only when that lowers their expected squared error — the
bias its rows put on them, estimated by |d_a|² − tr S_a, exceeds the variance leaving them out adds, tr S_a —
and the rest then tests consistent (the array explained the inconsistency); the most significant arrays are
tried first, then any a trial's own test names (MAX_TRIES). Otherwise the full solution is kept.

Cost: one warm-started solve and one covariance per tested array (a trial without an array: one calibration). At most MAX_TESTED arrays are tested
(all when there are that few; else those with the largest mean normalised squared residual per row), and
none when the problem has more than MAX_PARAMS free parameters (large deployments: the covariance of each
reduced problem would cost more than the calibration).
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np
import scipy.linalg
import scipy.sparse
from scipy.special import chdtrc  # χ² survival function: chdtrc(dof, x)

from .init import ObservabilityError
from .problem import make_layout
from .robust import FAMILY_ALPHA, array_mask, factor_sizes, per_array_kinds
from .solver import cholesky_solve, levenberg_marquardt, linearise
from .uncertainty import sandwich_covariance, velocity_rows
from .variance import covariance_factors

MIN_GROWTH = 0.01    # an eigen-direction whose variance grows by < 1 % without array a: a informs it too little
MAX_TESTED = 12      # arrays tested per calibration (the warehouse's 10-12 all; larger deployments: the worst 12)
MAX_PARAMS = 600     # no test above this many free parameters (dense algebra: a 12-array 150-event session has
                     # 546; a 40 x 1000 deployment ~3300, whose dense covariances would cost more than its calibration)
# An inconsistent array's rows are left out of the others' solution only when that lowers their expected squared
# error: the bias its rows put on them, estimated |d|² − tr S, exceeds the variance leaving them out adds, tr S
# (so |d|² > ADOPT_RATIO tr S); else the full solution is kept (the array is named either way).
ADOPT_RATIO = 2.0
# ... and an array is named only when leaving it out moves another by at least this many of that array's own std:
# a significant move inside the error bars changes no conclusion (the bundled lab3 sample: A2 at p = 0.002 moved
# A3 by 0.1 cm, 0.51 σ, and was named and isolated; lab 28's absorbed warm-up moved A4 by 3.1 σ)
MIN_MOVE_SIGMA = 1.0
MAX_TRIES = 2        # inconsistent arrays tried (most significant first), each a calibration without it: the
                     # first whose leaving out leaves the rest consistent is solved without


@dataclass(frozen=True)
class LeaveOneOut:
    """One array's test. array: its name; T, dof, p: the Hausman statistic, its χ² dof and p-value;
    moved: the other array whose position moved most in its own 1-σ of the full solution when it was left out,
    by ``move_sigma`` (σ), ``move_m`` (m); alpha: the level it was judged at (Bonferroni);
    inconsistent: p < alpha and move_sigma ≥ MIN_MOVE_SIGMA; shift_m: |d| over every compared position (m), noise_m: √tr S, its expected size
    when nothing is wrong (m)."""
    array: str
    T: float
    dof: int
    p: float
    moved: str
    move_m: float
    move_sigma: float
    alpha: float
    inconsistent: bool
    shift_m: float = 0.0
    noise_m: float = 0.0

    def as_dict(self):
        return asdict(self)


def hausman(d, S, V, min_growth=None):
    """(T, r): ``dᵀ S⁺ d`` over the directions whose variance S (of d) is at least ``min_growth`` (default
    MIN_GROWTH) of V's (the full solution's); d (n,), S, V (n, n). (0, 0) when V is not positive definite
    (a position left undetermined: nothing to test)."""
    min_growth = MIN_GROWTH if min_growth is None else min_growth
    D = 0.5 * (S + S.T)
    try:
        lam, W = scipy.linalg.eigh(D, 0.5 * (V + V.T))   # Wᵀ V W = I, Wᵀ D W = diag(lam)
    except (np.linalg.LinAlgError, ValueError):
        return 0.0, 0
    keep = lam > min_growth
    c = W[:, keep].T @ d
    return float(np.sum(c * c / lam[keep])), int(keep.sum())


def positions_of(st, lay, arrays):
    """(values (3m,), columns (3m,)) of the positions of ``arrays`` (indices) in the layout ``lay``."""
    return st.x[arrays].ravel(), lay.x[arrays].ravel()


def influence(lin, cov_cols):
    """(M, k): the first-order change of k parameters per unit whitened error of each row, J (JᵀJ)⁻¹ over the
    kept rows of ``lin`` (0 on the others); ``cov_cols`` (n, k): those parameters' columns of (JᵀJ)⁻¹."""
    keep = lin.w > 0
    out = np.zeros((len(lin.r), cov_cols.shape[1]))
    out[keep] = lin.J[keep] @ cov_cols
    return out


def error_covariance(p, lin, cov, *, shared, normals, velocity=None):
    """``(X, a) -> Xᵀ C X`` for C the whitened rows' error covariance at the full solution's linearisation ``lin``
    (``cov`` its dense (JᵀJ)⁻¹): the one ``uncertainty.sandwich_covariance`` uses for the ``*_std`` columns, a
    moving source's velocity error (``velocity``: ``uncertainty.velocity_rows`` of ``lin``) included; but for
    array ``a``'s own rows (the array tested; None: none) the σ² factors its residuals ask for are left out (1).
    Under the alternative those residuals carry the very bias tested, and would scale its test down: office 390's
    A4, one unflagged DOA 3.6° off (10 σ of its own sigma_deg) under the outlier threshold, doubled its DOA factor
    to 1.97 and cut its T from 23.6 to 20.0 (p 0.0006 → 0.0055, the level 0.0025); the others' factors stay."""
    factors = covariance_factors(p, lin, cov)

    def quad(X, a=None):
        own = factors if a is None else {k: v if k.endswith("_correlation") else np.where(np.arange(p.N) == a, 1.0, v)
                                         for k, v in factors.items()}
        return sandwich_covariance(p, lin._replace(J=X), np.eye(X.shape[1]), own, shared, normals, velocity)
    return quad


def normal_inverse(lin, cols=None):
    """(JᵀJ)⁻¹ of the kept rows of ``lin`` (dense or sparse J), all of it (n, n) or its columns ``cols``, by
    Cholesky of the Jacobi-scaled matrix (a pseudo-inverse where that is singular)."""
    J = lin.J[lin.w > 0]
    H = J.T @ J
    H = H.toarray() if scipy.sparse.issparse(H) else np.asarray(H)
    d = np.sqrt(np.diag(H))
    d = np.where(d > 0, d, 1.0)
    Hs = H / d[:, None] / d[None, :]
    idx = np.arange(len(d)) if cols is None else np.asarray(cols, int)
    E = np.zeros((len(d), len(idx)))
    E[idx, np.arange(len(idx))] = 1.0
    X = cholesky_solve(Hs, E)
    if X is None:
        X = np.linalg.pinv(Hs) @ E
    return X / d[:, None] / d[idx][None, :]


def tested_arrays(p, st, lay, kinds, mask, free, limit=MAX_TESTED):
    """The arrays to test (indices, not the reference, among ``free``): all when at most ``limit``, else the
    ``limit`` with the largest mean normalised squared residual per row (their rows fit least)."""
    cand = [i for i in free if i != p.ref]
    if len(cand) <= limit:
        return cand
    lin = linearise(p, st, lay, kinds, mask=mask)
    share, count, start = np.zeros(p.N), np.zeros(p.N), 0
    for f in lin.factors:
        n = len(f.r)
        if f.kind in per_array_kinds():
            arr = np.repeat(p.rows(f.kind).arr, f.dim)
            keep = mask.get(f.kind, np.ones(n, bool))
            np.add.at(share, arr[keep], lin.r[start:start + n][keep] ** 2)
            np.add.at(count, arr[keep], 1.0)
        start += n
    score = share / np.maximum(count, 1.0)
    return sorted(sorted(cand, key=lambda i: -score[i])[:limit])


def most_moved(d, V):
    """(k, |d_k| in m, |d_k| / σ_k): the array whose position moved most in its own error bars, d (3m,) the
    positions' change, V (3m, 3m) their covariance, σ_k = √tr of array k's 3×3 block (materiality is read in
    each array's σ: a 5 cm move of a 5 cm-σ array is no evidence, a 2 cm move of a 0.5 cm-σ one is)."""
    move = np.linalg.norm(d.reshape(-1, 3), axis=1)
    sd = np.sqrt(np.maximum(np.diag(V).reshape(-1, 3).sum(axis=1), 1e-30))
    k = int(np.argmax(move / sd))
    return k, float(move[k]), float(move[k] / sd[k])


def leave_one_out(p, st, lay, kinds, mask, a, *, free, full, quad, max_iter=200):
    """Array a's test against the full least-squares solution ``st`` at ``lay``/``mask`` (``free``: the arrays
    solved, the reference included); ``full`` = (its linearisation, its dense (JᵀJ)⁻¹); ``quad``:
    :func:`error_covariance`. Returns (LeaveOneOut, its level not yet decided; the reduced state)."""
    lin, cov = full
    solved = [i for i in free if i != a]               # the reference's drift stays free, as in the full solve
    others = [i for i in solved if i != p.ref]         # (its position is the frame's origin: nothing to compare)
    lay_a = make_layout(p, arrays=solved)
    mask_a = array_mask(p, mask, factor_sizes(p), a)
    st_a, _ = levenberg_marquardt(p, st, lay_a, kinds, loss=None, mask=mask_a, max_iter=max_iter, rtol=1e-9)
    lin_a = linearise(p, st_a, lay_a, kinds, mask=mask_a)
    x0, c0 = positions_of(st, lay, others)
    x1, c1 = positions_of(st_a, lay_a, others)
    d = x1 - x0
    S = quad(influence(lin_a, normal_inverse(lin_a, c1)) - influence(lin, cov[:, c0]), a)
    V = cov[np.ix_(c0, c0)]
    T, dof = hausman(d, S, V)
    k, move_m, move_sigma = most_moved(d, V)
    rec = LeaveOneOut(str(p.names[a]), T, dof, float(chdtrc(dof, T)) if dof else 1.0, str(p.names[others[k]]),
                      move_m, move_sigma, np.nan, False, float(np.linalg.norm(d)),
                      float(np.sqrt(max(np.trace(S), 0.0))))
    return rec, st_a


def untestable(p, lay, free):
    """Why the arrays ``free`` (the reference among them) of a solve with layout ``lay`` are not tested, or None."""
    if len([i for i in free if i != p.ref]) < 2:
        return "fewer than two arrays besides the reference: nothing to compare"
    if lay.n > MAX_PARAMS:
        return f"{lay.n} free parameters (> {MAX_PARAMS}): not tested (cost)"
    return None


def check(p, st, kinds, mask, dropped=(), *, shared=False, normals=None, max_iter=200, alpha=FAMILY_ALPHA,
          stated_errors=False, motion=None):
    """Test every array (up to MAX_TESTED) of a least-squares solution: ``st`` with the rows ``mask`` (or a
    function of the layout giving them, called only when there is something to test) and
    the arrays ``dropped`` (indices) left out. ``stated_errors``: C = I (the rows independent with the sigmas
    the solve ended with: the exact χ² case, for tests) instead of the ``*_std`` columns' C (``motion``: a moving
    source's velocity error in it, ``motion.MotionNoise``; unmodelled, its arrival shifts isolated the array of
    test_clocks' moving step at p 0.0017 against 0.0025, with its true step modelled). Returns {"tested":
    [LeaveOneOut dicts], "alpha", "skipped" (why none was tested, or None), "time_s"}."""
    t0 = time.perf_counter()
    free = [i for i in range(p.N) if i not in dropped]
    lay = make_layout(p, arrays=free)
    out = {"tested": [], "alpha": alpha, "skipped": untestable(p, lay, free), "time_s": 0.0}
    if out["skipped"]:
        return out
    mask = mask(lay) if callable(mask) else mask
    sizes = factor_sizes(p)
    for i in dropped:
        mask = array_mask(p, mask, sizes, i)
    st, _ = levenberg_marquardt(p, st, lay, kinds, loss=None, mask=mask, max_iter=max_iter, rtol=1e-9)
    lin = linearise(p, st, lay, kinds, mask=mask)
    cov = normal_inverse(lin)
    quad = (lambda X, a=None: X.T @ X) if stated_errors else error_covariance(
        p, lin, cov, shared=shared, normals=normals, velocity=velocity_rows(lin, lay, motion))
    tests = tested_arrays(p, st, lay, kinds, mask, free)
    level = alpha / len(tests)
    recs = []
    for a in tests:
        rec, _ = leave_one_out(p, st, lay, kinds, mask, a, free=free, full=(lin, cov), quad=quad, max_iter=max_iter)
        bad = rec.p < level and rec.move_sigma >= MIN_MOVE_SIGMA
        recs.append(LeaveOneOut(**{**rec.as_dict(), "alpha": level, "inconsistent": bool(bad)}))
    out["tested"] = [r.as_dict() for r in recs]
    out["time_s"] = time.perf_counter() - t0
    return out


def check_result(result, meta, *, max_iter=200, alpha=FAMILY_ALPHA, stated_errors=False):
    """:func:`check` on a ``calibrate`` result (its final problem, state, report ``outliers`` and
    ``unreliable_arrays``); ``meta``: the features' meta.json (shared arrivals, planar arrays' normals)."""
    from .assess import outlier_mask
    from .factors import active_kinds
    from .motion import motion_noise
    from .uncertainty import plane_normals

    p, st, rep = result["problem"], result["state"], result["report"]
    kinds = active_kinds(p)
    index = {str(n): i for i, n in enumerate(p.names)}
    dropped = [index[a] for a in rep.get("unreliable_arrays") or [] if a in index]

    def mask(lay):   # (only when there is something to test: it evaluates every factor)
        return outlier_mask(p, st, lay, kinds, rep.get("outliers"))
    return check(p, st, kinds, mask, dropped, shared=bool(meta.get("tdoa_shared_arrivals")),
                 normals=plane_normals(meta, p.names), max_iter=max_iter, alpha=alpha, stated_errors=stated_errors,
                 motion=motion_noise((rep.get("stages") or {}).get("motion"), p, meta.get("doa_time_s")))


def _inconsistent(chk):
    """The inconsistent arrays' records of a check, most significant first, each with ``helps``: leaving it out
    lowers the others' expected squared error (ADOPT_RATIO)."""
    bad = sorted((t for t in chk["tested"] if t["inconsistent"]), key=lambda t: t["p"])
    return [{**t, "helps": bool(t["shift_m"] ** 2 > ADOPT_RATIO * t["noise_m"] ** 2)} for t in bad]


def _trial(resolve, name, meta, **kw):
    """(result, its check, readmitted) of ``resolve((name,))``: the session without array ``name``, or with it
    given back (``readmitted``: not among the result's unreliable arrays). Given back, it must leave every array
    consistent; else the session is solved without it after all (``resolve(names, readmit=False)``)."""
    trial = resolve((name,))
    again = check_result(trial, meta, **kw)
    back = name not in (trial["report"].get("unreliable_arrays") or ())
    if back and _inconsistent(again):
        trial = resolve((name,), readmit=False)
        again, back = check_result(trial, meta, **kw), False
    return trial, again, back


def settle(result, meta, resolve, *, max_iter=200, alpha=FAMILY_ALPHA):
    """Test ``result`` (:func:`check_result`). When arrays are inconsistent, try them (most significant first,
    then any a trial's own test names; at most MAX_TRIES) where their rows bias the others more than leaving
    them out would cost (``helps``): ``resolve(names, readmit=True) -> result`` solves without that array (refitted alone);
    that solution is adopted when its own arrays then test consistent (the array explained the inconsistency).
    ``resolve`` may give the array back, solved with its rows again (``clockmodel.calibrate_clocks``' ``readmit``:
    clock terms the scan found once its rows were out explain them): kept so when every array then tests
    consistent, else solved without it (``readmit=False``, :func:`_trial`).
    Returns (the result adopted or ``result``, report.json ``leave_one_out``: {"rounds": [each check, with
    "isolated": the names solved without], "inconsistent": [the inconsistent arrays' test records, each with
    "helps", "isolated": solved without, and "readmitted": the trial gave it back with its rows, consistent],
    "explained": one array solved without left the rest consistent, or a single array was named})."""
    first = check_result(result, meta, max_iter=max_iter, alpha=alpha)
    rounds = [{**first, "isolated": []}]
    queue, found, tried = _inconsistent(first), {}, 0
    while queue and tried < MAX_TRIES:
        rec = queue.pop(0)
        if rec["array"] in found:
            continue
        found[rec["array"]] = rec
        if not rec["helps"]:
            continue
        try:
            trial, again, back = _trial(resolve, rec["array"], meta, max_iter=max_iter, alpha=alpha)
        except ObservabilityError:
            continue
        tried += 1
        rounds.append({**again, "isolated": [rec["array"]]})
        more = _inconsistent(again)
        if not more:
            return trial, {"rounds": rounds, "inconsistent": [{**rec, "isolated": not back, "readmitted": back}],
                           "explained": True}
        queue += more   # (their figures are those of the trial without rec's array)
    found.update({t["array"]: t for t in queue if t["array"] not in found})
    out = [{**t, "isolated": False} for t in found.values()]
    return result, {"rounds": rounds, "inconsistent": out, "explained": len(out) <= 1 and len(rounds) == 1}
