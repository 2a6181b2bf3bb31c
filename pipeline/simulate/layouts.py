"""Rewrite a simulated session into the layouts real hardware and robots produce (the renderer is untouched):

- :func:`to_board_layout`: each array's WAV as a board's raw recording (``calib.pipeline.formats.boards``):
  the mics on the board's channels, the other channels (processed beam, playback loopback, unused slot)
  filled with independent noise as loud as the mics, so a wrong channel cannot go unnoticed; session.toml
  gets the board's ``channels`` map.
- :func:`to_per_mic`: one mono WAV per mic, ``<array>-<m>.wav`` (the seed paper's ``arr<i>-<m>.wav`` layout),
  session.toml lists them as ``files``.
- :func:`to_bag`: the robot's log as a ROS 1 or ROS 2 bag instead of events.csv: the robot base's odometry
  (the speaker sits at ``speaker_offset`` in the robot frame, the robot heading along its path) and one
  message per chirp logged ``latency`` s before the sound leaves the speaker; session.toml gets
  ``[robot] speaker_offset``. ``calib import-bag`` then writes events.csv.

Each copies everything else (chirp.wav, truth/) as it is; the converted session calibrates to the same truth.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import soundfile as sf

from calib.errors import InputError
from calib.geometry import yaw_rotate
from calib.pipeline.formats.boards import BOARDS
from calib.pipeline.formats.io import read_events
from calib.pipeline.formats.rosbag import write_bag
from calib.pipeline.formats.outputs import BOOKKEEPING
from calib.pipeline.formats.session import write_session_toml
from calib.tomlcompat import tomllib

BAG_T0 = 1.7e9        # s: the bag's clock (a ROS time) at the session's time 0
ODOMETRY_RATE = 50.0  # Hz: the robot's odometry messages
STOP_BEFORE = 0.2     # s: the robot stands still this long before the logged emission ...
STOP_AFTER = 0.1      # s: ... until this long after the chirp ends (it stops for each chirp, as calib chirp asks)


def _copy_rest(src, dst, skip):
    """Copy every file and folder of ``src`` but the names in ``skip`` (and session.toml) into a new ``dst``.

    calib's bookkeeping (``outputs.BOOKKEEPING``: the manifest of what calib wrote in ``src``, stamps) is not
    copied: it describes ``src``'s files, not the rewritten ones."""
    src, dst = Path(src), Path(dst)
    if dst.exists():
        raise InputError(f"{dst}: exists")
    dst.mkdir(parents=True)
    for p in src.iterdir():
        if p.name in skip or p.name == "session.toml" or p.name in BOOKKEEPING:
            continue
        (shutil.copytree if p.is_dir() else shutil.copy2)(p, dst / p.name)
    return tomllib.loads((src / "session.toml").read_text())


def _write_toml(dst, cfg, arrays, robot=None):
    write_session_toml(dst / "session.toml", speed_of_sound=cfg.get("speed_of_sound", 343.0),
                       reference_array=cfg["reference_array"], chirp=cfg["chirp"], arrays=arrays,
                       noise=cfg.get("noise"), robot=robot)


def to_board_layout(src, dst, board, seed=0, arrays=None, session_toml=True):
    """``src`` session → ``dst`` with the WAVs of ``arrays`` (names; default all, each with the board's mic
    count) in ``board``'s raw layout; the other arrays' WAVs are copied as they are. ``session_toml=False``
    leaves session.toml out, as a board's own recording comes (``calib init`` writes it)."""
    b = BOARDS[board]
    cfg = tomllib.loads((Path(src) / "session.toml").read_text())
    names = [a["name"] for a in cfg["arrays"]] if arrays is None else list(arrays)
    _copy_rest(src, dst, {a["wav"] for a in cfg["arrays"] if a["name"] in names})
    rng = np.random.default_rng(seed)
    out = []
    for a in cfg["arrays"]:
        if a["name"] not in names:
            out.append(a)
            continue
        x, fs = sf.read(Path(src) / a["wav"], always_2d=True, dtype="float32")
        info = sf.info(str(Path(src) / a["wav"]))
        if x.shape[1] != len(b.channels):
            raise InputError(f"{a['wav']}: {x.shape[1]} mics, a {board} has {len(b.channels)}")
        raw = (rng.standard_normal((len(x), b.raw_channels)) * np.std(x)).astype(np.float32)
        raw[:, list(b.channels)] = x
        sf.write(Path(dst) / a["wav"], raw, fs, subtype=info.subtype)
        out.append({**a, "channels": list(b.channels)})
    if session_toml:
        _write_toml(Path(dst), cfg, out)
    return Path(dst)


def to_per_mic(src, dst, session_toml=True):
    """``src`` session → ``dst`` with one mono WAV per mic, ``<array>-<m>.wav`` (m from 1), listed as ``files``
    (``session_toml=False``: none written, as a recorder leaves it)."""
    cfg = tomllib.loads((Path(src) / "session.toml").read_text())
    _copy_rest(src, dst, {a["wav"] for a in cfg["arrays"]})
    arrays = []
    for a in cfg["arrays"]:
        x, fs = sf.read(Path(src) / a["wav"], always_2d=True, dtype="float32")
        info = sf.info(str(Path(src) / a["wav"]))
        files = [f"{a['name']}-{m + 1}.wav" for m in range(x.shape[1])]
        for m, f in enumerate(files):
            sf.write(Path(dst) / f, x[:, m], fs, subtype=info.subtype)
        arrays.append({k: v for k, v in a.items() if k != "wav"} | {"files": files})
    if session_toml:
        _write_toml(Path(dst), cfg, arrays)
    return Path(dst)


def headings(pos):
    """(K,) heading (rad) of a robot at stops ``pos`` (K, 3): along its way to the next stop (the last: from the
    one before), i.e. it turns on the spot, then drives straight."""
    d = np.diff(pos[:, :2], axis=0)
    d = np.vstack([d, d[-1:]])
    return np.arctan2(d[:, 1], d[:, 0])


def robot_path(ev, speaker_offset, latency, chirp_duration):
    """The robot base's odometry (DataFrame t, x, y, z, yaw; t on the session's clock) and the logged emission
    times (K,) of a session's events (speaker positions ``ev``): base = speaker − Rz(yaw) · offset, still from
    STOP_BEFORE before each logged emission to STOP_AFTER after its chirp, moving linearly between stops."""
    spk = ev[["odom_x", "odom_y", "odom_z"]].to_numpy(float)
    yaw = np.unwrap(headings(spk))
    off = np.asarray(speaker_offset, float)
    base = spk - yaw_rotate(off, yaw)
    t_true = ev["t_emit"].to_numpy(float)
    t_log = t_true - latency
    knots_t = np.column_stack([t_log - STOP_BEFORE, t_true + chirp_duration + STOP_AFTER]).ravel()
    if np.any(np.diff(knots_t) <= 0):
        raise InputError("the chirps are too close for the robot to stop for each (interval < chirp + stops)")
    knots = np.repeat(np.column_stack([base, yaw]), 2, axis=0)
    t = np.arange(knots_t[0] - 1.0, knots_t[-1] + 1.0, 1.0 / ODOMETRY_RATE)
    odo = pd.DataFrame({"t": t, **{c: np.interp(t, knots_t, knots[:, k]) for k, c in enumerate(("x", "y", "z", "yaw"))}})
    odo["yaw"] = np.angle(np.exp(1j * odo["yaw"]))  # as a robot logs it: wrapped to (−π, π]
    return odo, t_log


def to_bag(src, dst, *, ros=2, speaker_offset=(0.15, 0.0, 0.25), latency=0.02):
    """``src`` session → ``dst`` whose robot log is a bag (``dst/robot.bag`` for ROS 1, ``dst/robot`` for ROS 2)
    with the base's odometry on /odom and the logged emissions on /chirp, and no events.csv (``calib
    import-bag dst/robot... -o dst/events.csv --emit-topic /chirp --latency L`` writes it). Returns the bag."""
    cfg = _copy_rest(src, dst, {"events.csv"})
    ev = read_events(Path(src) / "events.csv")
    odo, t_log = robot_path(ev, speaker_offset, latency, cfg["chirp"]["duration"])
    odo["t"] += BAG_T0
    bag = Path(dst) / ("robot.bag" if ros == 1 else "robot")
    write_bag(bag, odo, t_log + BAG_T0, ros=ros)
    _write_toml(Path(dst), cfg, cfg["arrays"], robot={"speaker_offset": list(speaker_offset)})
    return bag
