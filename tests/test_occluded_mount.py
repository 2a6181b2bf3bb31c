"""An array mounted 10 cm in front of a wall whose direct path the mount attenuates (preset occluded-lab:
10-20 dB below the wall's reflection, 0.3-0.6 ms later), end to end: its arrivals are timed on the weak
direct path (truth: the simulator's analytic arrival times), the array is named and solved apart, never
`ok`, and the arrays in line of sight stay within issue 27's 3 cm. Seed 52: looked at only for validation."""
from __future__ import annotations

import json

import numpy as np
import pytest

from calib.estimator import calibrate
from calib.pipeline.features import session_features
from calib.pipeline.report.evaluate import evaluate
from calib.pipeline.formats.io import read_truth
from calib.pipeline.simulate import roomsim


@pytest.mark.slow
def test_mount_occluded_array_is_timed_on_its_direct_path_and_named(tmp_path):
    sc = roomsim.make_scenario("occluded-lab", 52)
    roomsim.simulate(sc, tmp_path / "rec")
    feats, diag = session_features(tmp_path / "rec")
    occluded = [a["name"] for a in sc["arrays"] if a.get("direct_db", 0.0) < 0]
    assert len(occluded) == 1
    name = occluded[0]
    k = [a["name"] for a in sc["arrays"]].index(name)
    truth = roomsim.arrival_times(sc)[k]
    beta = feats["meta"]["chirp_drift_bias"]
    arr = diag["arrays"][name]["arrivals"]
    err = np.array([a["time"] - truth[a["event"]] - beta * sc["arrays"][k]["drift"] for a in arr])
    err -= np.median(err)   # the clock offset's convention aside: the wall's reflection would be 0.3-0.6 ms late
    assert np.mean(np.abs(err) < 40e-6) >= 0.8, err
    assert sum("weak_direct" in a["flag"] for a in arr) > 0.5 * len(arr)
    out = calibrate(feats)
    v = out["report"]["verdict"]
    assert v["status"] != "ok" and name in v["flagged_arrays"] and name in out["report"]["unreliable_arrays"]
    per = {a["array"]: a for a in evaluate(out, read_truth(tmp_path / "rec" / "truth"))["per_array"]}
    clear = [a["name"] for a in sc["arrays"] if a["name"] not in (name, sc["reference_array"])]
    assert all(per[a]["position_m"] < 0.03 for a in clear), json.dumps(per)
