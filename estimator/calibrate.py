"""The estimator: initialise → IVE (paper's stage 1) → joint robust NLS → outlier removal → final NLS.

``calibrate(features) -> calibration dict`` is the library entry point; see :func:`calibrate`.
"""
from __future__ import annotations

import time
from typing import Any

import numpy as np
import pandas as pd
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg
from scipy.spatial.transform import Rotation
from threadpoolctl import ThreadpoolController

from calib import __version__
from calib.geometry import mirror
from calib.options import validate_options

from . import arraynoise, clockmodel
from .factors import KINDS, active_kinds, natural
from .init import ObservabilityError, doa_rotation, fold_basins, initialise, kabsch, subproblem
from .observability import check_observability
from .geometry import init_cone_axes
from .odoframe import initial_yaw, rotate_odometry, yaw_is_significant
from .problem import State, build_problem, make_layout, state_from_dict
from .motion import motion_solve
from .screen import distrusted, screen_rows
from .robust import (FAMILY_ALPHA, chi2_median, array_candidates, array_mask, concentrated_candidates, drop_test,
                     fit_array_alone, measurement_stats, count_measurements, factor_sizes, per_array_kinds,
                     variance_factors, remove_outliers, restore_inliers, sym_inverse)
from .solver import levenberg_marquardt, linearise
from .uncertainty import covariance, std_from_cov
from .verdict import MOVE_SIGMA, concentrated_outliers, fold_ambiguity, make_verdict, name_distrusted, residual_ratios, stated_sigma_excess



# The matrices here are tiny (~400 × 100): multi-threaded BLAS only adds synchronisation (measured 4×
# slower on 2 cores), so the estimator runs BLAS single-threaded and parallelism goes across calibrations.
_BLAS = ThreadpoolController()




def undetermined_parameters(p):
    """What the data leave undetermined but the estimator can work around, per parameter (report.json
    ``undetermined``): orientations of arrays with DOAs for fewer than 2 events (single microphones, arrays
    without usable DOAs) are not estimated — kept at identity with NaN std — while their positions and
    clocks come from the TDOAs. Returns a list of {"parameter", "array", "reason"}."""
    out = []
    for i in range(p.N):
        if i != p.ref and p.rot_free[i] and p.rot_fixed_axis[i] >= 0:
            out.append({"parameter": "roll", "array": str(p.names[i]), "axis": p.cone_axis[i].tolist(),
                        "reason": "linear array / mic pair: the rotation about its axis is not observable (not "
                                  "estimated, NaN std); the axis direction is"})
        if i != p.ref and not p.rot_free[i]:
            nd = int(p.n_doa_events[i])
            out.append({"parameter": "orientation", "array": str(p.names[i]),
                        "reason": f"DOAs for {nd} event(s) (>= 2 needed): not estimated, reported as identity "
                                  "with NaN std; position and clock from the TDOAs"})
    return out + list(p.unobservable)   # found by the rank check (observability.py)


def rotations_by_kabsch(p, st):
    """Each non-reference array's rotation by SVD alignment of DOA-scaled points (the paper's IVE step)."""
    for i in range(p.N):
        m = p.doa.arr == i
        if i == p.ref or m.sum() < 2:
            continue
        j = p.doa.ev[m]
        w = st.s[j] - st.x[i]
        d = np.linalg.norm(w, axis=1, keepdims=True)
        u = p.doa.u[m]
        n = p.fold[i]
        if np.any(n):
            # mirror-ambiguous DOAs: decide which events lie behind the mic plane afresh from the IVE's
            # positions and sources, which no longer depend on this array's DOAs
            u = np.where(((w @ doa_rotation(p, st, i, st.x[i])) @ n < 0)[:, None], mirror(u, n), u)
        st.R[i], _ = kabsch(u * d, w)
    return st


def residual_table(fs, mask=None):
    """Per measurement type: count, RMS in natural units (µs, deg, cm)."""
    out = {}
    for f in fs:
        if len(f.r) == 0:
            continue
        keep = mask[f.kind] if mask and f.kind in mask else np.ones(len(f.r), bool)
        r = natural(f)[keep]
        if f.dim == 3:
            r = np.linalg.norm(r.reshape(-1, 3), axis=1)
        unit, scale = KINDS[f.kind].unit, KINDS[f.kind].scale
        out[f.kind] = {"n": int(len(r)), f"rms_{unit}": float(np.sqrt(np.mean(r * r)) * scale) if len(r) else 0.0}
    return out


def _quaternions(R):
    """(N, 4) scalar-first unit quaternions of rotation matrices (N, 3, 3), with qw >= 0."""
    q = Rotation.from_matrix(R).as_quat(scalar_first=True)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q


def to_tables(p, st):
    """State → the plain tables scoring reads (``pipeline.report.evaluate.array_table`` / ``source_table``):
    the values :func:`to_frames` would put in its DataFrames, without building them (the Monte-Carlo study
    scores every run and stage)."""
    arrays = {"names": list(p.names), "xyz": st.x, "quat": _quaternions(st.R), "offset": st.offset,
              "drift": st.drift}
    return arrays, {"event": np.asarray(p.events), "xyz": st.s}


def to_frames(p, st, std=None):
    """State (+ std) → arrays and sources DataFrames of docs/formats.md section 3."""
    a, s = to_tables(p, st)
    arrays = {"array": a["names"], **{c: a["xyz"][:, k] for k, c in enumerate("xyz")},
              **{c: a["quat"][:, k] for k, c in enumerate(("qw", "qx", "qy", "qz"))},
              "offset": a["offset"], "drift": a["drift"]}
    sources = {"event": s["event"], **{c: s["xyz"][:, k] for k, c in enumerate("xyz")}}
    if std is not None:   # the columns collected first: one DataFrame each (a column insert costs ~0.1 ms)
        arrays.update({f"{c}_std": std["x"][:, k] for k, c in enumerate("xyz")})
        arrays.update({f"r{c}_std": std["rot"][:, k] for k, c in enumerate("xyz")})
        arrays.update({"offset_std": std["offset"], "drift_std": std["drift"]})
        sources.update({f"{c}_std": std["s"][:, k] for k, c in enumerate("xyz")})
    return pd.DataFrame(arrays), pd.DataFrame(sources)


def solve_from(p, st, *, kinds, loss="cauchy", robust_k=3.0, outlier_threshold=5.0, max_iter=200,
               check_arrays=True, noise_bounds=None, noise_floors=None):
    """Joint NLS from a given state: robust pass → inconsistent arrays → outlier rows → plain least squares.

    ``noise_bounds`` ({kind: factor}, noise="estimate"): first move the sigmas by the medians of the
    residual statistics (:func:`robust_noise_steps`; ``noise_floors``: {kind: the largest factor a sigma may
    be lowered by}, default the bound). ``p`` is updated in place (sigmas, ``odo_yaw_free``).

    Returns (state, info); info holds ``robust``/``final`` solver infos, ``mask`` (kind → keep per
    residual), ``outliers`` (flag records), ``layout``, ``arrays`` (per-array consistency results),
    ``capped`` (the row-wise removal hit its cap) and ``n_measurements``.
    """
    lay = make_layout(p)
    info = {"arrays": [], "capped": False, "stats": None}
    # the robust pass only has to find the basin and the outliers; the final pass converges tightly
    st, info["robust"] = levenberg_marquardt(p, st, lay, kinds, loss=loss, k=robust_k, max_iter=max_iter,
                                             rtol=1e-6)
    info["yaw_test"] = p.odo_yaw_test
    if noise_bounds is not None and loss:
        stated = {k: p.sigma[k] for k in reweighted()}
        st = robust_noise_steps(p, st, lay, kinds, bounds=noise_bounds, stated=stated, loss=loss,
                                robust_k=robust_k, max_iter=max_iter, floors=noise_floors)
    if lay.odo_yaw[0] >= 0 and info["yaw_test"] is None:
        st, lay, info["yaw_test"] = _odometry_yaw_test(p, st, lay, kinds, loss=loss, robust_k=robust_k,
                                                       max_iter=max_iter)
    mask, flagged, dropped = {}, [], []
    if loss:
        if check_arrays:
            st, lay, mask, dropped, info["arrays"], stats = consistency_stage(
                p, st, lay, kinds, mask, loss=loss, robust_k=robust_k, max_iter=max_iter,
                threshold=outlier_threshold)
        st, mask, flagged, _, _, cap1 = remove_outliers(p, st, lay, kinds, mask, threshold=outlier_threshold,
                                                        loss=loss, k=robust_k, max_iter=max_iter,
                                                        stats=stats if check_arrays and not dropped else None)
        st, info["final"] = levenberg_marquardt(p, st, lay, kinds, loss=None, mask=mask, max_iter=max_iter)
        # outliers that only show at the least-squares solution (the robust loss hid their pull)
        st, mask, more, _, stats_b, cap2 = remove_outliers(p, st, lay, kinds, mask, threshold=outlier_threshold,
                                                           loss=None, k=robust_k, max_iter=max_iter)
        info["capped"] = cap1 or cap2
        n_flagged = len(flagged) + len(more)
        st, mask, flagged = restore_inliers(p, st, lay, kinds, mask, flagged + more, threshold=outlier_threshold,
                                            max_iter=max_iter)
        if more or len(flagged) < n_flagged:
            st, info["final"] = levenberg_marquardt(p, st, lay, kinds, loss=None, mask=mask, max_iter=max_iter)
        else:
            info["stats"] = stats_b   # the statistics at the final state (for the verdict)
    else:
        st, info["final"] = levenberg_marquardt(p, st, lay, kinds, loss=None, mask=mask, max_iter=max_iter)
    info["n_measurements"] = count_measurements(p, dropped)
    for i in dropped:
        # the dropped array's own pose and clock from its data, everything else fixed (marked unreliable)
        st, _ = fit_array_alone(p, st, i, kinds, {}, loss=loss, k=robust_k, max_iter=max_iter)
    info["mask"], info["outliers"], info["layout"], info["dropped"] = mask, flagged, lay, dropped
    return st, info


ROBUST_VCE_STEPS = 2   # median-based sigma steps before the outlier tests (noise="estimate")


def robust_noise_steps(p, st, lay, kinds, *, bounds, stated, loss, robust_k, max_iter, steps=ROBUST_VCE_STEPS,
                       floors=None):
    """Sigmas from the median of each type's normalised statistics (outliers do not move a median), so
    the outlier tests and the robust loss work in the data's own noise units. Updates p in place."""
    for _ in range(steps):
        stats = measurement_stats(p, st, lay, kinds, {})
        changed = False
        for kind in reweighted():
            m = stats.kept & (stats.kind == kind)
            if m.sum() < 5:
                continue
            f = float(np.sqrt(np.median(stats.q[m]) / chi2_median(KINDS[kind].dof)))
            b = bounds.get(kind, FREE_MAX_FACTOR)
            lo = (floors or bounds).get(kind, b)
            new = float(np.clip(p.sigma[kind] * f, stated[kind] / lo, stated[kind] * b))
            changed |= abs(new / p.sigma[kind] - 1.0) > 0.05
            p.sigma[kind] = new
        if not changed:
            break
        st, _ = levenberg_marquardt(p, st, lay, kinds, loss=loss, k=robust_k, max_iter=max_iter, rtol=1e-6)
    return st


def _rows_per_array(p):
    """{array name: number of its measurement rows (of every per-array kind)}."""
    cols = [p.rows(k).arr for k in per_array_kinds()]
    counts = np.bincount(np.concatenate(cols).astype(int), minlength=p.N)
    return {str(n): int(k) for n, k in zip(p.names, counts)}


def _odometry_yaw_test(p, st, lay, kinds, *, loss, robust_k, max_iter):
    """Keep the odometry yaw free only when significant (``odoframe.YAW_SIGNIFICANCE``); else fix it at 0
    (sets ``p.odo_yaw_free = False``) and re-solve. Returns (state, layout, {yaw_deg, std_deg, kept})."""
    lin = linearise(p, st, lay, kinds, loss=loss, k=robust_k)
    J, w = lin.J, lin.w
    test = _yaw_decision(p, st, whiten(J, w), int(lay.odo_yaw[0]))
    if not test["kept"]:
        lay = make_layout(p)
        st, _ = levenberg_marquardt(p, st, lay, kinds, loss=loss, k=robust_k, max_iter=max_iter, rtol=1e-6)
    return st, lay, test


def _yaw_decision(p, st, Jw, k):
    """Test the odometry yaw (column k of the whitened Jacobian Jw); when not significant fix it: sets
    ``p.odo_yaw_free = False`` and ``st.odo_yaw = 0`` in place. Returns {yaw_deg, std_deg, kept}."""
    yaw, sd = float(st.odo_yaw[0]), _param_std(Jw, k)
    test = {"yaw_deg": float(np.rad2deg(yaw)), "std_deg": float(np.rad2deg(sd)), "kept": yaw_is_significant(yaw, sd)}
    if not test["kept"]:
        p.odo_yaw_free = False
        st.odo_yaw = np.zeros(1)
    return test


def whiten(J, w):
    """Rows of J scaled by sqrt(w) (IRLS weights), dense or sparse alike."""
    if scipy.sparse.issparse(J):
        return (scipy.sparse.diags(np.sqrt(w)) @ J).tocsr()
    return J * np.sqrt(w)[:, None]


def _param_std(J, k):
    """1-σ of parameter k from whitened J: sqrt((JᵀJ)⁻¹_kk) by one Cholesky solve (pinv if singular);
    a sparse J by one sparse LU solve."""
    if scipy.sparse.issparse(J):
        d = np.sqrt(np.asarray(J.multiply(J).sum(axis=0)).ravel())
        d = np.where(d > 0, d, 1.0)
        Js = (J @ scipy.sparse.diags(1.0 / d)).tocsc()
        e = np.zeros(J.shape[1])
        e[k] = 1.0
        x = scipy.sparse.linalg.splu((Js.T @ Js).tocsc()).solve(e)
        return float(np.sqrt(max(x[k], 0.0)) / d[k])
    d = np.linalg.norm(J, axis=0)
    d = np.where(d > 0, d, 1.0)
    Js = J / d
    e = np.zeros(J.shape[1])
    e[k] = 1.0
    try:
        x = scipy.linalg.cho_solve(scipy.linalg.cho_factor(Js.T @ Js), e)
    except np.linalg.LinAlgError:
        x = np.linalg.pinv(Js.T @ Js) @ e
    return float(np.sqrt(max(x[k], 0.0)) / d[k])


def consistency_stage(p, st, lay, kinds, mask, *, loss, robust_k, max_iter, threshold=5.0):
    """Per-array consistency: for each candidate array (``robust.array_candidates``, then
    ``robust.concentrated_candidates`` at the outlier ``threshold``), re-solve without it and keep the drop
    when the χ² drop test rejects it at FAMILY_ALPHA / N (a concentrated candidate only when dropping it
    also moves the rest by more than MOVE_SIGMA: its data bend the others' solution, as an occluded
    array's reflections do; otherwise its outlier rows are removed one by one as any others).

    Returns (state, layout, mask, dropped array indices, per-candidate records for the report, the
    statistics at the input state).
    """
    sizes = factor_sizes(p)
    stats = measurement_stats(p, st, lay, kinds, mask)
    records, dropped = [], []
    # (array, median ratios, outlier rows if it is a candidate only for holding most of them)
    cands = [(i, ratios, None) for i, ratios in array_candidates(p, stats)]
    listed = {i for i, _, _ in cands}
    cands += [(i, {}, k) for i, k in concentrated_candidates(p, stats, threshold).items() if i not in listed]
    for i, ratios, rows in cands:
        if len(dropped) + 2 >= p.N:
            break                      # keep the reference and at least one other array
        keep_arr = [a for a in range(p.N) if a != i and a not in dropped]
        lay_w = make_layout(p, arrays=keep_arr)
        mask_w = array_mask(p, mask, sizes, i)
        st_w, _ = levenberg_marquardt(p, st, lay_w, kinds, loss=loss, k=robust_k, mask=mask_w, max_iter=max_iter,
                                      rtol=1e-6)
        T, dof, logp = drop_test(p, st, st_w, lay, lay_w, kinds, mask, mask_w, 1.0)
        inconsistent = bool(logp < np.log(FAMILY_ALPHA / p.N))
        rec = {"array": str(p.names[i]), "median_ratio": {k: float(v) for k, v in ratios.items()},
               **({"outlier_rows": int(rows)} if rows is not None else {}),
               "drop_chi2": T, "drop_dof": dof, "inconsistent": inconsistent}
        if inconsistent:
            rec["moves_sigma"] = _moves_sigma(p, st, st_w, lay_w, kinds, mask_w)
        if inconsistent and rows is not None and rec["moves_sigma"] <= MOVE_SIGMA:
            # its worst rows stand out but the rest hardly depends on it: kept (its outliers go row by row)
            inconsistent = rec["inconsistent"] = False
        if inconsistent:
            rec["with_array"] = {"x": st.x.tolist()}
            st, lay, mask = st_w, lay_w, mask_w
            dropped.append(i)
        records.append(rec)
    return st, lay, mask, dropped, records, stats


def _moves_sigma(p, st_a, st_b, lay, kinds, mask):
    """Largest move of any free array position or source between two states, in 1-σ of state b."""
    lin = linearise(p, st_b, lay, kinds, mask=mask)
    J, w = lin.J, lin.w
    std = std_from_cov(p, lay, covariance(J[w > 0], lay.n, lay))
    z = []
    for key in ("x", "s"):
        free = getattr(lay, key) >= 0
        z.append(np.abs(getattr(st_a, key) - getattr(st_b, key))[free] / np.maximum(std[key][free], 1e-12))
    z = np.concatenate(z)
    return float(z.max()) if z.size else 0.0


def reweighted():
    """The kinds whose sigma the data may re-weight (``reweight`` in their spec), in registry order."""
    return [k for k, spec in KINDS.items() if spec.reweight]


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



def _row_scale_summary(scale):
    """report.json ``sigmas.doa_row_scale``: how the DOA rows' own sigmas (doa.csv ``sigma_deg``) spread
    their weights — rows weighted and the min / median / max of their scale — or None when none is."""
    own = scale[scale != 1.0]
    if not own.size:
        return None
    return {"rows": int(own.size), "min": float(own.min()), "median": float(np.median(own)), "max": float(own.max())}


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


def _vce_factors(p, st, lay, kinds, mask, min_redundancy, cov=None, arrays=None, redundancy=None):
    """One variance-component step: {kind: Σ_k r² / Σ_k (1 − h_ii)} for types with enough redundancy.

    ``cov``: (JᵀJ)⁻¹ at (st, lay, mask) when already computed. ``arrays`` (dict): filled with the
    per-array factors {kind: (N,)} of the types with per-array components (``arraynoise.vce_groups``).
    ``redundancy`` (dict): filled with each type's Σ_k (1 − h_ii) if given.
    """
    lin = linearise(p, st, lay, kinds, mask=mask)
    r, J, w, fs = lin.r, lin.J, lin.w, lin.factors
    keep = w > 0
    Jk = J[keep]
    h = np.zeros(len(r))
    if scipy.sparse.issparse(J):
        pass  # large problems: leverage neglected (mean n / rows ≈ 0.02 there; see robust.measurement_stats)
    elif cov is None or not isinstance(cov, np.ndarray):
        d = np.linalg.norm(Jk, axis=0)
        d = np.where(d > 0, d, 1.0)
        A = sym_inverse((Jk / d).T @ (Jk / d))
        h[keep] = np.einsum("ij,jk,ik->i", Jk / d, A, Jk / d)
    else:
        h[keep] = np.einsum("ij,jk,ik->i", Jk, cov, Jk)
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
    within [1/floors[k], bounds[k]] of ``stated`` (floors default to the bounds) (default: p's sigmas; see :func:`sigma_bounds`). Iterated while stable: at most
    ``iterations`` steps, stopping when every step factor is within 1 % of 1, or when a type's factor
    reverses direction (a type the parameters can absorb would otherwise shrink without bound).
    Returns (state, p with new sigmas, info with the total scales and which types hit their bound).
    """
    p = p.copy()   # (copies the sigmas and per-array components: the caller's problem is not changed)
    if p.array_scale:
        p.array_own = {}
    lay = lay or make_layout(p)
    bounds = bounds or {k: FREE_MAX_FACTOR for k in reweighted()}
    base = stated or {k: p.sigma[k] for k in reweighted()}
    scales = {k: p.sigma[k] / base[k] for k in reweighted()}
    last_dir = {}
    info, at_bound = {}, {}
    steps = max(iterations, VCE_ITERATIONS_ARRAYS) if p.array_scale else iterations
    for it in range(steps):
        per_array = {}
        fac = _vce_factors(p, st, lay, kinds, mask, min_redundancy, arrays=per_array)
        changed, reversed_ = False, False
        for kind, f2 in fac.items():
            own = kind in per_array and bool(np.any(arraynoise.own_components(p, kind, per_array[kind])))
            if own:
                f2 = arraynoise.type_factor(p, kind, per_array[kind], f2, min_redundancy)
            step = float(np.sqrt(np.clip(f2, 1e-8, 1e8)))
            b = bounds.get(kind, FREE_MAX_FACTOR)
            lo = (floors or bounds).get(kind, b)
            total = float(np.clip(scales[kind] * step, 1.0 / lo, b))
            at_bound[kind] = bool(scales[kind] * step > b * (1 + 1e-9) or scales[kind] * step < (1 - 1e-9) / lo)
            step = total / scales[kind]
            d = np.sign(step - 1.0) if abs(step - 1.0) > 0.01 else 0.0
            scales[kind] = total
            p.sigma[kind] = base[kind] * total
            changed |= abs(step - 1.0) > 0.01
            if own:
                a_steps = arraynoise.update_scales(p, kind, per_array[kind], step, total, b)
                changed |= bool(np.any(np.abs(a_steps - 1.0) > 0.01))
                continue   # the type's factor may reverse while its arrays' move (see VCE_ITERATIONS_ARRAYS)
            reversed_ |= bool(d and last_dir.get(kind, d) != d)
            last_dir[kind] = d
        st, info = levenberg_marquardt(p, st, lay, kinds, loss=None, mask=mask, max_iter=max_iter)
        own = any(np.any(v) for v in p.array_own.values())
        if not changed or reversed_ or (it + 1 >= iterations and not own):
            break
    return st, p, {"scale": scales, "at_bound": at_bound, "bounds": bounds, **info}


def _wang_initialise(p):
    from .wang import wang_initialise  # (wang builds on this module's solver: imported when chosen)

    return wang_initialise(p)


# Initialisation methods by name (``calibrate(method=...)``): a new method is one entry here.
INIT_METHODS = {"hybrid": initialise, "wang": _wang_initialise}


def initial_state(p, kinds, *, method, loss, robust_k, max_iter, times):
    """Initialisation (hybrid or Wang et al.'s) in the odometry frame's start yaw, the observability check,
    then the IVE (hybrid with TDOA-S), where the odometry yaw is kept or fixed. Returns (state, stages,
    stage_states); ``times`` gets "init" and "ive" (s).
    """
    t0 = time.perf_counter()
    stages, stage_states = {}, {}
    # the odometry frame's yaw: a start value from the reference DOAs, the initialisation in that frame
    yaw0 = initial_yaw(p) if p.odo_yaw_free else 0.0
    p_init = p.replace(odom=rotate_odometry(p.odom, yaw0), odo_yaw_free=False)
    st, init_info = INIT_METHODS[method](p_init)
    st.odo_yaw = np.array([yaw0])
    st = init_cone_axes(p, st)
    times["init"] = time.perf_counter() - t0
    lay_full = make_layout(p)
    t_obs = time.perf_counter()
    check_observability(p, lay_full, kinds, st)
    times["observability"] = time.perf_counter() - t_obs
    stages["init"] = {"cost": float(linearise(p, st, lay_full, kinds)[3]), **_jsonable(init_info)}
    stage_states["init"] = st.copy()
    if method == "hybrid" and len(p.tdoa_s.val) > 0:
        # Stage 1 (IVE): positions, clocks and sources from hybrid TDOA, odometry and the reference
        # array's DOAs; then rotations by SVD alignment of DOA-scaled points.
        t1 = time.perf_counter()
        q = subproblem(p, np.arange(p.N), doa_arrays=[p.ref])
        lay_ive = make_layout(q, rotations=False)
        st, ive = levenberg_marquardt(q, st, lay_ive, active_kinds(q, "ive"), loss=loss,
                                      k=robust_k, max_iter=max_iter, rtol=1e-6)
        st = init_cone_axes(p, rotations_by_kabsch(p, st))
        if lay_ive.odo_yaw[0] >= 0:
            # decide on the odometry yaw here (its σ from the IVE's data is a conservative one), so the
            # joint pass starts in the right parameter set
            lin = linearise(q, st, lay_ive, active_kinds(q, "ive"), loss=loss,
                                              k=robust_k)
            J_ive, w_ive = lin.J, lin.w
            p.odo_yaw_test = _yaw_decision(p, st, whiten(J_ive, w_ive), int(lay_ive.odo_yaw[0]))
        stage_states["ive"] = st.copy()
        stages["ive"] = {"cost": ive["cost"], "iterations": ive["iterations"], "reason": ive["reason"]}
        times["ive"] = time.perf_counter() - t1
    return st, stages, stage_states


def _yaw_std_deg(cov, yaw_i, p, st, lay, kinds, mask):
    """1-σ of the odometry yaw in degrees: from the dense covariance, or one sparse solve (large problems)."""
    if isinstance(cov, np.ndarray):
        return float(np.rad2deg(np.sqrt(max(cov[yaw_i, yaw_i], 0.0))))
    lin = linearise(p, st, lay, kinds, mask=mask)
    J, w = lin.J, lin.w
    return float(np.rad2deg(_param_std(whiten(J, w), yaw_i)))


def _judge(p, st, info, lay, cov, w, cost, *, scales, bounds, noise, kinds):
    """Residual ratios, odometry frame and verdict at the final state.

    ``lay``, ``cov``, ``w``, ``cost``: layout, covariance, weights and cost of the full final problem.
    Returns (verdict, ratios, odometry_frame dict, cost and residual count without dropped arrays' rows).
    """
    mask = info["mask"]
    # the statistics below leave out the rows of dropped arrays (their pose was fitted to them alone)
    lay_s = info["layout"]
    same = not info["dropped"]   # then lay_s is lay and cov is the one the factors need
    n_res = int((w > 0).sum())
    if not same:
        lin = linearise(p, st, lay_s, kinds, mask=mask)
        w_s, cost = lin.w, lin.cost
        n_res = int((w_s > 0).sum())
    counts = {}   # residual values (or the redundancy) per type, for the stated-sigma test
    if info["stats"] is not None and noise != "estimate":
        vf = variance_factors(info["stats"])
        st_ = info["stats"]
        counts = {str(k): int(np.sum(st_.dof[st_.kept & (st_.kind == k)])) for k in np.unique(st_.kind)}
    else:
        vf = _vce_factors(p, st, lay_s, kinds, mask, 1.0, cov=cov if same else None, redundancy=counts)
    ratios = residual_ratios(vf, scales, bounds)
    yaw_i = int(lay.odo_yaw[0])
    odo_frame = {
        "yaw_deg": float(np.rad2deg(st.odo_yaw[0])),
        "yaw_std_deg": _yaw_std_deg(cov, yaw_i, p, st, lay, kinds, mask) if yaw_i >= 0 else None,
        "estimated": yaw_i >= 0,
        "test": info.get("yaw_test"),
        "convention": "odometry z = reference z; a step Δo (odometry frame) is Rz(yaw) Δo in the reference frame"}
    verdict = make_verdict(converged=bool(info["final"]["converged"]), reason=info["final"]["reason"],
                           ratios=ratios, n_outliers=len(info["outliers"]), n_measurements=info["n_measurements"],
                           capped=info["capped"], arrays=info["arrays"],
                           odometry_yaw={"kept": odo_frame["estimated"], "yaw_deg": odo_frame["yaw_deg"],
                                         "std_deg": odo_frame["yaw_std_deg"]},
                           concentrated=concentrated_outliers(info["outliers"], _rows_per_array(p)),
                           excess=stated_sigma_excess(ratios, counts, bounds))
    return verdict, ratios, odo_frame, cost, n_res


def calibrate(features: dict[str, Any], **options: Any) -> dict[str, Any]:
    """Calibrate arrays (positions, rotations, offsets, drifts) and sources from a features dict.

    See :func:`calibrate_features` for the options; this wrapper pins BLAS to one thread and chooses each
    array's clock model (``clock_model="auto"``, or "linear", the default for now: ``estimator.clockmodel``).
    """
    with _BLAS.limit(limits=1, user_api="blas"):
        return clockmodel.calibrate_clocks(calibrate_features, features, **options)


def calibrate_features(features, *, method="hybrid", use_tdoa_s=True, emission_sigma=0.0, loss="cauchy", robust_k=3.0,
              outlier_threshold=5.0, max_iter=200, init_state=None, noise="auto", odometry_yaw=True,
              array_noise=False, outputs="all", problem=None):
    """Calibrate arrays (positions, rotations, offsets, drifts) and sources from a features dict.

    Parameters (declared in ``calib.options.OPTIONS``, which tests/test_options.py holds these defaults to)
    ----------
    features : dict from ``pipeline.formats.io.read_features`` (or a simulator).
    method : "hybrid" (this project's estimator, Zhang et al. structure) or "wang" (the baseline; see
        ``estimator.wang``).
    use_tdoa_s : use TDOA-S measurements (False gives Wang et al.'s setting with our solver).
    emission_sigma : prior std (s) of per-interval emission-time errors; 0 disables the correction.
    loss : robust loss on TDOA and DOA residuals for the robust passes ("cauchy", "huber", "linear"/None).
    robust_k : robust scale, in units of each type's sigma.
    outlier_threshold : measurements (TDOA, DOA, odometry, cone) whose normalised residual z exceeds
        max(this, the Bonferroni level) are removed one at a time (``estimator.robust``) and reported.
    init_state : optional state to start the joint solve from (skips initialisation; used to compare
        with a solve started from ground truth).
    noise : "meta" weights with the sigmas of meta.json (documented defaults when absent); "estimate"
        then re-estimates one sigma per measurement type from the residuals (variance components) and
        re-solves, so weights and error bars follow the data's actual noise; "auto" (default) estimates
        when meta.json says its sigmas are a frontend's own figures (``sigmas_estimated``), else "meta".
        User-stated sigmas move at most PRIOR_MAX_FACTOR (3×) either way.
    array_noise : with noise="estimate", also one sigma factor per (type, array) where the redundancy
        allows (``estimator.arraynoise``); no effect with noise="meta".
    odometry_yaw : estimate the odometry frame's yaw (kept only when significant; docs/method.md).
    outputs : "all" (default, below) or "solution": the solve only, for programs that score many runs
        (the Monte-Carlo study): no covariance, frames, verdict or report, so a few ms less per call.
    problem : optional :class:`~calib.estimator.problem.Problem` that ``build_problem(features,
        use_tdoa_s=..., sigma_emit=emission_sigma, odometry_yaw=odometry_yaw)`` gives for these options
        (programs that calibrate the same features several times build it once); a copy is solved.

    Returns
    -------
    dict with ``arrays`` and ``sources`` DataFrames (with ``*_std`` columns: 1-σ from (JᵀWJ)⁻¹, rotation
    std per axis of the array frame in rad), ``report`` (dict with ``verdict`` first, see docs/method.md;
    written as report.json), and for programs that go on from the solution: ``state`` (the final
    :class:`~calib.estimator.problem.State`), ``problem`` (the :class:`~calib.estimator.problem.Problem`
    with the final sigmas) and ``stage_states`` ({"init", "ive"}: the State after each stage, when run).
    With ``outputs="solution"``: ``state``, ``problem``, ``stage_states`` and, with the values the full
    report would give, ``converged``, ``cost`` (report ``cost.final``), ``outliers`` and ``undetermined``.
    """
    validate_options(method=method, use_tdoa_s=use_tdoa_s, emission_sigma=emission_sigma, loss=loss,
                     robust_k=robust_k, outlier_threshold=outlier_threshold, max_iter=max_iter, noise=noise,
                     array_noise=array_noise, outputs=outputs, odometry_yaw=odometry_yaw)
    if loss == "linear":
        loss = None
    times, t0 = {}, time.perf_counter()
    if method == "wang":
        use_tdoa_s = False
    screened = None
    if problem is None:   # absurd and reflection-only rows out first (estimator/screen.py)
        features, screened = screen_rows(features)
        p = build_problem(features, use_tdoa_s=use_tdoa_s, sigma_emit=emission_sigma, odometry_yaw=odometry_yaw)
    else:
        _check_given_problem(problem, use_tdoa_s=use_tdoa_s, emission_sigma=emission_sigma)
        p = problem.copy()   # the solve updates its problem in place (sigmas, odometry yaw, undetermined)
    if p.K < 3:
        raise ObservabilityError(f"only {p.K} event(s): at least 3 are needed to calibrate")
    kinds = active_kinds(p)
    if init_state is None:
        st, stages, stage_states = initial_state(p, kinds, method=method, loss=loss, robust_k=robust_k,
                                                 max_iter=max_iter, times=times)
    else:
        stages, stage_states = {}, {}
        st = init_state.copy() if isinstance(init_state, State) else state_from_dict(init_state)
    t2 = time.perf_counter()
    if noise == "auto":
        noise = "estimate" if features["meta"].get("sigmas_estimated") else "meta"
    if noise == "estimate" and array_noise:
        arraynoise.start_scales(p, kinds)
    st, p, info, scales, bounds, basins = _deployment_solve(
        p, st, kinds, stages, features, lambda p_, st_: _joint_solve(
            p_, st_, kinds, stages, features["meta"], noise=noise, loss=loss, robust_k=robust_k,
            outlier_threshold=outlier_threshold, max_iter=max_iter), max_iter)
    times["joint"] = time.perf_counter() - t2
    if outputs == "solution":
        return _solution(p, st, info, kinds, stage_states)
    return _name_untrusted(_full_outputs(p, st, info, kinds, stages, stage_states, scales, bounds, method=method,
                                         noise=noise, emission_sigma=emission_sigma, times=times, t0=t0), screened, basins)


def _name_untrusted(out, screened, basins):
    """report.json ``screened`` and the verdict's naming of the rows and arrays not trusted (in place)."""
    if screened is not None:
        out["report"]["screened"] = {"rows": screened["rows"], "arrays": distrusted(screened)}
        name_distrusted(out["report"]["verdict"], screened)
    return fold_ambiguity(out, basins)


def _deployment_solve(p, st, kinds, stages, features, joint, max_iter):
    """The joint solve (``joint(problem, state)``, :func:`_joint_solve`'s tuple), with a source moving during
    the sweep corrected (``estimator/motion.py``), then the other fold basin of planar arrays whose sources
    all lie near their mic plane tried (``init.fold_basins``). Records go to ``stages``. Returns
    (state, problem, info, scales, bounds, fold basin records)."""
    meta = features["meta"]
    p_raw = p.copy()
    (st, p, info, scales, bounds), motion = motion_solve(p_raw, features["events"], joint(p, st), joint, kinds=kinds,
                                                         curve=meta.get("chirp_stretch_shift"),
                                                         t_doa=float(meta.get("doa_time_s") or 0.0),
                                                         t_stretch=meta.get("stretch_time_s"))
    if motion["source"] is not None:
        stages["motion"] = motion
    st, basins = fold_basins(p, st, info["layout"], kinds, info["mask"], max_iter)
    if basins:
        stages["fold_basins"] = basins
    return st, p, info, scales, bounds, basins


def _check_given_problem(p, *, use_tdoa_s, emission_sigma):
    """A ``problem`` passed to :func:`calibrate_features` must be the one its options would build."""
    if ((len(p.tdoa_s.val) and not use_tdoa_s) or p.sigma["emission"] != float(emission_sigma) or p.unobservable
            or p.fixed_cols):
        raise ValueError("problem: not the problem build_problem gives for these features and options")


def _full_outputs(p, st, info, kinds, stages, stage_states, scales, bounds, *, method, noise, emission_sigma,
                  times, t0):
    """``calibrate``'s result at the final state: covariance, frames with std, verdict and report."""
    lay = make_layout(p)
    lin = linearise(p, st, lay, kinds, mask=info["mask"])
    J, w, cost, fs = lin.J, lin.w, lin.cost, lin.factors
    t_cov = time.perf_counter()
    cov = covariance(J[w > 0], lay.n, lay)
    times["uncertainty"] = time.perf_counter() - t_cov
    std = std_from_cov(p, lay, cov)
    for i in info.get("dropped", ()):
        # an unreliable array's pose was refitted alone from data the rest contradict; the joint covariance
        # holds no row of it (its std came out ~1e-8 m): no uncertainty is claimed (empty, as the reference's)
        for key in ("x", "rot", "offset", "drift"):
            std[key][i] = np.nan
    arrays, sources = to_frames(p, st, std)
    times["total"] = time.perf_counter() - t0
    judged = _judge(p, st, info, lay, cov, w, cost, scales=scales, bounds=bounds, noise=noise, kinds=kinds)
    report = _report(p, st, info, stages, judged, fs, method=method, noise=noise, emission_sigma=emission_sigma,
                     times=times)
    return {"arrays": arrays, "sources": sources, "report": report, "state": st, "problem": p,
            "stage_states": stage_states}


def _solution(p, st, info, kinds, stage_states):
    """``calibrate(outputs="solution")``: the state and the report's convergence, final cost (computed as
    :func:`_judge` does: without a dropped array's rows), outliers and undetermined parameters."""
    lay = info["layout"] if info["dropped"] else make_layout(p)
    return {"state": st, "problem": p, "stage_states": stage_states,
            "converged": bool(info["final"]["converged"]),
            "cost": linearise(p, st, lay, kinds, mask=info["mask"]).cost,
            "outliers": info["outliers"], "undetermined": undetermined_parameters(p),
            "unreliable_arrays": [str(p.names[i]) for i in info["dropped"]]}


def _joint_solve(p, st, kinds, stages, meta, *, noise, loss, robust_k, outlier_threshold, max_iter):
    """Robust joint solve with outlier and array tests, then (noise="estimate") bounded variance components.

    Returns (state, problem with the final sigmas, solve info, {kind: final / stated sigma}, sigma bounds);
    ``stages`` gets the noise step's record.
    """
    bounds = sigma_bounds(meta, noise)
    floors = sigma_floors(meta, bounds)
    stated = {k: p.sigma[k] for k in reweighted()}
    st, info = solve_from(p, st, kinds=kinds, loss=loss, robust_k=robust_k, outlier_threshold=outlier_threshold,
                          max_iter=max_iter, noise_bounds=bounds if noise == "estimate" else None,
                          noise_floors=floors)
    if noise == "estimate":
        st, p, vce = estimate_noise(p, st, kinds, info["mask"], bounds=bounds, floors=floors, max_iter=max_iter,
                                    lay=info["layout"], stated=stated)
        info["final"] = {**info["final"], **{k: vce[k] for k in ("iterations", "cost", "converged", "reason")}}
        stages["noise"] = {"scale": vce["scale"], "at_bound": vce["at_bound"], "bounds": bounds, "floors": floors,
                           "array_scale": arraynoise.report_scales(p)}
    scales = {k: p.sigma[k] / stated[k] for k in reweighted()}
    return st, p, info, scales, bounds


def _report(p, st, info, stages, judged, fs, *, method, noise, emission_sigma, times):
    """report.json of a calibration (docs/method.md): verdict first, then convergence, costs, residuals,
    outliers, array tests, undetermined parameters, sigmas, odometry frame, timings."""
    verdict, ratios, odo_frame, cost_s, n_res = judged
    report = {
        "verdict": verdict,
        "software": {"name": "calib", "version": __version__},
        "method": method,
        "converged": bool(info["final"]["converged"]),
        "reason": info["final"]["reason"],
        "iterations": {"robust": info["robust"]["iterations"], "final": info["final"]["iterations"]},
        "cost": {**{k: v["cost"] for k, v in stages.items() if "cost" in v}, "joint_robust": info["robust"]["cost"],
                 "final": cost_s},
        "stages": stages,
        "chi2_per_dof": float(2 * cost_s / max(n_res - info["layout"].n, 1)),
        "residual_ratio": ratios,
        "residuals": residual_table(fs, info["mask"]),
        "outliers": info["outliers"],
        "array_consistency": info["arrays"],
        "unreliable_arrays": [str(p.names[i]) for i in info["dropped"]],
        "undetermined": undetermined_parameters(p),
        "used": {**{k: bool(len(p.rows(k))) for k, spec in KINDS.items() if spec.table is not None},
                 "emission_correction": emission_sigma > 0},
        "drift_reference": "emitter clock" if len(p.tdoa_s.val) else "reference array (no TDOA-S: its drift fixed to 0)",
        "sigmas": {**{spec.report_sigma: p.sigma[k] for k, spec in KINDS.items() if spec.report_sigma},
                   "source": noise, "per_array_factor": arraynoise.report_scales(p),
                   "doa_row_scale": _row_scale_summary(p.doa.scale)},
        "timings_s": times,
        "odometry_frame": odo_frame,
        "odometry_yaw_deg": odo_frame["yaw_deg"],
    }
    if emission_sigma > 0:
        report["emission_corrections_s"] = {int(e): float(v) for e, v in zip(p.events, st.e)}
    return report


def _jsonable(d):
    return {k: (float(v) if isinstance(v, (np.floating, float)) else v) for k, v in d.items()
            if isinstance(v, (int, float, str, np.floating, dict))}
