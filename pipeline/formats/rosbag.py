"""Robot logs: ``events.csv`` (docs/formats.md) from a ROS 1 or ROS 2 bag, without a ROS install.

The bag is read with ``rosbags`` (pure Python; ROS 1 ``.bag`` files and ROS 2 bag folders alike).

- Odometry: a ``nav_msgs/Odometry`` topic, its ``header.stamp`` times; the robot base's position and heading
  (yaw of its orientation, rad) are interpolated linearly (yaw unwrapped) to each emission.
- Emission times: the header stamps of the messages of a topic (the time the robot logged "chirp played";
  the bag's record time for a message without a header), or a chirp schedule (``calib chirp``'s
  ``schedule.csv``) started at a given time.
- Playback latency ``latency`` (s): the sound leaves the speaker this long after the logged time; the
  emission is taken at logged + latency (time and pose).

The result has the robot base's pose, ``odom_x, odom_y, odom_z, odom_yaw``: session.toml's
``[robot] speaker_offset`` (the speaker in the robot frame) turns it into the speaker's position when the
session is read (:func:`calib.pipeline.formats.session.speaker_positions`). Times are seconds since the bag's
first message (small numbers: only differences matter).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from calib.errors import InputError

ODOMETRY_TYPES = ("nav_msgs/msg/Odometry", "nav_msgs/Odometry")
NS = 1e-9


def _stamp(msg, t_record):
    """A message's header stamp in s (ROS 1 ``secs/nsecs`` or ROS 2 ``sec/nanosec``), else its record time."""
    h = getattr(msg, "header", None)
    if h is None:
        return t_record * NS
    s = h.stamp
    return float(getattr(s, "sec", 0)) + float(getattr(s, "nanosec", 0)) * NS


def yaw_of(qw, qx, qy, qz):
    """Heading (rad) of an orientation quaternion: the rotation about z of its x axis (ZYX yaw)."""
    return np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy * qy + qz * qz))


def _open(bag):
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    path = Path(bag)
    if not path.exists():
        raise InputError(f"{path}: file not found")
    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as exc:  # rosbags raises its own errors for every kind of unreadable bag
        why = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise InputError(f"{path}: not a readable ROS 1 or ROS 2 bag ({why})") from None
    return reader


def _connections(reader, topic, bag):
    conns = [c for c in reader.connections if c.topic == topic]
    if not conns:
        have = ", ".join(sorted({c.topic for c in reader.connections})) or "none"
        raise InputError(f"{bag}: no topic {topic!r} (topics: {have})")
    return conns


def read_odometry(reader, topic, bag):
    """DataFrame t (s), x, y, z (m), yaw (rad, unwrapped) of a nav_msgs/Odometry topic, sorted by time."""
    conns = _connections(reader, topic, bag)
    bad = [c.msgtype for c in conns if c.msgtype not in ODOMETRY_TYPES]
    if bad:
        raise InputError(f"{bag}: topic {topic!r} is {bad[0]}, not nav_msgs/Odometry")
    rows = []
    for conn, t, raw in reader.messages(connections=conns):
        m = reader.deserialize(raw, conn.msgtype)
        p, q = m.pose.pose.position, m.pose.pose.orientation
        rows.append((_stamp(m, t), p.x, p.y, p.z, yaw_of(q.w, q.x, q.y, q.z)))
    odo = pd.DataFrame(rows, columns=["t", "x", "y", "z", "yaw"]).sort_values("t", kind="stable")
    if len(odo) < 2:
        raise InputError(f"{bag}: topic {topic!r} has {len(odo)} message(s); odometry needs at least 2")
    odo["yaw"] = np.unwrap(odo["yaw"].to_numpy())
    return odo.reset_index(drop=True)


def read_times(reader, topic, bag):
    """(n,) s: the time of each message of ``topic`` (header stamp, else record time), sorted."""
    conns = _connections(reader, topic, bag)
    return np.sort([_stamp(reader.deserialize(raw, conn.msgtype), t)
                    for conn, t, raw in reader.messages(connections=conns)])


def interpolate_pose(odo, t, bag="bag"):
    """(n, 4) x, y, z, yaw of the odometry at times ``t`` (linear; every t within the odometry's span)."""
    t = np.asarray(t, float)
    lo, hi = odo["t"].iloc[0], odo["t"].iloc[-1]
    out = (t < lo) | (t > hi)
    if out.any():
        k = int(np.flatnonzero(out)[0])
        raise InputError(f"{bag}: emission {k} at {t[k]:.3f} s is outside the odometry ({lo:.3f} .. {hi:.3f} s)")
    return np.column_stack([np.interp(t, odo["t"], odo[c]) for c in ("x", "y", "z", "yaw")])


def bag_events(bag, odom_topic, *, emit_topic=None, schedule=None, start=None, start_topic=None, latency=0.0):
    """The events of a bag: DataFrame event, t_emit (s since the bag's start), odom_x, odom_y, odom_z, odom_yaw.

    Emission times: the messages of ``emit_topic``, or ``schedule`` ((n,) s, e.g. schedule.csv's t_emit)
    plus a start: ``start`` (s, the bag's clock) or the first message of ``start_topic``. ``latency`` (s) is
    added to every emission time before the pose is interpolated.
    """
    if (emit_topic is None) == (schedule is None):
        raise InputError("give the emission times either as a topic (--emit-topic) or as a schedule (--schedule)")
    if schedule is not None and (start is None) == (start_topic is None):
        raise InputError("a schedule needs its start: --start SECONDS or --start-topic TOPIC")
    reader = _open(bag)
    try:
        t0 = reader.start_time * NS
        odo = read_odometry(reader, odom_topic, bag)
        if emit_topic is not None:
            t = read_times(reader, emit_topic, bag)
        else:
            s0 = start if start is not None else read_times(reader, start_topic, bag)[0]
            t = s0 + np.asarray(schedule, float)
    finally:
        reader.close()
    if len(t) < 3:
        raise InputError(f"{bag}: {len(t)} emission(s); calib needs at least 3")
    t = t + float(latency)
    pose = interpolate_pose(odo, t, bag)
    return pd.DataFrame({"event": np.arange(len(t)), "t_emit": t - t0, "odom_x": pose[:, 0], "odom_y": pose[:, 1],
                         "odom_z": pose[:, 2], "odom_yaw": pose[:, 3]})


EMIT_TYPE = "std_msgs/msg/Header"  # what write_bag logs per chirp: a header (stamp = the logged emission time)


def _time(typestore, t):
    sec = int(np.floor(t))
    return typestore.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((t - sec) * 1e9)) % 1_000_000_000)


def _odometry_msg(ts, t, x, y, z, yaw, frame="odom"):
    T = ts.types
    header = T["std_msgs/msg/Header"](stamp=_time(ts, t), frame_id=frame)
    pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=x, y=y, z=z),
                                       orientation=T["geometry_msgs/msg/Quaternion"](
                                           x=0.0, y=0.0, z=float(np.sin(yaw / 2)), w=float(np.cos(yaw / 2))))
    cov = np.zeros(36)
    twist = T["geometry_msgs/msg/Twist"](linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                                         angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0))
    return T["nav_msgs/msg/Odometry"](header=header, child_frame_id="base_link",
                                      pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov),
                                      twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=cov))


def write_bag(path, odometry, emit_times, *, ros=2, odom_topic="/odom", emit_topic="/chirp"):
    """Write a small bag (simulations and tests): ``odometry`` DataFrame t (s), x, y, z, yaw (rad) as
    nav_msgs/Odometry on ``odom_topic``, and one std_msgs/Header per emission (stamp = the logged time) on
    ``emit_topic``. ``ros``: 1 (a ``.bag`` file) or 2 (a bag folder, sqlite3). Record time = stamp."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    msgs = [(float(r.t), odom_topic, _odometry_msg(ts, r.t, r.x, r.y, r.z, r.yaw)) for r in odometry.itertuples()]
    msgs += [(float(t), emit_topic, ts.types[EMIT_TYPE](stamp=_time(ts, t), frame_id="speaker")) for t in emit_times]
    msgs.sort(key=lambda m: m[0])
    typename = {odom_topic: "nav_msgs/msg/Odometry", emit_topic: EMIT_TYPE}
    if ros == 1:
        from rosbags.rosbag1 import Writer

        writer, ser = Writer(Path(path)), ts.serialize_ros1
    else:
        from rosbags.rosbag2 import Writer

        writer, ser = Writer(Path(path), version=9), ts.serialize_cdr
    with writer:
        conns = {topic: writer.add_connection(topic, typ, typestore=ts) for topic, typ in typename.items()}
        for t, topic, m in msgs:
            writer.write(conns[topic], int(round(t * 1e9)), ser(m, typename[topic]))
