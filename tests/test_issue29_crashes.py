"""Crash reports of issue 29 reproduced: every DOA negated (an IndexError in the estimator: the reference array
dropped and refitted alone with nothing free), a TDOA-S row spanning many events (accepted; a NumPy repr in
its cell is refused with a hint)."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from calib.cli.main import app
from calib.errors import InputError
from calib.estimator.problem import Layout, _without_fixed
from calib.pipeline.formats.io import read_features

from .sessions import REAL_WORLD as REAL  # noqa: E402
runner = CliRunner()


def test_an_empty_layout_with_fixed_columns_stays_empty():
    """The reference array refitted alone (its drift held): no free parameter; the observability's fixed columns
    must not index into the empty renumbering."""
    N, K = 3, 5
    lay = Layout(x=-np.ones((N, 3), int), rot=-np.ones((N, 3), int), offset=-np.ones(N, int),
                 drift=-np.ones(N, int), s=-np.ones((K, 3), int), e=-np.ones(K, int), odo_yaw=-np.ones(1, int), n=0)
    out = _without_fixed(lay, {"drift": np.array([False, True, False])})
    assert out.n == 0 and np.all(out.drift == -1) and np.all(out.x == -1)


@pytest.mark.slow
@pytest.mark.skipif(not REAL.is_dir(), reason="the real feature sets are not here")
@pytest.mark.parametrize("k", [1, 5])
def test_every_doa_negated_ends_failed_not_in_a_traceback(tmp_path, k):
    feats = tmp_path / "features"
    shutil.copytree(REAL / f"zhang_real_{k:02d}" / "features", feats)
    doa = pd.read_csv(feats / "doa.csv")
    doa[["ux", "uy", "uz"]] *= -1
    doa.to_csv(feats / "doa.csv", index=False)
    r = runner.invoke(app, ["estimate", str(feats), "-o", str(tmp_path / "cal"), "-q"])
    assert r.exit_code == 3, r.output
    rep = (tmp_path / "cal" / "report.json").read_text()
    assert "mirrored" in rep and "away from" in rep


def _sample_features(tmp_path):
    src = Path(__file__).resolve().parents[1] / "sample_data" / "lab3"
    feats = tmp_path / "features"
    assert runner.invoke(app, ["features", str(src), "-o", str(feats), "-q"]).exit_code == 0
    return feats


@pytest.mark.slow
def test_a_tdoa_s_row_spanning_many_events_is_read(tmp_path):
    """A row from the first to the last event (the chain's sum) is a valid measurement; written as a NumPy repr
    (a script's ``f"{x!r}"``), its cell is refused naming the line and the fix."""
    feats = _sample_features(tmp_path)
    t = pd.read_csv(feats / "tdoa_s.csv")
    a = t[t["array"] == "A2"].sort_values("from_event")
    long = {"array": "A2", "from_event": int(a["from_event"].min()), "to_event": int(a["to_event"].max()),
            "tdoa": float(a["tdoa"].sum())}
    pd.concat([t[t["array"] != "A2"], pd.DataFrame([long])]).to_csv(feats / "tdoa_s.csv", index=False)
    got = read_features(feats)["tdoa_s"]
    row = got[(got["array"] == "A2")].iloc[0]
    assert row["to_event"] - row["from_event"] > 10 and np.isclose(row["tdoa"], long["tdoa"])
    r = runner.invoke(app, ["estimate", str(feats), "-o", str(tmp_path / "cal"), "-q"])
    assert r.exit_code in (0, 3) and "internal error" not in r.output
    text = (feats / "tdoa_s.csv").read_text().replace(f"{long['tdoa']:.10g}", f"np.float64({long['tdoa']})")
    text = text.replace(repr(long["tdoa"]), f"np.float64({long['tdoa']})")
    (feats / "tdoa_s.csv").write_text(text)
    with pytest.raises(InputError, match=r"line \d+: 'tdoa' is not a number \(a NumPy repr"):
        read_features(feats)
