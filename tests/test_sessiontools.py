"""calib chirp, calib init and calib check against hand-derived values and simulated sessions."""
import re
import shutil

import numpy as np
import pandas as pd
import pytest
import soundfile as sf
from typer.testing import CliRunner

from calib.cli.main import app
from .sessions import small_lab3_session
from calib.pipeline.formats.session import read_session
from calib.pipeline.formats.boards import BOARDS
from calib.pipeline.sessiontools import check_session, emission_schedule


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def test_chirp_wav_is_the_linear_sweep_and_schedule_respects_the_jitter(tmp_path):
    r = invoke("chirp", "-o", tmp_path, "--fs", 16000, "--n-events", 12, "--duration", 0.25, "--fade", 0, "-q")
    assert r.exit_code == 0, r.output
    x, fs = sf.read(tmp_path / "chirp.wav")
    assert fs == 16000 and len(x) == 4000
    u = np.arange(len(x)) / fs  # the linear sweep by its phase formula: 2π(f0 u + (f1 − f0) u² / 2T)
    want = 0.5 * np.sin(2 * np.pi * (500 * u + 0.5 * 3500 / 0.25 * u * u))
    assert np.abs(x - want).max() < 2 ** -22  # PCM_24
    sched = pd.read_csv(tmp_path / "schedule.csv")
    assert list(sched["event"]) == list(range(12))
    gaps = np.diff(sched["t_emit"])
    assert gaps.min() >= 2.0 * 0.75 - 1e-6 and gaps.max() <= 2.0 * 1.25 + 1e-6 and np.std(gaps) > 0.05
    # chirp.toml is a valid [chirp] table with the WAV as its exact reference
    sf.write(tmp_path / "A.wav", np.zeros((1600, 1)), 16000)
    body = (tmp_path / "chirp.toml").read_text()
    (tmp_path / "session.toml").write_text(body + '\n[[arrays]]\nname = "A"\nwav = "A.wav"\nmics = [[0, 0, 0]]\n')
    sched.assign(odom_x=0.0, odom_y=0.0, odom_z=0.0).to_csv(tmp_path / "events.csv", index=False)
    s = read_session(tmp_path)
    assert s["chirp"]["reference"].name == "chirp.wav" and s["chirp"]["f1"] == 4000.0
    assert invoke("chirp", "-o", tmp_path / "b", "--duration", 2.0).exit_code == 2  # longer than the interval
    with pytest.raises(ValueError):
        emission_schedule(2)


def _wav(path, channels, fs=16000):
    sf.write(path, np.zeros((160, channels)), fs)


def test_init_writes_a_session_for_each_model(tmp_path):
    for model, spec in BOARDS.items():
        d = tmp_path / model
        d.mkdir()
        _wav(d / "left.wav", len(spec.mics))
        _wav(d / "right.wav", len(spec.mics))
        r = invoke("init", d, "--model", model, "--reference", "right", "-q")
        assert r.exit_code == 0, r.output
        pd.DataFrame({"event": [0, 1, 2], "t_emit": [1.0, 2.0, 3.0], "odom_x": 0.0, "odom_y": 0.0,
                      "odom_z": 0.0}).to_csv(d / "events.csv", index=False)
        s = read_session(d)
        assert s["reference_array"] == "right" and [a["name"] for a in s["arrays"]] == ["left", "right"]
        assert np.allclose(s["arrays"][0]["mics"], spec.mics) and s["arrays"][0]["channels"] is None
    m = BOARDS["respeaker-6-circular"].mic_array()
    assert np.allclose(np.linalg.norm(m, axis=1), 0.0463, atol=1e-4)  # ODAS: circular, R = 46.3 mm
    # a WAV whose channel count does not fit its model: one line, exit 2, nothing written
    d = tmp_path / "bad"
    d.mkdir()
    _wav(d / "a.wav", 4)
    r = invoke("init", d, "--model", "minidsp-uma8")
    assert r.exit_code == 2 and "4 channels, but a minidsp-uma8 has 7 mics (raw layout: 8 channels)" in r.stderr
    assert not (d / "session.toml").exists()
    r = invoke("init", d, "--model", "a=custom")
    assert r.exit_code == 0 and np.allclose(read_session_mics(d / "session.toml"), 0)
    assert invoke("init", d, "--model", "custom").exit_code == 2  # exists: --force needed


def read_session_mics(path):
    from calib.tomlcompat import tomllib

    return np.asarray(tomllib.loads(path.read_text())["arrays"][0]["mics"])


@pytest.fixture(scope="module")
def small_session(tmp_path_factory):
    return small_lab3_session(tmp_path_factory.mktemp("chk") / "rec", seed=2, n_events=5, rt60=0.0)


def test_check_passes_a_good_session_and_lists_every_problem(small_session, tmp_path):
    rows = check_session(small_session)
    assert (rows["status"] != "FAIL").all(), rows
    assert set(rows.loc[rows["check"] == "chirp audible", "what"]) == {"A1", "A2", "A3"}
    bad = tmp_path / "rec"
    shutil.copytree(small_session, bad)
    x, fs = sf.read(bad / "A2.wav")
    sf.write(bad / "A2.wav", x[:, :4], fs)                      # channels ≠ mics
    sf.write(bad / "A3.wav", np.zeros((fs, x.shape[1])), fs)    # silent and too short
    ev = pd.read_csv(bad / "events.csv")
    ev.loc[4, ["odom_x"]] = 50.0                                # an implausible odometry jump
    ev.to_csv(bad / "events.csv", index=False)
    r = invoke("check", bad)
    assert r.exit_code == 2
    rows = check_session(bad)
    fails = set(zip(rows.loc[rows["status"] == "FAIL", "what"], rows.loc[rows["status"] == "FAIL", "check"]))
    assert ("A2", "channels vs mics") in fails and ("A3", "duration") in fails
    assert ((rows["check"] == "odometry steps") & (rows["status"] == "warn")).any()
    assert "FAIL" in r.stdout and "A2" in r.stdout
    # a custom session.toml whose mics were never filled in
    zeros = tmp_path / "zeros"
    shutil.copytree(small_session, zeros)
    text = (zeros / "session.toml").read_text()
    (zeros / "session.toml").write_text(re.sub(r"mics = \[.*\]", "mics = " + str([[0.0, 0.0, 0.0]] * 6), text))
    rows = check_session(zeros, detect=False)
    fail = rows[rows["status"] == "FAIL"]
    assert len(fail) == 1 and "same place" in fail["detail"].iloc[0] and "'A1'" in fail["detail"].iloc[0]
