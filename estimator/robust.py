"""Outliers over every measurement type: normalised residual tests, one row at a time, and per-array tests.

A *measurement* is one CSV row: a TDOA (1 residual), a DOA (3 residual components, 2 degrees of freedom:
the unit-vector residual has no noise along the direction itself) or an odometry step (3 components).
Its test statistic is the squared residual normalised by its *own* variance from the hat matrix,
``q = rᵀ (I − H_gg)⁻¹ r`` (``H = J (JᵀJ)⁻¹ Jᵀ`` of the whitened Jacobian, ``H_gg`` its block for the
measurement), which is χ²(dof) when the model and the sigmas hold. A measurement that the parameters fit
exactly (1 − h ≈ 0) cannot be tested and gets q = 0.

Each measurement type's statistics are divided by a robust variance factor ``v_k = max(1, median(q) /
median(χ²_dof))`` (sigmas stated too small do not turn every row into an outlier) and turned into the
two-sided normal z with the same tail probability. :func:`remove_outliers` removes the single worst
measurement while its z exceeds ``max(threshold, Bonferroni z at FAMILY_ALPHA over all measurements)``,
re-solves warm and repeats, so gross errors are taken out one by one and a good row is never condemned
for the pull of a bad one.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import scipy.linalg
import scipy.sparse
from scipy.special import gammaincc, gammainccinv, gammaln, ndtri


from .factors import KINDS
from .problem import make_layout
from .solver import cholesky_solve, levenberg_marquardt, linearise, use_dense

FAMILY_ALPHA = 0.01          # family-wise false-alarm rate of the outlier test (Bonferroni over measurements)
MAX_OUTLIER_FRACTION = 0.3   # the row-wise removal stops after this fraction of the measurements
UNTESTABLE = 1e-6            # 1 − h below this: the row is fitted exactly by its own parameters
ARRAY_RATIO = 9.0            # an array whose median statistic of one type is 9× (3× in σ) the pooled median
# large problems remove this share of the rows beyond the outlier level per re-solve (the worst first)
LARGE_BATCH_SHARE = 0.5
ARRAY_MIN_ROWS = 4           # ... over at least this many rows of that type is a candidate for the drop test
# An array holding most of the rows beyond the outlier level (at least CONCENTRATED_MIN of them, a
# CONCENTRATED_SHARE of all, CONCENTRATED_OWN of its own rows) may be biased as a whole (occluded: a
# reflection for every direct path). It partly fits its biased rows by moving itself and the sources, so
# its median statistic stays low and only its worst rows stand out; it gets the drop test too, and the
# verdict names it.
CONCENTRATED_MIN = 4
CONCENTRATED_SHARE = 0.5
CONCENTRATED_OWN = 0.1


@dataclass
class MeasurementStats:
    """Per-measurement test statistics at a state (only the kinds with ``dof``: :func:`tested_kinds`).

    kind (M,) str, index (M,) measurement index within its factor, line (M,) CSV line, array (M,) array index
    (-1 for odometry), event (M,) event index, q (M,) χ² statistic, dof (M,), kept (M,) bool (not masked),
    z (M,) equivalent two-sided normal z after the per-type robust variance factor (excluded rows: of
    their deletion residual, prediction variance I + H),
    natural (M,) residual in natural units (µs signed for TDOAs; |·| in deg / cm for DOA / odometry), scale {kind: robust variance factor}.
    """
    kind: np.ndarray
    index: np.ndarray
    line: np.ndarray
    array: np.ndarray
    event: np.ndarray
    q: np.ndarray
    dof: np.ndarray
    kept: np.ndarray
    z: np.ndarray
    natural: np.ndarray
    scale: dict


def tested_kinds():
    """The kinds the outlier tests cover (a ``dof`` in their spec), in registry order."""
    return [k for k, spec in KINDS.items() if spec.dof is not None]


def per_array_kinds():
    """The tested kinds measured per array (rows with ``arr``), in registry order."""
    return [k for k in tested_kinds() if KINDS[k].per_array]


def n_measurements(p, kind):
    """Number of measurements of ``kind``: its rows, or for a per-event kind its steps (odometry)."""
    return len(p.rows(kind)) if KINDS[kind].per_array else max(p.K - 1, 0)


def measurement_arrays(p, f):
    """(array index (m,), event index (m,)) of each measurement of factor ``f`` (-1 array for a per-event
    kind, whose factor rows are the event of each step)."""
    if KINDS[f.kind].per_array:
        rows = p.rows(f.kind)
        return rows.arr, rows.event
    return np.full(len(f.r) // f.dim, -1), np.asarray(f.row)[::f.dim]


def _hat_factor(J, keep):
    """(B, Js): Jacobi-scaled J (all rows) and B = Js (JsₖᵀJsₖ)⁺ over the kept rows k; H_ab = B_a · Js_b."""
    Jk = J[keep]
    d = np.linalg.norm(Jk, axis=0)
    d = np.where(d > 0, d, 1.0)
    Js = J / d
    return Js @ sym_inverse(Js[keep].T @ Js[keep]), Js


def sym_inverse(H):
    """Inverse of a symmetric positive semi-definite matrix: Cholesky when definite (the same values as
    ``cho_factor``/``cho_solve``), else pseudo-inverse."""
    H = np.asarray(H, float)
    x = cholesky_solve(H, np.eye(len(H)))
    return x if x is not None else np.linalg.pinv(H, hermitian=True)


def measurement_stats(p, st, lay, kinds, mask):
    """Test statistics of every measurement at ``st`` with the outlier ``mask`` (kind → keep per residual)."""
    lin = linearise(p, st, lay, kinds, mask=mask)
    r, J, w, fs = lin.r, lin.J, lin.w, lin.factors
    keep_rows = w > 0
    # residuals of excluded rows too (linearise zeroes them): the restore test needs them
    r = np.concatenate([f.r for f in fs]) if fs else r
    out = {k: [] for k in ("kind", "index", "line", "array", "event", "q", "dof", "kept", "natural")}
    start = 0
    blocks = []
    for f in fs:
        n = len(f.r)
        sl0, start = start, start + n
        if KINDS[f.kind].dof is None or n == 0:
            continue
        dim = f.dim
        m = n // dim
        groups = sl0 + np.arange(n).reshape(m, dim)
        blocks.append((f, groups, dim, m))
    # Large problems (sparse J): the leverage H_gg is neglected. Their mean leverage is n / rows (about 0.02
    # at 40 arrays × 1000 events), so q is biased by that fraction at most, and a dense hat matrix would
    # need rows × n memory.
    large = scipy.sparse.issparse(J)
    B, Js = _hat_factor(J, keep_rows) if blocks and not large else (None, None)
    for f, groups, dim, m in blocks:
        H = np.zeros((m, dim, dim)) if large else np.einsum("gin,gjn->gij", B[groups], Js[groups])
        rg = f.r.reshape(m, dim)
        kept = keep_rows[groups[:, 0]]
        # kept rows: residual variance I − H; excluded rows: prediction variance I + H (deletion residual)
        if dim == 1:
            den = 1.0 + np.where(kept, -1.0, 1.0) * H[:, 0, 0]
            q = np.where(den > UNTESTABLE, rg[:, 0] ** 2 / np.maximum(den, UNTESTABLE), 0.0)
        else:
            q = _block_quadratic(H, kept, rg)
        arr, ev = measurement_arrays(p, f)
        unit_scale = KINDS[f.kind].scale
        nat = rg[:, 0] if dim == 1 else np.linalg.norm(rg, axis=1)   # signed for scalar measurements
        out["kind"].append(np.full(m, f.kind, dtype=object))
        out["index"].append(np.arange(m))
        out["line"].append(np.asarray(f.row).reshape(m, dim)[:, 0] if len(f.row) else np.zeros(m, int))
        out["array"].append(np.asarray(arr, int))
        out["event"].append(np.asarray(ev, int))
        out["q"].append(q)
        out["dof"].append(np.full(m, KINDS[f.kind].dof))
        out["kept"].append(kept)
        out["natural"].append(nat * np.broadcast_to(f.row_sigma, rg.size)[::dim] * unit_scale)
    if not out["q"]:
        e = np.zeros(0)
        return MeasurementStats(e.astype(object), e.astype(int), e.astype(int), e.astype(int), e.astype(int), e, e,
                                e.astype(bool), e, e, {})
    cat = {k: np.concatenate(v) for k, v in out.items()}
    z, scale = _normal_scores(cat["kind"], cat["q"], cat["dof"], cat["kept"])
    return MeasurementStats(z=z, scale=scale, **cat)


def _block_quadratic(H, kept, r):
    """rᵀ (I ∓ H)⁻¹ r per block (G, d, d) of leverages H, residuals (G, d): − for kept rows (residual variance),
    + for excluded ones (deletion residual). A hat block's eigenvalues lie in [0, 1]; they are clipped there
    (an ill-conditioned solve's pseudo-inverse gave 1.006, a negative q and NaN sigmas), and the directions
    a kept row's own parameters fit exactly (1 − λ ≤ UNTESTABLE) are untested, as a scalar row's. A DOA's
    direction along the prediction has H ≈ 0 and r ≈ 0."""
    lam, V = np.linalg.eigh(0.5 * (H + np.swapaxes(H, 1, 2)))
    lam = np.clip(np.nan_to_num(lam), 0.0, 1.0)
    den = 1.0 + np.where(kept, -1.0, 1.0)[:, None] * lam
    proj = np.einsum("gij,gi->gj", V, r)   # r in the block's eigenbasis
    return np.sum(np.where(den > UNTESTABLE, proj**2 / np.maximum(den, UNTESTABLE), 0.0), axis=1)


def _normal_scores(kind, q, dof, kept):
    """Equivalent two-sided normal z of each q after its type's robust variance factor; the factors."""
    z = np.zeros(len(q))
    scale = {}
    for k in _kinds(kind):
        m = (kind == k) & kept
        if not m.any():
            continue
        d = int(dof[m][0])
        v = max(1.0, float(np.median(q[m])) / chi2_median(d))
        scale[str(k)] = v
        a = kind == k                      # excluded rows are scored in the kept rows' units
        z[a] = _z_from_logp(chi2_logsf(q[a] / v, d))
    return z, scale


def _kinds(kind):
    """The distinct values of a kind label array, sorted (as np.unique, without sorting every row)."""
    return np.array(sorted(set(kind.tolist())), dtype=kind.dtype)


def chi2_median(dof):
    """Median of χ²(dof)."""
    return float(2.0 * gammainccinv(dof / 2.0, 0.5))


def chi2_logsf(q, dof):
    """log P(χ²(dof) > q), finite far into the tail (asymptotic form where the survival underflows)."""
    q = np.maximum(np.asarray(q, float), 0.0)
    sf = gammaincc(dof / 2.0, q / 2.0)
    out = np.log(np.maximum(sf, 1e-300))
    far = ~(sf > 1e-300)
    if np.any(far):   # the asymptotic tail only where the survival underflows
        qf, df = (np.broadcast_to(v, np.shape(sf))[far] for v in (q, np.asarray(dof, float)))
        out = np.array(out, float)
        out[far] = (df / 2.0 - 1.0) * np.log(np.maximum(qf / 2.0, 1e-300)) - qf / 2.0 - gammaln(df / 2.0)
    return out[()] if np.ndim(out) == 0 else out


def _z_from_logp(logp):
    """Two-sided normal z with tail probability exp(logp) (finite for any logp)."""
    p = np.exp(logp)
    z = -ndtri(np.clip(p, 1e-300, 1.0) / 2.0)
    # beyond double precision: the asymptotic inverse of the normal tail, z ≈ sqrt(−2 log p)
    return np.where(p > 1e-300, z, np.sqrt(-2.0 * (logp - np.log(2.0))))


def variance_factors(stats):
    """{kind: Σ q / Σ dof over the kept rows}: each type's residual variance in units of its sigma²."""
    out = {}
    for k in _kinds(stats.kind):
        m = stats.kept & (stats.kind == k)
        if m.any():
            out[str(k)] = float(np.sum(stats.q[m]) / np.sum(stats.dof[m]))
    return out


def critical_z(threshold, n_tests, alpha=FAMILY_ALPHA):
    """Rejection level: the larger of ``threshold`` and the Bonferroni z at family-wise ``alpha``."""
    return max(float(threshold), float(-ndtri(alpha / (2.0 * max(n_tests, 1)))))


def _mask_measurement(mask, f_len, kind, index, dim):
    keep = mask.get(kind)
    if keep is None:
        keep = np.ones(f_len, bool)
    keep = keep.copy()
    keep[index * dim:(index + 1) * dim] = False
    mask[kind] = keep
    return mask


def flag_record(p, stats, k, reason="normalised residual"):
    """One ``report.json: outliers`` entry for measurement k of ``stats``."""
    kind = str(stats.kind[k])
    a = int(stats.array[k])
    rec = {"type": kind, "line": int(stats.line[k]), "array": str(p.names[a]) if a >= 0 else None,
           "event": int(p.events[stats.event[k]]),
           "residual_sigma": float(np.sign(stats.natural[k]) * min(stats.z[k], 1e6)),
           "residual": float(stats.natural[k]), "unit": KINDS[kind].unit.replace("us", "µs"), "reason": reason}
    if KINDS[kind].unit == "us":
        rec["residual_us"] = float(stats.natural[k])
    return rec


def factor_sizes(p):
    """{kind: (number of residuals, residuals per measurement)} of the tested factors, from the problem."""
    return {k: (KINDS[k].dim * n_measurements(p, k), KINDS[k].dim) for k in tested_kinds()}


def count_measurements(p, exclude_arrays=()):
    """Number of tested measurements (TDOA rows, DOAs, odometry steps), leaving out ``exclude_arrays``."""
    n = 0
    for kind in tested_kinds():
        if not KINDS[kind].per_array:
            n += n_measurements(p, kind)
            continue
        arr = p.rows(kind).arr
        # nothing excluded (the common case): every row counts, without np.isin's set machinery
        n += int(np.sum(~np.isin(arr, list(exclude_arrays)))) if len(exclude_arrays) else int(np.size(arr))
    return n


class Removal(NamedTuple):
    """:func:`remove_outliers`'s outcome: the state, the mask (kind → keep per residual), the flag records,
    the info of the last solve (None: none ran), the statistics at the end (None when a solve followed
    them) and whether the removal stopped at its cap."""
    state: Any
    mask: dict
    flagged: list
    info: dict | None
    stats: Any
    capped: bool


def remove_outliers(p, st, lay, kinds, mask, *, threshold, loss, k, max_iter, exclude_arrays=(),
                    max_fraction=MAX_OUTLIER_FRACTION, stats=None):
    """Remove the single worst measurement while it is an outlier, re-solving (warm start) after each.

    ``mask``: kind → keep (per residual), updated copy returned. ``exclude_arrays``: array indices whose
    rows are already dropped (not counted). Returns a :class:`Removal`. ``stats``: the statistics at
    (st, mask) when already known.
    """
    mask = {kk: v.copy() for kk, v in mask.items()}
    sizes = factor_sizes(p)
    flagged, info, capped = [], None, False
    while True:
        stats = measurement_stats(p, st, lay, kinds, mask) if stats is None else stats
        live = stats.kept & ~np.isin(stats.array, list(exclude_arrays)) if len(exclude_arrays) else stats.kept.copy()
        n_tests = int(live.sum())
        if n_tests == 0:
            break
        zc = critical_z(threshold, n_tests)
        zl = np.where(live, stats.z, -np.inf)
        order = np.argsort(zl)[::-1]
        n_out = int(np.sum(zl > zc))
        if n_out == 0:
            break
        if len(flagged) >= max_fraction * (n_tests + len(flagged)):
            capped = True
            break
        # one row per re-solve; large problems (low leverage, many rows) a batch of the worst per re-solve
        batch = 1 if use_dense(lay) else max(1, int(np.ceil(LARGE_BATCH_SHARE * n_out)))
        for worst in order[:batch]:
            flagged.append(flag_record(p, stats, int(worst)))
            kind = str(stats.kind[worst])
            mask = _mask_measurement(mask, sizes[kind][0], kind, int(stats.index[worst]), sizes[kind][1])
        st, info = levenberg_marquardt(p, st, lay, kinds, loss=loss, k=k, mask=mask, max_iter=max_iter, rtol=1e-6)
        stats = None
    return Removal(st, mask, flagged, info, stats, capped)


def restore_inliers(p, st, lay, kinds, mask, flagged, *, threshold, max_iter):
    """Give back flagged rows that fit the final solution (a bad row can make a good one look worst first).

    One at a time, the flagged row with the smallest deletion-residual z below the rejection level is
    restored and the least-squares solution re-solved (warm). Returns (state, mask, flagged left).
    """
    mask = {kk: v.copy() for kk, v in mask.items()}
    flagged = list(flagged)
    sizes = factor_sizes(p)
    while flagged:
        stats = measurement_stats(p, st, lay, kinds, mask)
        zc = critical_z(threshold, int(stats.kept.sum()))
        pos = []
        for rec in flagged:
            hit = np.flatnonzero((stats.kind == rec["type"]) & (stats.line == rec["line"]) & ~stats.kept)
            pos.append(int(hit[0]) if hit.size else -1)
        zs = np.array([stats.z[k] if k >= 0 else np.inf for k in pos])
        fits = np.flatnonzero(zs < zc)
        if fits.size == 0:
            break
        # the best-fitting row per re-solve; large problems every row that fits (low leverage)
        chosen = fits[np.argsort(zs[fits])][:1] if use_dense(lay) else fits
        for b in chosen:
            k = pos[b]
            kind, dim = str(stats.kind[k]), sizes[str(stats.kind[k])][1]
            keep = mask[kind].copy()
            keep[int(stats.index[k]) * dim:(int(stats.index[k]) + 1) * dim] = True
            mask[kind] = keep
        flagged = [rec for b, rec in enumerate(flagged) if b not in set(chosen.tolist())]
        st, _ = levenberg_marquardt(p, st, lay, kinds, loss=None, mask=mask, max_iter=max_iter, rtol=1e-6)
    return st, mask, flagged


def array_mask(p, mask, sizes, i):
    """``mask`` with every measurement of array i excluded (its rows of every per-array kind)."""
    out = {kk: v.copy() for kk, v in mask.items()}
    for kind in per_array_kinds():
        dim = KINDS[kind].dim
        keep = out.get(kind, np.ones(sizes[kind][0], bool)).copy()
        keep &= np.repeat(p.rows(kind).arr != i, dim)
        out[kind] = keep
    return out


def array_candidates(p, stats, ratio=ARRAY_RATIO, min_rows=ARRAY_MIN_ROWS):
    """Arrays whose measurements of some type are jointly inconsistent with the rest (median statistic).

    For each type, the median of q/median(χ²_dof) over each array's kept rows is compared with the
    median over all arrays' rows of that type; an array above ``ratio`` times that (and above ``ratio``
    absolutely, in units of the stated variance) is a candidate. Medians ignore the odd outlier row.
    Returns a list of (array index, {kind: ratio}) sorted by the largest ratio, worst first.
    """
    out = {}
    for kind in per_array_kinds():
        m = stats.kept & (stats.kind == kind)
        if m.sum() < 2 * min_rows:
            continue
        qn = stats.q[m] / chi2_median(KINDS[kind].dof)
        pooled = max(float(np.median(qn)), 1.0)
        arr = stats.array[m]
        for i in np.unique(arr):
            if i == p.ref and kind == "tdoa_m":
                continue
            qi = qn[arr == i]
            if len(qi) < min_rows:
                continue
            rr = float(np.median(qi)) / pooled
            if rr > ratio:
                out.setdefault(int(i), {})[kind] = rr
    return sorted(out.items(), key=lambda t: -max(t[1].values()))


def is_concentrated(k, total, n_rows):
    """The CONCENTRATED_* rule: an array with ``k`` of ``total`` outlier rows and ``n_rows`` rows of its own."""
    return k >= CONCENTRATED_MIN and k >= CONCENTRATED_SHARE * total and k >= CONCENTRATED_OWN * n_rows


def concentrated_candidates(p, stats, threshold):
    """Arrays (not the reference) holding most of the rows beyond the outlier rejection level at ``stats``
    (``critical_z(threshold, ·)``; :func:`is_concentrated`, before any row is removed): {array index: rows}."""
    live = stats.kept & (stats.array >= 0)
    n_tests = int(stats.kept.sum())
    if n_tests == 0:
        return {}
    beyond = live & (stats.z > critical_z(threshold, n_tests))
    k = np.bincount(stats.array[beyond].astype(int), minlength=p.N)
    n_rows = np.bincount(stats.array[live].astype(int), minlength=p.N)
    total = int(k.sum())
    return {i: int(k[i]) for i in range(p.N) if i != p.ref and is_concentrated(k[i], total, n_rows[i])}


def drop_test(p, st_all, st_without, lay, lay_without, kinds, mask, mask_without, scale):
    """χ² drop when array i's rows are removed, against χ²(m_i − p_i), in the robust variance units.

    Returns (statistic, dof, log p-value).
    """
    lin = linearise(p, st_all, lay, kinds, mask=mask)
    r_a, w_a = lin.r, lin.w
    lin = linearise(p, st_without, lay_without, kinds, mask=mask_without)
    r_w, w_w = lin.r, lin.w
    T = float(np.sum(r_a[w_a > 0] ** 2) - np.sum(r_w[w_w > 0] ** 2))
    m_rows = int((w_a > 0).sum() - (w_w > 0).sum())
    dof = max(m_rows - (lay.n - lay_without.n), 1)
    T /= max(scale, 1.0)
    return T, dof, float(chi2_logsf(max(T, 0.0), dof))


def fit_array_alone(p, st, i, kinds, mask, *, loss, k, max_iter):
    """Array i's pose and clock from its own measurements with every other parameter fixed (robust)."""
    lay_i = make_layout(p, arrays=[i], sources=False, ref_drift=False)
    st_i, info = levenberg_marquardt(p, st, lay_i, kinds, loss=loss, k=k, mask=mask, max_iter=max_iter)
    return st_i, info
