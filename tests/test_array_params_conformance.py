"""Conformance of the per-array parameter registry (scikit-learn's ``check_estimator`` style).

A toy per-array parameter — a range bias b_i of each array's range measurements (a speaker offset), used by
the toy range kind of tests/test_kinds_conformance.py — is added by exactly the recipe of
docs/architecture.md ("Adding a per-array parameter"): ONE ``ArrayParam`` appended to
``calib.tables.ARRAY_PARAMS`` and the factor that uses it, nothing else. Then the state, the layout, the
parameter step, the initial value, the truth reader, the observability check, the covariance and CRLB, the
output tables with their ``*_std`` columns, arrays.csv and calibration.json must all carry it, and the
calibration must find it.
"""
import dataclasses

import numpy as np
import pandas as pd
import pytest

from calib.estimator import calibrate, crlb, factors
from calib.estimator.factors import put
from calib.pipeline.formats.io import read_calibration, write_features
from calib.pipeline.formats.results import load_calibration
from calib.pipeline.run import estimate_stage
from calib.pipeline.simulate.featsim import simulate_features
from calib.tables import ARRAY_PARAMS, ArrayParam
from calib.cli.tables import print_arrays
from calib.pipeline.report.summary import arrays_markdown
from rich.console import Console

from .test_factors import check_jacobian
from .test_kinds_conformance import RANGE, SIGMA_RANGE, range_factor
from .sessions import NO_TARGET

# ---- the recipe: one parameter spec ...
RANGE_BIAS = ArrayParam("range_bias", "range bias", ("range_bias",), ("range_bias",), "m", reference="free")


# ... and the factor that uses it (st.range_bias (N,), lay.range_bias (N,)): the range kind's, plus the bias
def biased_range_factor(p, st, lay):
    """Range with its array's bias: |s_j − x_i| + b_i − ρ_ij; d/db_i = 1."""
    f, i = range_factor(p, st, lay), p.rows("range").arr
    put(f.J, np.arange(len(i)), lay.range_bias[i], np.full(len(i), 1.0 / f.sigma))
    return dataclasses.replace(f, r=f.r + st.range_bias[i] / f.sigma)


@pytest.fixture
def range_bias():
    ARRAY_PARAMS.append(RANGE_BIAS)
    factors.register(RANGE, biased_range_factor)
    yield RANGE_BIAS
    factors.unregister("range")
    ARRAY_PARAMS.remove(RANGE_BIAS)


def _biased_scene(seed, without=None):
    """A featsim scene with a range row per (event, array), each array's ranges off by its own bias (the
    truth's ``range_bias`` column); ``without``: an array with no range rows."""
    feats, truth = simulate_features(3, 1e-4, 5.0, seed=seed)
    rng = np.random.default_rng(seed)
    arrays = truth["arrays"].assign(range_bias=rng.uniform(-0.15, 0.15, len(truth["arrays"])))
    x, b = arrays.set_index("array")[["x", "y", "z"]], arrays.set_index("array")["range_bias"]
    s = truth["sources"].set_index("event")[["x", "y", "z"]]
    rows = [(e, a, float(np.linalg.norm(s.loc[e].to_numpy() - x.loc[a].to_numpy())) + b[a] + rng.normal(0, SIGMA_RANGE))
            for e in s.index for a in x.index if a != without]
    feats = feats.replace(range=pd.DataFrame(rows, columns=["event", "array", "range"]))
    feats["meta"]["sigma_range"] = SIGMA_RANGE
    return feats, {**truth, "arrays": arrays}


def test_a_per_array_parameter_added_by_one_spec_is_estimated_with_its_std(range_bias, tmp_path):
    feats, truth = _biased_scene(seed=7)
    out = calibrate(feats, noise="meta", **NO_TARGET)
    arrays = out["arrays"].set_index("array")
    true_b = truth["arrays"].set_index("array")["range_bias"]
    est, std = arrays["range_bias"], arrays["range_bias_std"]
    # every array's bias (the reference's too: "free") near truth, within its own error bar
    assert np.isfinite(std).all() and (std > 0).all() and (std < 2 * SIGMA_RANGE).all()
    assert (np.abs(est - true_b) < 4 * std).all(), (est - true_b, std)
    assert np.sqrt(np.mean((est - true_b) ** 2)) < 0.3 * np.sqrt(np.mean(true_b**2))   # (not left at 0)
    assert out["report"]["verdict"]["status"] == "ok"
    # its error bar is the Cramér–Rao bound's (same covariance machinery, at the truth)
    bound = crlb(feats, truth)
    assert bound["state"].range_bias == pytest.approx(true_b.to_numpy())   # the truth reader took its column
    ratio = std.to_numpy() / bound["std"]["range_bias"]
    assert ((0.5 < ratio) & (ratio < 2.0)).all(), ratio
    # the user's path: arrays.csv and calibration.json carry the value and its std (features written and read
    # back: rounded)
    write_features(tmp_path / "features", feats)
    estimate_stage(tmp_path, {"noise": "meta"})
    back = read_calibration(tmp_path / "calibration")["arrays"].set_index("array")
    np.testing.assert_allclose(back["range_bias"], est, atol=1e-3 * std.min())
    np.testing.assert_allclose(back["range_bias_std"], std, rtol=1e-3)
    typed = {a.name: a.std["range bias"] for a in load_calibration(tmp_path / "calibration").arrays}   # calibration.json
    np.testing.assert_allclose([typed[n] for n in std.index], std, rtol=1e-3)
    # the arrays tables a user reads (summary.md, the terminal) show it with its std, in its unit
    md = arrays_markdown(out["arrays"]).splitlines()
    assert "range_bias (m)" in md[0] and f"{est.iloc[1]:.4g} ± {std.iloc[1]:.2g}" in md[3]
    console = Console(record=True, width=300)
    print_arrays(out, console)
    text = console.export_text()
    assert "range_bias m" in text and f"{est.iloc[1]:.4g} ± {std.iloc[1]:.2g}" in text


@pytest.mark.parametrize("silent", ["A3", "A1"])   # (A1: the reference, whose bias is "free")
def test_an_undetermined_per_array_parameter_is_left_out_and_named(range_bias, silent):
    feats, truth = _biased_scene(seed=8, without=silent)   # no ranges of that array: its bias is not determined
    if silent == "A3":
        check_jacobian(feats, "range")   # (the factor's Jacobian in the bias columns too)
    out = calibrate(feats, noise="meta", **NO_TARGET)
    arrays = out["arrays"].set_index("array")
    assert np.isnan(arrays.loc[silent, "range_bias_std"]) and arrays.loc[silent, "range_bias"] == RANGE_BIAS.default
    assert {"parameter": "range bias", "array": silent} in [{k: u[k] for k in ("parameter", "array")}
                                                            for u in out["report"]["undetermined"]]
    others = arrays.drop(index=silent)
    assert np.isfinite(others["range_bias_std"]).all() and np.isfinite(arrays["x_std"].drop(index="A1")).all()
