"""`calib import-bag`: events.csv from ROS 1 and ROS 2 bags (built here with rosbags itself), against the
analytic trajectory; the speaker's lever arm applied when the session is read."""
import numpy as np
import pandas as pd
import pytest
import soundfile as sf
from typer.testing import CliRunner

from calib.cli.main import app
from calib.errors import InputError
from calib.pipeline.formats.rosbag import bag_events, write_bag, yaw_of
from calib.pipeline.formats.session import read_session

T0 = 1.7e9  # a ROS time (s since 1970): events.csv's times are relative to the bag's start
RADIUS, OMEGA = 1.5, 0.2  # the robot drives a circle: radius (m), angular rate (rad/s)


def _circle(t):
    """Base pose on a counter-clockwise circle, heading along the motion (yaw = phase + π/2)."""
    ph = OMEGA * (t - T0)
    return RADIUS * np.cos(ph), RADIUS * np.sin(ph), np.full_like(t, 0.1), ph + np.pi / 2


def _odometry(rate=20.0, span=40.0):
    t = T0 + np.arange(0, span, 1 / rate)
    x, y, z, yaw = _circle(t)
    return pd.DataFrame({"t": t, "x": x, "y": y, "z": z, "yaw": np.angle(np.exp(1j * yaw))})  # wrapped, as logged


EMIT = T0 + np.array([1.013, 7.5, 12.25, 20.0, 33.3])


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def _bag(tmp_path, ros):
    path = tmp_path / ("log.bag" if ros == 1 else "log")
    write_bag(path, _odometry(), EMIT, ros=ros)
    return path


@pytest.mark.parametrize("ros", [1, 2])
def test_import_bag_interpolates_the_odometry_to_each_emission(tmp_path, ros):
    bag = _bag(tmp_path, ros)
    r = invoke("import-bag", bag, "-o", tmp_path / "rec" / "events.csv", "--emit-topic", "/chirp")
    assert r.exit_code == 0, r.output
    ev = pd.read_csv(tmp_path / "rec" / "events.csv")
    assert list(ev.columns) == ["event", "t_emit", "odom_x", "odom_y", "odom_z", "odom_yaw"]
    assert np.allclose(ev["t_emit"], EMIT - T0, atol=1e-6)  # the bag's first message is at T0
    x, y, z, yaw = _circle(EMIT)
    # linear interpolation of a 20 Hz circle: chord error ≤ R (ω Δt)² / 8 ≈ 1.9e-5 m
    assert np.allclose(ev["odom_x"], x, atol=3e-5) and np.allclose(ev["odom_y"], y, atol=3e-5)
    assert np.allclose(ev["odom_z"], z) and np.allclose(np.angle(np.exp(1j * (ev["odom_yaw"] - yaw))), 0, atol=1e-6)
    # the playback latency: time and pose taken that much later
    lat = bag_events(bag, "/odom", emit_topic="/chirp", latency=0.03)
    x, y, _, _ = _circle(EMIT + 0.03)
    assert np.allclose(lat["t_emit"], EMIT - T0 + 0.03, atol=1e-6) and np.allclose(lat["odom_x"], x, atol=3e-5)
    # the schedule and its start (a topic's first message, or a time)
    sched = tmp_path / "schedule.csv"
    pd.DataFrame({"event": range(5), "t_emit": EMIT - EMIT[0]}).to_csv(sched, index=False)
    r = invoke("import-bag", bag, "-o", tmp_path / "s.csv", "--schedule", sched, "--start-topic", "/chirp")
    assert r.exit_code == 0, r.output
    assert np.allclose(pd.read_csv(tmp_path / "s.csv")["odom_y"], ev["odom_y"], atol=1e-9)
    by_time = bag_events(bag, "/odom", schedule=EMIT - EMIT[0], start=EMIT[0])
    assert np.allclose(by_time["odom_x"], ev["odom_x"], atol=1e-9)


def test_yaw_of_quaternion_is_the_heading():
    for yaw in (-3.0, -0.5, 0.0, 1.2, 3.1):
        assert np.isclose(yaw_of(np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)), yaw)


def test_the_lever_arm_rotates_with_the_heading_when_the_session_is_read(tmp_path):
    write_bag(tmp_path / "log", _odometry(), EMIT, ros=2)
    assert invoke("import-bag", tmp_path / "log", "-o", tmp_path / "events.csv", "--emit-topic", "/chirp").exit_code == 0
    sf.write(tmp_path / "A.wav", np.zeros((1600, 1)), 16000)
    base = '[chirp]\nf0 = 500.0\nf1 = 4000.0\nduration = 0.1\n\n[[arrays]]\nname = "A"\nwav = "A.wav"\nmics = [[0, 0, 0]]\n'
    (tmp_path / "session.toml").write_text(base + "\n[robot]\nspeaker_offset = [0.15, -0.05, 0.3]\n")
    s = read_session(tmp_path)
    x, y, z, yaw = _circle(EMIT)
    # robot frame x forward, y left: the speaker at base + Rz(yaw) (0.15, -0.05, 0.3)
    want = np.column_stack([x + 0.15 * np.cos(yaw) + 0.05 * np.sin(yaw), y + 0.15 * np.sin(yaw) - 0.05 * np.cos(yaw),
                            z + 0.3])
    assert np.allclose(s["events"][["odom_x", "odom_y", "odom_z"]], want, atol=3e-5)
    assert "odom_yaw" not in s["events"].columns  # consumed: features/events.csv holds speaker positions
    (tmp_path / "session.toml").write_text(base)
    assert np.allclose(read_session(tmp_path)["events"][["odom_x", "odom_y"]], np.column_stack([x, y]), atol=3e-5)
    # a lever arm without a heading cannot be applied: one line
    pd.read_csv(tmp_path / "events.csv").drop(columns="odom_yaw").to_csv(tmp_path / "events.csv", index=False)
    (tmp_path / "session.toml").write_text(base + "\n[robot]\nspeaker_offset = [0.15, 0, 0]\n")
    with pytest.raises(InputError, match="speaker_offset needs the robot's heading: an odom_yaw column"):
        read_session(tmp_path)


def test_bad_bags_and_options_are_one_line_errors(tmp_path):
    bag = _bag(tmp_path, 1)
    out = tmp_path / "events.csv"
    cases = [
        (["--emit-topic", "/nope"], "no topic '/nope' (topics: /chirp, /odom)"),
        (["--emit-topic", "/chirp", "--odom-topic", "/chirp"], "topic '/chirp' is std_msgs/msg/Header, not nav_msgs"),
        ([], "either as a topic (--emit-topic) or as a schedule"),
        (["--emit-topic", "/chirp", "--latency", "100"], "--latency"),
    ]
    for opts, message in cases:
        r = invoke("import-bag", bag, "-o", out, *opts)
        assert r.exit_code == 2 and message in r.stderr and r.stderr.count("\n") == 1, (opts, r.stderr)
        assert not out.exists()
    r = invoke("import-bag", bag, "-o", out, "--schedule", tmp_path / "none.csv", "--start", 0)
    assert r.exit_code == 2 and "none.csv" in r.stderr
    pd.DataFrame({"event": range(3), "t_emit": [0.0, 1.0, 99.0]}).to_csv(tmp_path / "late.csv", index=False)
    r = invoke("import-bag", bag, "-o", out, "--schedule", tmp_path / "late.csv", "--start", T0)
    assert r.exit_code == 2 and "emission 2" in r.stderr and "outside the odometry" in r.stderr
    (tmp_path / "junk.bag").write_bytes(b"not a bag")
    r = invoke("import-bag", tmp_path / "junk.bag", "-o", out, "--emit-topic", "/chirp")
    assert r.exit_code == 2 and "not a readable ROS 1 or ROS 2 bag" in r.stderr
    out.write_text("mine\n")
    r = invoke("import-bag", bag, "-o", out, "--emit-topic", "/chirp")
    assert r.exit_code == 2 and "exists (use --force" in r.stderr and out.read_text() == "mine\n"


def test_a_constant_playback_latency_leaves_the_calibration_unchanged():
    """docs/formats.md: every emission time and the clock model's t_0 shift together, so a constant latency
    changes no arrival time: the estimator's result is the same to rounding (it needs no latency parameter;
    the latency matters only through the pose of a robot moving while it plays, which import-bag handles)."""
    from calib.estimator import calibrate
    from calib.pipeline.simulate.featsim import simulate_features

    feats, _ = simulate_features(3, seed=5)
    late = {**feats, "events": feats["events"].assign(t_emit=feats["events"]["t_emit"] + 0.025)}
    a, b = calibrate(feats), calibrate(late)
    cols = ["x", "y", "z", "qw", "qx", "qy", "qz", "offset", "drift"]
    assert np.allclose(a["arrays"][cols], b["arrays"][cols], atol=1e-9, rtol=0)
    assert np.allclose(a["sources"][["x", "y", "z"]], b["sources"][["x", "y", "z"]], atol=1e-9, rtol=0)
