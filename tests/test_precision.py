"""The verdict names the arrays that the data do not determine to the precision asked for
(``estimator.verdict.name_imprecise``; options target_position / target_orientation_deg)."""
import numpy as np
import pandas as pd
import pytest

from calib.estimator import calibrate
from calib.estimator.verdict import median_error, median_norm_factor, name_imprecise
from calib.pipeline.report.evaluate import evaluate, truth_tables
from calib.pipeline.simulate.featsim import simulate_features


@pytest.mark.parametrize("d", [1, 2, 3])
def test_median_norm_factor_is_the_median_error_over_the_rms_std(d):
    rng = np.random.default_rng(7)
    sigma = rng.uniform(0.5, 2.0)
    e = rng.normal(0.0, sigma, (200_000, d))
    ratio = np.median(np.linalg.norm(e, axis=1)) / (sigma * np.sqrt(d))
    assert ratio == pytest.approx(median_norm_factor(d), rel=5e-3)
    assert median_norm_factor(1) == pytest.approx(0.6745, abs=1e-4)   # the half-normal's median


def test_median_error_of_unequal_axes_matches_sampling():
    rng = np.random.default_rng(3)
    for stds in ([0.6, 1.8, 0.4], [2.0, 0.1, 0.1], [np.nan, 1.0, 3.0]):
        s = np.array(stds)[np.isfinite(stds)]
        e = rng.normal(0.0, 1.0, (200_000, len(s))) * s
        assert median_error(stds) == pytest.approx(np.median(np.linalg.norm(e, axis=1)), rel=0.02)
    assert median_error([np.nan] * 3) == 0.0


def _table(rows):
    cols = ["array", "x_std", "y_std", "z_std", "rx_std", "ry_std", "rz_std"]
    return pd.DataFrame(rows, columns=cols)


def test_arrays_whose_likely_error_exceeds_the_target_are_named():
    f3, f2 = median_norm_factor(3), median_norm_factor(2)
    s_over = 0.03 / f3 / np.sqrt(3) * 1.02      # per axis: the median error 2 % above 3 cm
    s_under = 0.03 / f3 / np.sqrt(3) * 0.98
    r_pair = np.radians(1.5 / f2 / np.sqrt(2)) * 1.02   # a pair: two determined axes, just over 1.5°
    arrays = _table([["A1", np.nan, np.nan, np.nan, np.nan, np.nan, np.nan],      # the reference
                     ["A2", s_over, s_over, s_over, 1e-3, 1e-3, 1e-3],
                     ["A3", s_under, s_under, s_under, 1e-3, 1e-3, 1e-3],
                     ["A4", 1e-3, 1e-3, 1e-3, np.nan, r_pair, r_pair],
                     ["A5", 1.0, 1.0, 1.0, 1.0, 1.0, 1.0]])                    # named already: left alone
    verdict = {"status": "ok", "reasons": [], "flagged_arrays": ["A5"]}
    record = name_imprecise(verdict, arrays, 0.03, 1.5)
    assert [a["array"] for a in record["arrays"]] == ["A2", "A4"]
    assert verdict["flagged_arrays"] == ["A5", "A2", "A4"] and verdict["status"] == "suspect"
    assert "A2" in verdict["reasons"][0] and "position ±" in verdict["reasons"][0]
    assert "orientation ±" in verdict["reasons"][1] and "position ±" not in verdict["reasons"][1]
    off = {"status": "ok", "reasons": [], "flagged_arrays": []}
    assert name_imprecise(off, arrays, 0.0, 0.0)["arrays"] == [] and off["status"] == "ok"


def test_a_calibration_names_exactly_the_arrays_its_std_cannot_vouch_for():
    feats, truth = simulate_features(3, 1e-5, 0.5, 0.003, seed=11)      # precise data: no array named
    res = calibrate(feats)
    assert res.report["precision"]["arrays"] == [] and res.report["verdict"]["status"] == "ok"

    feats, truth = simulate_features(3, 5e-4, 15.0, 0.03, seed=11)      # the paper's noisiest cell: tens of cm
    res = calibrate(feats)
    named = {a["array"] for a in res.report["precision"]["arrays"]}
    per = {a["array"]: a for a in evaluate(res, truth_tables(truth))["per_array"]}
    assert named and named <= set(res.report["verdict"]["flagged_arrays"])
    assert res.report["verdict"]["status"] != "ok"
    off_by = [per[a]["position_m"] > 0.03 or per[a]["geodesic_deg"] > 1.5 for a in named]
    assert np.mean(off_by) >= 0.5            # named: more likely off than not, as the std said
    loose = calibrate(feats, target_position=1.0, target_orientation_deg=30.0)
    assert loose.report["precision"]["arrays"] == []
