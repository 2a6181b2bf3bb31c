"""report.json of a calibration (docs/method.md): the verdict and the figures it rests on (residual
ratios, the odometry frame, costs), then convergence, residuals, outliers, array tests, undetermined
parameters, sigmas and timings."""
from __future__ import annotations

import numpy as np

from calib import __version__

from . import arraynoise
from .factors import KINDS
from .outputs import residual_table, undetermined_parameters
from .robust import per_array_kinds, variance_factors
from .solver import linearise
from .uncertainty import param_std, whiten
from .verdict import concentrated_outliers, make_verdict, residual_ratios, stated_sigma_excess
from .variance import vce_factors


def judge(res, lay, cov, w, cost, *, noise, kinds):
    """Residual ratios, odometry frame and verdict at the final state of ``res`` (``joint.JointResult``).

    ``lay``, ``cov``, ``w``, ``cost``: layout, covariance, weights and cost of the full final problem.
    Returns (verdict, ratios, odometry_frame dict, cost and residual count without dropped arrays' rows).
    """
    p, st, mask = res.problem, res.state, res.mask
    # the statistics below leave out the rows of dropped arrays (their pose was fitted to them alone)
    lay_s = res.layout
    same = not res.dropped   # then lay_s is lay and cov is the one the factors need
    n_res = int((w > 0).sum())
    if not same:
        lin = linearise(p, st, lay_s, kinds, mask=mask)
        cost, n_res = lin.cost, int((lin.w > 0).sum())
    counts = {}   # residual values (or the redundancy) per type, for the stated-sigma test
    if res.stats is not None and noise != "estimate":
        vf = variance_factors(res.stats)
        counts = {str(k): int(np.sum(res.stats.dof[res.stats.kept & (res.stats.kind == k)]))
                  for k in np.unique(res.stats.kind)}
    else:
        vf = vce_factors(p, st, lay_s, kinds, mask, 1.0, cov=cov if same else None, redundancy=counts)
    ratios = residual_ratios(vf, res.scales, res.bounds)
    odo_frame = _odometry_frame(res, lay, cov, kinds)
    verdict = make_verdict(converged=bool(res.final["converged"]), reason=res.final["reason"],
                           ratios=ratios, n_outliers=len(res.outliers), n_measurements=res.n_measurements,
                           capped=res.capped, arrays=res.arrays,
                           odometry_yaw={"kept": odo_frame["estimated"], "yaw_deg": odo_frame["yaw_deg"],
                                         "std_deg": odo_frame["yaw_std_deg"]},
                           concentrated=concentrated_outliers(res.outliers, _rows_per_array(p)),
                           excess=stated_sigma_excess(ratios, counts, res.bounds))
    return verdict, ratios, odo_frame, cost, n_res


def _odometry_frame(res, lay, cov, kinds):
    """report.json ``odometry_frame``: the yaw, its 1-σ (when estimated) and the test that kept it."""
    yaw_i = int(lay.odo_yaw[0])
    return {
        "yaw_deg": float(np.rad2deg(np.angle(np.exp(1j * res.state.odo_yaw[0])))),   # in (−180, 180]
        "yaw_std_deg": _yaw_std_deg(cov, yaw_i, res.problem, res.state, lay, kinds, res.mask) if yaw_i >= 0 else None,
        "estimated": yaw_i >= 0,
        "test": res.yaw_test,
        "convention": "odometry z = reference z; a step Δo (odometry frame) is Rz(yaw) Δo in the reference frame"}


def _yaw_std_deg(cov, yaw_i, p, st, lay, kinds, mask):
    """1-σ of the odometry yaw in degrees: from the dense covariance, or one sparse solve (large problems)."""
    if isinstance(cov, np.ndarray):
        return float(np.rad2deg(np.sqrt(max(cov[yaw_i, yaw_i], 0.0))))
    lin = linearise(p, st, lay, kinds, mask=mask)
    return float(np.rad2deg(param_std(whiten(lin.J, lin.w), yaw_i)))


def _rows_per_array(p):
    """{array name: number of its measurement rows (of every per-array kind)}."""
    cols = [p.rows(k).arr for k in per_array_kinds()]
    counts = np.bincount(np.concatenate(cols).astype(int), minlength=p.N)
    return {str(n): int(k) for n, k in zip(p.names, counts)}


def make_report(res, stages, judged, fs, *, method, noise, emission_sigma, times):
    """report.json of a calibration (docs/method.md): verdict first, then convergence, costs, residuals,
    outliers, array tests, undetermined parameters, sigmas, odometry frame, timings. ``res``: the
    ``joint.JointResult``; ``judged``: :func:`judge`'s tuple; ``fs``: the factors at the final state."""
    p, st = res.problem, res.state
    verdict, ratios, odo_frame, cost_s, n_res = judged
    report = {
        "verdict": verdict,
        "software": {"name": "calib", "version": __version__},
        "method": method,
        "converged": bool(res.final["converged"]),
        "reason": res.final["reason"],
        "iterations": {"robust": res.robust["iterations"], "final": res.final["iterations"]},
        "cost": {**{k: v["cost"] for k, v in stages.items() if "cost" in v}, "joint_robust": res.robust["cost"],
                 "final": cost_s},
        "stages": stages,
        "chi2_per_dof": float(2 * cost_s / max(n_res - res.layout.n, 1)),
        "residual_ratio": ratios,
        "residuals": residual_table(fs, res.mask),
        "outliers": res.outliers,
        "array_consistency": res.arrays,
        "unreliable_arrays": [str(p.names[i]) for i in res.dropped],
        "undetermined": undetermined_parameters(p),
        "used": {**{k: bool(len(p.rows(k))) for k, spec in KINDS.items() if spec.table is not None},
                 "emission_correction": emission_sigma > 0},
        "drift_reference": "emitter clock" if len(p.tdoa_s.val) else "reference array (no TDOA-S: its drift fixed to 0)",
        "sigmas": {**{spec.report_sigma: p.sigma[k] for k, spec in KINDS.items() if spec.report_sigma},
                   "source": noise, "per_array_factor": arraynoise.report_scales(p),
                   "doa_row_scale": _row_scale_summary(p.doa.scale),
                   "arrival_scale": None if p.arrival_scale is None or np.all(p.arrival_scale == 1.0)
                   else {str(n): float(v) for n, v in zip(p.names, p.arrival_scale)}},
        "timings_s": times,
        "odometry_frame": odo_frame,
        "odometry_yaw_deg": odo_frame["yaw_deg"],
    }
    if emission_sigma > 0:
        report["emission_corrections_s"] = {int(e): float(v) for e, v in zip(p.events, st.e)}
    return report


def _row_scale_summary(scale):
    """report.json ``sigmas.doa_row_scale``: how the DOA rows' own sigmas (doa.csv ``sigma_deg``) spread
    their weights — rows weighted and the min / median / max of their scale — or None when none is."""
    own = scale[scale != 1.0]
    if not own.size:
        return None
    return {"rows": int(own.size), "min": float(own.min()), "median": float(np.median(own)), "max": float(own.max())}
