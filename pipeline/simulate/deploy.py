"""Layouts of the deployment presets of the room simulator (issue 27): non-convex rooms, a robot that keeps
moving while it chirps, boards of different makes and sample rates in one session, large low-SNR halls,
talkers and broadband interferers, arrays occluded by obstacles.

Every preset draws its conditions from the seed (room shape, RT60, motion profile, obstacle losses,
interferer levels), so no single wording of a scene is what the presets test. Pure functions of numpy
Generators; positions in the room frame (origin at a corner), metres, rotations array frame → room.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from calib.pipeline.simulate import polyroom

C = 343.0


# ----------------------------------------------------------------------------------------------- boards
def _circle(n, r, centre=False):
    a = 2 * np.pi * np.arange(n) / n
    m = np.stack([r * np.cos(a), r * np.sin(a), np.zeros(n)], axis=1)
    return np.round(np.vstack([m, np.zeros((1, 3))]) if centre else m, 12) + 0.0


def _line(n, spacing):
    x = spacing * (np.arange(n) - (n - 1) / 2)
    return np.column_stack([x, np.zeros(n), np.zeros(n)])


def _tetrahedron(r):
    v = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float) / math.sqrt(3)
    return v * r


# name → (mics (M, 3) m in the array frame, sample rate Hz, planar?): boards of the kinds users bring
BOARDS = {
    "circle7c": (_circle(6, 0.043, centre=True), 48000, True),   # 7-mic circle with a centre mic (UMA-8-like)
    "circle6": (_circle(6, 0.0463), 16000, True),                # 6-mic circle (ReSpeaker-6-like)
    "linear4": (_line(4, 0.05), 16000, True),                    # 4-mic linear
    "tetra": (_tetrahedron(0.035), 44100, False),                # 4-mic tetrahedron
    "pair": (_line(2, 0.1), 48000, True),                        # 2-mic pair
}


# ----------------------------------------------------------------------------------------------- rooms
def l_shape(rng):
    """An L-shaped floor plan, two arms of random length and width: (corners (6, 2), room_dim (3,), the
    robot's loop through both arms (6, 2))."""
    A, B = rng.uniform(9.0, 11.0), rng.uniform(7.0, 9.0)
    w, b = rng.uniform(3.5, 4.5), rng.uniform(3.5, 4.5)
    corners = np.array([[0, 0], [A, 0], [A, b], [w, b], [w, B], [0, B]])
    o = rng.uniform(0.5, 0.8)
    way = [[A - 1.3, b / 2 - o], [A - 1.3, b / 2 + o], [w / 2 + o, b / 2 + o], [w / 2 + o, B - 1.3],
           [w / 2 - o, B - 1.3], [w / 2 - o, b / 2 - o]]
    return corners, np.array([A, B, rng.uniform(2.8, 3.2)]), np.array(way)


def u_shape(rng):
    """A U-shaped floor plan (two legs joined by a base: two corners hide each leg from the other): (corners
    (8, 2), room_dim (3,), the robot's loop up one leg, along the base and up the other (8, 2))."""
    A, B = rng.uniform(10.0, 12.0), rng.uniform(8.0, 10.0)
    w, b = rng.uniform(3.5, 4.5), rng.uniform(3.5, 4.5)
    corners = np.array([[0, 0], [A, 0], [A, B], [A - w, B], [A - w, b], [w, b], [w, B], [0, B]])
    o, xl, xr = rng.uniform(0.5, 0.8), w / 2, A - w / 2
    way = [[xl - o, B - 1.3], [xl - o, b / 2 - o], [xr + o, b / 2 - o], [xr + o, B - 1.3], [xr - o, B - 1.3],
           [xr - o, b / 2 + o], [xl + o, b / 2 + o], [xl + o, B - 1.3]]
    return corners, np.array([A, B, rng.uniform(2.8, 3.4)]), np.array(way)


SHAPES = {"L": l_shape, "U": u_shape}   # room_shape "nonconvex": one of them, drawn from the seed


def mirrored(corners, room, way, rng):
    """The plan and loop mirrored in x and/or y at random (corners kept counter-clockwise)."""
    flip = rng.integers(2, size=2).astype(bool)
    c, w = corners.astype(float).copy(), way.astype(float).copy()
    for ax in np.flatnonzero(flip):
        c[:, ax], w[:, ax] = room[ax] - c[:, ax], room[ax] - w[:, ax]
    if flip.sum() == 1:
        c = c[::-1]
    return np.round(c, 3), np.round(w, 3)


def box(room):
    return np.array([[0, 0], [room[0], 0], [room[0], room[1]], [0, room[1]]], float)


# ----------------------------------------------------------------------------------------------- paths
def loop_waypoints(room, rng):
    """(9, 2) waypoints of a closed robot path in a box room: an irregular ellipse."""
    n = 9
    a = rng.uniform(0, 2 * np.pi) + 2 * np.pi * np.arange(n) / n + rng.uniform(-0.15, 0.15, n)
    r = (np.asarray(room[:2]) / 2 - 1.4) * rng.uniform(0.8, 1.0, (n, 1))
    return room[:2] / 2 + rng.uniform(-0.2, 0.2, 2) + r * np.stack([np.cos(a), np.sin(a)], axis=1)


def closed_curve(way, step=0.02, cuts=5):
    """A smooth closed curve through the corners of ``way`` (Chaikin corner cutting: it stays inside the
    polygon's convex corners): (points (n, 2) about ``step`` m apart, arc length (n,))."""
    p = np.asarray(way, float)
    for _ in range(cuts):
        q = np.roll(p, -1, axis=0)
        p = np.stack([0.75 * p + 0.25 * q, 0.25 * p + 0.75 * q], axis=1).reshape(-1, 2)
    p = np.vstack([p, p[:1]])
    s = np.r_[0, np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))]
    u = np.r_[np.arange(0, s[-1], step), s[-1]]          # closed: the last point is the first again
    pts = np.stack([np.interp(u, s, p[:, q]) for q in range(2)], axis=1)
    return pts, u


def speed_profile(rng, t, form):
    """Speed (m/s) at times ``t``: ``constant`` U(0.3, 0.6), or ``varying`` (accelerates and brakes
    between 0.3 and 0.6 m/s with a random period of 4-9 s)."""
    if form == "constant":
        return np.full_like(t, rng.uniform(0.3, 0.6))
    period, phase = rng.uniform(4.0, 9.0), rng.uniform(0, 2 * np.pi)
    return 0.45 + 0.15 * np.sin(2 * np.pi * t / period + phase)


def drive(curve, arclen, t, speed, heights, rng):
    """Positions (n, 3) at times ``t`` of a robot driving around the closed ``curve`` at ``speed`` (n,)
    m/s, its speaker at ``heights[0]`` for the first half of the time and ``heights[1]`` after (a smooth
    3 s change)."""
    dist = np.r_[0, np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(t))] + rng.uniform(0, arclen[-1])
    d = np.mod(dist, arclen[-1])
    xy = np.stack([np.interp(d, arclen, curve[:, q]) for q in range(2)], axis=1)
    mid = 0.5 * (t[0] + t[-1])
    f = np.clip((t - mid) / 3.0 + 0.5, 0, 1)
    z = heights[0] + (heights[1] - heights[0]) * (0.5 - 0.5 * np.cos(np.pi * f))
    return np.column_stack([xy, z])


def stops_on(curve, arclen, k, heights, rng):
    """(k, 3) stationary speaker stops spread along the closed curve, half at each height."""
    d = np.mod(rng.uniform(0, arclen[-1]) + arclen[-1] * (np.arange(k) + rng.uniform(-0.2, 0.2, k)) / k
               * (2 if k > 1 else 1), arclen[-1])
    xy = np.stack([np.interp(d, arclen, curve[:, q]) for q in range(2)], axis=1)
    z = np.where(np.arange(k) < (k + 1) // 2, heights[0], heights[1]) + rng.normal(0, 0.01, k)
    return np.column_stack([xy + rng.normal(0, 0.03, xy.shape), z])


# ----------------------------------------------------------------------------------------------- arrays
def wall_spots(corners, min_len=1.5):
    """Indices of the floor plan's edges long enough to mount an array on."""
    e = np.roll(corners, -1, axis=0) - corners
    return [w for w in range(len(corners)) if np.linalg.norm(e[w]) >= min_len]


def wall_mount(corners, w, rng, height, depth=0.1, tilt_max=30.0):
    """(position, Rotation): an array on edge ``w``, ``depth`` m into the room, its z axis along the inward
    normal tilted down by U(0, tilt_max)°, random roll."""
    a, b = corners[w], corners[(w + 1) % len(corners)]
    e = (b - a) / np.linalg.norm(b - a)
    n = np.array([-e[1], e[0]])                 # counter-clockwise corners: the inward normal
    xy = a + rng.uniform(0.2, 0.8) * (b - a) + depth * n
    yaw = math.degrees(math.atan2(n[1], n[0]))
    rot = Rotation.from_euler("ZYZ", [yaw, 90.0 + rng.uniform(0, tilt_max), rng.uniform(0, 360)], degrees=True)
    return np.r_[xy, height], rot


def table_mount(geo, rng, margin=0.8, height=(0.72, 0.78), tilt=3.0):
    """(position, Rotation): an array lying (nearly level) on a table somewhere in the room."""
    lo, hi = geo["corners"].min(0) + margin, geo["corners"].max(0) - margin
    for _ in range(200):
        p = np.r_[rng.uniform(lo, hi), rng.uniform(*height)]
        if polyroom.inside(geo, p[None], margin)[0]:
            break
    t = np.r_[np.deg2rad(tilt) * rng.standard_normal(2), 0.0]
    return p, Rotation.from_rotvec(t) * Rotation.from_euler("z", rng.uniform(-np.pi, np.pi))


def stand_mount(geo, rng, height=(1.0, 1.8)):
    """(position, Rotation): an array on a stand, any rotation."""
    lo, hi = geo["corners"].min(0) + 1.0, geo["corners"].max(0) - 1.0
    for _ in range(200):
        p = np.r_[rng.uniform(lo, hi), rng.uniform(*height)]
        if polyroom.inside(geo, p[None], 1.0)[0]:
            break
    return p, Rotation.random(rng=rng)


def place_arrays(kinds, geo, path, rng, dmin_src=0.7, dmin_pair=1.0, tries=500):
    """Poses for ``kinds`` (each ("wall", z-range) / ("table",) / ("stand",)), away from the speaker's
    ``path`` (n, 3) and from each other; None if impossible."""
    walls = wall_spots(geo["corners"])
    out = []
    for kind in kinds:
        for _ in range(tries):
            if kind[0] == "wall":
                p, r = wall_mount(geo["corners"], walls[rng.integers(len(walls))], rng, rng.uniform(*kind[1]))
            elif kind[0] == "table":
                p, r = table_mount(geo, rng)
            else:
                p, r = stand_mount(geo, rng)
            mics = p + BOARDS["circle7c"][0] @ r.as_matrix().T
            if not np.all(polyroom.inside(geo, mics, 0.02)):
                continue
            if np.min(np.linalg.norm(path[:, :2] - p[:2], axis=1)) < dmin_src:
                continue
            if all(np.linalg.norm(p - q) >= dmin_pair for q, _ in out):
                out.append((p, r))
                break
        else:
            return None
    return out


def clocks(rng, n, offset_max=0.1, drift_max=1e-4, lead_in=0.3):
    """(tau (n,), drift (n,)): as the other presets (reference offset 0, earliest clock reads lead_in)."""
    off = rng.uniform(-offset_max, offset_max, n)
    off[0] = 0.0
    drift = rng.uniform(-drift_max, drift_max, n)
    return off - off.min() + lead_in, drift


def array_entry(name, board, pos, rot, tau, drift, mount):
    """One array of the scenario; ``board`` a BOARDS name, optionally ``name@rate`` (another sample rate)."""
    kind, _, rate = board.partition("@")
    mics, fs, planar = BOARDS[kind]
    fs = int(rate) if rate else fs
    q = rot.as_quat(scalar_first=True)
    q = q if q[0] >= 0 else -q
    a = {"name": name, "position": np.round(pos, 6).tolist(), "quat": q.tolist(), "mics": mics.tolist(),
         "tau": float(tau), "drift": float(drift), "board": board}
    if fs is not None:
        a["fs"] = fs
    if planar and mount in ("wall", "table"):
        a["doa_hemisphere"] = [0.0, 0.0, 1.0]   # the side of the room: every source is in front
    return a


# ----------------------------------------------------------------------------------------------- obstacles
def obstacle_across(src_xy, arr_xy, rng, loss_range, width=(0.8, 1.6), z=(0.0, 2.2)):
    """A vertical panel (cabinet, partition, shelf) placed across the line from a source area to an array,
    at 30-60 % of the way, perpendicular to it; loss at 1 kHz drawn from ``loss_range`` dB."""
    d = arr_xy - src_xy
    f = rng.uniform(0.3, 0.6)
    c = src_xy + f * d + rng.normal(0, 0.1, 2)
    n = np.array([-d[1], d[0]]) / np.linalg.norm(d)
    half = rng.uniform(*width) / 2
    return {"p0": np.round(c - half * n, 3).tolist(), "p1": np.round(c + half * n, 3).tolist(),
            "z": [z[0], float(np.round(rng.uniform(1.8, z[1]) if z[1] > 1.8 else z[1], 3))],
            "loss_db": float(np.round(rng.uniform(*loss_range), 2)), "loss_slope_db": 3.0}


# ----------------------------------------------------------------------------------------------- scenario
def build(g, sc, rng, overrides):
    """Fill the scene keys of a deployment preset into ``sc`` (in place): room (and floor plan), arrays,
    emission times, speaker stops or trajectory, obstacles, interferers. ``g``: generation keys;
    ``rng(k)``: the k-th independent random stream of the seed; keys in ``overrides`` are kept."""
    room = np.asarray(sc["room_dim"], float) if sc.get("room_dim") is not None else None
    way = None
    shape = g["room_shape"]
    if shape != "box" and "floor_plan" not in overrides:
        r = rng(1)
        if shape == "nonconvex":
            shape = ("L", "U")[int(r.integers(2))]
        corners, room, way = SHAPES[shape](r)
        corners, way = mirrored(corners, room, way, r)
        room = np.round(room, 3)
        sc["floor_plan"] = corners.tolist()
    corners = np.asarray(sc["floor_plan"], float) if sc.get("floor_plan") is not None else box(room)
    sc["room_dim"] = room.tolist()
    geo = polyroom.make_geometry(corners, room[2])
    if "arrays" in overrides and "sources" in overrides:     # e.g. a manifest: everything is given
        curve = arclen = None
    else:
        curve, arclen = _robot_curve(geo, room, rng(2), way)
    heights = g["heights"]
    n = int(g["n_arrays"])
    if "arrays" not in overrides:
        probe = np.column_stack([curve, np.full(len(curve), heights[0])])
        sc["arrays"] = _arrays(g, geo, probe, n, rng(3), rng(4))
    tau_max = max(a["tau"] for a in sc["arrays"])
    k = int(g["n_events"] if g["n_events"] is not None else g["n_stops"])
    if "t_emit" not in overrides:
        steps = g["interval"] * rng(5).uniform(1 - g["interval_jitter"], 1 + g["interval_jitter"], max(k - 1, 0))
        sc["t_emit"] = np.round(0.3 + tau_max + np.r_[0.0, np.cumsum(steps)], 6).tolist()
    t_emit = np.asarray(sc["t_emit"], float)
    if "sources" not in overrides:
        _speaker(sc, g, curve, arclen, heights, t_emit, rng(6))
    if "obstacles" not in overrides and g["n_obstacles"] > 0:
        sc["obstacles"] = _obstacles(g, geo, np.asarray(sc["sources"]), sc["arrays"], rng(7))
    if "interferers" not in overrides:
        sc["interferers"] = _talkers(g, geo, room, t_emit, sc["chirp"]["duration"], rng(8))
    if "reference_array" not in overrides:
        sc["reference_array"] = best_view(sc, corners, room)
    return sc


def best_view(sc, corners, room):
    """The array with the direct path (no wall, no obstacle) to the most speaker stops: the one a user
    would pick as the reference (the first of equals). Linear arrays and pairs (collinear mics: no full
    direction, so the sources cannot be placed in their frame) are never the reference."""
    geo = polyroom.make_geometry(corners, room[2], [
        {**o, "loss_db": np.full(7, float(o["loss_db"]))} for o in sc.get("obstacles") or []])
    src = np.asarray(sc["sources"], float)
    seen = [np.mean([polyroom.direct_gain(geo, s, np.array([a["position"]]))[0, 3] > 0.99 for s in src])
            if np.linalg.matrix_rank(np.asarray(a["mics"]) - np.mean(a["mics"], axis=0), tol=1e-6) >= 2 else -1.0
            for a in sc["arrays"]]
    return sc["arrays"][int(np.argmax(seen))]["name"]


def _robot_curve(geo, room, rng, way):
    """The robot's closed path: the plan's loop (jittered) or an ellipse in a box, inside with 0.6 m to spare."""
    for _ in range(50):
        w = way + rng.normal(0, 0.1, way.shape) if way is not None else loop_waypoints(room, rng)
        curve, arclen = closed_curve(w)
        if np.all(polyroom.inside(geo, np.column_stack([curve, np.full(len(curve), 1.0)]), 0.6)):
            return curve, arclen
    raise ValueError("deploy: no robot path fits this room (give 'sources' for a floor plan of your own)")


MOUNTS = ("wall", "table", "stand")


def _names(value, key, choices):
    """``value`` (one name, or a list of names) as a list of names from ``choices`` (a board name may carry
    ``@rate``); else a ValueError naming the value and the choices (``--set boards=pair`` is one board for
    every array; ``--set boards=[pair,tetra]``, TOML without quotes, arrives as one string)."""
    names = [value] if isinstance(value, str) else value
    known = isinstance(names, list) and len(names) > 0 and all(
        isinstance(v, str) and v.partition("@")[0] in choices and (v.partition("@")[2] or "0").isdigit()
        for v in names)
    if not known:
        bad = next((v for v in names if not isinstance(v, str) or v.partition("@")[0] not in choices), value) \
            if isinstance(names, list) else value
        raise ValueError(f"{key}: unknown {bad!r} (give a name or a list of names, quoted in TOML: "
                         f"{key}=[\"{choices[0]}\", ...]; one of {', '.join(choices)})")
    return names


def _arrays(g, geo, path, n, rng_pose, rng_clock):
    boards = _names(g["boards"] or ["circle6"], "boards", tuple(BOARDS))
    mounts = _names(g["mounts"] or ["wall", "table"], "mounts", MOUNTS)
    kinds = [mounts[i % len(mounts)] for i in range(n)]
    hi = min(geo["height"] - 0.3, 4.0)
    poses = place_arrays([("wall", (1.5, hi)) if m == "wall" else (m,) for m in kinds], geo, path, rng_pose)
    if poses is None:
        raise ValueError(f"deploy: cannot place {n} arrays")
    tau, drift = clocks(rng_clock, n)
    return [array_entry(f"A{i + 1}", boards[i % len(boards)], p, r, tau[i], drift[i], kinds[i])
            for i, (p, r) in enumerate(poses)]


def _speaker(sc, g, curve, arclen, heights, t_emit, rng):
    """Stops (the robot halts for each chirp) or a trajectory (it keeps moving) and the speaker axes."""
    from calib.pipeline.simulate.motion import Trajectory

    form = g["motion"]
    if form == "none":
        sc["sources"] = np.round(stops_on(curve, arclen, len(t_emit), heights, rng), 6).tolist()
        return
    if form == "any":
        form = ("constant", "varying")[int(rng.integers(2))]
    t = np.arange(t_emit[0] - 1.0, t_emit[-1] + sc["chirp"]["duration"] + 1.0, 0.1)
    pos = np.round(drive(curve, arclen, t, speed_profile(rng, t, form), heights, rng), 6)
    sc["trajectory"] = {"t": np.round(t, 6).tolist(), "pos": pos.tolist(), "form": form}
    traj = Trajectory(sc["trajectory"])
    sc["sources"] = traj(t_emit).tolist()
    v = traj.velocity(t_emit)
    v[:, 2] = 0.0
    sc["source_axis"] = (v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-9)).tolist()


def _obstacles(g, geo, sources, arrays, rng):
    """Panels across the lines from groups of stops to some arrays (never the reference), off the path."""
    out = []
    lo, hi = g["obstacle_loss_db"]
    targets = rng.permutation(np.arange(1, len(arrays)))[:int(g["n_obstacles"])]
    for i in targets:
        arr = np.asarray(arrays[i]["position"])
        for _ in range(100):
            s = sources[rng.integers(len(sources))]
            ob = obstacle_across(s[:2], arr[:2], rng, (lo, hi))
            seg = np.array([ob["p0"], ob["p1"]])
            clear = _segment_distance(seg, sources[:, :2]) > 0.4 and _segment_distance(
                seg, np.array([a["position"][:2] for a in arrays])) > 0.4
            if clear and np.all(polyroom.inside(geo, np.c_[seg, [1.0, 1.0]], 0.05)):
                out.append(ob)
                break
    return out


def _segment_distance(seg, pts):
    a, b = seg
    t = np.clip((pts - a) @ (b - a) / np.sum((b - a) ** 2), 0, 1)
    return float(np.min(np.linalg.norm(pts - (a + t[:, None] * (b - a)), axis=1)))


def _talkers(g, geo, room, t_emit, dur, rng):
    """Talkers (speech), broadband noise bursts and tone bursts, each in a random gap between two chirps
    at a level drawn from ``interferer_levels_db``; with ``talker_overlap`` the last one also spans a chirp
    (at the lower half of the levels)."""
    kinds = ["speech"] * int(g["n_speech"]) + ["noise"] * int(g["n_noise"]) + ["tones"] * int(g["n_interferers"])
    lo, hi = g["interferer_levels_db"]
    out = []
    gaps = rng.permutation(max(len(t_emit) - 1, 0))
    for k, kind in enumerate(kinds):
        if len(gaps) == 0:
            break
        j = int(gaps[k % len(gaps)])
        gap = t_emit[j + 1] - t_emit[j] - dur
        start, length, level = t_emit[j] + dur + rng.uniform(0.15, 0.35) * gap, rng.uniform(0.3, 0.5) * gap, \
            rng.uniform(lo, hi)
        if g["talker_overlap"] and k == len(kinds) - 1:
            start, length, level = t_emit[j] - 0.3, dur + 0.8, rng.uniform(lo, 0.5 * (lo + hi))
        for _ in range(200):
            p = np.r_[rng.uniform(0.5, room[:2] - 0.5), rng.uniform(1.0, min(1.8, room[2] - 0.3))]
            if polyroom.inside(geo, p[None], 0.5)[0]:
                break
        it = {"kind": kind, "position": np.round(p, 3).tolist(), "t_start": float(np.round(start, 6)),
              "duration": float(np.round(length, 6)), "level_db": float(np.round(level, 2))}
        if kind == "speech":
            it["f0"] = float(np.round(rng.uniform(100.0, 220.0), 1))
        else:
            it |= {"f_lo": 200.0, "f_hi": 6000.0}
        out.append(it)
    return out
