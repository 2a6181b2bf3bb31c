"""Wang et al. (T-RO 2024) baseline: each initialisation step against hand-built geometry, the whole
initialisation on noise-free simulated scenes, and ``calibrate(method="wang")`` on low-noise data."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib.estimator import ObservabilityError, calibrate
from calib.estimator.outputs import to_frames
from calib.estimator.problem import build_problem
from calib.estimator.wang import clock_line_fit, pose_by_alignment, range_windows, wang_initialise, wang_ranges
from calib.pipeline.report.evaluate import evaluate
from calib.pipeline.simulate.featsim import simulate_features


def scene(rng, n=9):
    """An array pose and n sources around it; DOAs in the array frame and true ranges."""
    R = Rotation.random(random_state=rng)
    x = rng.uniform(-1, 1, 3)
    s = x + rng.uniform(-4, 4, (n, 3))
    d = np.linalg.norm(s - x, axis=1)
    return R, x, s, R.inv().apply((s - x) / d[:, None]), d


def test_ranges_from_doa_angles_and_source_distances():
    rng = np.random.default_rng(0)
    us, ss, ds = [], [], []
    for _ in range(3):
        _, _, s, u, d = scene(rng)
        us.append(u), ss.append(s), ds.append(d)
    ranges, res = wang_ranges(us, ss)
    for b, d, r in zip(ranges, ds, res):
        np.testing.assert_allclose(b, d, atol=1e-6)
        assert r < 1e-6


def test_windows_cover_every_source_several_times():
    idx = range_windows(14)
    assert idx.shape[1] == 4 and len(np.unique(idx, axis=0)) == len(idx)
    counts = np.bincount(idx.ravel(), minlength=14)
    assert counts.min() >= 10  # the first/last events too (C(6, 3) = 20 windows inside their span of 7)
    assert np.all(np.diff(idx, axis=1) > 0) and idx.max() - idx.min() == 13
    assert len(range_windows(5)) == 5  # fewer events than the span: all 4-subsets


def test_pose_by_alignment_recovers_rotation_and_position():
    R, x, s, u, d = scene(np.random.default_rng(1))
    R_est, x_est = pose_by_alignment(u, d, s)
    np.testing.assert_allclose(R_est, R.as_matrix(), atol=1e-9)
    np.testing.assert_allclose(x_est, x, atol=1e-9)


def test_clock_line_fit_leaves_out_a_gross_outlier():
    t = np.linspace(0, 60, 12)
    y = 0.031 + 4e-5 * t
    y[5] += 0.02
    off, drift, rejected = clock_line_fit(t, y)
    assert rejected == 1
    assert off == pytest.approx(0.031, abs=1e-12) and drift == pytest.approx(4e-5, abs=1e-12)
    assert clock_line_fit(t[:1], y[:1]) == (pytest.approx(y[0]), 0.0, 0)


@pytest.mark.parametrize("traj", [1, 2, 3])
def test_initialisation_is_exact_on_noise_free_scenes(traj):
    for seed in range(4):
        feats, truth = simulate_features(traj, seed=seed, noise=False)
        p = build_problem(feats, use_tdoa_s=False)
        st, info = wang_initialise(p)
        arrays, sources = to_frames(p, st)
        m = evaluate({"arrays": arrays, "sources": sources}, truth)
        assert m["position_rmse_m"] < 1e-6 and m["source_rmse_m"] < 1e-6
        assert m["orientation_geodesic_deg"] < 1e-5
        # the reference's drift is unknown without TDOA-S: the clock model then leaves O(δ_ref·d/c) terms
        assert m["offset_rmse_s"] < 2e-6 and m["relative_drift_rmse"] < 1e-7
        assert st.drift[p.ref] == 0.0 and max(info["range_rms_residual_m2"].values()) < 1e-6


def test_initialisation_is_close_on_noisy_scenes():
    """A closed-form initialisation: decimetres and degrees, well inside the joint solve's basin."""
    pos = []
    for seed in range(6):
        feats, truth = simulate_features(3, 1e-4, 5.0, seed=seed)
        p = build_problem(feats, use_tdoa_s=False)
        st, _ = wang_initialise(p)
        arrays, sources = to_frames(p, st)
        pos.append(evaluate({"arrays": arrays, "sources": sources}, truth)["position_rmse_m"])
    assert np.median(pos) < 0.4


def test_calibrate_wang_recovers_truth_on_low_noise_data():
    feats, truth = simulate_features(2, 1e-6, 0.05, 1e-4, seed=3)
    cal = calibrate(feats, method="wang")
    m = evaluate(cal, truth)
    assert cal["report"]["method"] == "wang" and not cal["report"]["used"]["tdoa_s"]
    assert m["position_rmse_m"] < 0.005 and m["orientation_geodesic_deg"] < 0.05
    assert m["offset_rmse_s"] < 2e-5 and m["relative_drift_rmse"] < 1e-7
    assert cal["arrays"].set_index("array").loc["A1", "drift"] == 0.0


def test_too_few_doas_is_an_observability_error_naming_the_array():
    feats, _ = simulate_features(1, seed=0, noise=False)
    doa = feats["doa"]
    feats = feats.replace(doa=doa[(doa["array"] != "A3") | (doa["event"] < 3)].reset_index(drop=True))
    with pytest.raises(ObservabilityError, match="A3"):
        calibrate(feats, method="wang")


def test_mirror_ambiguous_doas_are_refused_with_a_clear_message():
    feats, _ = simulate_features(1, seed=0, noise=False, planar=(0, 0, 1))
    with pytest.raises(ObservabilityError, match="mirror-ambiguous.*hybrid"):
        calibrate(feats, method="wang")
