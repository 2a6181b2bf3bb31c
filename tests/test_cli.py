"""CLI behaviour of `calib estimate`, `calib evaluate` and `calib run`: one-line errors with exit code 2 and
nothing written on bad input; machine-readable --json; --quiet."""
import json
import shutil

import numpy as np
import pytest
from typer.testing import CliRunner

from calib.cli.main import app
from calib.estimator import calibrate
from calib.pipeline.report.evaluate import evaluate
from calib.pipeline.simulate.featsim import simulate_features
from calib.pipeline.formats.io import read_calibration, read_features, write_features, write_truth
from .sessions import small_lab3_session

runner = CliRunner()


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


def assert_user_error(r, *fragments):
    assert r.exit_code == 2, (r.exit_code, r.stdout, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), r.stderr
    for f in fragments:
        assert f in lines[0], (f, lines[0])


@pytest.fixture(scope="module")
def featdir(tmp_path_factory):
    feats, truth = simulate_features(trajectory=1, seed=2)
    d = tmp_path_factory.mktemp("f")
    write_features(d / "features", feats)
    write_truth(d / "truth", truth)
    return d, feats, truth


def test_estimate_bad_inputs(featdir, tmp_path):
    d, _, _ = featdir
    assert_user_error(invoke("estimate", tmp_path / "none", "-o", tmp_path / "c1"), "none: not a directory")
    bad = tmp_path / "bad"
    shutil.copytree(d / "features", bad)
    lines = (bad / "tdoa_m.csv").read_text().splitlines()
    lines[3] = lines[3].rsplit(",", 1)[0] + ",abc"
    (bad / "tdoa_m.csv").write_text("\n".join(lines) + "\n")
    assert_user_error(invoke("estimate", bad, "-o", tmp_path / "c2"), "tdoa_m.csv", "line 4", "not a number")
    assert_user_error(invoke("estimate", d / "features", "-o", tmp_path / "c3", "--method", "magic"), "--method")
    few = tmp_path / "few"
    shutil.copytree(d / "features", few)
    ev = (few / "events.csv").read_text().splitlines()
    (few / "events.csv").write_text("\n".join(ev[:3]) + "\n")  # events 0, 1 only
    for name in ("tdoa_m.csv", "tdoa_s.csv", "doa.csv"):
        rows = (few / name).read_text().splitlines()
        keep = [rows[0]] + [r for r in rows[1:] if all(f in ("0", "1") for f in _event_fields(name, r))]
        (few / name).write_text("\n".join(keep) + "\n")
    assert_user_error(invoke("estimate", few, "-o", tmp_path / "c4"), "at least 3")
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(("c", ".c"))]  # nothing written


def test_estimate_names_a_wrong_speed_of_sound(tmp_path):
    """The set-up findings a features folder shows (computed in a second process beside the estimator) reach
    report.json and the verdict: meta.json's speed of sound against the odometry's metric scale (trajectory 3:
    14 events, enough arrivals per array beyond the fit's unknowns; trajectory 1's 8 are not)."""
    wrong = tmp_path / "wrong"
    write_features(wrong, simulate_features(trajectory=3, seed=2)[0])
    meta = json.loads((wrong / "meta.json").read_text())
    (wrong / "meta.json").write_text(json.dumps({**meta, "speed_of_sound": 300.0}))
    r = invoke("estimate", wrong, "-o", tmp_path / "cal", "-q")
    assert r.exit_code == 3, (r.exit_code, r.stdout, r.stderr)
    rep = json.loads((tmp_path / "cal" / "report.json").read_text())
    assert rep["verdict"]["status"] == "failed" and "speed_of_sound = 300" in json.dumps(rep["setup"])


def _event_fields(name, row):
    f = row.split(",")
    return [f[0]] if name in ("tdoa_m.csv", "doa.csv") else [f[1], f[2]]


def test_estimate_then_evaluate_json(featdir, tmp_path):
    d, feats, truth = featdir
    r = invoke("estimate", d / "features", "-o", tmp_path / "cal", "-q")
    assert r.exit_code == 0 and r.stdout == ""
    got = read_calibration(tmp_path / "cal")
    want = calibrate(read_features(d / "features"))["arrays"]  # the CLI = the library on the same files
    np.testing.assert_allclose(got["arrays"][["x", "y", "z"]].to_numpy(), want[["x", "y", "z"]].to_numpy(), atol=1e-9)
    r = invoke("evaluate", tmp_path / "cal", d / "truth", "--json")
    assert r.exit_code == 0 and len(r.stdout.strip().splitlines()) == 1
    m = json.loads(r.stdout)
    assert m["position_rmse_m"] == pytest.approx(evaluate(got, truth)["position_rmse_m"])
    assert_user_error(invoke("evaluate", tmp_path / "cal", tmp_path / "nowhere"), "nowhere: not a directory")


def test_estimate_array_noise_option_reaches_the_estimator(featdir, tmp_path):
    """--array-noise: per-array noise components, as ``calibrate(array_noise=True)`` on the same files."""
    d, _, _ = featdir
    for flag, out in (([], "plain"), (["--array-noise"], "per-array")):
        r = invoke("estimate", d / "features", "-o", tmp_path / out, "-q", "--noise", "estimate", *flag)
        assert r.exit_code == 0, r.stderr
    plain, per_array = (read_calibration(tmp_path / o)["report"]["sigmas"] for o in ("plain", "per-array"))
    want = calibrate(read_features(d / "features"), noise="estimate", array_noise=True)["report"]["sigmas"]
    assert plain["per_array_factor"] == {}
    assert per_array["per_array_factor"] == want["per_array_factor"] and set(want["per_array_factor"])


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    return small_lab3_session(tmp_path_factory.mktemp("rec") / "s", seed=5, n_events=6, rt60=0.15)


def test_run_bad_inputs_write_nothing(session, tmp_path):
    assert_user_error(invoke("run", tmp_path / "none", "-o", tmp_path / "o1"), "none: not a directory")
    assert_user_error(invoke("run", session, "-o", tmp_path / "o2", "--loss", "square"), "loss")
    broken = tmp_path / "broken"
    shutil.copytree(session, broken)
    (broken / "A2.wav").unlink()
    assert_user_error(invoke("run", broken, "-o", tmp_path / "o3"), "A2.wav", "file not found")
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(("o", ".o"))]


@pytest.mark.slow
def test_run_json_quiet_and_skip(session, tmp_path):
    out = tmp_path / "out"
    r = invoke("run", session, "-o", out, "--json")
    assert r.exit_code == 0, r.stderr
    first = json.loads(r.stdout)
    assert first["ran"] == ["features", "estimate", "report"] and first["skipped"] == []
    assert first["metrics"]["position_rmse_m"] < 0.15
    assert (out / "report" / "summary.md").is_file() and first["outputs"]["report"].endswith("summary.md")
    r = invoke("run", session, "-o", out, "-q")
    assert r.exit_code == 0 and r.stdout == "" and r.stderr == ""
    r = invoke("run", session, "-o", out)
    assert r.exit_code == 0
    assert "skipped" in r.stderr and "features" in r.stderr
    assert "Calibrated arrays" in r.stdout and "Calibration vs ground truth" in r.stdout
    assert "skipped (unchanged): features, estimate, report" in " ".join(r.stdout.split())


def test_one_command_line_loads_only_its_command():
    import subprocess
    import sys

    from calib.cli import main

    script = ("import sys; from calib.cli.main import app_for; app = app_for(['montecarlo', '--help']); "
              "print(sorted(c.name for c in app.registered_commands), "
              "[m for m in ('calib.estimator', 'calib.frontend.signals', 'scipy') if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "['montecarlo'] []"       # the study's parent: no estimator, frontend or scipy
    for name in main.COMMANDS:                      # each command's help is the same alone as among all
        one = CliRunner().invoke(main.app_for([name]), [name, "--help"])
        every = CliRunner().invoke(app, [name, "--help"])
        assert one.exit_code == every.exit_code == 0 and one.output == every.output
    assert [c.name for c in main.app_for(["nosuch"]).registered_commands] == list(main.COMMANDS)
