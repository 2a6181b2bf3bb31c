"""The estimator's speed paths agree with the plain computations they replace (issue #12)."""
from __future__ import annotations


import numpy as np
import pandas as pd
import pytest

from calib.estimator.problem import build_problem, make_layout
from calib.estimator.solver import Schur, event_columns, linearise, normal_equations
from calib.estimator.uncertainty import state_from_frames
from calib.pipeline.report.evaluate import evaluate as evaluate_calibration
from calib.pipeline.simulate.featsim import simulate_features

KINDS = ["tdoa_s", "tdoa_m", "doa", "odometry"]


@pytest.fixture(scope="module")
def scene():
    feats, truth = simulate_features(3, 1e-4, 10.0, 0.03, seed=11)
    p = build_problem(feats)
    st = state_from_frames(p, truth["arrays"], truth["sources"])
    return feats, truth, p, st


def test_schur_blocks_are_the_scaled_permuted_normal_matrix(scene):
    _, _, p, st = scene
    lay = make_layout(p)
    lin = linearise(p, st, lay, KINDS, dense=False)
    r, J, w = lin.r, lin.J, lin.w
    H, _ = normal_equations(J, w, r)
    sch = Schur(H, lay)
    Hd = H.toarray()
    d = np.sqrt(np.diag(Hd))
    P = (Hd / np.outer(d, d))[np.ix_(sch.perm, sch.perm)]
    nA = sch.nA
    assert nA == lay.n - len(event_columns(lay))
    assert np.allclose(sch.Haa, P[:nA, :nA], rtol=1e-14, atol=0)
    assert np.allclose(sch.Hea, P[nA:, :nA], rtol=1e-14, atol=0)
    assert np.allclose(sch.Hee.toarray(), P[nA:, nA:], rtol=1e-14, atol=0)


def test_evaluation_lookups_follow_names_not_row_order(scene):
    feats, truth, p, st = scene
    from calib.estimator import to_frames

    arrays, sources = to_frames(p, st)
    arrays.loc[1:, "x"] += 0.1                                    # 10 cm error on every non-reference array
    shuffled = {"arrays": arrays.iloc[::-1].reset_index(drop=True),
                "sources": sources.iloc[2:].sample(frac=1.0, random_state=0)}
    m = evaluate_calibration(shuffled, truth)
    assert np.isclose(m["position_rmse_m"], 0.1) and m["source_rmse_m"] < 1e-9
    back = state_from_frames(p, shuffled["arrays"], pd.concat([sources.iloc[:2], shuffled["sources"]]))
    assert np.allclose(back.x[1:] - st.x[1:], [0.1, 0, 0]) and np.allclose(back.s, st.s)


def test_calibrations_in_threads_match_a_sequential_one(scene):
    from concurrent.futures import ThreadPoolExecutor

    from calib.estimator import calibrate

    from threadpoolctl import threadpool_limits

    feats = scene[0]
    # BLAS single-threaded throughout: calibrate's own limit is process-wide, and threads leaving it in
    # another order would let BLAS round differently (not the cache's doing)
    with threadpool_limits(limits=1, user_api="blas"):
        ref = calibrate(feats)["state"]
        with ThreadPoolExecutor(3) as pool:
            states = [c["state"] for c in pool.map(lambda _: calibrate(feats), range(3))]
    for st in states:
        assert all(np.array_equal(getattr(st, f), v) for f, v in vars(ref).items())


def test_coarse_cost_matches_the_zoom_cost(scene):
    """The coarse grid's fast layout (transposed clock IRLS, Kabsch matrices as vectors over points,
    closed-form eigenvalues) computes profile_cost's concentrated cost: equal up to rounding."""
    from calib.estimator.init import coarse_cost, coarse_grid, profile_cost

    _, _, p, st = scene
    grid = coarse_grid(st.s)
    for i in range(p.N):
        if i == p.ref:
            continue
        fast = coarse_cost(p, st, i, 3e-4, 0.1, grid)
        ref = profile_cost(p, st, i, grid["pts"], 3e-4, 0.1)[0]
        assert np.allclose(fast, ref, rtol=1e-9, atol=1e-7)


def _faulty_scenes():
    """A clean scene, one with outliers (a TDOA-M row 40 σ off, a flipped DOA) and one whose array B is
    biased as a whole (the array test drops it): ``outputs="solution"`` must agree on each."""
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location("bench_faults", Path(__file__).parents[1] / "benchmarks" /
                                                  "bench_faults.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    feats, truth = simulate_features(3, 1e-4, 5.0, 0.03, seed=11)
    tm, doa = feats["tdoa_m"].copy(), feats["doa"].copy()
    tm.loc[5, "tdoa"] += 0.004
    doa.loc[44, ["ux", "uy", "uz"]] = -doa.loc[44, ["ux", "uy", "uz"]].to_numpy(float)
    f_biased, truth_b = simulate_features(1, 1e-4, 5.0, 0.03, seed=1000)
    f_biased, _ = bench.fault_array(f_biased, truth_b, np.random.default_rng(0))
    return [(feats, truth), ({**feats, "tdoa_m": tm, "doa": doa}, truth), (f_biased, truth_b)]


@pytest.mark.parametrize("method", ["hybrid", "wang"])
def test_solution_outputs_are_the_full_calibrations_values(method):
    """calibrate(outputs="solution") (the Monte-Carlo study's) gives exactly the state, final cost,
    convergence, outliers and undetermined parameters of the full result, from its own start and from
    ground truth; and scoring from the state's tables equals scoring the full result's DataFrames."""
    from calib.estimator import calibrate, to_tables
    from calib.pipeline.montecarlo import truth_state
    from calib.pipeline.report.evaluate import truth_tables

    kinds_seen = set()
    for feats, truth in _faulty_scenes():
        full = calibrate(feats, method=method)
        starts = [None, truth_state(full["problem"], truth)]
        for start in starts:
            a = calibrate(feats, method=method, init_state=start)
            b = calibrate(feats, method=method, init_state=start, outputs="solution")
            rep = a["report"]
            assert b["cost"] == rep["cost"]["final"] and b["converged"] == rep["converged"]
            assert b["outliers"] == rep["outliers"] and b["undetermined"] == rep["undetermined"]
            assert all(np.array_equal(v, getattr(b["state"], f)) for f, v in vars(a["state"]).items())
            arrays, sources = to_tables(b["problem"], b["state"])
            lean = evaluate_calibration({"arrays": arrays, "sources": sources,
                                         "report": {"undetermined": b["undetermined"]}}, truth_tables(truth))
            ref = evaluate_calibration(a, truth)
            assert {k: v for k, v in lean.items() if k != "per_array"} == pytest.approx(
                {k: v for k, v in ref.items() if k != "per_array"}, rel=0, abs=0, nan_ok=True)
            kinds_seen |= {"outliers"} if rep["outliers"] else set()
            kinds_seen |= {"dropped"} if rep["unreliable_arrays"] else set()
    assert kinds_seen == {"outliers", "dropped"}   # the paths the light result must reproduce were taken
    with pytest.raises(ValueError, match="outputs"):
        calibrate(feats, outputs="frames")


@pytest.mark.slow
@pytest.mark.parametrize("method", ["hybrid", "wang"])
def test_prebuilt_problem_gives_the_same_calibration_and_crlb(method):
    """calibrate(problem=...) (the Monte-Carlo study builds each method's problem once) solves a copy: the
    same state and cost as building it inside, twice in a row (the first solve must not leak into the
    given problem: outliers, a dropped array, sigmas); crlb(problem=, state=) equals crlb(); a problem
    built with other options is refused."""
    from calib.estimator import calibrate, crlb
    from calib.pipeline.montecarlo import truth_state

    use_ts = method != "wang"
    for feats, truth in _faulty_scenes():
        p0 = build_problem(feats, use_tdoa_s=use_ts, odometry_yaw=True)
        ref = calibrate(feats, method=method, outputs="solution")
        for _ in range(2):
            got = calibrate(feats, method=method, outputs="solution", problem=p0)
            assert got["cost"] == ref["cost"] and got["outliers"] == ref["outliers"]
            assert all(np.array_equal(getattr(got["state"], f), v) for f, v in vars(ref["state"]).items())
        fresh = build_problem(feats, use_tdoa_s=use_ts, odometry_yaw=True)
        assert p0.sigma == fresh.sigma and not p0.unobservable and not p0.fixed_cols and p0.odo_yaw_free == fresh.odo_yaw_free
        st0 = truth_state(ref["problem"], truth)
        gt_ref = calibrate(feats, method=method, init_state=st0, outputs="solution")
        gt = calibrate(feats, method=method, init_state=st0, outputs="solution", problem=p0)
        assert gt["cost"] == gt_ref["cost"] and np.array_equal(gt["state"].x, gt_ref["state"].x)
        frames = state_from_frames(p0, truth["arrays"], truth["sources"])
        a = crlb(feats, truth, use_tdoa_s=use_ts)
        b = crlb(feats, truth, use_tdoa_s=use_ts, problem=p0.replace(odo_yaw_free=False), state=frames)
        assert np.array_equal(a["cov"], b["cov"])
    if method == "wang":   # a problem with TDOA-S rows for the method that ignores them
        with pytest.raises(ValueError):
            calibrate(feats, method="wang", problem=build_problem(feats, use_tdoa_s=True))


def test_measurement_count_matches_isin(scene):
    """count_measurements equals the np.isin count with and without excluded arrays."""
    from calib.estimator.robust import count_measurements

    p = scene[2]
    for excl in ((), [0], (1, 3), set(range(p.N))):
        ref = max(p.K - 1, 0) + sum(int(np.sum(~np.isin(r.arr, list(excl)))) for r in (p.tdoa_s, p.tdoa_m, p.doa, p.cone))
        assert count_measurements(p, excl) == ref
