"""The estimator: initialise → IVE (paper's stage 1) → joint robust NLS → outlier removal → final NLS.

``calibrate(features) -> calibration dict`` is the library entry point; see :func:`calibrate`. The stages
live by concern: ``staging`` (initialisation, observability, IVE), ``joint`` (the robust joint solve with
its array and outlier tests: a ``JointResult``), ``variance`` (sigmas from the residuals), ``outputs``
(tables), ``reporting`` (verdict and report.json). Each stage takes the immutable ``problem.Problem`` and
returns a new one when it changes a setting.
"""
from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from typing import Any


from calib.blas import single_thread_blas
from calib.options import validate_options

from . import arraynoise, clockmodel, consistency
from .ambiguity import mirror_basins, retry_dropped
from .assess import labelled_array_covariance
from .factors import active_kinds
from .init import ObservabilityError, fold_basins
from .joint import joint_solve
from .motion import motion_noise, motion_solve, velocity_in_sigma
from .outputs import CalibrationResult, blank_diverged, to_frames, to_tables, undetermined_parameters, without_claims
from .problem import State, build_problem, make_layout, state_from_dict
from .reporting import judge, make_report
from .screen import distrusted, isolated, screen_rows
from .solver import forget_linearisation, linearise
from .soundspeed import speed_check, speed_report
from .staging import initial_state
from .uncertainty import covariance, honest_covariance, plane_normals, std_from_cov
from .verdict import fold_ambiguity, majority_apart, mirror_ambiguity, name_distrusted, name_imprecise, name_inconsistent, \
    name_speed

__all__ = ["CalibrationResult", "calibrate", "calibrate_features", "to_frames", "to_tables", "validate_options"]

def calibrate(features: Mapping[str, Any], *, target_position: float = 0.03, target_orientation_deg: float = 1.5,
              clock_veto: Callable[[], str | None] | None = None, **options: Any) -> CalibrationResult:
    """Calibrate arrays (positions, rotations, offsets, drifts) and sources from features (a
    ``calib.records.Features`` or its dict form) → a :class:`~calib.estimator.outputs.CalibrationResult`.

    See :func:`calibrate_features` for the options; this wrapper pins BLAS to one thread, chooses each
    array's clock model (``clock_model="auto"``, the default: linear unless the evidence asks for more; or
    "linear": ``estimator.clockmodel``), and names in the verdict the arrays that the data do not determine
    to ``target_position`` (m) / ``target_orientation_deg`` (``verdict.name_imprecise``; 0 = off; report.json
    ``precision``). ``clock_veto``: a reason to keep the linear clock, asked once the first solve is done
    (``clockmodel.calibrate_clocks``; each array the leave-one-array-out test isolates asks again).
    """
    validate_options(target_position=target_position, target_orientation_deg=target_orientation_deg)
    try:
        with single_thread_blas():  # tiny matrices (calib.blas): parallelism goes across calibrations
            result = clockmodel.calibrate_clocks(calibrate_features, features, clock_veto=clock_veto, **options)
            result = _leave_one_out(result, features, options, clock_veto)
    finally:
        forget_linearisation()
    if result.get("report") is not None and result.get("arrays") is not None:
        result["report"]["precision"] = name_imprecise(result["report"]["verdict"], result["arrays"],
                                                       target_position, target_orientation_deg)
        # last: the arrays named for the declared c alone are those no other check named (a set-up finding
        # that blames the odometry's scale gives them back: pipeline.setupcheck.settled_by_estimate)
        name_speed(result["report"]["verdict"], (result["report"].get("speed_of_sound") or {}).get("check"),
                   result["arrays"])
    return CalibrationResult(**result)


def _leave_one_out(result, features, options, clock_veto=None):
    """The leave-one-array-out test (``estimator.consistency``) on a full result of the hybrid method: arrays
    whose rows move the others more than the noise allows are solved without (the clock models chosen
    again; one whose own new clock terms then explain its rows is given back: ``clockmodel._readmit``) and named
    in the verdict; report.json ``leave_one_out``."""
    if options.get("outputs", "all") != "all" or options.get("method", "hybrid") != "hybrid":
        return result
    t0 = time.perf_counter()
    before = list(options.get("isolate") or ())

    def resolve(names, readmit=True):
        return clockmodel.calibrate_clocks(calibrate_features, features, clock_veto=clock_veto,
                                           readmit=names if readmit else (),
                                           **{**options, "isolate": before + list(names)})

    result, record = consistency.settle(result, features["meta"], resolve, max_iter=options.get("max_iter", 200))
    record["time_s"] = time.perf_counter() - t0
    result["report"]["leave_one_out"] = record
    name_inconsistent(result["report"]["verdict"], record)
    result["report"]["timings_s"]["leave_one_out"] = record["time_s"]
    return result


def calibrate_features(features, *, method="hybrid", use_tdoa_s=True, emission_sigma=0.0, loss="cauchy",
                       robust_k=3.0, outlier_threshold=5.0, max_iter=200, init_state=None, noise="auto",
                       odometry_yaw=True, array_noise=False, outputs="all", problem=None, isolate=(),
                       speed_of_sound="fixed", speed_of_sound_sigma=0.035):
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
    speed_of_sound : "fixed" (default): c as meta.json's ``speed_of_sound`` declares; "auto": solved with the
        rest when the data tell it from the declared value (estimator/soundspeed.py). The data fix c only
        against the odometry's scale: "auto" trusts the odometry's metres over the declared c.
    speed_of_sound_sigma : relative 1-σ of the declared c, its prior when solved.
    outputs : "all" (default, below) or "solution": the solve only, for programs that score many runs
        (the Monte-Carlo study): no covariance, frames, verdict or report, so a few ms less per call.
    problem : optional :class:`~calib.estimator.problem.Problem` that ``build_problem(features,
        use_tdoa_s=..., sigma_emit=emission_sigma, odometry_yaw=odometry_yaw)`` gives for these options
        (programs that calibrate the same features several times build it once; it is not changed).
    isolate : names of arrays to solve without and refit alone (marked unreliable), as the joint solve's own
        array tests do (``calibrate``: arrays the leave-one-array-out test, ``estimator.consistency``, found
        inconsistent).

    Returns the dict form of a :class:`~calib.estimator.outputs.CalibrationResult` (its fields and units;
    ``calibrate`` returns the record): ``arrays``, ``sources`` (with 1-σ ``*_std`` columns from (JᵀWJ)⁻¹),
    ``report``, ``state``, ``problem``, ``stage_states``; with ``outputs="solution"`` no tables or report but
    ``converged``, ``cost``, ``outliers``, ``undetermined`` and ``unreliable_arrays``.
    """
    validate_options(method=method, use_tdoa_s=use_tdoa_s, emission_sigma=emission_sigma, loss=loss,
                     robust_k=robust_k, outlier_threshold=outlier_threshold, max_iter=max_iter, noise=noise,
                     array_noise=array_noise, outputs=outputs, odometry_yaw=odometry_yaw,
                     speed_of_sound=speed_of_sound, speed_of_sound_sigma=speed_of_sound_sigma)
    loss = None if loss == "linear" else loss
    times, t0 = {}, time.perf_counter()
    use_tdoa_s = use_tdoa_s and method != "wang"
    features, p, screened = _problem(features, problem, use_tdoa_s=use_tdoa_s, emission_sigma=emission_sigma,
                                     odometry_yaw=odometry_yaw,
                                     speed_sigma=speed_of_sound_sigma if speed_of_sound == "auto" else 0.0)
    kinds = active_kinds(p)
    if init_state is None:
        p, st, stages, stage_states = initial_state(p, kinds, method=method, loss=loss, robust_k=robust_k,
                                                    max_iter=max_iter, times=times)
    else:
        stages, stage_states = {}, {}
        st = init_state.copy() if isinstance(init_state, State) else state_from_dict(init_state)
    t2 = time.perf_counter()
    if noise == "auto":
        noise = "estimate" if features["meta"].get("sigmas_estimated") else "meta"
    if noise == "estimate" and array_noise:
        p = arraynoise.start_scales(p, kinds)
    res, basins, mirrors = _deployment_solve(p, st, kinds, stages, features, lambda p_, st_: joint_solve(
        p_, st_, active_kinds(p_), stages, features["meta"], noise=noise, loss=loss, robust_k=robust_k,
        outlier_threshold=outlier_threshold, max_iter=max_iter,
        isolate=isolated(screened, p.names) + [i for i, n in enumerate(p.names) if str(n) in isolate]), max_iter)
    times["joint"] = time.perf_counter() - t2
    kinds = active_kinds(res.problem)   # (a moving source's velocity error adds its prior)
    if outputs == "solution":
        return _solution(res, kinds, stage_states)
    out = _full_outputs(res, kinds, stages, stage_states, method=method, noise=noise, emission_sigma=emission_sigma,
                        times=times, t0=t0, meta=features["meta"])
    if speed_of_sound == "fixed" and loss:   # the data's c checked, never used (named in the verdict by ``calibrate``)
        out["report"]["speed_of_sound"]["check"] = _speed_check(res, kinds, speed_of_sound_sigma, max_iter)
    return blank_diverged(_name_untrusted(out, screened, basins, mirrors))


def _problem(features, problem, *, use_tdoa_s, emission_sigma, odometry_yaw, speed_sigma):
    """The problem to solve: ``problem`` when given (checked against the options; its speed-of-sound prior
    ``speed_sigma`` set), else built from the features with absurd and reflection-only rows screened out first
    (estimator/screen.py). Returns (features, problem, screening record or None)."""
    screened = None
    if problem is None:
        features, screened = screen_rows(features)
        p = build_problem(features, use_tdoa_s=use_tdoa_s, sigma_emit=emission_sigma, odometry_yaw=odometry_yaw,
                          speed_sigma=speed_sigma)
    else:
        _check_given_problem(problem, use_tdoa_s=use_tdoa_s, emission_sigma=emission_sigma)
        # (immutable: every stage that changes a setting makes a new one)
        p = problem if problem.sigma.get("speed", 0.0) == speed_sigma else \
            problem.replace(sigma={**problem.sigma, "speed": float(speed_sigma)})
    if p.K < 3:
        raise ObservabilityError(f"only {p.K} event(s): at least 3 are needed to calibrate")
    return features, p, screened


def _speed_check(res, kinds, prior, max_iter):
    """``soundspeed.speed_check`` at the joint result ``res`` (its outlier rows out, its dropped arrays fixed)."""
    return speed_check(res.problem, res.state, res.layout, kinds, prior=prior, max_iter=max_iter, mask=res.mask,
                       dropped=res.dropped)


def _name_untrusted(out, screened, basins, mirrors=()):
    """report.json ``screened`` and the verdict's naming of the rows and arrays not trusted (in place)."""
    if screened is not None:
        out["report"]["screened"] = {"rows": screened["rows"], "arrays": distrusted(screened)}
        name_distrusted(out["report"]["verdict"], screened)
    majority_apart(out["report"]["verdict"], out["report"].get("unreliable_arrays") or [], len(out["arrays"]),
                   str(out["problem"].names[out["problem"].ref]))
    return mirror_ambiguity(fold_ambiguity(out, basins), mirrors)


def _deployment_solve(p, st, kinds, stages, features, joint, max_iter):
    """The joint solve (``joint(problem, state) -> joint.JointResult``), with a source moving during the
    sweep corrected (``estimator/motion.py``), then the other fold basin of planar arrays whose sources all
    lie near their mic plane tried (``init.fold_basins``), then the mirror image across their sources' plane
    of arrays whose DOAs cannot see it (``ambiguity.mirror_basins``; dropped ones first retried at their
    mirror and fresh placements, ``ambiguity.retry_dropped``; a moving source's correction made again at each
    start).
    Records go to ``stages``. Returns (the
    ``JointResult`` with its state after both, fold basin records, mirror records)."""
    meta = features["meta"]
    res, motion, (p_again, joint_again) = motion_solve(
        p, features["events"], joint(p, st), joint, kinds=kinds, curve=meta.get("chirp_stretch_shift"),
        t_doa=float(meta.get("doa_time_s") or 0.0), t_stretch=meta.get("stretch_time_s"),
        nuisance=not velocity_in_sigma(meta))
    if motion["source"] is not None:
        stages["motion"] = motion
    # (a moving source's joint solve started again with its correction: deploy 501's clear pair was dropped in
    # its mirror basin, 3 m off, and never restarted while the retry was skipped for a moving source)
    res, retried = retry_dropped(p_again, res, kinds, joint_again)
    if retried:
        stages["mirror_rejoined"] = retried
    kinds = active_kinds(res.problem)   # (a moving source's velocity error adds its prior)
    res.state, basins = fold_basins(res.problem, res.state, res.layout, kinds, res.mask, max_iter)
    if basins:
        stages["fold_basins"] = basins
    res.state, mirrors = mirror_basins(res.problem, res.state, res.layout, kinds, res.mask, skip=res.dropped,
                                       max_iter=max_iter)
    if mirrors:
        stages["mirror_basins"] = mirrors
    return res, basins, mirrors


def _check_given_problem(p, *, use_tdoa_s, emission_sigma):
    """A ``problem`` passed to :func:`calibrate_features` must be the one its options would build."""
    if ((len(p.tdoa_s.val) and not use_tdoa_s) or p.sigma["emission"] != float(emission_sigma) or p.unobservable
            or p.fixed_cols):
        raise ValueError("problem: not the problem build_problem gives for these features and options")


def _full_outputs(res, kinds, stages, stage_states, *, method, noise, emission_sigma, times, t0, meta=None):
    """``calibrate``'s result at the final state of ``res`` (``joint.JointResult``): covariance, frames with
    std (``uncertainty.honest_covariance``, with what the features' ``meta`` says of the rows), verdict and
    report."""
    p, st = res.problem, res.state
    lay = make_layout(p)
    lin = linearise(p, st, lay, kinds, mask=res.mask)
    t_cov = time.perf_counter()
    cov = covariance(lin.J[lin.w > 0], lay.n, lay)
    meta = meta or {}
    std_cov = honest_covariance(p, lin, lay, shared=bool(meta.get("tdoa_shared_arrivals")), cov=cov,
                                normals=plane_normals(meta, p.names),   # the verdict's tests keep the plain one
                                motion=motion_noise(stages.get("motion"), p, meta.get("doa_time_s")), state=st)
    times["uncertainty"] = time.perf_counter() - t_cov
    arrays, sources = to_frames(p, st, without_claims(std_from_cov(p, lay, std_cov), res.dropped))
    arr_cov = labelled_array_covariance(p, lay, std_cov, without=set(res.dropped))
    times["total"] = time.perf_counter() - t0
    judged = judge(res, lay, cov, lin.w, lin.cost, noise=noise, kinds=kinds)
    report = make_report(res, stages, judged, lin.factors, method=method, noise=noise, emission_sigma=emission_sigma,
                         times=times)
    report["speed_of_sound"] = speed_report(p, st, lay, cov, lin)
    return {"arrays": arrays, "sources": sources, "report": report, "state": st, "problem": p,
            "stage_states": stage_states, "array_covariance": arr_cov}


def _solution(res, kinds, stage_states):
    """``calibrate(outputs="solution")``: the state and the report's convergence, final cost (computed as
    :func:`reporting.judge` does: without a dropped array's rows), outliers and undetermined parameters."""
    p, st = res.problem, res.state
    lay = res.layout if res.dropped else make_layout(p)
    return {"state": st, "problem": p, "stage_states": stage_states,
            "converged": bool(res.final["converged"]),
            "cost": linearise(p, st, lay, kinds, mask=res.mask).cost,
            "outliers": res.outliers, "undetermined": undetermined_parameters(p),
            "unreliable_arrays": [str(p.names[i]) for i in res.dropped]}
