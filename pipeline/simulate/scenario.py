"""Scenario keys of the room simulator: presets, defaults, validation and the analytic truth.

A scenario is a plain dict (made by ``roomsim.make_scenario``); :func:`validate_scenario` checks one and
returns a normalised copy with numpy arrays, which everything downstream (rendering, truth) works on.
:func:`arrival_times`, :func:`scenario_truth` and :func:`odometry` are the analytic truth of a scenario.
"""
from __future__ import annotations

import copy
import math
from typing import Any

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from calib.frontend.signals import SWEEP_KINDS

from calib.pipeline.simulate import acoustics as ac
from calib.pipeline.simulate import motion, polyroom, scenes
from calib.pipeline.formats.io import ARRAYS_COLS, InputError
from calib.pipeline.simulate.presets import PRESETS, REALISTIC  # noqa: F401  (public names)
from calib.pipeline.simulate import clocks
from calib.pipeline.simulate.featsim import TRAJECTORIES

SUBTYPES = ("FLOAT", "PCM_24", "PCM_16")
INTERFERER_KINDS = ("tones", "speech", "noise")
MODELS = ("flat", "bands")

# Speaker trajectories of Zhang et al. 2025 (simulation section; published with their code, gt_generation.m).
_PAPER_TRAJ = {f"paper-traj{k}": v["stops"] for k, v in TRAJECTORIES.items()}
# The real lab loop (zhang_real_01 truth, x/y in metres, centred): 7 stops, flown at two speaker heights.
_LAB_LOOP = np.array([[0.87, 0.25], [0.87, -0.27], [0.37, -0.57], [-0.40, -0.57],
                      [-0.87, -0.03], [-0.44, 0.56], [0.36, 0.56]])
_LAB_HEIGHTS = (1.12, 0.75)  # m above the floor: first loop high, second low (as in the real data)

DEFAULT_MATERIALS = {"walls": "plasterboard", "floor": "linoleum_on_concrete", "ceiling": "ceiling_plasterboard"}

# Keys that only steer the random generation in make_scenario (kept in the scenario for the record).
GEN_DEFAULTS: dict[str, Any] = {
    "n_arrays": 5,             # number of arrays (names A1..AN, A1 = reference)
    "n_events": None,          # speaker stops used (≤ the preset's trajectory length; None = all)
    "interval": 2.0,           # mean time between chirp emissions, s
    "interval_jitter": 0.25,   # each interval is interval · U(1 − jitter, 1 + jitter)
    "offset_max": 0.1,         # offsets τ_i − τ_ref ~ U(−offset_max, offset_max), s (reference: 0)
    "drift_max": 1e-4,         # drifts δ_i ~ U(−drift_max, drift_max) for every array (reference included)
    "lead_in": 0.3,            # the earliest-starting clock reads τ = lead_in at t_emit[0], s
    "n_mics": 6,               # default mic geometry: circular array of n_mics ...
    "mic_radius": 0.0354,      # ... with this radius (m), in the array's x-y plane, origin at the centre
    "mics": None,              # or one (M, 3) geometry (m, array frame) for every generated array
    "geometries": None,        # or per generated array (A1 first; missing = default) one of GEOMETRIES
    "mic_spacing": 0.06,       # m between neighbouring mics of "pair" and "linear" arrays (along their x axis)
    "tilt_deg": None,          # None: rotations uniform on SO(3); else upright, random yaw, tilt N(0, tilt_deg)
    "room_margin": 1.5,        # paper presets: room = trajectory box + this margin on each side, m
    "wall_margin": 0.3,        # generated arrays keep at least this distance from the walls, m
    "min_source_distance": 0.5,  # generated arrays keep at least this distance from every speaker stop, m
    "n_interferers": 0,        # random interfering noise bursts (see the 'interferers' key)
    "interferer_level_db": 0.0,  # their power relative to the chirp's, dB
}
NEW_GEN_DEFAULTS = {
    "n_occluded": 0,           # 'hard': wall arrays whose direct path is occluded (see occlusion_*)
    "occlusion_db": 15.0,      # ... their direct path this many dB below the wall reflection, ...
    "occlusion_delay": 6e-4,   # ... which arrives this much later (median over the stops), s
    "n_speech": 0,             # speech-like interferers, each between two consecutive chirps
    "speech_level_db": 0.0,    # their power re. the chirp's emitted power, dB
    "n_quiet": 0,              # quiet events: emitted so that one array's matched-filter SNR is ...
    "quiet_snr_db": 0.0,       # ... this (single mic, white self-noise + diffuse noise), dB
    # deployment presets (pipeline/simulate/deploy.py)
    "room_shape": "box",       # "box" (room_dim), "L" / "U" (random L- / U-shaped plan), "nonconvex" (L or U)
    "motion": "none",          # the robot: "none" (stops for each chirp), "constant" / "varying" speed, "any"
    "n_stops": 16,             # events of a deployment preset (n_events overrides)
    "heights": [1.3, 1.0],     # m: speaker height in the first and second half of the session
    "boards": None,            # board names (deploy.BOARDS), cycled over the arrays (None: 6-mic circles)
    "mounts": None,            # "wall" | "table" | "stand", cycled over the arrays (None: wall, table)
    "n_obstacles": 0,          # panels across the line from the speaker to some arrays ...
    "obstacle_loss_db": [6.0, 20.0],   # ... with a 1 kHz loss drawn from this range, dB
    "n_noise": 0,              # broadband noise bursts (fans, trolleys) between chirps
    "interferer_levels_db": [-10.0, 6.0],  # deployment presets: each interferer's level drawn from this range
    "talker_overlap": False,   # deployment presets: the last interferer also spans a chirp
}
GEN_DEFAULTS |= NEW_GEN_DEFAULTS

SCENE_DEFAULTS = {
    "fs": 16000,
    "speed_of_sound": 343.0,
    "room_dim": None,
    "rt60": 0.3,
    "max_order": None,
    "chirp": {"f0": 500.0, "f1": 4000.0, "duration": 0.5, "fade": 0.005},
    "snr": 30.0,
    "diffuse_snr": math.inf,
    "sigma_odo": 0.01,
    "priors": {},  # none by default: the frontend then estimates TDOA/DOA noise from the recordings
    "subtype": "FLOAT",
    "tail": 0.3,
    "reference_array": "A1",
}
# Keys of the realistic acoustics; their defaults keep the original ("flat") simulator unchanged.
NEW_SCENE_DEFAULTS = {
    "model": "flat",           # "flat" (ISM, one absorption) | "bands" (materials, air, tail, directivity)
    "materials": None,         # bands: {walls, floor, ceiling, west, east, south, north} → material
    "air_absorption": True,    # bands: air absorption per band (pyroomacoustics coefficients)
    "mixing_time": 0.05,       # bands: image sources up to this long after the direct path, then the tail
    "directivity": "omni",     # bands: speaker pattern (omni|subcardioid|cardioid|supercardioid|hypercardioid|p)
    "rear_floor_db": -20.0,    # bands: the pattern's gain never drops below this (real speakers have no null)
    "source_axis": None,       # bands: (K, 3) speaker axes; None = the heading along the trajectory
    "event_level_db": None,    # (K,) emission level of each chirp, dB (None = all 0)
    "hum_snr": math.inf,       # mains hum re. P, dB (inf = off)
    "hum_freq": 50.0,          # Hz
    "hum_harmonics": 5,        # number of harmonics (amplitude 1/h)
    "gain_mismatch_db": 0.0,   # per-mic gains drawn U(−x, x) dB (arrays may give mic_gain_db instead)
    "floor_plan": None,        # bands: (P, 2) m corners of a polygonal (e.g. L-shaped) room, extruded to room_dim[2]
    "obstacles": None,         # bands: [{p0, p1 (2,) m, z (2,) m, loss_db, loss_slope_db}] attenuating panels
    "image_order": 3,          # bands, polygonal rooms / obstacles: reflections per image path
    "trajectory": None,        # {t (n,) s, pos (n, 3) m}: the speaker moves (cubic spline), also while chirping
    "sigma_vel": 0.01,         # m/s per axis: noise of the velocity odometry reports (events.csv vel_*)
}
SCENE_DEFAULTS |= NEW_SCENE_DEFAULTS
SCENE_KEYS = set(SCENE_DEFAULTS) | {"arrays", "sources", "t_emit", "interferers", "clock_faults"}
META_KEYS = {"preset", "seed"}
ALL_KEYS = SCENE_KEYS | set(GEN_DEFAULTS) | META_KEYS



# ----------------------------------------------------------------------------------------------- values
def _rng(seed, *purpose):
    # one independent stream per purpose: overriding one part of a scene never changes the draws of another
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=purpose))


def _merge(base, over):
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(out.get(k), dict) and not isinstance(v, (dict, type(None))):
            raise InputError(f"scenario: {k} must be a table (e.g. [{k}]), got {type(v).__name__} {v!r}")
        out[k] = {**out[k], **v} if isinstance(out.get(k), dict) and isinstance(v, dict) else copy.deepcopy(v)
    return out


def _int(v, name, lo):
    if isinstance(v, bool) or not isinstance(v, (int, np.integer, float)) or v != int(v) or v < lo:
        raise InputError(f"scenario: {name} must be an integer ≥ {lo}, got {v!r}")
    return int(v)


def _float(v, name, lo=None, allow_inf=False, strict=False):
    if v is None and allow_inf:
        return math.inf
    if isinstance(v, str) and allow_inf and v.strip().lower() in ("inf", "+inf", "infinity"):
        return math.inf
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise InputError(f"scenario: {name} must be a number, got {v!r}")
    v = float(v)
    if math.isnan(v) or (math.isinf(v) and not (allow_inf and v > 0)):
        raise InputError(f"scenario: {name} must be finite, got {v!r}")
    if lo is not None and (v < lo or (strict and v == lo)):
        raise InputError(f"scenario: {name} must be {'>' if strict else '≥'} {lo:g}, got {v:g}")
    return v


def _vector(v, name, n=None):
    try:
        a = np.asarray(v, float)
    except (TypeError, ValueError):
        raise InputError(f"scenario: {name} must be a list of numbers") from None
    if a.ndim != 1 or (n is not None and a.size != n) or not np.all(np.isfinite(a)):
        raise InputError(f"scenario: {name} must be {n if n else 'a list of'} finite numbers")
    return a


def _matrix(v, name, ncol):
    try:
        a = np.asarray(v, float)
    except (TypeError, ValueError):
        raise InputError(f"scenario: {name} must be a list of [x, y, z]") from None
    if a.size == 0:
        raise InputError(f"scenario: {name} is empty (zero events)" if name == "sources" else
                         f"scenario: {name} is empty")
    if a.ndim != 2 or a.shape[1] != ncol or not np.all(np.isfinite(a)):
        raise InputError(f"scenario: {name} must be a list of [x, y, z] with finite numbers")
    return a


def _materials(sc):
    m = sc.get("materials") or DEFAULT_MATERIALS
    return {"walls": m} if isinstance(m, (str, list)) else m


# ----------------------------------------------------------------------------------------------- validation
class Scenario(dict):
    """A validated scenario (what :func:`validate_scenario` returns): numpy arrays, defaults filled in.
    A plain dict is a raw scenario (JSON-like, as written in scenario.json or by ``make_scenario``)."""


def validate_scenario(scenario):
    """Check a scenario; return a normalised copy with numpy arrays (raises InputError, one line).

    The copy has ``room_dim`` (3,), ``sources`` (K, 3), ``t_emit`` (K,), ``chirp`` floats (+ ``kind``),
    ``event_level_db`` (K,), per array ``position`` (3,), ``R`` (3, 3) array → room, ``mics`` (M, 3),
    ``mics_room`` (M, 3), ``tau``, ``drift``, ``direct_db``, ``mic_gain_db`` (M,), ``index``; with the
    ``bands`` model also ``source_axis`` (K, 3) and ``acoustic`` (absorption (6, 7), air (7,),
    ``rt60_bands`` (7,), ``volume``).
    """
    sc = copy.deepcopy(scenario)
    for key in ("fs", "speed_of_sound", "room_dim", "rt60", "chirp", "arrays", "sources", "t_emit"):
        if key not in sc:
            raise InputError(f"scenario: missing key {key!r}")
    if sc.get("preset", "paper-traj3") not in PRESETS:
        raise InputError(f"scenario: unknown preset {sc['preset']!r} (choose from {', '.join(PRESETS)})")
    _check_scalars(sc)
    sc["chirp"] = _check_chirp(sc["chirp"], sc["fs"])
    src = sc["sources"] = _matrix(sc["sources"], "sources", 3)
    room = sc["room_dim"]
    sc["geometry"] = _check_geometry(sc)
    t = sc["t_emit"] = _vector(sc["t_emit"], "t_emit")
    if t.size != len(src):
        raise InputError(f"scenario: t_emit has {t.size} values for {len(src)} speaker stops")
    if np.any(np.diff(t) <= 0):
        raise InputError("scenario: t_emit must increase strictly")
    for j, s_ in enumerate(src):
        if np.any(s_ < 0.05) or np.any(s_ > room - 0.05) or not _inside(sc, s_, 0.05):
            raise InputError(f"scenario: speaker stop {j} {np.round(s_, 3).tolist()} is outside the room "
                             f"{room.tolist()} (or within 5 cm of a wall)")
    lev = sc.get("event_level_db")
    sc["event_level_db"] = np.zeros(len(src)) if lev is None else _vector(lev, "event_level_db", len(src))
    arrays = sc["arrays"]
    if not isinstance(arrays, (list, tuple)) or not arrays:
        raise InputError("scenario: no arrays")
    sc["arrays"] = [_check_array(k, a, sc) for k, a in enumerate(arrays)]
    names = [a["name"] for a in sc["arrays"]]
    if len(set(n.lower() for n in names)) != len(names):
        raise InputError("scenario: duplicate array name")
    ref = sc.get("reference_array", names[0])
    if ref not in names:
        raise InputError(f"scenario: reference_array {ref!r} is not one of the arrays {names}")
    sc["reference_array"] = ref
    sc["interferers"] = [_check_interferer(k, it, sc) for k, it in enumerate(sc.get("interferers") or [])]
    sc["trajectory"] = _check_trajectory(sc)
    clocks.attach(sc, sc.get("clock_faults"), sc["seed"])   # dropped/inserted blocks, drift changes, wrong rates
    _check_spacing(sc)
    if sc["model"] == "bands":
        _check_bands(sc)
    elif sc["rt60"] > 0 and sc.get("max_order") is None:
        _room_acoustics(sc)  # raises if the RT60 is not reachable in this room
    return Scenario(sc)


def _check_scalars(sc):
    """Scalar scene keys, in place (defaults for the optional ones)."""
    sc["seed"] = _int(sc.get("seed", 0), "seed", 0)
    sc["fs"] = _int(sc["fs"], "fs", 1000)
    sc["speed_of_sound"] = _float(sc["speed_of_sound"], "speed_of_sound", 0, strict=True)
    room = sc["room_dim"] = _vector(sc["room_dim"], "room_dim", 3)
    if np.any(room <= 0):
        raise InputError("scenario: room_dim must be positive")
    sc["rt60"] = _float(sc["rt60"], "rt60", 0)
    if sc.get("max_order") is not None:
        sc["max_order"] = _int(sc["max_order"], "max_order", 0)
    for key in ("snr", "diffuse_snr", "hum_snr"):
        sc[key] = _float(sc.get(key, math.inf), key, allow_inf=True)
    sc["sigma_odo"] = _float(sc.get("sigma_odo", 0.0), "sigma_odo", 0)
    sc["sigma_vel"] = _float(sc.get("sigma_vel", 0.01), "sigma_vel", 0)
    sc["tail"] = _float(sc.get("tail", 0.3), "tail", 0)
    sc["subtype"] = str(sc.get("subtype", "FLOAT")).upper()
    if sc["subtype"] not in SUBTYPES:
        raise InputError(f"scenario: subtype must be one of {', '.join(SUBTYPES)}, got {sc['subtype']!r}")
    pri = sc.get("priors") or {}
    sc["priors"] = {k: _float(v, f"priors.{k}", 0, strict=True) for k, v in pri.items()}
    for k, v in NEW_SCENE_DEFAULTS.items():
        sc.setdefault(k, copy.deepcopy(v))
    if sc["model"] not in MODELS:
        raise InputError(f"scenario: model must be one of {', '.join(MODELS)}, got {sc['model']!r}")
    sc["hum_freq"] = _float(sc["hum_freq"], "hum_freq", 0, strict=True)
    sc["hum_harmonics"] = _int(sc["hum_harmonics"], "hum_harmonics", 1)
    sc["gain_mismatch_db"] = _float(sc["gain_mismatch_db"], "gain_mismatch_db", 0)
    sc["mixing_time"] = _float(sc["mixing_time"], "mixing_time", 0, strict=True)
    sc["rear_floor_db"] = _float(sc["rear_floor_db"], "rear_floor_db")
    d = sc["directivity"]
    if not (d in ac.PATTERNS or (not isinstance(d, (str, bool)) and isinstance(d, (int, float)) and 0 <= d <= 1)):
        raise InputError(f"scenario: directivity must be one of {', '.join(ac.PATTERNS)} or a number in [0, 1], "
                         f"got {d!r}")
    if sc["model"] == "flat" and d != "omni":
        raise InputError("scenario: directivity needs model = \"bands\"")


def _check_chirp(ch, fs):
    if not isinstance(ch, dict):
        raise InputError("scenario: chirp must be a table")
    kind = ch.get("kind", "linear")
    out = {k: _float(ch.get(k), f"chirp.{k}", 0, strict=k != "fade") for k in ("f0", "f1", "duration", "fade")}
    if kind not in SWEEP_KINDS:
        raise InputError(f"scenario: chirp.kind must be one of {', '.join(SWEEP_KINDS)}, got {kind!r}")
    out["kind"] = kind
    if out["f0"] == out["f1"]:
        raise InputError("scenario: chirp.f0 and chirp.f1 must differ")
    if max(out["f0"], out["f1"]) > 0.45 * fs:
        raise InputError(f"scenario: chirp up to {max(out['f0'], out['f1']):g} Hz needs fs > "
                         f"{max(out['f0'], out['f1']) / 0.45:.0f} Hz (fs = {fs})")
    if 2 * out["fade"] > out["duration"]:
        raise InputError("scenario: chirp.fade must be at most half of chirp.duration")
    return out


def _check_array(k, a, sc):
    """One array (dict) → its normalised form (see :func:`validate_scenario`)."""
    if not isinstance(a, dict):
        raise InputError(f"scenario: arrays[{k}] must be a table")
    name = a.get("name")
    if not isinstance(name, str) or not name or any(ch_ in name for ch_ in "/\\\0") or name.startswith("."):
        raise InputError(f"scenario: arrays[{k}] needs a name usable as a file name, got {name!r}")
    for key in ("position", "quat", "mics", "tau", "drift"):
        if key not in a:
            raise InputError(f"scenario: array {name!r}: missing {key!r}")
    room, src = sc["room_dim"], sc["sources"]
    pos = _vector(a["position"], f"array {name!r} position", 3)
    q = _vector(a["quat"], f"array {name!r} quat", 4)
    if not np.linalg.norm(q) > 1e-9:
        raise InputError(f"scenario: array {name!r}: quat must be non-zero")
    q = q / np.linalg.norm(q)
    R = Rotation.from_quat(q, scalar_first=True).as_matrix()
    mics = _matrix(a["mics"], f"array {name!r} mics", 3)
    tau = _float(a["tau"], f"array {name!r} tau")
    drift = _float(a["drift"], f"array {name!r} drift")
    if abs(drift) >= 0.01:
        raise InputError(f"scenario: array {name!r}: |drift| must be < 0.01, got {drift:g}")
    mr = pos + mics @ R.T
    if np.any(pos <= 0) or np.any(pos >= room) or np.any(mr <= 0.01) or np.any(mr >= room - 0.01):
        raise InputError(f"scenario: array {name!r} at {np.round(pos, 3).tolist()} is outside the room "
                         f"{room.tolist()}")
    if not np.all(_inside(sc, mr, 0.01)):
        raise InputError(f"scenario: array {name!r} at {np.round(pos, 3).tolist()} is outside the floor plan")
    if np.min(np.linalg.norm(src[:, None, :] - mr[None], axis=2)) < 0.05:
        raise InputError(f"scenario: array {name!r} is within 5 cm of a speaker stop")
    hemi = a.get("doa_hemisphere")
    if hemi is not None:
        hemi = _vector(hemi, f"array {name!r} doa_hemisphere", 3)
    direct_db = _float(a.get("direct_db", 0.0), f"array {name!r} direct_db")
    if direct_db != 0 and sc["model"] != "bands":
        raise InputError(f"scenario: array {name!r}: direct_db needs model = \"bands\"")
    if a.get("mic_gain_db") is not None:
        gains = _vector(a["mic_gain_db"], f"array {name!r} mic_gain_db", len(mics))
    else:
        x = sc["gain_mismatch_db"]
        gains = _rng(sc["seed"], 7, k).uniform(-x, x, len(mics)) if x > 0 else np.zeros(len(mics))
    fs = _int(a.get("fs", sc["fs"]), f"array {name!r} fs", sc["fs"])   # mixed rates: ≥ the scenario's fs
    return {"name": name, "position": pos, "quat": q, "R": R, "mics": mics, "mics_room": mr, "tau": tau,
            "drift": drift, "doa_hemisphere": hemi, "direct_db": direct_db, "mic_gain_db": gains, "index": k,
            "fs": fs}


def _check_interferer(k, it, sc):
    if not isinstance(it, dict):
        raise InputError(f"scenario: interferers[{k}] must be a table")
    room = sc["room_dim"]
    p = _vector(it.get("position"), f"interferers[{k}] position", 3)
    if np.any(p < 0.05) or np.any(p > room - 0.05) or not _inside(sc, p, 0.05):
        raise InputError(f"scenario: interferers[{k}] is outside the room")
    kind = it.get("kind", "tones")
    if kind not in INTERFERER_KINDS:
        raise InputError(f"scenario: interferers[{k}] kind must be one of {', '.join(INTERFERER_KINDS)}, "
                         f"got {kind!r}")
    f_lo = _float(it.get("f_lo", 300.0), f"interferers[{k}] f_lo", 0, strict=True)
    f_hi = _float(it.get("f_hi", 5000.0), f"interferers[{k}] f_hi", f_lo, strict=True)
    f_hi = min(f_hi, 0.45 * sc["fs"])  # keep the burst band-limited on every clock
    return {"position": p, "t_start": _float(it.get("t_start"), f"interferers[{k}] t_start"),
            "duration": _float(it.get("duration"), f"interferers[{k}] duration", 0, strict=True),
            "level_db": _float(it.get("level_db", 0.0), f"interferers[{k}] level_db"),
            "f_lo": f_lo, "f_hi": max(f_hi, f_lo + 1.0), "kind": kind,
            "f0": _float(it.get("f0", 120.0), f"interferers[{k}] f0", 20.0)}


def _check_spacing(sc):
    """Every chirp must be fully recorded and separated from the next one at every array."""
    a = _arrivals(sc)  # (N, K, M)
    dur = sc["chirp"]["duration"]
    for i, arr in enumerate(sc["arrays"]):
        first = np.nanmin(a[i, 0])
        if first < 0.0:
            raise InputError(f"scenario: array {arr['name']!r} starts recording after the first chirp arrives "
                             f"(tau = {arr['tau']:.6g} s; its clock must read ≥ 0 when the chirp arrives)")
        gap = np.nanmin(a[i, 1:], axis=1) - np.nanmax(a[i, :-1], axis=1) - (1 + arr["drift"]) * dur
        if gap.size and gap.min() < 0.05:
            j = int(np.argmin(gap))
            raise InputError(f"scenario: chirps {j} and {j + 1} overlap at array {arr['name']!r} "
                             f"(gap {gap[j]:.3f} s < 0.05 s): increase the interval between emissions")


def _check_bands(sc):
    """The ``bands`` model: speaker axes and the per-band acoustics (in place)."""
    k = len(sc["sources"])
    if sc["source_axis"] is None:
        sc["source_axis"] = scenes.headings(sc["sources"])
    else:
        ax = _matrix(sc["source_axis"], "source_axis", 3)
        if len(ax) != k or np.any(np.linalg.norm(ax, axis=1) < 1e-9):
            raise InputError(f"scenario: source_axis must be {k} non-zero [x, y, z]")
        sc["source_axis"] = ax / np.linalg.norm(ax, axis=1, keepdims=True)
    room, c, air = sc["room_dim"], sc["speed_of_sound"], bool(sc["air_absorption"])
    geo = sc["geometry"]
    surf = ac.poly_surfaces(geo) if geo is not None else None
    n_walls = 6 if geo is None else len(geo["area"])
    try:
        alpha = (ac.scaled_absorption(_materials(sc), room, sc["rt60"], c, air, surf) if sc["rt60"] > 0
                 else np.ones((n_walls, len(ac.BAND_CENTERS))))
    except ValueError as exc:
        raise InputError(f"scenario: {exc}") from None
    sc["acoustic"] = {
        "alpha": alpha, "air": ac.air_attenuation() if air else np.zeros(len(ac.BAND_CENTERS)),
        "rt60_bands": (ac.band_rt60(alpha, room, c, air, surf) if sc["rt60"] > 0
                       else np.zeros(len(ac.BAND_CENTERS))),
        "volume": float(np.prod(room)) if geo is None else float(geo["volume"])}


def _check_geometry(sc):
    """A polygonal room and/or obstacles (``polyroom.make_geometry``), or None for a plain shoebox."""
    fp, obs = sc.get("floor_plan"), sc.get("obstacles") or []
    sc["image_order"] = _int(sc.get("image_order", 3), "image_order", 0)
    if fp is None and not obs:
        return None
    if sc["model"] != "bands":
        raise InputError("scenario: floor_plan and obstacles need model = \"bands\"")
    room = sc["room_dim"]
    if fp is None:
        fp = [[0.0, 0.0], [room[0], 0.0], [room[0], room[1]], [0.0, room[1]]]
    c = _matrix([list(p) + [0.0] for p in fp] if _is_rows(fp, 2) else fp, "floor_plan", 3)[:, :2]
    if len(c) < 3 or np.any(c < 0) or np.any(c > room[:2] + 1e-9) or abs(polyroom.signed_area(c)) < 1e-6:
        raise InputError("scenario: floor_plan must be ≥ 3 corners [x, y] inside room_dim's x-y box, "
                         "enclosing an area")
    out = []
    for k, o in enumerate(obs):
        if not isinstance(o, dict):
            raise InputError(f"scenario: obstacles[{k}] must be a table")
        loss = _float(o.get("loss_db", 10.0), f"obstacles[{k}] loss_db", 0)
        slope = _float(o.get("loss_slope_db", 3.0), f"obstacles[{k}] loss_slope_db")
        out.append({"p0": _vector(o.get("p0"), f"obstacles[{k}] p0", 2),
                    "p1": _vector(o.get("p1"), f"obstacles[{k}] p1", 2),
                    "z": _vector(o.get("z", [0.0, room[2]]), f"obstacles[{k}] z", 2),
                    "loss_db": obstacle_loss(loss, slope)})
    return polyroom.make_geometry(c, room[2], out)


def obstacle_loss(loss_db, slope_db):
    """(7,) band losses (dB ≥ 0) of an obstacle: ``loss_db`` at 1 kHz, ``slope_db`` more per octave up."""
    return np.maximum(loss_db + slope_db * np.log2(np.asarray(ac.BAND_CENTERS) / ac.RT60_BAND), 0.0)


def _is_rows(v, n):
    try:
        return all(len(p) == n for p in v)
    except TypeError:
        return False


def _inside(sc, p, margin):
    """Whether point(s) ``p`` lie inside the floor plan (True for a shoebox: its box is checked elsewhere)."""
    geo = sc.get("geometry")
    if geo is None or sc.get("floor_plan") is None:
        return True
    return bool(np.all(polyroom.inside(geo, np.atleast_2d(p), margin)))


def _check_trajectory(sc):
    """A moving speaker: its Trajectory (None if it stops for each chirp). The stops ``sources`` must be
    its positions at the sweep starts ``t_emit`` and it must stay in the room while chirping."""
    spec = sc.get("trajectory")
    if spec is None:
        return None
    if sc["model"] != "bands":
        raise InputError("scenario: a trajectory needs model = \"bands\"")
    if not isinstance(spec, dict) or "t" not in spec or "pos" not in spec:
        raise InputError("scenario: trajectory must be a table with t (s) and pos ([x, y, z] m)")
    t = _vector(spec["t"], "trajectory.t")
    pos = _matrix(spec["pos"], "trajectory.pos", 3)
    if len(t) != len(pos) or len(t) < 4 or np.any(np.diff(t) <= 0):
        raise InputError("scenario: trajectory needs ≥ 4 increasing times t, one pos per time")
    dur = sc["chirp"]["duration"]
    if t[0] > sc["t_emit"][0] or t[-1] < sc["t_emit"][-1] + dur:
        raise InputError("scenario: the trajectory must cover every chirp (t_emit[0] to t_emit[-1] + duration)")
    traj = motion.Trajectory({"t": t, "pos": pos})
    if np.max(np.abs(traj(sc["t_emit"]) - sc["sources"])) > 1e-6:
        raise InputError("scenario: sources must be the trajectory's positions at t_emit (the sweep starts)")
    ts = np.concatenate([np.linspace(x, x + dur, 11) for x in sc["t_emit"]])
    p = traj(ts)
    if np.any(p < 0.05) or np.any(p > sc["room_dim"] - 0.05) or not _inside(sc, p, 0.05):
        raise InputError("scenario: the speaker leaves the room while chirping")
    return traj


def _room_acoustics(sc):
    """(energy absorption, max ISM order) for the scenario's room."""
    import pyroomacoustics as pra

    if sc["rt60"] == 0:
        return 1.0, 0
    try:
        e_abs, order = pra.inverse_sabine(sc["rt60"], list(sc["room_dim"]), c=sc["speed_of_sound"])
    except ValueError:
        raise InputError(f"scenario: rt60 = {sc['rt60']:g} s is too short for a "
                         f"{'×'.join(f'{x:g}' for x in sc['room_dim'])} m room (Sabine absorption > 1)") from None
    if sc.get("max_order") is not None:
        order = sc["max_order"]
    return float(e_abs), int(order)

# ----------------------------------------------------------------------------------------------- analytic truth
def _arrivals(sc):
    """(N, K, M) local arrival times of the direct path at each mic (normalised scenario, equal M)."""
    t0 = sc["t_emit"][0]
    out = []
    for a in sc["arrays"]:
        d = np.linalg.norm(sc["sources"][:, None, :] - a["mics_room"][None], axis=2)  # (K, M)
        out.append(clocks.local(a, sc["t_emit"][:, None] + d / sc["speed_of_sound"], t0))
    m = {x.shape[1] for x in out}
    if len(m) == 1:
        return np.stack(out)
    width = max(m)  # ragged mic counts: pad with NaN so min/max still work with nan-aware callers
    return np.stack([np.pad(x, ((0, 0), (0, width - x.shape[1])), constant_values=np.nan) for x in out])


def arrival_times(scenario, mics=False):
    """Analytic arrival times of each chirp's START, on each array's own clock (s).

    ``a_ij = L_i(t_emit[j] + |s_j − x_i| / c)`` at the array ORIGIN: returns (n_arrays, n_events).
    With ``mics=True``: a list (one per array) of (n_events, n_mics) times at the individual mics.
    """
    sc = scenario if isinstance(scenario, Scenario) else _normalise_light(scenario)
    t0 = sc["t_emit"][0]
    if mics:
        return [clocks.local(a, sc["t_emit"][:, None] + np.linalg.norm(sc["sources"][:, None, :] - a["mics_room"][None],
                                                                       axis=2) / sc["speed_of_sound"], t0)
                for a in sc["arrays"]]
    return np.stack([clocks.local(a, sc["t_emit"] + np.linalg.norm(sc["sources"] - a["position"], axis=1)
                                  / sc["speed_of_sound"], t0) for a in sc["arrays"]])


def _normalise_light(scenario):
    sc = {"t_emit": np.asarray(scenario["t_emit"], float), "sources": np.asarray(scenario["sources"], float),
          "speed_of_sound": float(scenario["speed_of_sound"]), "arrays": []}
    for a in scenario["arrays"]:
        R = Rotation.from_quat(np.asarray(a["quat"], float), scalar_first=True).as_matrix()
        pos = np.asarray(a["position"], float)
        sc["arrays"].append({"name": a["name"], "position": pos, "R": R, "tau": float(a["tau"]),
                             "drift": float(a["drift"]), "mics_room": pos + np.asarray(a["mics"], float) @ R.T})
    return clocks.attach(sc, scenario.get("clock_faults"), scenario.get("seed", 0))


def scenario_truth(scenario):
    """Truth in the reference array's frame: ``{"arrays": df, "sources": df}`` (docs/formats.md section 4).

    ``x_i' = R_refᵀ(x_i − x_ref)``, ``R_i' = R_refᵀ R_i``, ``s_j' = R_refᵀ(s_j − x_ref)``,
    ``offset_i = τ_i − τ_ref``, ``drift_i = δ_i``.
    """
    sc = scenario if isinstance(scenario, Scenario) else _normalise_light(scenario)
    ref = next(a for a in sc["arrays"] if a["name"] == scenario.get("reference_array", sc["arrays"][0]["name"]))
    Rr, xr = ref["R"], ref["position"]
    rows = []
    for a in sc["arrays"]:
        x = Rr.T @ (a["position"] - xr)
        q = Rotation.from_matrix(Rr.T @ a["R"]).as_quat(scalar_first=True)
        q = q if q[0] >= 0 else -q
        rows.append([a["name"], *x, *q, a["tau"] - ref["tau"], a["drift"]])
    arrays = pd.DataFrame(rows, columns=ARRAYS_COLS)
    arrays.loc[arrays["array"] == ref["name"], ["x", "y", "z", "offset"]] = 0.0
    s = (sc["sources"] - xr) @ Rr
    sources = pd.DataFrame({"event": np.arange(len(s)), "x": s[:, 0], "y": s[:, 1], "z": s[:, 2]})
    return {"arrays": arrays, "sources": sources}


def odometry(scenario):
    """(K, 3) odometry in the reference frame: ``R_refᵀ(s_j − s_0)`` + cumulative N(0, σ_odo²) steps."""
    sc = scenario if isinstance(scenario, Scenario) else _normalise_light(scenario)
    ref = next(a for a in sc["arrays"] if a["name"] == scenario.get("reference_array", sc["arrays"][0]["name"]))
    s = sc["sources"]
    steps = _rng(int(scenario.get("seed", 0)), 10).normal(0.0, float(scenario.get("sigma_odo", 0.0)), s.shape)
    steps[0] = 0.0
    return (s - s[0]) @ ref["R"] + np.cumsum(steps, axis=0)


VEL_COLS = ["vel_x", "vel_y", "vel_z"]   # optional events.csv columns: the robot's velocity at the sweep start
TRAJECTORY_STEP = 0.02                   # s between the rows of truth/trajectory.csv


def odometry_velocity(scenario):
    """(K, 3) the moving speaker's velocity at each sweep start in the reference frame (m/s), as odometry
    reports it: ``R_refᵀ v(t_emit)`` + N(0, σ_vel²) per axis (``sigma_vel``)."""
    sc = scenario if isinstance(scenario, Scenario) else validate_scenario(scenario)
    ref = next(a for a in sc["arrays"] if a["name"] == sc["reference_array"])
    v = sc["trajectory"].velocity(sc["t_emit"]) @ ref["R"]
    return v + _rng(int(sc.get("seed", 0)), 12).normal(0.0, float(sc.get("sigma_vel", 0.0)), v.shape)


def trajectory_truth(scenario):
    """The moving speaker's true path in the reference frame: DataFrame ``t`` (emitter clock, s), ``x``,
    ``y``, ``z`` (m) every TRAJECTORY_STEP from the first sweep start to the end of the last sweep."""
    sc = scenario if isinstance(scenario, Scenario) else validate_scenario(scenario)
    ref = next(a for a in sc["arrays"] if a["name"] == sc["reference_array"])
    t = np.arange(sc["t_emit"][0], sc["t_emit"][-1] + sc["chirp"]["duration"] + 1e-9, TRAJECTORY_STEP)
    p = (sc["trajectory"](t) - ref["position"]) @ ref["R"]
    return pd.DataFrame({"t": t, "x": p[:, 0], "y": p[:, 1], "z": p[:, 2]})
