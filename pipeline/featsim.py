"""Feature-level simulator: the Monte-Carlo protocol of Zhang et al. (2025), Sec. IV-A.

It draws a scene (array poses, clocks, source trajectory, emission intervals), computes the exact
measurements of ``docs/architecture.md`` and adds noise, returning the same dicts the readers of
``pipeline.io`` return, so a simulated data set exercises exactly the code paths of real data.
"""
from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

# The paper's three trajectories (speaker stops, metres, before the +0.5 m shift) and the boxes the
# non-reference arrays are drawn in (low corner, size).
TRAJECTORIES = {
    1: {
        "stops": 3.0 * np.array([[0, 1, 1, 0, 0, 0, 1, 1], [0, 0, 1, 1, 1, 0, 0, 1], [0, 0, 0, 0, 1, 1, 1, 1]]).T,
        "box": (np.array([0.0, 0.0, 0.0]), np.array([3.0, 3.0, 3.0])),
    },
    2: {
        "stops": np.array([[0, 2, 2, 2, 2, 2, 2, 2, 2, 0], [0, 0, 2, 4, 6, 6, 4, 2, 0, 0],
                           [0, 0, 0, 0, 0, 2, 2, 2, 2, 2]], float).T,
        "box": (np.array([0.0, 0.0, 0.0]), np.array([2.0, 6.0, 2.0])),
    },
    3: {
        "stops": 2.0 * np.array([[0, 1, 1, 1, 0, -1, -1, -1, -1, -1, -1, 0, 1, 1],
                                 [0, 0, 1, 2, 2, 2, 1, 0, 0, 1, 2, 2, 2, 1],
                                 [0, 0, 0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 1]], float).T,
        "box": (np.array([-2.0, 0.0, 0.0]), np.array([4.0, 4.0, 2.0])),
    },
}
SHIFT = 0.5


def random_rotations(rng, n, max_angle=np.pi):
    """Rotations about random axes by angles uniform in (-max_angle, max_angle) (the paper's draw)."""
    axis = rng.uniform(-1, 1, (n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return Rotation.from_rotvec(axis * rng.uniform(-max_angle, max_angle, (n, 1)))


def perturb_directions(rng, u, sigma):
    """Rotate unit vectors ``u`` (n, 3) about random axes by angles ~ N(0, sigma) (rad), as the paper does."""
    axis = rng.uniform(-1, 1, u.shape)
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    ang = np.clip(rng.normal(0.0, sigma, (len(u), 1)), -np.pi, np.pi)
    return Rotation.from_rotvec(axis * ang).apply(u)


def arrival_times(x, s, t, offset, drift, c, beta=0.0):
    """Local-clock arrival times ``a_ij`` (N, K) of the clock model in docs/architecture.md.

    x : (N, 3) array positions; s : (K, 3) sources; t : (K,) emission times minus t_0;
    offset, drift : (N,); beta : chirp drift bias (s per unit drift).
    """
    d = np.linalg.norm(s[None, :, :] - x[:, None, :], axis=2)
    return (1.0 + drift[:, None]) * (t[None, :] + d / c) + offset[:, None] + beta * drift[:, None]


def simulate_features(trajectory=3, sigma_tdoa=1e-4, sigma_doa_deg=5.0, sigma_odo=0.03, seed=0, *,
                      n_arrays=5, c=340.0, max_offset=0.1, max_drift=1e-4, max_interval=10.0,
                      tdoa_s=True, tdoa_m=True, names=None, noise=True, reference_drift=None, planar=None,
                      positions=None):
    """Draw one scene of the paper's protocol and its noisy features.

    Parameters
    ----------
    trajectory : 1, 2 or 3 (see ``TRAJECTORIES``), or a (K, 3) array of speaker stops (arrays are then
        drawn in the stops' bounding box).
    sigma_tdoa : TDOA noise std (s), applied to every TDOA-S and TDOA-M value.
    sigma_doa_deg : DOA noise: rotation about a random axis by an angle ~ N(0, sigma) (degrees, the
        paper's convention; meta.json gets the equivalent per-axis std sigma/√3).
    sigma_odo : odometry noise std per axis and step (m).
    seed : seed of the numpy Generator; same seed, same scene and noise.
    tdoa_s, tdoa_m : include that measurement type.
    noise : False gives exact measurements (the sigmas still go to meta.json as weights).
    reference_drift : force the reference array's drift (e.g. 0, the gauge used without TDOA-S).
    planar : None, or a mic-plane normal (3,) in the array frame: every array is then planar and its DOAs
        are mirror-ambiguous, given folded to n·u >= 0 with meta ``doa_mirror_normals``.
    positions : None, or the array positions (N, 3) (then ``n_arrays`` = N); positions[0] is the
        reference array and must be the origin (it defines the frame).

    Returns
    -------
    features, truth : dicts as returned by ``pipeline.io.read_features`` / ``read_truth``.
    """
    rng = np.random.default_rng(seed)
    scale = 1.0 if noise else 0.0
    if np.ndim(trajectory) == 0:
        spec = TRAJECTORIES[int(trajectory)]
        stops, (lo, size) = spec["stops"] + SHIFT, spec["box"]
    else:
        stops = np.asarray(trajectory, float)
        lo, size = stops.min(0), np.ptp(stops, 0)
    K = len(stops)
    N = n_arrays if positions is None else len(positions)
    names = names or [f"A{i + 1}" for i in range(N)]
    x = np.zeros((N, 3))
    if positions is None:
        x[1:] = lo + size * rng.uniform(0, 1, (N - 1, 3))
    else:
        x[:] = positions
        if np.any(x[0] != 0):
            raise ValueError("positions[0] (the reference array) must be the origin")
    rot = random_rotations(rng, N)
    rotvec = rot.as_rotvec()
    rotvec[0] = 0.0
    rot = Rotation.from_rotvec(rotvec)
    offset = rng.uniform(-max_offset, max_offset, N)
    offset[0] = 0.0
    drift = rng.uniform(-max_drift, max_drift, N)
    if reference_drift is not None:
        drift[0] = reference_drift
    dt = rng.uniform(0, max_interval, K - 1)
    t = np.concatenate([[0.0], np.cumsum(dt)])

    a = arrival_times(x, stops, t, offset, drift, c)
    ev = np.arange(K)
    odo_steps = np.diff(stops, axis=0) + scale * rng.normal(0, sigma_odo, (K - 1, 3))
    odom = np.vstack([np.zeros(3), np.cumsum(odo_steps, axis=0)])
    events = pd.DataFrame({"event": ev, "t_emit": t, "odom_x": odom[:, 0], "odom_y": odom[:, 1],
                           "odom_z": odom[:, 2]})

    ii, jj = np.meshgrid(np.arange(1, N), ev, indexing="ij")
    tm = pd.DataFrame({"event": jj.ravel(), "array": np.asarray(names)[ii.ravel()],
                       "tdoa": (a[1:] - a[:1]).ravel() + scale * rng.normal(0, sigma_tdoa, ii.size)})
    ii, jj = np.meshgrid(np.arange(N), ev[:-1], indexing="ij")
    ts = pd.DataFrame({"array": np.asarray(names)[ii.ravel()], "from_event": jj.ravel(), "to_event": jj.ravel() + 1,
                       "tdoa": np.diff(a, axis=1).ravel() + scale * rng.normal(0, sigma_tdoa, ii.size)})
    ii, jj = np.meshgrid(np.arange(N), ev, indexing="ij")
    ii, jj = ii.ravel(), jj.ravel()
    u_true = rot[ii].inv().apply(stops[jj] - x[ii])
    u_true /= np.linalg.norm(u_true, axis=1, keepdims=True)
    u = perturb_directions(rng, u_true, scale * np.deg2rad(sigma_doa_deg))
    if planar is not None:
        n = np.asarray(planar, float) / np.linalg.norm(planar)
        u = np.where((u @ n < 0)[:, None], u - 2.0 * (u @ n)[:, None] * n, u)
    doa = pd.DataFrame({"event": jj, "array": np.asarray(names)[ii], "ux": u[:, 0], "uy": u[:, 1], "uz": u[:, 2]})

    empty_m = pd.DataFrame({"event": np.zeros(0, int), "array": np.zeros(0, str), "tdoa": np.zeros(0)})
    empty_s = pd.DataFrame({"array": np.zeros(0, str), "from_event": np.zeros(0, int), "to_event": np.zeros(0, int),
                            "tdoa": np.zeros(0)})
    # meta's sigma_doa_deg is the std per tangent axis: a rotation by N(0, σ²) about an isotropic random
    # axis moves a direction by σ/√3 along each axis perpendicular to it
    meta = {"speed_of_sound": c, "reference_array": names[0], "arrays": list(names), "sigma_tdoa": sigma_tdoa,
            "sigma_doa_deg": sigma_doa_deg / np.sqrt(3.0), "sigma_odo": sigma_odo}
    if planar is not None:
        meta["doa_mirror_normals"] = {a: n.tolist() for a in names}
    features = {"meta": meta, "events": events, "tdoa_m": tm if tdoa_m else empty_m,
                "tdoa_s": ts if tdoa_s else empty_s, "doa": doa}
    q = rot.as_quat(scalar_first=True)
    arrays = pd.DataFrame({"array": names, "x": x[:, 0], "y": x[:, 1], "z": x[:, 2], "qw": q[:, 0], "qx": q[:, 1],
                           "qy": q[:, 2], "qz": q[:, 3], "offset": offset, "drift": drift})
    sources = pd.DataFrame({"event": ev, "x": stops[:, 0], "y": stops[:, 1], "z": stops[:, 2]})
    return features, {"arrays": arrays, "sources": sources}
