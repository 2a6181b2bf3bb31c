"""The joint solve: robust NLS from a start state → odometry-yaw test → inconsistent arrays → outlier rows →
plain least squares, then (noise="estimate") bounded variance components (:func:`joint_solve`).

Each step takes a problem and returns a new one when it changes a setting (sigmas, the odometry yaw's
freedom); the outcome is one typed :class:`JointResult`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from . import arraynoise
from .factors import active_kinds
from .odoframe import yaw_decision
from .problem import Layout, Problem, State, make_layout
from .robust import (FAMILY_ALPHA, array_candidates, array_mask, concentrated_candidates, count_measurements,
                     drop_test, factor_sizes, fit_array_alone, measurement_stats, remove_outliers, restore_inliers)
from .solver import levenberg_marquardt, linearise
from .soundspeed import speed_test
from .uncertainty import covariance, std_from_cov, whiten
from .variance import estimate_arrival_scales, estimate_noise, reweighted, robust_noise_steps, sigma_bounds, sigma_floors
from .verdict import MOVE_SIGMA


@dataclass
class JointResult:
    """What the joint solve found. ``state`` and ``problem`` (with the sigmas and odometry-yaw freedom it
    ended with); ``layout`` of the final solve (a dropped array's parameters fixed); ``robust`` / ``final``:
    solver infos (cost, iterations, converged, reason) of the robust and the last least-squares pass;
    ``mask`` {kind: (residuals,) bool}: the residuals kept; ``outliers``: flag records (report.json
    ``outliers``); ``arrays``: per-candidate array-consistency records; ``dropped``: indices of arrays found
    inconsistent (refitted alone, unreliable); ``capped``: the row-wise removal hit its cap;
    ``n_measurements``: tested measurements; ``stats``: the measurement statistics at the final state (None
    when a re-solve followed them); ``yaw_test``: the odometry-yaw decision; ``scales`` {kind: final /
    stated sigma} and ``bounds`` {kind: the factor a sigma may move}: set by :func:`joint_solve`."""
    state: State
    problem: Problem
    layout: Layout
    robust: dict
    final: dict
    mask: dict = field(default_factory=dict)
    outliers: list = field(default_factory=list)
    arrays: list = field(default_factory=list)
    dropped: list = field(default_factory=list)
    capped: bool = False
    n_measurements: int = 0
    stats: Any = None
    yaw_test: dict | None = None
    scales: dict = field(default_factory=dict)
    bounds: dict = field(default_factory=dict)


class ArrayCheck(NamedTuple):
    """:func:`consistency_stage`'s outcome: the state, layout and mask after the inconsistent arrays were
    dropped (their parameters fixed, their rows out), their indices, one record per candidate tested
    (report.json ``array_consistency``) and the measurement statistics at the input state."""
    state: State
    layout: Layout
    mask: dict
    dropped: list
    records: list
    stats: Any


def solve_from(p, st, *, kinds, loss="cauchy", robust_k=3.0, outlier_threshold=5.0, max_iter=200,
               check_arrays=True, noise_bounds=None, noise_floors=None, isolate=()):
    """Joint NLS from a given state: robust pass → inconsistent arrays → outlier rows → plain least squares.

    ``noise_bounds`` ({kind: factor}, noise="estimate"): first move the sigmas by the medians of the
    residual statistics (:func:`~calib.estimator.variance.robust_noise_steps`; ``noise_floors``: {kind: the
    largest factor a sigma may be lowered by}, default the bound). ``isolate``: indices of arrays the data
    already distrust as a whole (``screen.isolated``): solved without them from the start and refitted
    alone, as the inconsistent ones (:func:`consistency_stage`). Returns a :class:`JointResult` (its
    ``problem`` carries the new sigmas and odometry-yaw freedom; ``p`` is not changed).
    """
    # arrays distrusted as a whole: out before anything is fitted (their rows move no sigma, yaw or source)
    lay, mask, dropped = _isolation(p, isolate)
    # the robust pass only has to find the basin and the outliers; the final pass converges tightly
    st, robust = levenberg_marquardt(p, st, lay, kinds, loss=loss, k=robust_k, mask=mask, max_iter=max_iter,
                                     rtol=1e-6)
    yaw_test = None if p.odo_yaw_test is None else dict(p.odo_yaw_test)
    if noise_bounds is not None and loss:
        stated = {k: p.sigma[k] for k in reweighted()}
        st, p = robust_noise_steps(p, st, lay, kinds, bounds=noise_bounds, stated=stated, loss=loss,
                                   robust_k=robust_k, max_iter=max_iter, floors=noise_floors, mask=mask)
    if lay.odo_yaw[0] >= 0 and yaw_test is None:
        st, p, lay, yaw_test = _odometry_yaw_test(p, st, lay, kinds, loss=loss, robust_k=robust_k, max_iter=max_iter,
                                                  mask=mask, dropped=dropped)
    res = JointResult(st, p, lay, robust, {}, mask=mask, dropped=dropped, yaw_test=yaw_test,
                      arrays=[{"array": str(p.names[i]), "isolated": True, "inconsistent": False} for i in dropped])
    if loss:
        _robust_stages(res, kinds, check_arrays=check_arrays, loss=loss, robust_k=robust_k, max_iter=max_iter,
                       threshold=outlier_threshold)
    else:
        res.state, res.final = levenberg_marquardt(p, st, lay, kinds, loss=None, mask=mask, max_iter=max_iter)
    res.n_measurements = count_measurements(p, res.dropped)
    for i in res.dropped:
        # the dropped array's own pose and clock from its data, everything else fixed (marked unreliable)
        res.state, _ = fit_array_alone(p, res.state, i, kinds, {}, loss=loss, k=robust_k, max_iter=max_iter)
    return res


def _isolation(p, isolate):
    """(layout, mask, dropped) with the arrays ``isolate`` (indices; never the reference, and at least one
    other array stays) left out: their parameters fixed, their rows masked."""
    sizes, mask, dropped = factor_sizes(p), {}, []
    for i in isolate:
        if i != p.ref and i not in dropped and len(dropped) + 2 < p.N:
            mask = array_mask(p, mask, sizes, i)
            dropped.append(int(i))
    return make_layout(p, arrays=[a for a in range(p.N) if a not in dropped]), mask, dropped


def _robust_stages(res, kinds, *, check_arrays, loss, robust_k, max_iter, threshold):
    """After the robust pass (``res``: its state, layout, mask and the arrays isolated so far, updated
    here): inconsistent arrays out (``check_arrays``), outlier rows out one by one, least squares, the
    outliers only the least-squares solution shows, flagged rows that fit given back."""
    p, st, lay, mask, stats = res.problem, res.state, res.layout, res.mask, None
    if check_arrays:
        chk = consistency_stage(p, st, lay, kinds, mask, loss=loss, robust_k=robust_k, max_iter=max_iter,
                                threshold=threshold, dropped=res.dropped)
        st, lay, mask, stats = chk.state, chk.layout, chk.mask, chk.stats
        res.dropped, res.arrays = chk.dropped, res.arrays + chk.records
    first = remove_outliers(p, st, lay, kinds, mask, threshold=threshold, loss=loss, k=robust_k, max_iter=max_iter,
                            stats=stats if not res.dropped else None)
    st, res.final = levenberg_marquardt(p, first.state, lay, kinds, loss=None, mask=first.mask, max_iter=max_iter)
    # outliers that only show at the least-squares solution (the robust loss hid their pull)
    more = remove_outliers(p, st, lay, kinds, first.mask, threshold=threshold, loss=None, k=robust_k,
                           max_iter=max_iter)
    res.capped = first.capped or more.capped
    n_flagged = len(first.flagged) + len(more.flagged)
    st, mask, flagged = restore_inliers(p, more.state, lay, kinds, more.mask, first.flagged + more.flagged,
                                        threshold=threshold, max_iter=max_iter)
    if more.flagged or len(flagged) < n_flagged:
        st, res.final = levenberg_marquardt(p, st, lay, kinds, loss=None, mask=mask, max_iter=max_iter)
    else:
        res.stats = more.stats   # the statistics at the final state (for the verdict)
    res.state, res.layout, res.mask, res.outliers = st, lay, mask, flagged


def _odometry_yaw_test(p, st, lay, kinds, *, loss, robust_k, max_iter, mask=None, dropped=()):
    """Keep the odometry yaw free only when significant (``odoframe.YAW_SIGNIFICANCE``); else fix it at 0
    and re-solve (``mask``, ``dropped``: rows and arrays left out). Returns (state, problem, layout,
    {yaw_deg, std_deg, kept})."""
    lin = linearise(p, st, lay, kinds, loss=loss, k=robust_k, mask=mask)
    p, st, test = yaw_decision(p, st, whiten(lin.J, lin.w), int(lay.odo_yaw[0]))
    if not test["kept"]:
        lay = make_layout(p, arrays=[a for a in range(p.N) if a not in dropped])
        st, _ = levenberg_marquardt(p, st, lay, kinds, loss=loss, k=robust_k, mask=mask, max_iter=max_iter, rtol=1e-6)
    return st, p, lay, test


def consistency_stage(p, st, lay, kinds, mask, *, loss, robust_k, max_iter, threshold=5.0, dropped=()):
    """Per-array consistency: for each candidate array (``robust.array_candidates``, then
    ``robust.concentrated_candidates`` at the outlier ``threshold``), re-solve without it and keep the drop
    when the χ² drop test rejects it at FAMILY_ALPHA / N (a concentrated candidate only when dropping it
    also moves the rest by more than MOVE_SIGMA: its data bend the others' solution, as an occluded
    array's reflections do; otherwise its outlier rows are removed one by one as any others). ``dropped``:
    arrays already left out (isolated; not tested again, listed first in the result's ``dropped``).

    Returns an :class:`ArrayCheck`.
    """
    sizes = factor_sizes(p)
    stats = measurement_stats(p, st, lay, kinds, mask)
    records, dropped = [], list(dropped)
    # (array, median ratios, outlier rows if it is a candidate only for holding most of them)
    cands = [(i, ratios, None) for i, ratios in array_candidates(p, stats)]
    listed = {i for i, _, _ in cands}
    cands += [(i, {}, k) for i, k in concentrated_candidates(p, stats, threshold).items() if i not in listed]
    for i, ratios, rows in cands:
        if i in dropped:
            continue
        if len(dropped) + 2 >= p.N:
            break                      # keep the reference and at least one other array
        keep_arr = [a for a in range(p.N) if a != i and a not in dropped]
        lay_w = make_layout(p, arrays=keep_arr)
        mask_w = array_mask(p, mask, sizes, i)
        st_w, _ = levenberg_marquardt(p, st, lay_w, kinds, loss=loss, k=robust_k, mask=mask_w, max_iter=max_iter,
                                      rtol=1e-6)
        T, dof, logp = drop_test(p, st, st_w, lay, lay_w, kinds, mask, mask_w, 1.0)
        rec = {"array": str(p.names[i]), "median_ratio": {k: float(v) for k, v in ratios.items()},
               **({"outlier_rows": int(rows)} if rows is not None else {}),
               "drop_chi2": T, "drop_dof": dof, "inconsistent": bool(logp < np.log(FAMILY_ALPHA / p.N))}
        if rec["inconsistent"]:
            rec["moves_sigma"] = _moves_sigma(p, st, st_w, lay_w, kinds, mask_w)
            if rows is not None and rec["moves_sigma"] <= MOVE_SIGMA:
                # its worst rows stand out but the rest hardly depends on it: kept (its outliers go row by row)
                rec["inconsistent"] = False
        if rec["inconsistent"]:
            rec["with_array"] = {"x": st.x.tolist()}
            st, lay, mask = st_w, lay_w, mask_w
            dropped.append(i)
        records.append(rec)
    return ArrayCheck(st, lay, mask, dropped, records, stats)


def _moves_sigma(p, st_a, st_b, lay, kinds, mask):
    """Largest move of any free array position or source between two states, in 1-σ of state b."""
    lin = linearise(p, st_b, lay, kinds, mask=mask)
    std = std_from_cov(p, lay, covariance(lin.J[lin.w > 0], lay.n, lay))
    z = []
    for key in ("x", "s"):
        free = getattr(lay, key) >= 0
        z.append(np.abs(getattr(st_a, key) - getattr(st_b, key))[free] / np.maximum(std[key][free], 1e-12))
    z = np.concatenate(z)
    return float(z.max()) if z.size else 0.0


def joint_solve(p, st, kinds, stages, meta, *, noise, loss, robust_k, outlier_threshold, max_iter, isolate=()):
    """Robust joint solve with outlier and array tests, then (noise="estimate") bounded variance components.

    ``isolate``: array indices solved without (:func:`solve_from`).
    Returns a :class:`JointResult` with the final sigmas in its problem, ``scales`` ({kind: final / stated
    sigma}) and ``bounds``; ``stages`` gets the noise step's record.
    """
    bounds = sigma_bounds(meta, noise)
    floors = sigma_floors(meta, bounds)
    stated = {k: p.sigma[k] for k in reweighted()}
    res = solve_from(p, st, kinds=kinds, loss=loss, robust_k=robust_k, outlier_threshold=outlier_threshold,
                     max_iter=max_iter, noise_bounds=bounds if noise == "estimate" else None, noise_floors=floors,
                     isolate=isolate)
    if noise == "estimate":
        res.state, res.problem, vce = estimate_noise(res.problem, res.state, kinds, res.mask, bounds=bounds,
                                                     floors=floors, max_iter=max_iter, lay=res.layout, stated=stated)
        res.final = {**res.final, **{k: vce[k] for k in ("iterations", "cost", "converged", "reason")}}
        # each array's arrival sigma from its TDOA-S residuals (arraynoise "arrival scales")
        res.state, res.problem, arr_info = estimate_arrival_scales(res.problem, res.state, kinds, res.mask,
                                                                   lay=res.layout, max_iter=max_iter)
        if arr_info is not None:
            res.final = {**res.final, **{k: arr_info[k] for k in ("iterations", "cost", "converged", "reason")}}
        stages["noise"] = {"scale": vce["scale"], "at_bound": vce["at_bound"], "bounds": bounds, "floors": floors,
                           "array_scale": arraynoise.report_scales(res.problem),
                           "arrival_scale": None if res.problem.arrival_scale is None else
                           {str(n): float(v) for n, v in zip(res.problem.names, res.problem.arrival_scale)}}
    if p.sigma.get("speed", 0.0) > 0 and p.c_test is None and loss:
        # the speed of sound, tested at the solution with the final sigmas (estimator/soundspeed.py); kept: the
        # whole solve again with c free, from the free fit (the array and outlier tests and sigmas judged anew)
        st_c, p_c, _, test = speed_test(res.problem, res.state, res.layout, active_kinds(res.problem),
                                        max_iter=max_iter, mask=res.mask, dropped=res.dropped)
        if test["kept"]:
            return joint_solve(p.replace(c_free=True, c_test=test), st_c, kinds, stages, meta, noise=noise, loss=loss,
                               robust_k=robust_k, outlier_threshold=outlier_threshold, max_iter=max_iter,
                               isolate=isolate)
        res.problem = p_c
    res.scales = {k: res.problem.sigma[k] / stated[k] for k in reweighted()}
    res.bounds = bounds
    return res
