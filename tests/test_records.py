"""The typed records between stages (calib.records; calibrate()'s CalibrationResult): Features, Session and the
calibration read like the earlier dicts, are frozen, and Features goes to its folder and back unchanged."""
import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from calib.pipeline.formats.io import read_features, write_features
from calib.pipeline.formats.session import read_session
from calib.pipeline.simulate.featsim import simulate_features
from calib.records import Features, Session
from calib.tables import ARRAY_PARAMS, ARRAYS_COLUMNS

ROOT = Path(__file__).resolve().parents[1]


def test_features_from_their_folder_and_back(tmp_path):
    feats, _ = simulate_features(1, seed=3)
    assert isinstance(feats, Features)
    write_features(tmp_path / "f", feats)
    back = read_features(tmp_path / "f")
    assert isinstance(back, Features) and set(back) == set(feats)
    assert back.meta == feats.meta
    for name in feats.tables:   # (the reader adds each row's CSV line; the writer orders the rows)
        keys = [c for c in feats[name].columns if feats[name][c].dtype.kind in "iOU"]
        a, b = (t[list(feats[name].columns)].sort_values(keys).reset_index(drop=True) for t in (back[name], feats[name]))
        pd.testing.assert_frame_equal(a, b, check_dtype=False, rtol=1e-8, atol=1e-12)
    write_features(tmp_path / "g", back.to_dict())   # the dict form is written the same
    assert (tmp_path / "f" / "tdoa_m.csv").read_bytes() == (tmp_path / "g" / "tdoa_m.csv").read_bytes()


def test_features_read_like_the_dict_form_and_are_frozen():
    feats, _ = simulate_features(1, seed=3)
    d = dict(feats)
    assert set(d) == {"meta", "events", "tdoa_m", "tdoa_s", "doa"} and d["doa"] is feats.tables["doa"]
    assert feats.get("range") is None and "doa" in feats and len(feats) == 5
    with pytest.raises(TypeError):
        feats["doa"] = feats["doa"].iloc[:0]
    with pytest.raises(dataclasses.FrozenInstanceError):
        feats.events = pd.DataFrame()
    fewer = feats.replace(doa=feats["doa"].iloc[:3], tdoa_s=None)
    assert len(fewer["doa"]) == 3 and "tdoa_s" not in fewer and len(feats["doa"]) > 3 and "tdoa_s" in feats
    assert Features.from_dict({**feats}).to_dict().keys() == d.keys()


def test_session_record_reads_like_the_dict_form():
    s = read_session(ROOT / "sample_data" / "lab3")
    assert isinstance(s, Session)
    assert s["reference_array"] == s.reference_array and s["arrays"] is s.arrays
    assert ("temperature" in s) == (s.temperature is not None) and s.get("temperature") == s.temperature
    assert set(s) <= {f.name for f in dataclasses.fields(Session)}
    assert Session.from_dict(s.to_dict()).to_dict().keys() == s.to_dict().keys()
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.speed_of_sound = 300.0


def test_arrays_columns_come_from_the_per_array_parameters():
    assert ARRAYS_COLUMNS == ("array", "x", "y", "z", "qw", "qx", "qy", "qz", "offset", "drift")   # docs/formats.md
    assert [c for a in ARRAY_PARAMS for c in a.std_columns] == ["x_std", "y_std", "z_std", "rx_std", "ry_std",
                                                                 "rz_std", "offset_std", "drift_std"]


def test_calibrate_returns_a_frozen_record_that_reads_like_the_dict_form():
    from calib.estimator import CalibrationResult, calibrate
    from calib.pipeline.report.evaluate import evaluate

    feats, truth = simulate_features(1, seed=2)
    res = calibrate(feats)
    assert isinstance(res, CalibrationResult) and res["arrays"] is res.arrays and res.get("cost") is None
    assert list(res) == ["arrays", "sources", "report", "state", "problem", "stage_states", "clock_models",
                         "array_covariance"]
    assert "converged" not in res and dict(res).keys() == {**res}.keys()
    with pytest.raises(dataclasses.FrozenInstanceError):
        res.arrays = None
    with pytest.raises(KeyError):
        res["converged"]
    assert evaluate(res, truth)["position_rmse_m"] == evaluate(dict(res), truth)["position_rmse_m"] < 0.2
    # the solution form: the fields the full report would give, no tables
    sol = calibrate(feats, outputs="solution")
    assert isinstance(sol, CalibrationResult) and sol.arrays is None and "arrays" not in sol
    assert sol["cost"] == pytest.approx(res.report["cost"]["final"]) and sol.converged == res.report["converged"]
    assert CalibrationResult.from_dict(sol.to_dict()).to_dict().keys() == sol.to_dict().keys()
