"""Variance components per array: one sigma multiplier per (measurement type, array) where redundancy allows.

Model (docs/method.md, "Weights from the data"): a row of type k measured by array i has the sigma
σ_k · a_{k,i}. σ_k is the type's component (``variance.robust_noise_steps`` / ``estimate_noise``);
a_{k,i} (``p.array_scale[k][i]``, 1 to start) is the array's, for the types measured per array
(TDOA-S, TDOA-M — attributed to the non-reference array of the pair —, DOA, cone). ``factors.evaluate``
divides those rows' residuals and Jacobians by a_{k,i}.

Rule: the components are estimated with the types' in the variance-component steps after the outlier
and array tests (``variance.estimate_noise``, kept rows only). An array gets its own component for a
type only when its rows of that type carry enough redundancy, Σ(1 − h_ii) ≥ ARRAY_MIN_REDUNDANCY (h the
hat matrix's diagonal, as for the types), and when its factor is significantly above the type's pooled
one (χ²(redundancy) upper tail at ARRAY_ALPHA, Bonferroni-corrected over the arrays tested), so an array
is not re-weighted by the scatter of a dozen residuals: unconditional per-array factors made the positions of clean scenes worse, and a
median-based per-array step before the outlier tests (n ≈ 8–14 rows) gave false factors of 1.5–2 in 6 of
10 clean scenes. Otherwise the array's rows keep their current factor (1 to start). Components only
raise an array's sigma (a ≥ 1): they are for an array worse than the rest; a component below the type's
ran away to its bound (as its weight grows, its own parameters absorb its residuals). Each a stays
within [1, ARRAY_MAX_FACTOR], and σ_k · a_{k,i} within the type's bound around the stated
sigma (``variance.sigma_bounds``: a measured prior is never inflated beyond PRIOR_MAX_FACTOR per array
either).
"""
from __future__ import annotations

import numpy as np
from scipy.special import chdtrc  # χ² survival function (scipy.stats.chi2.sf without importing scipy.stats, ~0.3 s)

from calib.kinds import KINDS

ARRAY_MIN_REDUNDANCY = 5.0    # Σ(1 − h) of an array's rows of one type for its own component
# either way, relative to the type's sigma: covers one array several times noisier than the others, and
# keeps an array whose data are wrong as a whole from being silenced instead of flagged
ARRAY_MAX_FACTOR = 4.0
ARRAY_ALPHA = 0.01            # family level of the tests "this array's noise is above the others'"


def start_scales(p, kinds):
    """A new problem whose ``array_scale`` is a = 1 for every array of each per-array type with rows in ``kinds``."""
    return p.replace(array_scale={k: np.ones(p.N) for k in kinds if KINDS[k].per_array and len(p.rows(k).arr)})


def vce_groups(p, f, r, h, keep):
    """Per array (N,) of factor ``f``'s kept rows (whitened residuals r, leverages h): Σ r² and the
    redundancy Σ(1 − h), and whether its σ² factor Σ r² / Σ(1 − h) is significantly above the type's
    pooled one: χ²(redundancy) upper tail below ARRAY_ALPHA / (arrays tested), redundancy ≥
    ARRAY_MIN_REDUNDANCY."""
    arr = np.repeat(p.rows(f.kind).arr, f.dim)[keep]
    dof = KINDS[f.kind].dof   # e.g. DOA: 2 dof of 3 components
    red_rows = (1.0 - h[keep]) - ((f.dim - dof) / f.dim if dof is not None and dof < f.dim else 0.0)
    red = np.bincount(arr, weights=red_rows, minlength=p.N)
    ss = np.bincount(arr, weights=r[keep] ** 2, minlength=p.N)
    pooled = ss.sum() / max(red.sum(), 1e-12)
    testable = red >= ARRAY_MIN_REDUNDANCY
    tail = chdtrc(np.maximum(red, 1e-9), ss / max(pooled, 1e-300))   # χ²(red) when its noise is the type's
    return {"ss": ss, "red": red, "significant": testable & (tail < ARRAY_ALPHA / max(int(testable.sum()), 1))}


def own_components(w, kind, groups):
    """Arrays of ``kind`` with their own component: those that had one, plus the newly significant ones
    (``w.array_own``, updated; ``w`` the stage's :class:`~calib.estimator.problem.Weights`). An array keeps
    its own component once it has one."""
    own = w.array_own.get(kind, np.zeros(len(groups["red"]), bool)) | groups["significant"]
    w.array_own[kind] = own
    return own


def type_factor(w, kind, groups, pooled, min_redundancy):
    """The type's σ² factor from the arrays without their own component (``pooled``, the factor over all
    rows, when those carry less than ``min_redundancy``)."""
    rest = ~own_components(w, kind, groups)
    red = float(groups["red"][rest].sum())
    return float(groups["ss"][rest].sum()) / red if red >= min_redundancy else pooled


def update_scales(w, kind, groups, type_step, total, bound):
    """After the type's sigma moved by ``type_step``: each array with its own component gets the sigma its
    rows ask for (σ² × Σ r² / Σ(1 − h)), the others keep the type's (a unchanged; ``w.array_scale``
    updated). ``total``: the type's sigma / stated, ``bound`` its allowed factor either way. Returns the
    arrays' total steps (N,)."""
    a = w.array_scale[kind]
    own = w.array_own[kind] & (groups["red"] > 0)
    new = a.copy()
    f2 = groups["ss"][own] / groups["red"][own]
    new[own] = a[own] * np.sqrt(np.clip(f2, 1e-8, 1e8)) / type_step
    lo = 1.0
    hi = min(ARRAY_MAX_FACTOR, bound / total)
    new = np.clip(new, lo, hi)
    w.array_scale[kind] = new
    return new / a * type_step


def report_scales(p):
    """{kind: {array name: a}} for the report (only arrays whose component moved)."""
    return {k: {str(n): float(v) for n, v in zip(p.names, a) if abs(v - 1.0) > 1e-9}
            for k, a in (p.array_scale or {}).items()}


# ------------------------------------------------------------------------------------ arrival scales
# Each array's arrival sigma relative to the type's (``p.arrival_scale``, a_i: its TDOA-S rows ∝ a_i, its TDOA-M
# rows ∝ √((a_i² + a_ref²) / 2), problem.with_arrival_scale) from its own TDOA-S residuals, both ways. One
# session-wide sigma_tdoa is wrong for every array when boards time their arrivals unequally well: measured
# against the true geometry and clocks, the TDOA-S rows of mixed 90's 6- and 7-mic circles and tetrahedron
# scatter 0.4–0.6 × the session's sigma_tdoa, its 4-mic linear board's 2.2 × and its 2-mic pair's 3.3 ×; in
# talkers 97 a talker near the reference puts its arrivals at 1.4 × and the others' at 0.3 × (the stated stds
# then 4–5 × the errors). The frontend's per-array claims (meta ``sigma_arrival_per_array``) are the prior, worth
# ARRIVAL_PRIOR_DOF residual degrees of freedom; the data move each array from it. The type's own sigma is
# not lowered by this (variance.FRONTEND_MIN_FACTOR): the arrays' relative variances are normalised so that
# their mean over the TDOA-S rows is at least 1, a redistribution of the frontend's figure between arrays.
ARRIVAL_PRIOR_DOF = 4.0
ARRIVAL_MAX_FACTOR = ARRAY_MAX_FACTOR   # either way, relative to the type's sigma


def arrival_variances(v, red, prior, rows_arr):
    """Per array (N,) the relative arrival variance a_i²: its residuals' estimate ``v`` (N,) (relative to the type's
    sigma, :func:`calib.estimator.variance.arrival_components`), worth its redundancy ``red`` (N,), combined
    with the ``prior`` scales c (N,) worth ARRIVAL_PRIOR_DOF: (v red + P c²) / (red + P) where the redundancy is
    at least ARRAY_MIN_REDUNDANCY, else c² (few arrays, rows taken out: the sources take up nearly all of an
    array's arrival errors, Σ(1 − h) 0.01–2 on four-array sessions, and the estimate is noise); then normalised so that
    the mean over the TDOA-S rows (``rows_arr``: their arrays) is at least 1 (never below the type's sigma on
    average) and clipped to [1/ARRIVAL_MAX_FACTOR, ARRIVAL_MAX_FACTOR]²."""
    red = np.maximum(red, 0.0)
    out = np.where(red >= ARRAY_MIN_REDUNDANCY, (v * red + ARRIVAL_PRIOR_DOF * prior**2) / (red + ARRIVAL_PRIOR_DOF),
                   prior**2)
    if len(rows_arr):
        out = out / min(float(np.mean(out[rows_arr])), 1.0)
    return np.clip(out, ARRIVAL_MAX_FACTOR**-2, ARRIVAL_MAX_FACTOR**2)
