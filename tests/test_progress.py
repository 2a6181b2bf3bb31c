"""Progress of long commands where stderr is not a terminal (a log file): plain timestamped lines."""
import re

from typer.testing import CliRunner

from calib.cli.main import app


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def test_progress_is_plain_timestamped_lines_in_a_log_file(tmp_path):
    """stderr not a terminal (a log file, CliRunner): `calib simulate` and `calib features` still say how far
    they are, as `HH:MM:SS name: done/total message` lines."""
    r = invoke("simulate", "-o", tmp_path / "rec", "--preset", "lab3", "--n-events", 3, "--interval", 1,
               "--chirp-duration", 0.1, "--rt60", 0)
    assert r.exit_code == 0, r.output
    assert re.search(r"^\d\d:\d\d:\d\d simulate: (\d+)/\1 ", r.stderr, re.M), r.stderr
    r = invoke("features", tmp_path / "rec", "-o", tmp_path / "feat")
    assert r.exit_code == 0, r.output
    assert re.search(r"^\d\d:\d\d:\d\d features: (\d+)/\1", r.stderr, re.M), r.stderr
