"""`calib init --force` and the single-file writer rule (issue 29): a session.toml calib wrote, whichever of its
session writers wrote it (`calib init`, `calib simulate`), is replaced with --force; a hand-edited one, or one
of another kind of command, never."""
from __future__ import annotations

import json

from typer.testing import CliRunner

from calib.cli.main import app
from calib.pipeline.formats.outputs import MARKER
from calib.pipeline.simulate.roomsim import make_scenario, simulate

from .sessions import EVENT_INTERVAL, SHORT_CHIRP

runner = CliRunner()


def test_init_force_replaces_the_session_toml_of_calib_simulate(tmp_path):
    rec = simulate(make_scenario("lab3", 3, n_events=3, interval=EVENT_INTERVAL, chirp=SHORT_CHIRP, rt60=0.0),
                   tmp_path / "rec")
    assert json.loads((rec / MARKER).read_text())["command"] == "calib simulate"
    before = (rec / "session.toml").read_text()
    init = ["init", str(rec), "--model", "respeaker-6-circular", "-q"]
    r = runner.invoke(app, init)
    assert r.exit_code == 2 and "--force" in r.stderr and (rec / "session.toml").read_text() == before
    r = runner.invoke(app, init + ["--force"])
    assert r.exit_code == 0, r.stderr
    assert (rec / "session.toml").read_text() != before
    assert runner.invoke(app, init + ["--force"]).exit_code == 0  # now init's own: replaced again
    (rec / "session.toml").write_text((rec / "session.toml").read_text() + "# my edit\n")
    r = runner.invoke(app, init + ["--force"])
    assert r.exit_code == 2 and "edited" in r.stderr
    assert (rec / "session.toml").read_text().endswith("# my edit\n")


def test_init_force_never_replaces_another_commands_file(tmp_path):
    """events.csv written by `calib simulate` is a recording's log, not a session.toml: init -o onto it stops."""
    rec = simulate(make_scenario("lab3", 3, n_events=3, interval=EVENT_INTERVAL, chirp=SHORT_CHIRP, rt60=0.0),
                   tmp_path / "rec")
    before = (rec / "events.csv").read_bytes()
    r = runner.invoke(app, ["init", str(rec), "-o", str(rec / "events.csv"), "--force", "-q"])
    assert r.exit_code == 2 and (rec / "events.csv").read_bytes() == before
