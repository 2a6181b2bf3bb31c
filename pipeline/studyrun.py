"""One run of a Monte-Carlo study (:mod:`calib.pipeline.montecarlo`): the workers' side.

A *run* = one scene from ``pipeline.simulate.featsim`` (a cell ``(sigma_tdoa, sigma_doa_deg)``, a trajectory, a
run number → a seed) calibrated by each method, scored against truth, next to the same solve started from
ground truth (the convergence check) and to one draw from the CRLB. :func:`run_chunk` runs a worker's chunk
of runs and times each (:mod:`calib.pipeline.studytiming`). The study's parent process does not import this
module (it would load the estimator for nothing).
"""
from __future__ import annotations

import time
import zlib

import numpy as np

from calib.blas import single_thread_blas
from calib.estimator import calibrate, crlb, draw_from_crlb, state_from_frames, to_tables
from calib.estimator.problem import build_problem
from calib.pipeline import studytiming
from calib.pipeline.montecarlo import METRICS, SIGMA_ODO
from calib.pipeline.report.evaluate import evaluate, truth_tables
from calib.pipeline.simulate.featsim import simulate_features

def run_seed(sigma_tdoa, sigma_doa_deg, trajectory, run, base_seed=0):
    """Deterministic seed of one run (same cell/trajectory/run → same scene, whatever the order)."""
    key = f"{base_seed}|{sigma_tdoa:.6g}|{sigma_doa_deg:.6g}|{trajectory}|{run}".encode()
    return zlib.crc32(key)


def truth_state(p, truth, frames_state=None):
    """Ground truth as a state of problem ``p``, in the parametrisation the estimator solves for.

    Without TDOA-S the reference array's drift is fixed to 0 (drifts relative to it), so the truth start
    is expressed the same way; otherwise a truth start would solve a different model.
    ``frames_state``: ``state_from_frames`` of the truth for a problem with the same arrays and events,
    when the caller has it (copied).
    """
    st = state_from_frames(p, truth["arrays"], truth["sources"]) if frames_state is None else frames_state.copy()
    if len(p.tdoa_s.val) == 0:
        st.drift = (1.0 + st.drift) / (1.0 + st.drift[p.ref]) - 1.0
    return st


def _scores(p, st, truth, undetermined=()):
    """The METRICS of state ``st`` of problem ``p`` against ``truth`` (a dict of ``evaluate.truth_tables``)."""
    arrays, sources = to_tables(p, st)
    m = evaluate({"arrays": arrays, "sources": sources, "report": {"undetermined": undetermined}}, truth)
    return {k: m[k] for k in METRICS}


def run_methods(sigma_tdoa, sigma_doa_deg, trajectory, run, *, methods=("hybrid",), base_seed=0,
                check_convergence=True, with_crlb=True, sigma_odo=SIGMA_ODO):
    """Simulate one scene, calibrate it with each method and score it. Returns a list of row dicts.

    Per method: one ``final`` row, plus one row per intermediate stage when ``calibrate`` returns
    ``stage_states`` (dict stage → state). Failures (any exception of the estimator) give a row with
    ``ok=False`` and the message: counted, never hidden.
    Each method's problem is built once (``calibrate``'s default options) and handed, as a copy, to its
    solve, its truth-start solve and its CRLB; the truth's state is read from the frames once per scene.
    """
    seed = run_seed(sigma_tdoa, sigma_doa_deg, trajectory, run, base_seed)
    feats, truth = simulate_features(trajectory, sigma_tdoa, sigma_doa_deg, sigma_odo, seed=seed)
    truth_t = truth_tables(truth)   # scored up to 7 times per method: its DataFrames read once
    rows = []
    truth_st = None   # the truth as a state (every method's problem has the same arrays and events)
    for method in methods:
        base = {"sigma_tdoa": sigma_tdoa, "sigma_doa_deg": sigma_doa_deg, "trajectory": trajectory, "run": run,
                "method": method, "seed": seed}
        row = {**base, "stage": "final"}
        t0 = time.perf_counter()
        try:   # the solution only: the study reads no covariance, frames or report
            p0 = build_problem(feats, use_tdoa_s=method != "wang", odometry_yaw=True)  # calibrate's defaults
            # the study's scenes have linear clocks by construction: no clock-model selection (it would cost
            # ~10 % of each solve; its false-model rate on this protocol: benchmarks/bench_clocks.py)
            cal = calibrate(feats, method=method, outputs="solution", problem=p0, clock_model="linear")
        except Exception as exc:  # noqa: BLE001 - unobservable draw or estimator failure: a counted failure
            row.update({"ok": False, "error": f"{type(exc).__name__}: {exc}", "time_s": time.perf_counter() - t0})
            rows.append(row)
            continue
        row["time_s"] = time.perf_counter() - t0
        row["ok"] = True
        p = cal["problem"]
        if truth_st is None:
            truth_st = state_from_frames(p0, truth["arrays"], truth["sources"])
        for stage, st in (cal.get("stage_states") or {}).items():
            rows.append({**base, "stage": stage, "ok": True, **_scores(p, st, truth_t)})
        row["solver_converged"] = cal["converged"]
        row["cost"] = cal["cost"]
        row["n_outliers"] = len(cal["outliers"])
        row.update(_scores(p, cal["state"], truth_t, cal["undetermined"]))
        if check_convergence:
            gt = calibrate(feats, method=method, init_state=truth_state(p, truth, truth_st), outputs="solution",
                           problem=p0, clock_model="linear")
            row["cost_truth_start"] = gt["cost"]
            row["converged"] = bool(row["cost"] <= row["cost_truth_start"] * (1 + 1e-6) + 1e-9)
        if with_crlb:
            rng = np.random.default_rng(seed + 1)
            with single_thread_blas():  # (calib.blas)
                use_ts = bool(len(p.tdoa_s.val))   # crlb's problem: p0 without the odometry yaw, when the same
                same = use_ts == bool(len(p0.tdoa_s.val))
                bound = crlb(feats, truth, use_tdoa_s=use_ts, problem=p0.replace(odo_yaw_free=False) if same else None,
                             state=truth_st)
                draw = _scores(bound["problem"], draw_from_crlb(bound, rng), truth_t)
            row.update({f"crlb_{k}": v for k, v in draw.items()})
        rows.append(row)
    return rows


def run_one(sigma_tdoa, sigma_doa_deg, trajectory, run, *, method="hybrid", base_seed=0, check_truth_start=True,
            with_crlb=True, sigma_odo=SIGMA_ODO):
    """Simulate, calibrate and score one run with one method. Returns the flat ``final`` row (dict)."""
    rows = run_methods(sigma_tdoa, sigma_doa_deg, trajectory, run, methods=(method,), base_seed=base_seed,
                       check_convergence=check_truth_start, with_crlb=with_crlb, sigma_odo=sigma_odo)
    return rows[-1]


def run_chunk(tasks, settings):
    """Worker entry point: tasks = [(sigma_tdoa, sigma_doa_deg, trajectory, run, methods)] → a dict of ``rows``
    and the chunk's timing (:mod:`calib.pipeline.studytiming`: the worker, its CPU before the chunk, and
    per task its start and end (epoch s), its own CPU and its process's CPU)."""
    rows = []
    timing = studytiming.chunk_timing()
    with single_thread_blas():   # tiny matrices (calib.blas): parallelism across runs instead
        for task in tasks:
            st, sd, traj, run, methods = task
            with studytiming.task_timer(timing, task):
                rows += run_methods(st, sd, traj, run, methods=tuple(methods), **settings)
    return {"rows": rows, "timing": timing}
