"""Arrays named imprecise (estimator.verdict.name_imprecise) against simulated truth (issue 27): the arrays left
unnamed are beyond the target at most at the rule's stated chance, and less often than those named."""
from __future__ import annotations

import numpy as np
import pytest


@pytest.mark.slow
def test_named_arrays_are_the_ones_beyond_the_target_in_simulated_truth():
    """The paper's protocol (its 5° DOAs, 0.1 ms TDOAs: arrays 1.5-12 cm off), eight scenes, target 8 cm
    (orientation off): named ones beyond it 7 of 24, not named 1 of 8 (≤ EXCEED_ALPHA; h55p, 1 Dec). The median
    rule it replaced (alpha 0.5) left 5 of 22 unnamed beyond it."""
    from calib.estimator import calibrate
    from calib.estimator.verdict import EXCEED_ALPHA
    from calib.pipeline.report.evaluate import evaluate
    from calib.pipeline.simulate.featsim import simulate_features

    target = 0.08
    named, beyond = [], []
    for seed in range(8):
        f, truth = simulate_features(1 + seed % 3, seed=seed)
        r = calibrate(f, target_position=target, target_orientation_deg=0.0)
        names = {a["array"] for a in r["report"]["precision"]["arrays"]}
        for a in evaluate(r, truth)["per_array"]:
            named.append(a["array"] in names)
            beyond.append(a["position_m"] > target)
    named, beyond = np.array(named), np.array(beyond)
    assert named.any() and (~named).any()
    assert beyond[named].mean() > beyond[~named].mean() and beyond[~named].mean() <= EXCEED_ALPHA


@pytest.mark.parametrize("apart, status", [([], "suspect"), (["A3"], "suspect"), (["A2", "A3", "A4"], "failed"),
                                           (["A1"], "failed"), (["A1", "A3"], "failed")])
def test_a_reference_solved_apart_fails_the_calibration(apart, status):
    """Every pose is given in the reference's frame: with the reference solved apart (its rows dropped as
    inconsistent), nothing ties the others to that frame but the odometry, so the verdict is `failed` and names
    it; a minority of other arrays apart stays `suspect` (the majority rule)."""
    from calib.estimator.verdict import majority_apart

    v = majority_apart({"status": "suspect", "reasons": [], "flagged_arrays": []}, apart, 5, reference="A1")
    assert v["status"] == status
    if "A1" in apart:
        assert "A1" in v["flagged_arrays"] and any("reference array A1" in r for r in v["reasons"])
    else:
        assert not any("the reference array" in r for r in v["reasons"])
