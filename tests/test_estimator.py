"""Estimator against simulated ground truth: exact recovery, robustness, observability, honest error bars."""
import numpy as np
import pandas as pd
import pytest

from calib.estimator import ObservabilityError, calibrate
from calib.estimator.factors import FACTORS
from calib.estimator.factors import evaluate as factor_eval
from calib.estimator.problem import retract
from calib.estimator.uncertainty import crlb
from calib.pipeline.report.evaluate import evaluate
from calib.pipeline.simulate.featsim import simulate_features


def arrays_close(cal, truth, tol):
    e, t = cal["arrays"], truth["arrays"]
    for cols in (["x", "y", "z"], ["offset"], ["drift"], ["qw", "qx", "qy", "qz"]):
        np.testing.assert_allclose(e[cols].to_numpy(float), t[cols].to_numpy(float), atol=tol)
    np.testing.assert_allclose(cal["sources"][["x", "y", "z"]].to_numpy(float),
                               truth["sources"][["x", "y", "z"]].to_numpy(float), atol=tol)


@pytest.mark.parametrize("traj,seed", [(1, 0), (2, 1), (3, 2)])
def test_noise_free_data_is_recovered_exactly(traj, seed):
    feats, truth = simulate_features(traj, seed=seed, noise=False)
    cal = calibrate(feats)
    assert cal["report"]["converged"]
    arrays_close(cal, truth, 1e-6)


@pytest.mark.parametrize("traj,seed", [(1, 3), (3, 8)])
def test_planar_arrays_with_mirror_ambiguous_doas(traj, seed):
    """Planar arrays at random 3-D rotations only know DOAs up to the mirror image across their plane."""
    feats, truth = simulate_features(traj, seed=seed, noise=False, planar=(0, 0, 1))
    arrays_close(calibrate(feats), truth, 1e-6)
    feats, truth = simulate_features(traj, 1e-4, 5.0, seed=seed, planar=(0, 0, 1))
    m = evaluate(calibrate(feats), truth)
    assert m["position_rmse_m"] < 0.15 and m["orientation_geodesic_deg"] < 6


def test_without_tdoa_s_still_solves():
    # without TDOA-S only drifts relative to the reference are observable: its drift is fixed at 0
    feats, truth = simulate_features(3, seed=4, noise=False, tdoa_s=False, reference_drift=0.0)
    cal = calibrate(feats)
    assert not cal["report"]["used"]["tdoa_s"]
    arrays_close(cal, truth, 1e-6)


def test_noisy_solution_is_deterministic_and_near_truth():
    feats, truth = simulate_features(3, 1e-4, 5.0, seed=7)
    a, b = calibrate(feats), calibrate(feats)
    pd.testing.assert_frame_equal(a["arrays"], b["arrays"])
    m = evaluate(a, truth)
    assert m["position_rmse_m"] < 0.15 and m["orientation_geodesic_deg"] < 5


def test_gross_tdoa_outliers_are_flagged_and_do_not_drag_the_solution():
    feats, truth = simulate_features(3, 1e-4, 5.0, seed=11)
    clean = evaluate(calibrate(feats), truth)
    tm = feats["tdoa_m"].copy()
    bad = [5, 20]
    tm.loc[bad, "tdoa"] += [0.04, -0.035]  # ~40 ms, as in real sets 07/08
    ts = feats["tdoa_s"].copy()
    ts.loc[3, "tdoa"] += 0.02
    cal = calibrate({**feats, "tdoa_m": tm, "tdoa_s": ts})
    flagged = {(o["type"], o["line"]) for o in cal["report"]["outliers"]}
    assert {("tdoa_m", 7), ("tdoa_m", 22), ("tdoa_s", 5)} <= flagged  # data rows 5, 20, 3 = file lines 7, 22, 5
    m = evaluate(cal, truth)
    assert m["position_rmse_m"] < clean["position_rmse_m"] + 0.02
    assert m["offset_rmse_s"] < clean["offset_rmse_s"] + 50e-6


def test_missing_measurements_are_tolerated():
    feats, truth = simulate_features(3, 1e-4, 5.0, seed=5)
    rng = np.random.default_rng(0)
    drop = lambda df, frac: df.drop(index=rng.choice(len(df), int(frac * len(df)), replace=False))
    # array A3 misses event 6 entirely
    feats = {**feats,
             "tdoa_m": drop(feats["tdoa_m"][~((feats["tdoa_m"].array == "A3") & (feats["tdoa_m"].event == 6))], 0.1),
             "doa": drop(feats["doa"][~((feats["doa"].array == "A3") & (feats["doa"].event == 6))], 0.1),
             "tdoa_s": drop(feats["tdoa_s"][~((feats["tdoa_s"].array == "A3") & (feats["tdoa_s"].to_event == 6))], 0.1)}
    m = evaluate(calibrate(feats), truth)
    assert m["position_rmse_m"] < 0.2 and m["orientation_geodesic_deg"] < 6


def test_collinear_sources_are_refused():
    stops = np.column_stack([np.linspace(0, 4, 8), np.full(8, 1.0), np.full(8, 0.5)])
    feats, _ = simulate_features(stops, seed=1, noise=False)
    with pytest.raises(ObservabilityError, match="collinear"):
        calibrate(feats)


def test_two_events_are_refused():
    feats, _ = simulate_features(np.array([[0.5, 0.5, 0.5], [1.5, 1.5, 1.0]]), seed=1, noise=False)
    with pytest.raises(ObservabilityError, match="at least 3"):
        calibrate(feats)


def test_arrays_without_doas_get_position_and_clock_from_tdoas():
    """A single microphone (no DOAs) and an array with one DOA: positions and clocks from the TDOAs, the
    orientation reported undetermined (not estimated, NaN std) instead of refusing the session."""
    feats, truth = simulate_features(3, 1e-4, 5.0, seed=2)
    d = feats["doa"]
    feats = feats.replace(doa=d[~d.array.isin(["A2", "A4"]) | ((d.array == "A2") & (d.event == 3))])
    cal = calibrate(feats)
    und = {u["array"]: u for u in cal["report"]["undetermined"]}
    assert set(und) == {"A2", "A4"} and und["A4"]["parameter"] == "orientation"
    a = cal["arrays"].set_index("array")
    assert np.isnan(a.loc["A4", "rx_std"]) and np.isfinite(a.loc["A3", "rx_std"])
    t = truth["arrays"].set_index("array")
    err = np.linalg.norm((a[["x", "y", "z"]] - t[["x", "y", "z"]]).to_numpy(float), axis=1)
    assert np.all(err[1:] < 0.1)
    np.testing.assert_allclose(a["offset"].to_numpy(float), t["offset"].to_numpy(float), atol=3e-4)


@pytest.mark.slow
def test_error_bars_are_honest():
    """Normalised errors (estimate − truth)/std over many scenes have unit RMS."""
    z = []
    for seed in range(24):
        feats, truth = simulate_features(3, 1e-4, 5.0, seed=100 + seed)
        cal = calibrate(feats)
        e, t = cal["arrays"].iloc[1:], truth["arrays"].iloc[1:]
        for c in "xyz":
            z.append((e[c] - t[c]).to_numpy() / e[f"{c}_std"].to_numpy())
        z.append((e["offset"] - t["offset"]).to_numpy() / e["offset_std"].to_numpy())
    z = np.concatenate(z)
    assert 0.8 < np.sqrt(np.mean(z ** 2)) < 1.25


def _fisher_by_finite_differences(p, st, lay, kinds, h=1e-6):
    """Fisher information of the whitened residuals from central differences of the residuals alone
    (no analytic Jacobian, no covariance code of the estimator)."""
    def r(delta):
        return np.concatenate([f.r for f in factor_eval(p, retract(st, lay, delta), lay, kinds)])

    cols = []
    for k in range(lay.n):
        d = np.zeros(lay.n)
        d[k] = h
        cols.append((r(d) - r(-d)) / (2 * h))
    J = np.column_stack(cols)
    return J.T @ J


@pytest.mark.parametrize("traj,seed", [(1, 5), (3, 6)])
def test_crlb_matches_an_independent_fisher_inverse(traj, seed):
    """crlb()'s 1-σ bounds equal the square roots of diag(F⁻¹), F built here by finite differences."""
    feats, truth = simulate_features(traj, 1e-4, 5.0, seed=seed)
    bound = crlb(feats, truth)
    p, st, lay = bound["problem"], bound["state"], bound["layout"]
    kinds = [k for k in FACTORS if k != "emission"]
    F = _fisher_by_finite_differences(p, st, lay, kinds)
    cov = np.linalg.inv(F)
    sd = np.sqrt(np.diag(cov))
    for key in ("x", "rot", "offset", "drift", "s"):
        idx = getattr(lay, key)
        free = idx >= 0
        np.testing.assert_allclose(bound["std"][key][free], sd[idx[free]], rtol=1e-4)


def test_noise_estimation_recovers_wrong_sigmas():
    """meta sigmas 10× / 17× off: one variance-component step moves them most of the way to the truth."""
    est = {"tdoa": [], "doa": []}
    for seed in range(3):
        feats, truth = simulate_features(3, 1e-4, 5.0, seed=20 + seed)
        feats["meta"].update(sigma_tdoa=1e-3, sigma_doa_deg=0.3)
        cal = calibrate(feats, noise="estimate")
        assert cal["report"]["sigmas"]["source"] == "estimate"
        est["tdoa"].append(cal["report"]["sigmas"]["tdoa_s"])
        est["doa"].append(cal["report"]["sigmas"]["doa_rad_per_axis"])
    assert 0.7e-4 < np.mean(est["tdoa"]) < 4e-4  # from 1e-3 toward the simulated 1e-4
    assert 0.6 < np.mean(est["doa"]) / np.deg2rad(5.0 / np.sqrt(3)) < 1.6  # from 0.3° toward 2.9°
    # "auto" only re-estimates when the frontend says the sigmas are its own figures
    feats["meta"]["sigmas_estimated"] = ["sigma_tdoa"]
    assert calibrate(feats)["report"]["sigmas"]["source"] == "estimate"
    feats["meta"].pop("sigmas_estimated")
    assert calibrate(feats)["report"]["sigmas"]["source"] == "meta"


def test_a_frontends_own_sigma_is_raised_by_the_residuals_but_never_lowered():
    """The same 10×-too-large TDOA sigma: stated by the user it is re-estimated toward the truth; as the
    frontend's own figure (meta sigmas_estimated) it stays (FRONTEND_MIN_FACTOR = 1). A 10×-too-small
    frontend figure is raised toward the truth."""
    from calib.estimator.variance import FRONTEND_MIN_FACTOR

    assert FRONTEND_MIN_FACTOR == 1.0
    feats, _ = simulate_features(3, 1e-4, 5.0, seed=21)
    feats["meta"].update(sigma_tdoa=1e-3)
    user = calibrate(feats, noise="estimate")["report"]
    feats["meta"]["sigmas_estimated"] = ["sigma_tdoa"]
    own = calibrate(feats)["report"]
    assert user["sigmas"]["tdoa_s"] < 0.3e-3                 # free: toward the simulated 1e-4
    assert np.isclose(own["sigmas"]["tdoa_s"], 1e-3)          # the frontend's: kept
    assert own["stages"]["noise"]["at_bound"]["tdoa_s"]
    feats["meta"].update(sigma_tdoa=1e-5)
    low = calibrate(feats)["report"]
    assert 0.5e-4 < low["sigmas"]["tdoa_s"] < 2e-4            # raised toward the simulated 1e-4


def test_doa_rows_with_their_own_sigmas_are_weighted_by_them():
    """Half of the DOA rows 20× noisier than the rest (0.3° and 6° per axis), the session's sigma their RMS:
    with each row's own sigma in doa.csv (sigma_deg) the orientations come out closer to the truth than with
    the one pooled sigma on every seed (2.6–3.2° → 1.4–2.0°), the positions on average (they rest mostly on
    the TDOAs and the odometry)."""
    from scipy.spatial.transform import Rotation

    pos = {"pooled": [], "rows": []}
    for seed in range(4):
        feats, truth = simulate_features(3, 1e-4, 1e-6, seed=30 + seed)
        rng = np.random.default_rng(seed)
        doa = feats["doa"].copy()
        own = np.where(rng.random(len(doa)) < 0.5, 0.3, 6.0)  # degrees per axis
        u = doa[["ux", "uy", "uz"]].to_numpy(float).copy()
        tilt = Rotation.from_rotvec(np.radians(own)[:, None] * rng.standard_normal((len(doa), 3)))
        doa[["ux", "uy", "uz"]] = tilt.apply(u)  # (the component along u only spins it)
        feats = feats.replace(doa=doa)
        feats["meta"]["sigma_doa_deg"] = float(np.sqrt(np.mean(own**2)))
        pooled = evaluate(calibrate(feats), truth)
        feats = feats.replace(doa=doa.assign(sigma_deg=own))
        rows = evaluate(calibrate(feats), truth)
        assert rows["orientation_geodesic_deg"] < 0.8 * pooled["orientation_geodesic_deg"], seed
        pos["pooled"].append(pooled["position_rmse_m"])
        pos["rows"].append(rows["position_rmse_m"])
    assert np.mean(pos["rows"]) < np.mean(pos["pooled"])
