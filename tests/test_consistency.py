"""The leave-one-array-out (Hausman) test, estimator/consistency.py: χ² under the model, no false alarms on
clean scenes, a planted inconsistent array named (simulated truth), and the verdict's wording."""
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import kstest

from calib.blas import single_thread_blas
from calib.estimator import calibrate
from calib.estimator.consistency import check_result, hausman
from calib.estimator.verdict import name_inconsistent
from calib.pipeline.simulate.featsim import simulate_features

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_clocks import scene  # noqa: E402 (the 3-minute session of issue 28's benchmark)
from .sessions import NO_TARGET


def _random_spd(rng, n, rank=None):
    A = rng.normal(size=(n, rank or n))
    return A @ A.T


def test_hausman_statistic_of_gaussian_moves_is_chi2_with_the_rank_as_dof():
    rng = np.random.default_rng(1)
    n, r = 6, 4
    V = _random_spd(rng, n) + np.eye(n)
    S = _random_spd(rng, n, r)            # the move's covariance, rank r
    L = np.linalg.cholesky(S + 1e-12 * np.eye(n))
    Ts = []
    for _ in range(2000):
        T, dof = hausman(L @ rng.normal(size=n), S, V, min_growth=1e-6)
        assert dof == r
        Ts.append(T)
    assert abs(np.mean(Ts) - r) < 4 * np.sqrt(2 * r / 2000)
    assert kstest(Ts, "chi2", args=(r,)).pvalue > 1e-3


def test_directions_the_left_out_array_hardly_informs_are_not_tested():
    V = np.eye(3)
    S = np.diag([1.0, 0.5, 1e-5])         # the third direction grows by 0.001 %: nothing of the array in it
    T, dof = hausman(np.array([1.0, 0.5, 3.0]), S, V, min_growth=0.01)
    assert dof == 2 and T == pytest.approx(1.0 + 0.5)


def _first_round(f, **kw):
    r = calibrate(f, clock_model="linear")
    with single_thread_blas():   # as calibrate runs it (small matrices: threads only contend)
        return check_result(r, f["meta"], **kw)


def test_statistic_is_chi2_on_clean_feature_scenes_under_the_stated_errors():
    # the paper's protocol: independent rows with the stated sigmas, so T ~ χ²(dof) exactly to first order
    ps, ratio = [], []
    for seed in range(12):
        f, _ = simulate_features(1 + seed % 3, seed=seed)
        for t in _first_round(f, stated_errors=True)["tested"]:
            ps.append(t["p"])
            ratio.append(t["T"] / t["dof"])
    assert len(ps) == 48
    assert 0.7 < np.mean(ratio) < 1.3          # E[T/dof] = 1 (its spread over 48 tests: ~0.09)
    assert kstest(ps, "uniform").pvalue > 0.01


@pytest.mark.slow
def test_statistic_is_chi2_over_many_clean_scenes():
    ps = []
    for seed in range(40, 100):
        f, _ = simulate_features(1 + seed % 3, seed=seed)
        ps += [t["p"] for t in _first_round(f, stated_errors=True)["tested"]]
    assert kstest(ps, "uniform").pvalue > 0.01


@pytest.mark.parametrize("seed", range(6))
def test_clean_sessions_name_no_array(seed):
    f, _ = scene(seed)
    r = calibrate(f)
    rec = r["report"]["leave_one_out"]
    assert rec["rounds"][0]["tested"] and not rec["inconsistent"]
    # the errors the *_std columns are computed with never make it less conservative than the stated ones
    assert all(t["p"] > rec["rounds"][0]["alpha"] for t in rec["rounds"][0]["tested"])


@pytest.mark.slow
def test_false_alarms_at_most_nominal_over_clean_sessions():
    flagged = 0
    for seed in range(6, 46):
        f, _ = scene(seed) if seed % 2 else simulate_features(1 + seed % 3, seed=seed)
        flagged += bool(calibrate(f)["report"]["leave_one_out"]["inconsistent"])
    assert flagged <= 2      # family-wise level 1 % per session: 0.4 expected over 40


def _position_errors(r, truth):
    t = truth["arrays"].set_index("array")
    a = r["arrays"].set_index("array")
    return {n: float(np.linalg.norm(a.loc[n, ["x", "y", "z"]].to_numpy(float) - t.loc[n, ["x", "y", "z"]].to_numpy(float)))
            for n in a.index}


WARMUP = {"A3": {"warmup": {"amplitude": 3e-5, "time_constant": 60.0}}}   # 30 ppm settling over a minute


def _planted(seed):
    """(result, truth) of issue 28's session with A3 warming up, calibrated with the linear clock (which cannot
    model it: A3's rows are biased with the geometry and pull the rest)."""
    f, truth = scene(seed, clocks=WARMUP)
    return calibrate(f, clock_model="linear", **NO_TARGET), truth


def test_a_planted_clock_warm_up_absorbed_by_the_geometry_is_named():
    """Named when leaving it out moves another array by at least MIN_MOVE_SIGMA of that array's std (seed 2:
    2.7 σ); a significant move inside the others' error bars is not (seed 0: p 9e-5, 0.71 σ): either way no
    unflagged array is 3σ off."""
    from calib.estimator.consistency import MIN_MOVE_SIGMA

    isolated = 0
    for seed in (0, 2):
        r, truth = _planted(seed)
        v = r["report"]["verdict"]
        first = {t["array"]: t for t in r["report"]["leave_one_out"]["rounds"][0]["tested"]}
        material = first["A3"]["move_sigma"] >= MIN_MOVE_SIGMA
        assert ("A3" in v["flagged_arrays"]) == material and (v["status"] != "ok" or not material)
        err = _position_errors(r, truth)
        std = r["arrays"].set_index("array")[["x_std", "y_std", "z_std"]].pow(2).sum(axis=1) ** 0.5
        assert all(err[n] < 3 * std[n] for n in err if n not in v["flagged_arrays"] and std[n] > 0)
        for t in r["report"]["leave_one_out"]["inconsistent"]:
            if t["isolated"]:
                isolated += 1
                # solved without it, the others' errors are what their std says (truth: simulated): above
    assert isolated >= 1


@pytest.mark.slow
def test_a_planted_warm_up_is_named_over_seeds():
    named = 0
    for seed in range(8):
        v = _planted(seed)[0]["report"]["verdict"]
        assert v["status"] != "ok"
        named += "A3" in v["flagged_arrays"]
    assert named >= 7


def test_verdict_names_the_array_the_move_and_what_was_done():
    v = {"status": "ok", "reasons": [], "flagged_arrays": []}
    rec = {"array": "A3", "T": 35.0, "dof": 5, "p": 1.5e-6, "moved": "A4", "move_m": 0.084, "alpha": 0.0033,
           "shift_m": 0.094, "noise_m": 0.024, "helps": True, "isolated": True}
    name_inconsistent(v, {"inconsistent": [rec], "explained": True})
    assert v["status"] == "suspect" and v["flagged_arrays"] == ["A3"]
    assert "moves A4 by 8.4 cm" in v["reasons"][0] and "p = 2e-06" in v["reasons"][0]
    w = {"status": "ok", "reasons": [], "flagged_arrays": []}
    tested = [{"array": a} for a in ("A2", "A3", "A4")]
    name_inconsistent(w, {"inconsistent": [{**rec, "isolated": False}, {**rec, "array": "A2", "isolated": False}],
                          "explained": False, "rounds": [{"tested": tested}]})
    assert w["flagged_arrays"] == ["A3", "A2", "A4"] and "no single one" in w["reasons"][-1]


def test_the_move_that_matters_is_the_largest_in_its_own_sigma():
    """Hand values: A moves 5 cm with a 5 cm σ (1σ), B 2 cm with a 0.5 cm σ (4σ): B is the material move."""
    from calib.estimator.consistency import most_moved

    d = np.array([0.05, 0.0, 0.0, 0.0, 0.02, 0.0])
    V = np.diag(np.r_[np.full(3, 0.05 ** 2 / 3), np.full(3, 0.005 ** 2 / 3)])
    k, move_m, move_sigma = most_moved(d, V)
    assert k == 1 and move_m == pytest.approx(0.02) and move_sigma == pytest.approx(4.0)
    k, _, move_sigma = most_moved(d, np.eye(6) * 0.01 ** 2 / 3)   # equal error bars: the largest in metres
    assert k == 0 and move_sigma == pytest.approx(5.0)
