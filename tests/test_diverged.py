"""A solve that runs off (data that fit no one geometry) is called `failed` and named, and calib writes only
what its own readers take back: the places no recording can come from become unknown (empty cells)."""
import json

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

import calib.estimator as est
from calib.cli.main import app
from calib.estimator.outputs import AUDIBLE_RANGE, blank_diverged
from calib.pipeline.formats.io import read_calibration, write_calibration, write_features, write_truth
from calib.pipeline.simulate.featsim import simulate_features
from .sessions import small_lab3_session


class _Ref:
    ref = 0


def _out(xa, xs):
    arrays = pd.DataFrame({"array": [f"A{i + 1}" for i in range(len(xa))], **dict(zip("xyz", np.asarray(xa, float).T)),
                           "x_std": 0.01, "y_std": 0.01, "z_std": 0.01})
    sources = pd.DataFrame({"event": range(len(xs)), **dict(zip("xyz", np.asarray(xs, float).T))})
    return {"arrays": arrays, "sources": sources, "problem": _Ref(),
            "report": {"verdict": {"status": "ok", "reasons": [], "flagged_arrays": []}}}


def test_blank_diverged_by_hand():
    src = [[1.0, 0, 0], [2.0, 1, 0], [3.0, -1, 1]]
    ok = blank_diverged(_out([[0, 0, 0], [5, 5, 1], [0.5 * AUDIBLE_RANGE, 0, 0]], src))
    assert ok["report"]["verdict"]["status"] == "ok" and np.isfinite(ok["arrays"][["x", "y", "z"]]).all().all()
    # A3 beyond the range from every source, event 2 from every array
    bad = blank_diverged(_out([[0, 0, 0], [5, 5, 1], [3 * AUDIBLE_RANGE, 0, 0]],
                              [*src[:2], [-2.5 * AUDIBLE_RANGE, 0, 0]]))
    v = bad["report"]["verdict"]
    assert v["status"] == "failed" and v["flagged_arrays"] == ["A3"]
    assert "diverged" in v["reasons"][0] and "A3" in v["reasons"][0] and "1 source" in v["reasons"][0]
    a = bad["arrays"]
    assert a.loc[2, ["x", "y", "z", "x_std"]].isna().all() and np.isfinite(a.loc[:1, ["x", "y", "z"]]).all().all()
    assert bad["sources"].loc[2, ["x", "y", "z"]].isna().all() and bad["sources"].loc[:1, "x"].notna().all()
    # the reference is the gauge: never blanked; it heard every source, so when all ran off (with the other
    # arrays: near each other, far from it), everything but the reference is unknown
    for xa in ([[0, 0, 0], [5, 5, 1]], [[0, 0, 0], [5e4, 1, 1]]):
        far = blank_diverged(_out(xa, [[5e4, 0, 0]] * 3))
        assert far["report"]["verdict"]["status"] == "failed" and far["report"]["verdict"]["flagged_arrays"] == ["A2"]
        assert far["arrays"].loc[0, ["x", "y", "z"]].notna().all() and far["arrays"].loc[1, ["x", "y", "z"]].isna().all()
        assert far["sources"][["x", "y", "z"]].isna().all().all()


def test_a_clock_run_off_is_unknown_and_named(tmp_path):
    # a clock beyond any recording's span (a refit alone of data no clock explains): its offset and drift are
    # unknown (empty cells the readers take back), the verdict failed and naming it; the readers' bound is this one
    from calib.estimator.outputs import CLOCK_SPAN, DRIFT_SPAN
    from calib.pipeline.formats.results import MAX_ABS_CAL_DRIFT
    from calib.pipeline.formats.validate import MAX_ABS_TIME

    assert CLOCK_SPAN == MAX_ABS_TIME and DRIFT_SPAN == MAX_ABS_CAL_DRIFT
    for offset, drift in ((-1.26e7, 0.3), (2.0, -0.7)):
        out = _out([[0, 0, 0], [5, 5, 1], [2, 3, 1]], [[1.0, 0, 0], [2.0, 1, 0], [3.0, -1, 1]])
        out["arrays"] = out["arrays"].assign(qw=1.0, qx=0.0, qy=0.0, qz=0.0, offset=[0.0, 0.01, offset],
                                             drift=[0.0, 1e-5, drift], offset_std=1e-6, drift_std=1e-7)
        v = blank_diverged(out)["report"]["verdict"]
        assert v["status"] == "failed" and v["flagged_arrays"] == ["A3"] and "A3" in v["reasons"][-1]
        a = out["arrays"]
        assert a.loc[2, ["offset", "drift", "offset_std", "drift_std"]].isna().all() and a.loc[:1, "offset"].notna().all()
        write_calibration(tmp_path / "c", out)
        back = read_calibration(tmp_path / "c")["arrays"]
        assert np.isnan(back.loc[2, "offset"]) and back.loc[1, "offset"] == pytest.approx(0.01)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("div")
    feats, truth = simulate_features(trajectory=1, seed=3)
    write_features(d / "features", feats), write_truth(d / "truth", truth)
    return d, feats


def _runaway(real):
    """``calibrate`` started 300 km off and stopped after a few iterations: the solve a garbage session gives."""
    def calibrate(feats, **opts):
        st = real(feats, outputs="solution", clock_model="linear")["state"].copy()
        st.x[1:] += [3e5, 1e5, 0.0]
        st.s += [2e5, 0.0, 0.0]
        return real(feats, **{**opts, "init_state": st, "max_iter": 3})
    return calibrate


def test_runaway_solve_is_failed_and_readable(scene, tmp_path):
    _, feats = scene
    out = _runaway(est.calibrate)(feats)
    v = out["report"]["verdict"]
    assert v["status"] == "failed" and v["reasons"][0].startswith("the solve diverged")
    assert set(v["flagged_arrays"]) >= set(map(str, feats["meta"]["arrays"][1:]))
    write_calibration(tmp_path / "cal", out, feats)
    back = read_calibration(tmp_path / "cal")
    assert back["arrays"].loc[1:, "x"].isna().all() and back["arrays"].loc[0, ["x", "y", "z"]].notna().all()
    doc = json.loads((tmp_path / "cal" / "calibration.json").read_text())
    assert doc["covariance"] is None


def test_cli_names_the_runaway(scene, tmp_path, monkeypatch):
    d, _ = scene
    monkeypatch.setattr(est, "calibrate", _runaway(est.calibrate))
    r = CliRunner().invoke(app, ["estimate", str(d / "features"), "-o", str(tmp_path / "cal")])
    assert r.exit_code == 3 and "diverged" in r.output and "Traceback" not in r.output and "Warning" not in r.output, r.output
    r = CliRunner().invoke(app, ["evaluate", str(tmp_path / "cal"), str(d / "truth")])
    assert r.exit_code in (0, 3) and "error" not in r.stderr and "Traceback" not in r.output and "Warning" not in r.output, r.output
    for fmt in ("json", "urdf"):   # nothing to export, said in one line (not calib refusing its own file)
        r = CliRunner().invoke(app, ["export", str(tmp_path / "cal"), "-f", fmt, "-o", str(tmp_path / f"exp.{fmt}")])
        lines = r.stderr.strip().splitlines()
        assert r.exit_code == 2 and len(lines) == 1 and "no position for array(s) A2" in lines[0], r.output
        assert "must be" not in lines[0] and not (tmp_path / f"exp.{fmt}").exists()


@pytest.mark.slow
def test_run_reports_the_runaway(tmp_path, monkeypatch):
    """`calib run` on a recorded session: exit 3 naming the divergence, a readable calibration and a report."""
    rec = small_lab3_session(tmp_path / "rec", seed=5, n_events=10, rt60=0.2)
    monkeypatch.setattr(est, "calibrate", _runaway(est.calibrate))
    r = CliRunner().invoke(app, ["run", str(rec), "-o", str(tmp_path / "out")])
    assert r.exit_code == 3 and "diverged" in r.output and "Traceback" not in r.output and "Warning" not in r.output, r.output
    assert (tmp_path / "out" / "report").is_dir()
    assert read_calibration(tmp_path / "out" / "calibration")["arrays"].loc[1:, "x"].isna().all()
