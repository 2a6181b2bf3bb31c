"""Variance components: the sigma of each measurement type (and, opt-in, each array's) from the residuals.

``sigma_bounds`` / ``sigma_floors`` say how far the data may move each type's sigma from the one stated
(a user's figure is a prior; a frontend's own figure may only rise); :func:`robust_noise_steps` moves the
sigmas by the medians of the residual statistics before the outlier tests, :func:`estimate_noise` by
variance-component estimation after them. Each returns a new problem with the new sigmas (the input is
not changed: ``problem.Problem`` is immutable, the stage works on a :class:`~calib.estimator.problem.Weights`).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse

from . import arraynoise
from .factors import KINDS, row_arrays
from .problem import make_layout, with_arrival_scale
from .robust import chi2_median, measurement_stats, sym_inverse
from .solver import levenberg_marquardt, linearise, use_dense

# A sigma the user states as measured (meta.json/session.toml, not listed in ``sigmas_estimated``) is a
# prior: variance components may move it by at most this factor either way (the data can say "a bit
# worse than stated", never replace a 3 cm odometry prior with 3 m and so hide a failure).
PRIOR_MAX_FACTOR = 3.0
FREE_MAX_FACTOR = 100.0   # a frontend's own figure (or noise="estimate" for TDOA/DOA): bounded, not fixed
# ... but a frontend's own figure is never lowered (only raised): it is measured against truth (issue 9: within
# 1.5 of the errors on the realistic rooms), while the residuals cannot see the part of the errors the fit
# absorbs (per-event sources, clocks) and shrink with a type's weight. Lowered down to a third, the TDOA sigma
# sat at that bound in every lab session: position errors 1.9× their stated std (z RMS), half the lab verdicts
# false "suspect"s, 40 % larger errors (CHANGELOG.md, 24 Nov 16:10); with no bound it ran to 1/100 and the
# fit bent the sources to biased TDOAs
FRONTEND_MIN_FACTOR = 1.0
VCE_ITERATIONS = 4        # variance-component steps at most; stopped early when a factor reverses or settles
# with per-array components: more steps (the type's factor first takes up a noisy array's excess, then
# gives it back when that array gets its own: a reversal that is not a sign of instability)
VCE_ITERATIONS_ARRAYS = 10
ROBUST_VCE_STEPS = 2   # median-based sigma steps before the outlier tests (noise="estimate")


def reweighted():
    """The kinds whose sigma the data may re-weight (``reweight`` in their spec), in registry order."""
    return [k for k, spec in KINDS.items() if spec.reweight]


def sigma_bounds(meta, noise):
    """Per measurement type, the largest factor (either way) variance components may apply to its sigma.

    ``noise="estimate"``: TDOA and DOA sigmas are free (bounded by FREE_MAX_FACTOR), odometry is a prior
    unless meta lists it in ``sigmas_estimated``; ``"auto"``: only the sigmas meta lists as estimated are
    free, the others are priors (PRIOR_MAX_FACTOR).
    """
    est = set(meta.get("sigmas_estimated") or [])
    out = {}
    for kind in reweighted():
        key = KINDS[kind].noise_key
        free = key in est or (noise == "estimate" and kind != "odometry")
        out[kind] = FREE_MAX_FACTOR if free else PRIOR_MAX_FACTOR
    return out


def sigma_floors(meta, bounds):
    """Per type, the largest factor variance components may LOWER its sigma by: FRONTEND_MIN_FACTOR for a
    frontend's own figure (meta ``sigmas_estimated``), else its bound (:func:`sigma_bounds`)."""
    est = set(meta.get("sigmas_estimated") or [])
    return {kind: min(bounds[kind], FRONTEND_MIN_FACTOR) if KINDS[kind].noise_key in est else bounds[kind]
            for kind in reweighted()}


def robust_noise_steps(p, st, lay, kinds, *, bounds, stated, loss, robust_k, max_iter, steps=ROBUST_VCE_STEPS,
                       floors=None, mask=None):
    """Sigmas from the median of each type's normalised statistics (outliers do not move a median), so
    the outlier tests and the robust loss work in the data's own noise units (``mask``: rows left out).
    Returns (state, problem with those sigmas)."""
    mask = mask or {}
    for _ in range(steps):
        stats = measurement_stats(p, st, lay, kinds, mask)
        sigma, changed = dict(p.sigma), False
        for kind in reweighted():
            m = stats.kept & (stats.kind == kind)
            if m.sum() < 5:
                continue
            f = float(np.sqrt(np.median(stats.q[m]) / chi2_median(KINDS[kind].dof)))
            b = bounds.get(kind, FREE_MAX_FACTOR)
            lo = (floors or bounds).get(kind, b)
            new = float(np.clip(sigma[kind] * f, stated[kind] / lo, stated[kind] * b))
            changed |= abs(new / sigma[kind] - 1.0) > 0.05
            sigma[kind] = new
        p = p.replace(sigma=sigma)
        if not changed:
            break
        st, _ = levenberg_marquardt(p, st, lay, kinds, loss=loss, k=robust_k, mask=mask, max_iter=max_iter, rtol=1e-6)
    return st, p


def _leverages(J, keep, cov):
    """Hat-matrix diagonal h (rows,) of the kept rows of the whitened Jacobian J (0 elsewhere, and 0 for a
    sparse J: large problems, mean n / rows ≈ 0.02 there; see robust.measurement_stats). ``cov``: (JᵀJ)⁻¹
    of the kept rows when already computed (dense)."""
    h = np.zeros(len(keep))
    if scipy.sparse.issparse(J):
        return h
    Jk = J[keep]
    if cov is None or not isinstance(cov, np.ndarray):
        d = np.linalg.norm(Jk, axis=0)
        d = np.where(d > 0, d, 1.0)
        A = sym_inverse((Jk / d).T @ (Jk / d))
        h[keep] = np.einsum("ij,jk,ik->i", Jk / d, A, Jk / d)
    else:
        h[keep] = np.einsum("ij,jk,ik->i", Jk, cov, Jk)
    return h


def vce_factors(p, st, lay, kinds, mask, min_redundancy, cov=None, arrays=None, redundancy=None):
    """One variance-component step: {kind: Σ_k r² / Σ_k (1 − h_ii)} for types with enough redundancy.

    ``cov``: (JᵀJ)⁻¹ at (st, lay, mask) when already computed. ``arrays`` (dict): filled with the
    per-array factors {kind: (N,)} of the types with per-array components (``arraynoise.vce_groups``).
    ``redundancy`` (dict): filled with each type's Σ_k (1 − h_ii) if given.
    """
    lin = linearise(p, st, lay, kinds, mask=mask)
    r, J, w, fs = lin.r, lin.J, lin.w, lin.factors
    keep = w > 0
    h = _leverages(J, keep, cov)
    out, start = {}, 0
    for f in fs:
        n = len(f.r)
        sl = slice(start, start + n)
        start += n
        if not KINDS[f.kind].reweight or n == 0:
            continue
        if arrays is not None and f.kind in (p.array_scale or {}):
            arrays[f.kind] = arraynoise.vce_groups(p, f, r[sl], h[sl], keep[sl])
        red = float(np.sum((1.0 - h[sl])[keep[sl]]))
        dof = KINDS[f.kind].dof
        if dof is not None and dof < f.dim:   # e.g. a unit-vector residual: no noise along the direction itself
            red -= float(keep[sl].sum()) * (f.dim - dof) / f.dim
        if red >= min_redundancy:
            out[f.kind] = float(np.sum(r[sl][keep[sl]] ** 2)) / red
            if redundancy is not None:
                redundancy[f.kind] = red
    return out


def estimate_noise(p, st, kinds, mask, *, bounds=None, floors=None, iterations=VCE_ITERATIONS, min_redundancy=5.0,
                   max_iter=200, lay=None, stated=None):
    """Re-estimate each measurement type's sigma from its residuals (variance-component estimation).

    σ_k² ← σ_k² · Σ_k r² / Σ_k (1 − h_ii), h the hat matrix of the whitened Jacobian, then re-solve (warm);
    types with redundancy below ``min_redundancy`` keep their sigma. The total factor of type k stays
    within [1/floors[k], bounds[k]] of ``stated`` (floors default to the bounds) (default: p's sigmas; see
    :func:`sigma_bounds`). Iterated while stable: at most ``iterations`` steps, stopping when every step
    factor is within 1 % of 1, or when a type's factor reverses direction (a type the parameters can absorb
    would otherwise shrink without bound).
    Returns (state, a new problem with the new sigmas, info with the total scales and which types hit their
    bound); ``p`` is not changed.
    """
    w = p.weights()
    if p.array_scale:
        w.array_own = {}
    p = p.with_weights(w)
    lay = lay or make_layout(p)
    bounds = bounds or {k: FREE_MAX_FACTOR for k in reweighted()}
    base = stated or {k: p.sigma[k] for k in reweighted()}
    scales = {k: p.sigma[k] / base[k] for k in reweighted()}
    last_dir = {}
    info, at_bound = {}, {}
    steps = max(iterations, VCE_ITERATIONS_ARRAYS) if p.array_scale else iterations
    for it in range(steps):
        per_array = {}
        fac = vce_factors(p, st, lay, kinds, mask, min_redundancy, arrays=per_array)
        changed, reversed_ = _vce_step(w, fac, per_array, scales, base, last_dir, at_bound, bounds=bounds,
                                       floors=floors, min_redundancy=min_redundancy)
        p = p.with_weights(w)
        st, info = levenberg_marquardt(p, st, lay, kinds, loss=None, mask=mask, max_iter=max_iter)
        own = any(np.any(v) for v in p.array_own.values())
        if not changed or reversed_ or (it + 1 >= iterations and not own):
            break
    return st, p, {"scale": scales, "at_bound": at_bound, "bounds": bounds, **info}


def _vce_step(w, fac, per_array, scales, base, last_dir, at_bound, *, bounds, floors, min_redundancy):
    """Apply one step's factors ``fac`` ({kind: σ² factor}; ``per_array``: the arrays' groups) to the
    weights ``w``, within the bounds; updates ``scales`` (total factors), ``last_dir`` and ``at_bound``.
    Returns (a factor moved by more than 1 %, a type's factor reversed direction)."""
    changed, reversed_ = False, False
    for kind, f2 in fac.items():
        own = kind in per_array and bool(np.any(arraynoise.own_components(w, kind, per_array[kind])))
        if own:
            f2 = arraynoise.type_factor(w, kind, per_array[kind], f2, min_redundancy)
        step = float(np.sqrt(np.clip(f2, 1e-8, 1e8)))
        b = bounds.get(kind, FREE_MAX_FACTOR)
        lo = (floors or bounds).get(kind, b)
        total = float(np.clip(scales[kind] * step, 1.0 / lo, b))
        at_bound[kind] = bool(scales[kind] * step > b * (1 + 1e-9) or scales[kind] * step < (1 - 1e-9) / lo)
        step = total / scales[kind]
        d = np.sign(step - 1.0) if abs(step - 1.0) > 0.01 else 0.0
        scales[kind] = total
        w.sigma[kind] = base[kind] * total
        changed |= abs(step - 1.0) > 0.01
        if own:
            a_steps = arraynoise.update_scales(w, kind, per_array[kind], step, total, b)
            changed |= bool(np.any(np.abs(a_steps - 1.0) > 0.01))
            continue   # the type's factor may reverse while its arrays' move (see VCE_ITERATIONS_ARRAYS)
        reversed_ |= bool(d and last_dir.get(kind, d) != d)
        last_dir[kind] = d
    return changed, reversed_


ARRIVAL_ITERATIONS = 4     # arrival-scale steps at most (each a warm re-solve); stopped when every scale settles
ARRIVAL_SETTLED = 0.02     # ... within this fraction


def estimate_arrival_scales(p, st, kinds, mask, *, lay, max_iter=200):
    """Each array's arrival scale from the residuals (:func:`arrival_components`, the problem's scales from meta
    ``sigma_arrival_per_array`` the prior; :func:`calib.estimator.arraynoise.arrival_variances`), re-solving
    (warm, plain least squares on the kept rows) after each step. Returns (state, a new problem with the
    scales, solver info), or (st, p, None) when there is nothing to estimate from (no TDOA-S row kept, or a
    problem too large for the dense redundancy matrix)."""
    if "tdoa_s" not in kinds or not len(p.tdoa_s.val) or not use_dense(lay):
        return st, p, None
    prior = np.ones(p.N) if p.arrival_scale is None else np.asarray(p.arrival_scale, float)
    info = None
    for _ in range(ARRIVAL_ITERATIONS):
        comp = arrival_components(p, st, lay, kinds, mask)
        if comp is None:
            break
        old = np.ones(p.N) if p.arrival_scale is None else np.asarray(p.arrival_scale, float)
        new = np.sqrt(arraynoise.arrival_variances(comp["v"] * old**2, comp["red"], prior, comp["rows_arr"]))
        p = with_arrival_scale(p, new)
        st, info = levenberg_marquardt(p, st, lay, kinds, loss=None, mask=mask, max_iter=max_iter)
        if np.all(np.abs(new / old - 1.0) < ARRIVAL_SETTLED):
            break
    return st, p, info


def arrival_components(p, st, lay, kinds, mask):
    """Helmert variance components of the arrays' arrivals at ``st``: each array's arrival variance factor v_h
    (relative to the current scales) from the whitened residuals r of the kept rows, r = R e with R = I − J (JᵀJ)⁻¹
    Jᵀ the redundancy matrix and e the rows' errors. The TDOA rows' errors are differences of arrivals
    (``uncertainty.arrival_rows``: e = Σ_h D_h n_h, n_h array h's arrivals in their units), the other kinds one
    group each (nuisance components). For each group g the quadratic form q_g = Σ r² over its rows (an array:
    its TDOA-S rows and, but for the reference, its TDOA-M rows) has E q_g = Σ_h v_h ‖P_g R D_h‖²_F; the system
    is solved for v. So an array whose errors the fit spreads onto the others' rows (few arrays: the sources
    take up most of one noisy array's arrivals) is still found, and the others are not charged with its noise.
    Returns {"v": (N,), "red": (N,) each array's own redundancy ‖P_h R D_h‖², "rows_arr": TDOA-S rows' arrays
    (kept)}, or None without kept TDOA rows."""
    from .uncertainty import arrival_rows   # (uncertainty's covariance uses this module lazily)

    lin = linearise(p, st, lay, kinds, mask=mask, dense=True)
    keep = lin.w > 0
    D = arrival_rows(p, lin, {})
    if D is None:
        return None
    J = np.asarray(lin.J)[keep]
    d = np.linalg.norm(J, axis=0)
    d = np.where(d > 0, d, 1.0)
    Jd = J / d
    R = np.eye(len(J)) - Jd @ sym_inverse(Jd.T @ Jd) @ Jd.T
    r = lin.r[keep]
    D = D[np.flatnonzero(keep)].toarray()
    kind = np.concatenate([np.full(len(f.r), f.kind, dtype=object) for f in lin.factors])[keep]
    arr = np.where((kind == "tdoa_s") | (kind == "tdoa_m"), row_arrays(p, lin.factors)[keep], -1)
    K = p.K
    cols = [D[:, h * K:(h + 1) * K] for h in range(p.N)]
    others = [k for k in dict.fromkeys(kind) if k not in ("tdoa_s", "tdoa_m")]
    sel = [arr == h for h in range(p.N)] + [kind == k for k in others]
    RE = [R @ c for c in cols] + [R[:, m] for m in sel[p.N:]]
    A = np.array([[float(np.sum(x[g] ** 2)) for x in RE] for g in sel])
    q = np.array([float(np.sum(r[g] ** 2)) for g in sel])
    live = np.diag(A) > 1e-9
    v = np.ones(len(sel))
    v[live] = np.linalg.lstsq(A[np.ix_(live, live)], q[live], rcond=None)[0]
    red = np.diag(A)[:p.N]
    v = np.where(red > 1e-9, np.maximum(v[:p.N], 0.0), 1.0)
    return {"v": v, "red": red, "rows_arr": arr[(kind == "tdoa_s") & (arr >= 0)]}


# --------------------------------------------------------------------------------- honest error bars
# The weights of the solve are one sigma per type (and, opt-in, per array); the error bars must also hold
# for an array whose rows are worse than its type's (a close reflection biasing all of its mics alike: the
# frontend's mic-scatter sigma misses it; per-row DOA sigmas 1.3–3.2x optimistic on such arrays, issue 27).
# Each array's own residuals say so: its rows' variance factor Σ r² / Σ(1 − h) inflates, for the covariance
# only, that array's rows of that type (never below the type's sigma: a factor below 1 is the scatter of a
# few residuals, or an array whose parameters absorb its own rows). The factor is shrunk toward 1 by a prior
# worth COVARIANCE_PRIOR_DOF residual degrees of freedom, so an array with little redundancy is not inflated
# by the scatter of a handful of residuals.
COVARIANCE_PRIOR_DOF = 4.0
# The direction kinds' sigma is a frontend's spread figure that the solve never lowers (FRONTEND_MIN_FACTOR), and
# it is wide: against simulated truth the DOA rows err 0.31-0.93 of it (RMS at the true geometry; moving 500, 501,
# 503, lshape 500, 503, office 501), while their variance components Σ r² / Σ(1 − h) read 0.98-1.28 × the truth's.
# For the covariance only, the factors of the kinds asked for (``lower``: these, and the TDOA kinds of a moving
# source whose σ_TDOA holds its velocity error, ``uncertainty.honest_covariance``: that error is one per event and in
# the covariance as such; less a per-event source shift the rows err 0.03-0.12 of σ at the true geometry, moving
# 500-504, their components read 0.26-0.55) may therefore go below 1, to the type's own variance component (pooled
# over its arrays), never below COVARIANCE_MIN_FACTOR (σ down to a third, as PRIOR_MAX_FACTOR) and only with
# COVARIANCE_MIN_REDUNDANCY residual degrees of freedom behind it; an array's factor is shrunk toward the type's.
LOWERED_KINDS = ("doa", "cone")
COVARIANCE_MIN_FACTOR = 1.0 / 9.0
COVARIANCE_MIN_REDUNDANCY = 20.0


def covariance_factors(p, lin, cov=None, lower=()):
    """Per (type, array) σ² factors for the covariance: {kind: (N,)} from the final linearisation ``lin``
    (``solver.Linearised``, weights 0 on excluded rows) and its covariance ``cov`` when dense (leverages;
    0 for a sparse problem, see :func:`_leverages`), and under ``<kind>_correlation`` the part of it from the
    residuals' lag-1 correlation. Types without per-array rows or not re-weighted by the data are left out.
    The factors are ≥ 1, but those of the kinds in ``lower`` are ≥ the type's own variance component
    (:func:`_type_floor`), which may be below 1."""
    keep = lin.w > 0
    h = _leverages(lin.J, keep, cov if isinstance(cov, np.ndarray) else None)
    out, start = {}, 0
    for f in lin.factors:
        n = len(f.r)
        sl = slice(start, start + n)
        start += n
        if n == 0 or not KINDS[f.kind].per_array or not KINDS[f.kind].reweight:
            continue
        g = arraynoise.vce_groups(p, f, lin.r[sl], h[sl], keep[sl])
        red = np.maximum(g["red"], 0.0)
        t = _type_floor(g["ss"], red) if f.kind in lower else 1.0
        v = np.maximum(t, (g["ss"] + t * COVARIANCE_PRIOR_DOF) / (red + COVARIANCE_PRIOR_DOF))
        corr = _correlation_inflation(p, f, lin.r[sl], keep[sl])
        out[f.kind] = v * corr
        out[f.kind + "_correlation"] = corr
    return out


def _type_floor(ss, red):
    """The lowest σ² factor of a type's rows (per array Σ r² ``ss`` and redundancy ``red``, (N,)): its pooled variance
    component Σ ss / Σ red, within [COVARIANCE_MIN_FACTOR, 1]; 1 with less than COVARIANCE_MIN_REDUNDANCY."""
    total = float(np.sum(red))
    if total < COVARIANCE_MIN_REDUNDANCY:
        return 1.0
    return float(np.clip(np.sum(ss) / total, COVARIANCE_MIN_FACTOR, 1.0))


MAX_CORRELATION = 0.8   # lag-1 correlation used at most: (1 + ρ) / (1 − ρ) ≤ 9


def _correlation_inflation(p, f, r, keep):
    """Per array (N,): (1 + ρ) / (1 − ρ) for ρ the lag-1 correlation of its kept residual vectors in event order,
    less 1/√n (a white series' spread of it: n = 14 white residuals reach 0.27 one time in six), positive part,
    ≤ MAX_CORRELATION. Errors that drift along the trajectory (a reflection or the robot's
    motion biasing consecutive events alike) are not independent: n such rows carry the information of about
    n (1 − ρ) / (1 + ρ) independent ones (the variance of a mean of an AR(1) series), which the covariance
    would otherwise claim n times over. A fit leaves white residuals slightly anti-correlated, so clean rows
    stay at 1."""
    rows = p.rows(f.kind)
    order = rows.a if hasattr(rows, "a") else rows.ev
    R = r.reshape(len(order), f.dim)
    if f.kind == "doa":   # each row whitened along its own axes: compare them in the array frame
        R = np.einsum("kba,kb->ka", p.doa.axes, R)
    k = keep.reshape(len(order), f.dim).all(axis=1)
    out = np.ones(p.N)
    for i in np.unique(rows.arr[k]):
        m = np.flatnonzero(k & (rows.arr == i))
        x = R[m[np.argsort(order[m], kind="stable")]]
        if len(x) < 4:
            continue
        x = x - x.mean(axis=0)
        rho = float(np.sum(x[1:] * x[:-1]) / max(float(np.sum(x * x)), 1e-300))
        rho = min(max(rho - 1.0 / np.sqrt(len(x)), 0.0), MAX_CORRELATION)   # beyond a white series' spread
        out[i] = (1.0 + rho) / (1.0 - rho)
    return out

