"""Arrays named imprecise (estimator.verdict.name_imprecise) against simulated truth (issue 27): at a target near
the errors' median, the arrays named are beyond it far more often than those not named."""
from __future__ import annotations

import numpy as np
import pytest


@pytest.mark.slow
def test_named_arrays_are_the_ones_beyond_the_target_in_simulated_truth():
    """The paper's protocol (its 5° DOAs, 0.1 ms TDOAs: arrays 1.5-12 cm off), eight scenes, target 5 cm
    (orientation off): named ones beyond it 17 of 24 (h35n, 28 Nov), not named 2 of 8."""
    from calib.estimator import calibrate
    from calib.pipeline.report.evaluate import evaluate
    from calib.pipeline.simulate.featsim import simulate_features

    target = 0.05
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
    assert beyond[named].mean() > 0.5 > beyond[~named].mean()
