"""Layouts of the realistic room-simulator presets (``lab``, ``hall``, ``hard``): speaker loops, array
poses on walls, tables and stands, the speaker's heading, and the hostile additions of ``hard``.

All positions in the room frame (origin at a corner, axes along the walls), metres; rotations map the
array frame to the room. Pure functions of a numpy Generator: the room simulator seeds them.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

N_LOOP = 7                 # speaker stops per loop (two loops at two heights, like the paper's experiment)
WALL_YAW = {0: 0.0, 1: 180.0, 2: 90.0, 3: -90.0}   # wall index (x=0, x=Lx, y=0, y=Ly) → yaw of its inward normal
WALL_TILT_MAX = 30.0       # deg: wall-mounted arrays look into the room, tilted down by U(0, 30°)
TABLE_TILT = 3.0           # deg (1σ): arrays lying on tables are nearly level
OCTAHEDRON_RADIUS = 0.05   # m: the hall's non-planar 6-mic arrays (mics on ±x, ±y, ±z)


def loop_stops(room, rng, radii, heights):
    """(2·N_LOOP, 3) speaker stops: an irregular loop (ellipse of ``radii`` m, jittered) flown at each of
    ``heights`` m, centred near the middle of the room."""
    phase = rng.uniform(0, 2 * np.pi)
    a = phase + 2 * np.pi * np.arange(N_LOOP) / N_LOOP + rng.uniform(-0.2, 0.2, N_LOOP)
    r = np.asarray(radii) * rng.uniform(0.85, 1.15, (N_LOOP, 1))
    xy = room[:2] / 2 + rng.uniform(-0.2, 0.2, 2) + r * np.stack([np.cos(a), np.sin(a)], axis=1)
    return np.concatenate([np.column_stack([xy + rng.normal(0, 0.03, xy.shape), h + rng.normal(0, 0.01, N_LOOP)])
                           for h in heights])


def headings(sources):
    """(K, 3) unit speaker axes: the horizontal direction of travel (towards the next stop; the last stop
    keeps the previous heading). A stop with no horizontal motion keeps the previous axis."""
    s = np.asarray(sources, float)
    k = len(s)
    axes = np.tile([1.0, 0.0, 0.0], (k, 1))
    for j in range(k):
        d = s[j + 1] - s[j] if j + 1 < k else s[j] - s[j - 1] if k > 1 else np.zeros(3)
        d[2] = 0.0
        n = np.linalg.norm(d)
        axes[j] = d / n if n > 1e-6 else (axes[j - 1] if j else axes[j])
    return axes


def wall_pose(room, wall, rng, height, depth):
    """(position (3,), Rotation) of an array on ``wall`` (0-3), ``depth`` m into the room at ``height`` m,
    its normal (array z) pointing into the room, tilted down by U(0, WALL_TILT_MAX), random roll."""
    axis, far = divmod(wall, 2)
    pos = np.empty(3)
    pos[axis] = room[axis] - depth if far else depth
    pos[1 - axis] = rng.uniform(0.2, 0.8) * room[1 - axis]
    pos[2] = height
    tilt = rng.uniform(0, WALL_TILT_MAX)
    rot = Rotation.from_euler("ZYZ", [WALL_YAW[wall], 90.0 + tilt, rng.uniform(0, 360)], degrees=True)
    return pos, rot


def table_pose(room, rng, margin=0.8):
    """(position, Rotation) of an array lying on a table (0.72-0.78 m), nearly level, random yaw."""
    pos = np.r_[rng.uniform(margin, room[:2] - margin), rng.uniform(0.72, 0.78)]
    tilt = np.r_[np.deg2rad(TABLE_TILT) * rng.standard_normal(2), 0.0]
    return pos, Rotation.from_rotvec(tilt) * Rotation.from_euler("z", rng.uniform(-np.pi, np.pi))


def octahedron_mics(radius=OCTAHEDRON_RADIUS):
    """(6, 3) mics on the ±x, ±y, ±z axes: a non-planar array (no DOA mirror ambiguity)."""
    return np.concatenate([np.eye(3), -np.eye(3)]) * radius


# Mic geometries a generated array may have (scenario key ``geometries``): "default" is the preset's
# (circle of n_mics, the hall's octahedron, or the ``mics`` key); "linear" is n_mics on the x axis.
GEOMETRIES = ("default", "circle", "octahedron", "linear", "pair", "single")


def named_mics(kind, default, n_mics, radius, spacing):
    """(M, 3) mic positions of a named geometry, centred on the array origin (m, array frame).

    default : the preset's geometry. circle : n_mics on a circle of ``radius`` in the x-y plane.
    octahedron : 6 mics on ±x, ±y, ±z at OCTAHEDRON_RADIUS. linear / pair : n_mics / 2 mics on the x axis,
    ``spacing`` apart (a linear array and a 2-mic pair measure only the angle to that axis). single : 1 mic.
    """
    if kind == "default":
        return np.asarray(default, float)
    if kind == "circle":
        a = 2 * np.pi * np.arange(n_mics) / n_mics
        return np.round(np.stack([radius * np.cos(a), radius * np.sin(a), np.zeros(n_mics)], axis=1), 12) + 0.0
    if kind == "octahedron":
        return octahedron_mics()
    if kind == "single":
        return np.zeros((1, 3))
    m = 2 if kind == "pair" else n_mics
    x = spacing * (np.arange(m) - (m - 1) / 2)
    return np.column_stack([x, np.zeros(m), np.zeros(m)])


def far_enough(p, sources, placed, dmin_src, dmin_pair):
    return (np.min(np.linalg.norm(sources - p, axis=1)) >= dmin_src
            and all(np.linalg.norm(p - q) >= dmin_pair for q in placed))


def place(kinds, room, sources, rng, dmin_src=0.5, dmin_pair=0.8, tries=2000):
    """Poses for arrays of ``kinds`` (each ("wall", wall, z-range, depth) or ("table",) or ("stand", z-range)),
    by rejection sampling under the distance constraints; None if impossible."""
    out = []
    for kind in kinds:
        for _ in range(tries):
            if kind[0] == "wall":
                p, r = wall_pose(room, kind[1], rng, rng.uniform(*kind[2]), kind[3])
            elif kind[0] == "table":
                p, r = table_pose(room, rng)
            else:
                p = np.r_[rng.uniform(1.0, room[:2] - 1.0), rng.uniform(*kind[1])]
                r = Rotation.random(rng=rng)
            if far_enough(p, sources, [q for q, _ in out], dmin_src, dmin_pair):
                out.append((p, r))
                break
        else:
            return None
    return out


def reflection_delay(src, pos, wall, room, c):
    """Extra path time (s) of the first-order reflection on ``wall`` (0-3) over the direct path, per stop."""
    axis, far = divmod(wall, 2)
    mirror = np.array(src, float)
    mirror[:, axis] = 2 * room[axis] - mirror[:, axis] if far else -mirror[:, axis]
    return (np.linalg.norm(mirror - pos, axis=1) - np.linalg.norm(src - pos, axis=1)) / c


def occlusion_depth(src, wall, room, c, target, depth0=0.1):
    """Depth (m) from ``wall`` at which its first-order reflection arrives ``target`` s after the direct
    path, in the median over the speaker stops (the delay is close to linear in the depth)."""
    depth = depth0
    for _ in range(4):
        pos = np.array(room, float) / 2
        axis, far = divmod(wall, 2)
        pos[axis] = room[axis] - depth if far else depth
        pos[1 - axis] = np.median(src[:, 1 - axis])
        pos[2] = 1.2
        depth *= target / float(np.median(reflection_delay(src, pos, wall, room, c)))
    return float(np.clip(depth, 0.06, 0.5))
