"""Feature-level simulator: the Monte-Carlo protocol of Zhang et al. (2025), Sec. IV-A.

It draws a scene (array poses, clocks, source trajectory, emission intervals), computes the exact
measurements of ``docs/architecture.md`` and adds noise, returning the same dicts the readers of
``pipeline.formats.io`` return, so a simulated data set exercises exactly the code paths of real data.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from calib.geometry import arrival_time, fold, steered_doas
from calib.records import Features

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
    return arrival_time(t[None, :], d, offset[:, None], drift[:, None], c, beta)


@dataclass(frozen=True)
class SceneSpec:
    """How the paper's protocol draws a scene (defaults: Zhang et al. 2025, Sec. IV-A).

    n_arrays : number of arrays (the first is the reference). c : speed of sound (m/s).
    max_offset : clock offsets uniform in ±max_offset (s). max_drift : drifts uniform in ±max_drift.
    max_interval : emission intervals uniform in [0, max_interval] (s). names : array names (default A1..AN).
    reference_drift : force the reference array's drift (e.g. 0, the gauge used without TDOA-S).
    planar : None, or a mic-plane normal (3,) in the array frame: every array is then planar and its DOAs
        are mirror-ambiguous, given folded to n·u >= 0 with meta ``doa_mirror_normals``.
    positions : None, or the array positions (N, 3) (then ``n_arrays`` = N); positions[0] is the
        reference array and must be the origin (it defines the frame).
    declared_c : None, or the speed of sound (m/s) meta.json declares and the frontend steered its DOAs with
        (the scene is rendered at ``c``): a planar array's DOAs then carry that steering's bias (their in-plane
        part scaled by declared_c / c, ``calib.geometry.steered_doas``), as calib's frontend gives them.
    """
    n_arrays: int = 5
    c: float = 340.0
    max_offset: float = 0.1
    max_drift: float = 1e-4
    max_interval: float = 10.0
    names: tuple | None = None
    reference_drift: float | None = None
    planar: tuple | None = None
    positions: Any = None
    declared_c: float | None = None


def simulate_features(trajectory: int | np.ndarray = 3, sigma_tdoa: float = 1e-4, sigma_doa_deg: float = 5.0,
                      sigma_odo: float = 0.03, seed: int = 0, *, tdoa_s: bool = True, tdoa_m: bool = True,
                      noise: bool = True, clocks: dict | None = None, **scene: Any) -> tuple[Features, dict[str, Any]]:
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
    clocks : None, or {array name or index: clock faults} (``pipeline.simulate.clocks``: a preset name or a
        fault dict: dropped/inserted blocks, warm-up, random walk, wrong nominal rate); drawn from their own
        seeded stream, so the scene of a seed is the same with and without them. The truth then has
        ``clocks`` ({array: clock record}) and its ``drift`` includes a rate error.
    scene : fields of :class:`SceneSpec` (n_arrays, c, max_offset, max_drift, max_interval, names,
        reference_drift, planar, positions).

    Returns
    -------
    features, truth : a :class:`calib.records.Features` and a dict, as ``calib.pipeline.formats.io.read_features``
        / ``read_truth`` return them.
    """
    spec = SceneSpec(**scene)
    if spec.positions is not None:
        if np.any(np.asarray(spec.positions, float)[0] != 0):
            raise ValueError("positions[0] (the reference array) must be the origin")
        spec = replace(spec, n_arrays=len(spec.positions))
    rng = np.random.default_rng(seed)
    stops, box = _stops_and_box(trajectory)
    truth = _draw_scene(rng, stops, box, spec)
    truth["clocks"] = _fault_clocks(clocks, truth, seed)
    sig = {"tdoa": sigma_tdoa, "doa": np.deg2rad(sigma_doa_deg), "odo": sigma_odo}
    features = _measure(rng, stops, truth, spec, sig, 1.0 if noise else 0.0, tdoa_s, tdoa_m)
    # meta's sigma_doa_deg is the std per tangent axis: a rotation by N(0, σ²) about an isotropic random
    # axis moves a direction by σ/√3 along each axis perpendicular to it
    features["meta"] = {"speed_of_sound": spec.c if spec.declared_c is None else float(spec.declared_c), "reference_array": truth["names"][0],
                        "arrays": list(truth["names"]), "sigma_tdoa": sigma_tdoa,
                        "sigma_doa_deg": sigma_doa_deg / np.sqrt(3.0), "sigma_odo": sigma_odo}
    if spec.planar is not None:
        features["meta"]["doa_mirror_normals"] = {a: _unit(spec.planar).tolist() for a in truth["names"]}
    out = _truth_frames(stops, truth)
    if truth["clocks"]:
        out["clocks"] = {truth["names"][i]: rec for i, (_, rec) in truth["clocks"].items()}
    return Features.from_dict(features), out


def _fault_clocks(clocks, tr, seed):
    """{array index: (clock with faults, its truth record)} (their own random stream); sets the truth's drift
    to each clock's."""
    if not clocks:
        return {}
    from calib.pipeline.simulate import clocks as ck

    rng = np.random.default_rng([int(seed), 28])
    out = {}
    for key, faults in clocks.items():
        i = tr["names"].index(key) if isinstance(key, str) else int(key)
        clk = ck.fault_clock(tr["offset"][i], tr["drift"][i], faults, event_times=tr["t"], rng=rng)
        tr["drift"][i] = clk.drift
        out[i] = (clk, ck.clock_record(clk, faults, tr["t"]))
    return out


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def _stops_and_box(trajectory):
    """(K, 3) speaker stops and the (low corner, size) box the non-reference arrays are drawn in."""
    if np.ndim(trajectory) == 0:
        spec = TRAJECTORIES[int(trajectory)]
        return spec["stops"] + SHIFT, spec["box"]
    stops = np.asarray(trajectory, float)
    return stops, (stops.min(0), np.ptp(stops, 0))


def _draw_scene(rng, stops, box, spec):
    """Array poses, clocks and emission times (the draw order fixes every seed's scene)."""
    N, K = spec.n_arrays, len(stops)
    lo, size = box
    x = np.zeros((N, 3))
    if spec.positions is None:
        x[1:] = lo + size * rng.uniform(0, 1, (N - 1, 3))
    else:
        x[:] = np.asarray(spec.positions, float)
    rotvec = random_rotations(rng, N).as_rotvec()
    rotvec[0] = 0.0
    offset = rng.uniform(-spec.max_offset, spec.max_offset, N)
    offset[0] = 0.0
    drift = rng.uniform(-spec.max_drift, spec.max_drift, N)
    if spec.reference_drift is not None:
        drift[0] = spec.reference_drift
    t = np.concatenate([[0.0], np.cumsum(rng.uniform(0, spec.max_interval, K - 1))])
    names = list(spec.names or [f"A{i + 1}" for i in range(N)])
    return {"x": x, "rot": Rotation.from_rotvec(rotvec), "offset": offset, "drift": drift, "t": t,
            "names": names}


def _measure(rng, stops, tr, spec, sig, scale, use_tdoa_s, use_tdoa_m):
    """Noisy events, TDOA-M, TDOA-S and DOA tables of a drawn scene (noise std × ``scale``)."""
    N, K = spec.n_arrays, len(stops)
    names = np.asarray(tr["names"])
    a = arrival_times(tr["x"], stops, tr["t"], tr["offset"], tr["drift"], spec.c)
    for i, (clk, _) in tr["clocks"].items():   # faulty clocks: L_i(t_j + d_ij / c) in full
        a[i] = clk.local(tr["t"] + np.linalg.norm(stops - tr["x"][i], axis=1) / spec.c)
    ev = np.arange(K)
    odo_steps = np.diff(stops, axis=0) + scale * rng.normal(0, sig["odo"], (K - 1, 3))
    odom = np.vstack([np.zeros(3), np.cumsum(odo_steps, axis=0)])
    events = pd.DataFrame({"event": ev, "t_emit": tr["t"], "odom_x": odom[:, 0], "odom_y": odom[:, 1],
                           "odom_z": odom[:, 2]})
    ii, jj = np.meshgrid(np.arange(1, N), ev, indexing="ij")
    tm = pd.DataFrame({"event": jj.ravel(), "array": names[ii.ravel()],
                       "tdoa": (a[1:] - a[:1]).ravel() + scale * rng.normal(0, sig["tdoa"], ii.size)})
    ii, jj = np.meshgrid(np.arange(N), ev[:-1], indexing="ij")
    ts = pd.DataFrame({"array": names[ii.ravel()], "from_event": jj.ravel(), "to_event": jj.ravel() + 1,
                       "tdoa": np.diff(a, axis=1).ravel() + scale * rng.normal(0, sig["tdoa"], ii.size)})
    ii, jj = (g.ravel() for g in np.meshgrid(np.arange(N), ev, indexing="ij"))
    u_true = tr["rot"][ii].inv().apply(stops[jj] - tr["x"][ii])
    u_true /= np.linalg.norm(u_true, axis=1, keepdims=True)
    u = perturb_directions(rng, u_true, scale * sig["doa"])
    if spec.planar is not None:
        n = _unit(spec.planar)
        if spec.declared_c is not None:
            u = steered_doas(u, spec.declared_c / spec.c, normal=n)
        u = fold(u, n)
    doa = pd.DataFrame({"event": jj, "array": names[ii], "ux": u[:, 0], "uy": u[:, 1], "uz": u[:, 2]})
    return {"events": events, "tdoa_m": tm if use_tdoa_m else tm.iloc[:0].reset_index(drop=True),
            "tdoa_s": ts if use_tdoa_s else ts.iloc[:0].reset_index(drop=True), "doa": doa}


def _truth_frames(stops, tr):
    """Truth dict (arrays, sources DataFrames) of a drawn scene."""
    x, q = tr["x"], tr["rot"].as_quat(scalar_first=True)
    arrays = pd.DataFrame({"array": tr["names"], "x": x[:, 0], "y": x[:, 1], "z": x[:, 2], "qw": q[:, 0],
                           "qx": q[:, 1], "qy": q[:, 2], "qz": q[:, 3], "offset": tr["offset"], "drift": tr["drift"]})
    sources = pd.DataFrame({"event": np.arange(len(stops)), "x": stops[:, 0], "y": stops[:, 1], "z": stops[:, 2]})
    return {"arrays": arrays, "sources": sources}
