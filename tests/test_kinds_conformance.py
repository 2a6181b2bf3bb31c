"""Conformance of the measurement-kind registry (scikit-learn's ``check_estimator`` style).

A toy kind — a speaker-to-array range, range_ij = |s_j − x_i| + noise, in its own ``range.csv`` — is added
by exactly the recipe of docs/architecture.md ("Adding a measurement kind"): ONE spec and ONE factor
function, nothing else. Then every place that lists kinds must handle it: reading, validation and writing
of its CSV, its meta.json noise key, the problem, the Jacobian, the calibration, the outlier tests, the
per-array tests, report.json (``sigmas``, ``used``, ``residuals``, ``outliers``), summary.md and the
``calib run`` stage key.
"""
import warnings

import numpy as np
import pandas as pd
import pytest

from calib.estimator import calibrate, factors
from calib.estimator.factors import Factor, jacobian, put
from calib.kinds import KindSpec, Table
from calib.tables import LINE_COLUMN
from calib.pipeline.formats.io import read_features, write_features
from calib.pipeline.run import estimate_stage, features_inputs, report_stage, stage_key
from calib.pipeline.report.evaluate import evaluate
from calib.pipeline.simulate.featsim import simulate_features

from .test_factors import check_jacobian
from .sessions import NO_TARGET

SIGMA_RANGE = 0.02   # m

# ---- the recipe: one spec ...
RANGE = KindSpec("range", Table("range", ("event", "array", "range"), ("event",), ("event",), ("event", "array")),
                 source="range", unit="cm", scale=100.0, label="range residual (cm)", title="Range",
                 noise_key="sigma_range", noise_default=0.05, noise_range=(0.0, 10.0), report_sigma="range_m",
                 dof=1, reweight=True)


# ... and one factor function
def range_factor(p, st, lay):
    """Range: |s_j − x_i| − ρ_ij; d/ds_j = n, d/dx_i = −n (n the unit vector from the array to the source)."""
    rows, sig = p.rows("range"), p.sigma["range"]
    i, j, m = rows.arr, rows.ev, len(rows)
    w = st.s[j] - st.x[i]
    d = np.linalg.norm(w, axis=1)
    n = w / np.where(d > 0, d, 1.0)[:, None]
    J = jacobian(m, lay)
    put(J, np.arange(m), np.column_stack([lay.s[j], lay.x[i]]), np.column_stack([n, -n]) / sig)
    return Factor("range", (d - rows.val) / sig, J, rows.row, 1, True, sig)


@pytest.fixture
def range_kind():
    factors.register(RANGE, range_factor)
    yield RANGE
    factors.unregister("range")


def _with_ranges(seed, outlier=None):
    """A featsim scene with a range row for every (event, array); ``outlier``: (row, metres) added to one."""
    feats, truth = simulate_features(3, 1e-4, 5.0, seed=seed)
    x = truth["arrays"].set_index("array")[["x", "y", "z"]]
    s = truth["sources"].set_index("event")[["x", "y", "z"]]
    rng = np.random.default_rng(seed)
    rows = [(e, a, float(np.linalg.norm(s.loc[e].to_numpy() - x.loc[a].to_numpy())) + rng.normal(0, SIGMA_RANGE))
            for e in s.index for a in x.index]
    df = pd.DataFrame(rows, columns=["event", "array", "range"])
    if outlier is not None:
        df.loc[outlier[0], "range"] += outlier[1]
    feats = feats.replace(range=df)
    feats["meta"]["sigma_range"] = SIGMA_RANGE
    return feats, truth


def test_the_range_kind_added_by_one_spec_and_one_factor_works_everywhere(range_kind, tmp_path):
    bad_row, bad_by = 17, 1.0   # 50 σ
    feats, truth = _with_ranges(seed=5, outlier=(bad_row, bad_by))
    out = tmp_path / "out"
    # its CSV is written, read back and validated; its meta key is known (no "unknown key ... ignored")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_features(out / "features", feats)
        back = read_features(out / "features")
    assert (out / "features" / "range.csv").is_file() and len(back["range"]) == len(feats["range"])
    assert back["meta"]["sigma_range"] == SIGMA_RANGE
    r = back["range"]
    bad_line = int(r.loc[(r["event"] == feats["range"]["event"][bad_row])
                         & (r["array"] == feats["range"]["array"][bad_row]), LINE_COLUMN].iloc[0])

    # the calibration uses it (the user's path: calib run's estimate and report stages)
    calib = estimate_stage(out, {"noise": "meta", **NO_TARGET})
    rep = calib["report"]
    assert rep["used"]["range"] is True
    assert rep["sigmas"]["range_m"] == SIGMA_RANGE
    assert rep["residuals"]["range"]["n"] == len(feats["range"]) - 1   # the outlier excluded
    # the outlier is flagged (type, file line), and nothing else of its kind
    flagged = [o for o in rep["outliers"] if o["type"] == "range"]
    assert [o["line"] for o in flagged] == [bad_line]
    assert flagged[0]["residual"] == pytest.approx(-bad_by * 100.0, rel=0.1)   # model − measured and flagged[0]["unit"] == "cm"
    # the kept range rows fit to their sigma
    assert 0.5 < rep["residuals"]["range"]["rms_cm"] / (100 * SIGMA_RANGE) < 1.5
    assert rep["verdict"]["status"] == "ok"
    assert evaluate(calib, truth)["position_rmse_m"] < 0.05

    # summary.md names the kind and the outlier's file and line
    report_stage(out)
    summary = (out / "report" / "summary.md").read_text()
    assert "| Range |" in summary
    assert f"features/range.csv line {bad_line}" in summary

    # the stage key hashes its CSV: editing it changes the estimate's key
    k0 = stage_key(features_inputs(out), {})[0]
    path = out / "features" / "range.csv"
    df = pd.read_csv(path)
    df.loc[0, "range"] += 0.001
    df.to_csv(path, index=False)
    assert stage_key(features_inputs(out), {})[0] != k0


def test_the_range_factor_jacobian_and_the_per_array_tests(range_kind):
    feats, _ = _with_ranges(seed=6)
    check_jacobian(feats, "range")
    # one array's ranges biased as a whole (a wrong speaker offset): the per-array test finds that array
    bad = feats["meta"]["arrays"][2]
    m = feats["range"]["array"] == bad
    feats["range"].loc[m, "range"] += np.random.default_rng(0).normal(0.3, 0.1, int(m.sum()))
    rep = calibrate(feats, noise="meta")["report"]
    tested = {r["array"]: r for r in rep["array_consistency"]}
    assert bad in tested and "range" in tested[bad]["median_ratio"]


def test_registering_and_removing_a_kind_leaves_the_built_in_registry():
    from calib.kinds import KINDS

    before = list(KINDS), list(factors.FACTORS), list(factors.ROWS)
    factors.register(RANGE, range_factor)
    assert list(KINDS)[-1] == "range" and "range" in factors.ROWS
    factors.unregister("range")
    assert (list(KINDS), list(factors.FACTORS), list(factors.ROWS)) == before
