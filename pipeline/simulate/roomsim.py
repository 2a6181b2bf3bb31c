"""Room (audio) simulator with per-array drifting clocks → a recording session folder + ``truth/``.

pyroomacoustics gives the image-source model (ISM) of a shoebox room, but all its microphones share one
integer ``fs``, ``add_source(delay=...)`` floors the emission delay to whole samples and ``compute_rir``
shifts every RIR by ``frac_delay_length // 2`` samples. This module adds what is missing, exactly:

* Clock model (docs/architecture.md): array ``i`` reads local time ``L_i(t) = (1 + δ_i)(t − t_0) + τ_i``
  with ``t_0 = t_emit[0]``; sample ``n`` of its WAV is taken at local time ``n / fs``. Sample 0 is local
  time 0, i.e. true time ``t_0 − τ_i / (1 + δ_i)``.
* Every mic signal is synthesised directly on its array's sample instants: on array ``i`` the true-time
  step between samples is ``1 / fs'_i`` with ``fs'_i = fs (1 + δ_i)``. The chirp is evaluated analytically
  at those instants (sub-sample emission time, stretched by the drift) and convolved with an RIR whose
  image delays are expressed in the same samples (``fs'_i · d / c``), built by pyroomacoustics' own
  windowed-sinc RIR builder. Band-limited interpolation makes the sum of images exact up to the
  fractional-delay filter (81-tap Hann-windowed sinc); the builder's global delay is measured once
  (``builder_delay``) and removed.

The scenario is a plain dict (see :func:`make_scenario`); :func:`simulate` writes docs/formats.md section 1
(``session.toml``, one float32/PCM WAV per array, ``events.csv``, ``chirp.wav``) plus ``truth/``
(section 4, in the reference array's frame) and ``truth/manifest.json`` (the room-frame scenario and
everything derived from it).
"""
from __future__ import annotations

import copy
import json
import math
import zlib
from calib.tomlcompat import tomllib
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation
from calib.jsonutil import jsonable  # inf (no noise) and NaN ↔ null

from calib.pipeline.simulate import acoustics as ac
from calib.pipeline.simulate import deploy, scenes, simrender
from calib.pipeline.simulate.presets import DEPLOY
from calib.pipeline.simulate import clocks
from calib.pipeline.formats.io import EVENTS_COLS, InputError, atomic_dir, write_table, write_truth
from calib.geometry import local_time, yaw_matrix  # noqa: F401  (local_time: a public name)
from calib.pipeline.simulate.render import EARLY, FDL, FDL_LATE, builder_delay  # noqa: F401  (public names)
from calib.pipeline.simulate.scenario import (  # noqa: F401  (PRESETS, REALISTIC, _PAPER_TRAJ, _room_acoustics: public/test names)
    _LAB_HEIGHTS, _LAB_LOOP, _PAPER_TRAJ, ALL_KEYS, GEN_DEFAULTS, NEW_GEN_DEFAULTS,
    NEW_SCENE_DEFAULTS, PRESETS, REALISTIC, SCENE_DEFAULTS, SCENE_KEYS, _float, _int, _materials, _matrix, _merge,
    _room_acoustics, _rng, _vector, VEL_COLS, Scenario, arrival_times, odometry, odometry_velocity, scenario_truth,
    trajectory_truth, validate_scenario)
from calib.pipeline.formats.session import write_session_toml
from calib.pipeline.formats.validate import read_text
from calib.pipeline.simulate.simrender import direct_amplitudes, line_of_sight, noise_levels, render_session
from calib.pipeline.simulate.sounds import chirp_signal  # noqa: F401  (a public name of the simulator)


# ----------------------------------------------------------------------------------------------- signals
def circular_array(n_mics=6, radius=0.0354):
    """Mic positions (n_mics, 3) of a uniform circular array in the x-y plane, centred on the origin (m)."""
    return scenes.named_mics("circle", None, n_mics, radius, 0.0)


# ----------------------------------------------------------------------------------------------- scenario
def make_scenario(preset: str = "paper-traj3", seed: int = 0, **overrides: Any) -> dict[str, Any]:
    """A complete, deterministic scenario (plain dict) from a preset, a seed and overrides.

    Presets: ``paper-traj1`` (8 stops, 3×3×3 m cube), ``paper-traj2`` (10 stops, 2×6×2 m),
    ``paper-traj3`` (14 stops, 4×4×2 m) — the trajectories of Zhang et al. 2025, 5 arrays at random
    positions inside the trajectory box and rotations uniform on SO(3), room = box + 1.5 m on each side —
    ``lab3`` (3 roughly upright arrays near the floor, 7 stops on a ~1.7 m loop flown at 1.12 m then
    0.75 m, like the paper's real experiment, in a 6×5×3 m room), and the realistic presets (``bands``
    model: materials, air absorption, late tail, cardioid speaker, noise, hum, gain mismatch) ``lab``
    (6×5×3 m, RT60 0.4 s, 16 kHz, 4 planar 6-mic circles on tables and walls), ``hall`` (12×8×4 m, RT60
    0.8 s, 48 kHz, 6 non-planar arrays) and ``hard`` (the lab plus an occluded array, a speech-like
    interferer and a quiet event).

    Any key below may be overridden (nested dicts ``chirp``/``priors`` are merged). All values are SI and
    in the ROOM frame (origin at a room corner, walls along the axes).

    Scene keys (what :func:`simulate` uses):
      ``preset`` str, ``seed`` int (drives every random draw, including noise and odometry);
      ``fs`` int Hz (nominal rate of every recorder); ``speed_of_sound`` m/s; ``room_dim`` (3,) m;
      ``rt60`` s (flat: Sabine, via ``pyroomacoustics.inverse_sabine``; bands: Sabine RT60 of the 1 kHz
      octave; 0 = anechoic); ``max_order`` int|None (flat ISM order; None = from inverse_sabine);
      ``chirp`` {f0 Hz, f1 Hz, duration s, fade s, kind linear|exponential};
      ``arrays`` list of {``name`` str, ``position`` (3,) m, ``quat`` (4,) scalar-first rotation array
      frame → room, ``mics`` (M, 3) m in the array frame (one per WAV channel), ``tau`` s (local clock
      reading at t_emit[0]), ``drift`` (δ, dimensionless), optional ``doa_hemisphere`` (3,) array frame,
      ``direct_db`` dB (bands: direct-path gain, default 0), ``mic_gain_db`` (M,) dB};
      ``reference_array`` str (its frame is the world frame of everything written);
      ``sources`` (K, 3) m speaker stops; ``t_emit`` (K,) s emission times of the chirp STARTS on the
      emitter clock; ``snr`` dB (white sensor noise re. the mean direct-path chirp power at the mics;
      inf = none); ``diffuse_snr`` dB (pink noise with diffuse-field coherence, same reference);
      ``interferers`` list of {``position`` (3,) m, ``t_start`` s (emitter clock), ``duration`` s,
      ``level_db`` dB re. the chirp's emitted power, ``kind`` tones|speech, ``f_lo``/``f_hi`` Hz (tones),
      ``f0`` Hz (speech pitch)}; ``sigma_odo`` m (odometry step noise, per axis); ``priors``
      {sigma_tdoa s, sigma_doa_deg deg} written to session.toml [noise] (default none);
      ``subtype`` FLOAT|PCM_24|PCM_16; ``tail`` s recorded after the last reverberation;
      and the realistic-acoustics keys of ``NEW_SCENE_DEFAULTS`` (docs/simulation.md).
    Generation keys (only steer the random draws): see ``GEN_DEFAULTS``.
    """
    g, sc = _start(preset, seed, overrides)
    seed = sc["seed"]
    if preset in DEPLOY:
        return _deploy_scenario(preset, g, sc, overrides)
    # speaker stops (room frame) and the room
    if "sources" in overrides:
        sources = _matrix(overrides["sources"], "sources", 3)
        if sc["room_dim"] is None:
            raise InputError("scenario: 'sources' given without 'room_dim'")
        room = _vector(sc["room_dim"], "room_dim", 3)
    else:
        sources, room = _make_sources(preset, g, sc["room_dim"], _rng(seed, 1))
    # arrays: poses and clocks (placed around the full trajectory, so n_events does not move them)
    if "arrays" in overrides:
        arrays = _user_arrays(overrides["arrays"], g)
    else:
        arrays = _make_arrays(preset, g, np.asarray(sources), room, _int(g["n_arrays"], "n_arrays", 1),
                              _rng(seed, 2), _rng(seed, 3), sc)
    sc["arrays"] = arrays
    sc["reference_array"] = overrides.get("reference_array", arrays[0]["name"])
    if g["n_events"] is not None and "sources" not in overrides:
        sources = _first_events(sources, g["n_events"], preset)
    sc["room_dim"] = room.tolist()
    sc["sources"] = np.asarray(sources, float).tolist()

    # emission schedule: t_emit[0] = lead time after the latest clock start, rounded to the microsecond
    if "t_emit" in overrides:
        sc["t_emit"] = _vector(overrides["t_emit"], "t_emit").tolist()
    else:
        sc["t_emit"] = _make_emissions(len(sources), g, max(a["tau"] for a in arrays), _rng(seed, 4)).tolist()

    if "interferers" in overrides:
        sc["interferers"] = copy.deepcopy(list(overrides["interferers"]))
    else:
        sc["interferers"] = _make_interferers(g, room, sc["t_emit"], _rng(seed, 5))
        sc["interferers"] += _make_speech(g, room, sc, _rng(seed, 6))
    if "event_level_db" not in overrides and _int(g["n_quiet"], "n_quiet", 0) > 0:
        sc["event_level_db"] = _quiet_events(sc, g)
    sc["generator"] = {k: g[k] for k in GEN_DEFAULTS}
    return sc


def _deploy_scenario(preset, g, sc, overrides):
    """A deployment preset (pipeline/simulate/deploy.py): the layout drawn from the seed, overrides kept."""
    # keys _start merged (tables such as chirp: --chirp-duration keeps f0/f1) stay merged; the rest as given
    sc |= {k: copy.deepcopy(v) for k, v in overrides.items() if k in SCENE_KEYS and not isinstance(v, dict)}
    try:
        stream = zlib.crc32(preset.encode())       # each preset its own draws: no two share a room by seed
        deploy.build(g, sc, lambda k: _rng(sc["seed"], 200 + k, stream), overrides)
    except ValueError as exc:
        raise InputError(f"scenario: {exc}") from None
    sc["reference_array"] = overrides.get("reference_array", sc.get("reference_array", sc["arrays"][0]["name"]))
    sc.setdefault("interferers", [])
    sc["generator"] = {k: g[k] for k in GEN_DEFAULTS}
    return sc


def _draws(preset, seed, overrides):
    """The preset's per-seed draws {key: U(lo, hi)} (integers for integer keys), keys given kept."""
    rng = _rng(seed, 11)
    out = {}
    for k, (lo, hi) in sorted(PRESETS[preset].get("draws", {}).items()):
        v = rng.uniform(lo, hi)
        if k not in overrides:
            out[k] = int(rng.integers(lo, hi + 1)) if isinstance(lo, int) else round(float(v), 3)
    return out


def _start(preset, seed, overrides):
    """Checked preset/seed/keys → (generation keys, scene keys with preset and overrides merged)."""
    if preset not in PRESETS:
        raise InputError(f"scenario: unknown preset {preset!r} (choose from {', '.join(PRESETS)})")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"scenario: seed must be a non-negative integer, got {seed!r}")
    unknown = sorted(set(overrides) - ALL_KEYS)
    if unknown:
        raise InputError(f"scenario: unknown key(s) {', '.join(map(repr, unknown))}")
    overrides = {**_draws(preset, seed, overrides), **overrides}
    g = {**GEN_DEFAULTS, **{k: v for k, v in PRESETS[preset].items() if k in GEN_DEFAULTS},
         **{k: v for k, v in overrides.items() if k in GEN_DEFAULTS}}
    base = _merge(SCENE_DEFAULTS, {k: v for k, v in PRESETS[preset].items() if k in SCENE_DEFAULTS})
    sc = _merge(base, {k: v for k, v in overrides.items()
                       if k in SCENE_DEFAULTS and k not in ("reference_array",)})
    if overrides.get("clock_faults"):   # {array: clock faults} (pipeline.simulate.clocks), checked with the arrays
        sc["clock_faults"] = copy.deepcopy(dict(overrides["clock_faults"]))
    return g, {"preset": preset, "seed": int(seed), **sc}


def _first_events(sources, n_events, preset):
    k = _int(n_events, "n_events", 0)
    if k == 0:
        raise InputError("scenario: n_events must be at least 1 (zero events)")
    if k > len(sources):
        raise InputError(f"scenario: preset {preset!r} has {len(sources)} speaker stops, n_events={k} asked")
    return sources[:k]


def _make_sources(preset, g, room_dim, rng):
    """Speaker stops (K, 3) in the room frame and the room size (3,)."""
    if preset in _PAPER_TRAJ:
        traj = _PAPER_TRAJ[preset]
        extent = traj.max(0) - traj.min(0)
        room = (extent + 2 * float(g["room_margin"]) if room_dim is None else _vector(room_dim, "room_dim", 3))
        return traj - traj.min(0) + (room - extent) / 2, np.asarray(room, float)
    if preset in REALISTIC:
        room = _vector(room_dim, "room_dim", 3)
        radii, heights = ((4.0, 2.6), (1.5, 1.0)) if preset == "hall" else ((1.6, 1.2), (1.3, 1.05))
        return scenes.loop_stops(room, rng, radii, heights), room
    # lab3: the real loop, rotated about z, jittered, centred near the middle of the room
    room = _vector(room_dim, "room_dim", 3)
    psi = rng.uniform(-np.pi, np.pi)
    rot = yaw_matrix(psi)[:2, :2]
    centre = room[:2] / 2 + rng.uniform(-0.3, 0.3, 2)
    stops = []
    for h in _LAB_HEIGHTS:
        xy = _LAB_LOOP @ rot.T + centre + rng.normal(0, 0.03, (len(_LAB_LOOP), 2))
        stops.append(np.column_stack([xy, h + rng.normal(0, 0.01, len(_LAB_LOOP))]))
    return np.concatenate(stops), room


def _make_arrays(preset, g, sources, room, n, rng_pose, rng_clock, sc):
    """Random array poses (rejection sampling under the distance constraints) and clocks."""
    if preset in REALISTIC:
        positions, rots, extra = _realistic_poses(preset, g, sources, room, n, rng_pose, sc)
        mics = scenes.octahedron_mics() if preset == "hall" and g["mics"] is None else _default_mics(g)
    else:
        positions, rots = _legacy_poses(preset, g, sources, room, n, rng_pose)
        extra = [{"doa_hemisphere": [0.0, 0.0, 1.0]} if g["tilt_deg"] is not None else {} for _ in range(n)]
        mics = _default_mics(g)
    mics = _geometries(g, n, mics)
    offmax, drmax = float(g["offset_max"]), float(g["drift_max"])
    off = rng_clock.uniform(-offmax, offmax, n)
    off[0] = 0.0
    drift = rng_clock.uniform(-drmax, drmax, n)
    tau = off - off.min() + float(g["lead_in"])
    out = []
    for i in range(n):
        q = rots[i].as_quat(scalar_first=True)
        q = q if q[0] >= 0 else -q
        out.append({"name": f"A{i + 1}", "position": np.asarray(positions[i], float).tolist(), "quat": q.tolist(),
                    "mics": mics[i].tolist(), "tau": float(tau[i]), "drift": float(drift[i]), **extra[i]})
    return out


def _geometries(g, n, default):
    """Each generated array's (M, 3) mics: scenario key ``geometries`` (names of scenes.GEOMETRIES, one per
    array from A1; missing entries = the preset's default geometry)."""
    names = g.get("geometries")
    if names is None:
        return [default] * n
    if isinstance(names, str) or not isinstance(names, (list, tuple)) or len(names) > n:
        raise InputError(f"scenario: geometries must be a list of at most n_arrays = {n} names")
    bad = [x for x in names if x not in scenes.GEOMETRIES]
    if bad:
        raise InputError(f"scenario: unknown geometry {bad[0]!r} (choose from {', '.join(scenes.GEOMETRIES)})")
    spacing = _float(g["mic_spacing"], "mic_spacing", 0, strict=True)
    n_mics = _int(g["n_mics"], "n_mics", 1)
    kinds = list(names) + ["default"] * (n - len(names))
    return [scenes.named_mics(k, default, n_mics, float(g["mic_radius"]), spacing) for k in kinds]


def _legacy_poses(preset, g, sources, room, n, rng_pose):
    """Poses of the paper and lab3 presets: (positions list, Rotation of n)."""
    wall, dmin = float(g["wall_margin"]), float(g["min_source_distance"])
    if preset == "lab3":
        lo = np.r_[sources[:, :2].min(0) + 0.2, 0.30]
        hi = np.r_[sources[:, :2].max(0) - 0.2, 0.40]
        pair = (0.5, 1.2)
    else:
        lo, hi = sources.min(0), sources.max(0)
        pair = (0.3, np.inf)
    lo, hi = np.maximum(lo, wall), np.minimum(hi, room - wall)
    if np.any(lo >= hi):
        raise InputError("scenario: no room to place arrays (room too small for the wall margin)")
    pos = []
    for _ in range(20000):
        if len(pos) == n:
            break
        p = rng_pose.uniform(lo, hi)
        if np.min(np.linalg.norm(sources - p, axis=1)) < dmin:
            continue
        d = [np.linalg.norm(p - q) for q in pos]
        if d and (min(d) < pair[0] or max(d) > pair[1]):
            continue
        pos.append(p)
    if len(pos) < n:
        raise InputError(f"scenario: cannot place {n} arrays under the distance constraints "
                         f"(≥ {dmin} m from speaker stops, ≥ {wall} m from walls)")
    if g["tilt_deg"] is None:
        return pos, Rotation.random(n, rng=rng_pose)
    yaw = Rotation.from_euler("z", rng_pose.uniform(-np.pi, np.pi, (n, 1)))
    tilt = np.zeros((n, 3))
    tilt[:, :2] = np.deg2rad(float(g["tilt_deg"])) * rng_pose.standard_normal((n, 2))
    return pos, Rotation.from_rotvec(tilt) * yaw


WALL_ARRAY_DEPTH = 0.1     # m: wall-mounted arrays of lab/hard sit this far from their wall
HALL_WALL_DEPTH = 0.15     # m: the hall's wall arrays


def _realistic_poses(preset, g, sources, room, n, rng, sc):
    """Poses of lab/hall/hard: lab alternates tables and walls (planar, hemisphere = the array normal);
    the hall puts 4 arrays on the walls (1.5-3 m high) and the rest on stands (any rotation).
    ``hard`` moves its first ``n_occluded`` wall arrays to the depth where the wall's reflection arrives
    ``occlusion_delay`` after the direct path and attenuates that direct path (``direct_db``)."""
    walls = list(rng.permutation(4))
    n_occ = _int(g["n_occluded"], "n_occluded", 0)
    kinds, extra = [], []
    for i in range(n):
        if preset == "hall":
            kinds.append(("wall", walls[i % 4], (1.5, 3.0), HALL_WALL_DEPTH) if i < 4 else ("stand", (1.0, 1.6)))
            extra.append({})
            continue
        if i % 2 == 0:
            kinds.append(("table",))
            extra.append({"doa_hemisphere": [0.0, 0.0, 1.0]})
            continue
        wall, depth, e = walls[(i // 2) % 4], WALL_ARRAY_DEPTH, {"doa_hemisphere": [0.0, 0.0, 1.0]}
        if i // 2 < n_occ:
            depth = scenes.occlusion_depth(sources, wall, room, sc["speed_of_sound"], float(g["occlusion_delay"]))
            e["direct_db"] = _occlusion_db(sources, wall, room, depth, sc, float(g["occlusion_db"]))
        kinds.append(("wall", wall, (2.0, 2.4), depth))
        extra.append(e)
    poses = scenes.place(kinds, room, sources, rng, float(g["min_source_distance"]))
    if poses is None:
        raise InputError(f"scenario: cannot place {n} arrays under the distance constraints")
    return [p for p, _ in poses], [r for _, r in poses], extra


def _occlusion_db(sources, wall, room, depth, sc, below_db):
    """Direct-path gain (dB) that puts the direct path ``below_db`` under the first-order reflection on
    ``wall`` (median over the stops; reflection factor of the wall at 1 kHz, spherical spreading)."""
    try:
        alpha = ac.scaled_absorption(_materials(sc), room, _float(sc["rt60"], "rt60", 0), sc["speed_of_sound"]) \
            if sc["rt60"] > 0 else np.ones((6, len(ac.BAND_CENTERS)))
    except ValueError as exc:
        raise InputError(f"scenario: {exc}") from None
    beta = math.sqrt(1 - alpha[wall, ac.BAND_CENTERS.index(ac.RT60_BAND)])
    pos = np.array(room, float) / 2
    axis, far = divmod(wall, 2)
    pos[axis] = room[axis] - depth if far else depth
    extra = scenes.reflection_delay(sources, pos, wall, room, 1.0)       # path difference, m
    d = np.linalg.norm(sources - pos, axis=1)
    ratio = float(np.median(beta * d / (d + extra))) if beta > 0 else 1.0   # anechoic: re. the direct path
    return round(20 * math.log10(ratio) - below_db, 2)


def _default_mics(g):
    if g.get("mics") is not None:
        return _matrix(g["mics"], "mics", 3)
    return circular_array(_int(g["n_mics"], "n_mics", 1), float(g["mic_radius"]))


def _user_arrays(arrays, g):
    if not isinstance(arrays, (list, tuple)) or not arrays:
        raise InputError("scenario: 'arrays' must be a non-empty list of tables")
    out = []
    for k, a in enumerate(arrays):
        if not isinstance(a, dict):
            raise InputError(f"scenario: arrays[{k}] must be a table")
        a = copy.deepcopy(a)
        a.setdefault("name", f"A{k + 1}")
        a.setdefault("quat", [1.0, 0.0, 0.0, 0.0])
        a.setdefault("mics", _default_mics(g).tolist())
        a.setdefault("tau", float(g["lead_in"]))
        a.setdefault("drift", 0.0)
        out.append(a)
    return out


def _make_emissions(k, g, tau_max, rng):
    mean = _float(g["interval"], "interval", 0, strict=True)
    jit = _float(g["interval_jitter"], "interval_jitter", 0)
    if jit >= 1:
        raise InputError("scenario: interval_jitter must be < 1")
    steps = mean * rng.uniform(1 - jit, 1 + jit, max(k - 1, 0))
    t = 0.3 + tau_max + np.concatenate([[0.0], np.cumsum(steps)])
    return np.round(t, 6)


def _make_interferers(g, room, t_emit, rng):
    n = _int(g["n_interferers"], "n_interferers", 0)
    out = []
    wall = float(g["wall_margin"])
    for _ in range(n):
        out.append({"position": rng.uniform(wall, room - wall).tolist(),
                    "t_start": float(np.round(rng.uniform(t_emit[0], t_emit[-1] + 0.5), 6)),
                    "duration": float(np.round(rng.uniform(0.1, 0.4), 6)),
                    "level_db": float(g["interferer_level_db"]), "f_lo": 300.0, "f_hi": 5000.0})
    return out


def _make_speech(g, room, sc, rng):
    """``n_speech`` speech-like interferers, each in the gap between two consecutive chirps (the middle
    ones), at a random place in the room: from a quarter into the gap, half the gap long."""
    n = _int(g["n_speech"], "n_speech", 0)
    t, dur = sc["t_emit"], sc["chirp"]["duration"]
    wall = float(g["wall_margin"])
    out = []
    for i in range(min(n, len(t) - 1)):
        j = (len(t) - 1) // 2 + i - n // 2
        gap = t[j + 1] - t[j] - dur
        out.append({"kind": "speech", "position": rng.uniform(wall, room - wall).tolist(),
                    "t_start": float(np.round(t[j] + dur + 0.25 * gap, 6)),
                    "duration": float(np.round(0.5 * gap, 6)), "level_db": float(g["speech_level_db"]),
                    "f0": float(np.round(rng.uniform(100.0, 220.0), 1))})
    return out


def _quiet_events(sc, g):
    """Per-event emission levels (dB, list) with ``n_quiet`` quiet events: those whose weakest array is
    most below the others (by :func:`early_snr_db`), emitted so that array's SNR is ``quiet_snr_db``
    (default 0 dB: it cannot detect the event; the others are 8-20 dB above it in the presets)."""
    snr = early_snr_db(validate_scenario({**sc, "event_level_db": None}))
    if not np.all(np.isfinite(snr)):
        return [0.0] * snr.shape[1]             # noise-free: no level makes an array miss a chirp
    srt = np.sort(snr, axis=0)
    gap = srt[1] - srt[0] if len(snr) > 1 else np.zeros(snr.shape[1])
    levels = np.zeros(snr.shape[1])
    for j in np.argsort(-gap)[:_int(g["n_quiet"], "n_quiet", 0)]:
        levels[j] = round(float(g["quiet_snr_db"]) - float(srt[0, j]), 2)
    return levels.tolist()


def early_snr_db(v):
    """(N, K) single-mic matched-filter SNR (dB) of each chirp's strongest early arrival at each array
    (validated scenario): the direct path WITHOUT any ``direct_db`` attenuation (an occluded array still
    hears the wall reflection right after it), emission levels included, over self-noise + diffuse noise."""
    lv = noise_levels(v)
    amp2 = np.stack([np.mean(x ** 2, axis=1) * 10 ** (-a["direct_db"] / 10)
                     for a, x in zip(v["arrays"], direct_amplitudes(v))]) * lv["gain"] ** 2
    energy = lv["p_chirp"] * v["chirp"]["duration"] * v["fs"] * 10 ** (v["event_level_db"] / 10)
    noise = lv["sigma"] ** 2 + lv["sigma_diff"] ** 2
    return 10 * np.log10(amp2 * energy / noise) if noise > 0 else np.full(amp2.shape, np.inf)


def load_scenario(path, **overrides):
    """A scenario from a TOML file (or a ``truth/manifest.json``) of overrides, then ``overrides``.

    The TOML holds top-level ``preset`` and ``seed`` plus any key of :func:`make_scenario`, e.g.::

        preset = "lab3"
        seed = 4
        rt60 = 0.4
        [chirp]
        duration = 0.2
        [[arrays]]              # optional: the full list of arrays
        name = "A1"
        position = [2.0, 2.0, 0.4]
        quat = [1.0, 0.0, 0.0, 0.0]
        tau = 0.3
        drift = 2e-5
    Errors name the file.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    try:
        if path.suffix == ".json":
            cfg = json.loads(read_text(path))
            cfg = cfg.get("scenario") if isinstance(cfg, dict) else None
            if not isinstance(cfg, dict):
                raise InputError(f"{path}: no 'scenario' object in the manifest")
        else:
            cfg = tomllib.loads(read_text(path))
    except (tomllib.TOMLDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise InputError(f"{path}: cannot parse ({' '.join(str(exc).split())})") from None
    cfg = {k: v for k, v in cfg.items() if k != "generator"} | (
        cfg.get("generator", {}) if isinstance(cfg.get("generator"), dict) else {})
    cfg = _merge(cfg, overrides)                # tables (chirp, priors) merge: --set chirp.kind keeps chirp.f0
    preset, seed = cfg.pop("preset", "paper-traj3"), cfg.pop("seed", 0)
    try:
        sc = make_scenario(preset, seed, **cfg)
        validate_scenario(sc)
    except InputError as exc:
        raise InputError(f"{path}: {str(exc).removeprefix('scenario: ')}") from None
    return sc

# ----------------------------------------------------------------------------------------------- simulate
def simulate(scenario: dict[str, Any], out_dir: str | Path, progress: Callable | None = None,
             overwrite: bool = False) -> Path:
    """Simulate a scenario and write a recording session (+ truth/) to ``out_dir``; returns its Path.

    Written (atomically: a failure leaves nothing): ``session.toml``, ``<array>.wav`` (n_samples,
    n_mics), ``chirp.wav`` (the emitted chirp sampled at fs from its start), ``events.csv`` (t_emit,
    odometry), ``truth/arrays.csv``, ``truth/sources.csv``, ``truth/manifest.json``.
    Noise: white Gaussian with variance ``P / 10^(snr/10)`` where ``P`` is the mean over arrays, mics and
    events of the direct-path chirp power at the mic; ``diffuse_snr`` (coherent pink) and ``hum_snr`` the
    same way. Signals are scaled so the largest direct-path amplitude is 0.25 (and the whole set never
    clips). Recordings are rendered emission by emission and streamed to the WAVs (bounded memory).
    progress : optional callback ``progress(done, total, message)``.
    """
    sc = validate_scenario(scenario)
    out_dir = Path(out_dir)
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())) and not overwrite:
        raise InputError(f"{out_dir}: exists and is not empty (use --force to replace it)")
    flat = _room_acoustics(sc) if sc["model"] == "flat" else (None, None)
    with atomic_dir(out_dir, command="calib simulate") as tmp:
        derived = render_session(sc, tmp, flat, progress=progress, zero_peak=_zero_peak_timestamp)
        _write_session(tmp, sc, derived, flat, scenario)
    return out_dir


def impulse_response(scenario, event, array):
    """The simulator's impulse response (M, L) from chirp ``event`` to array number ``array`` on that
    array's sample grid (unit emission; index ``n`` is ``n − builder_delay()`` samples after the emission)
    and the grid's true-time rate fs' (Hz): ``(h, fs')``."""
    sc = scenario if isinstance(scenario, Scenario) else validate_scenario(scenario)
    flat = _room_acoustics(sc) if sc["model"] == "flat" else (None, None)
    return simrender.impulse_response(sc, event, array, flat)


def _write_session(tmp, sc, derived, flat, scenario):
    """Everything but the recordings: chirp.wav, events.csv, session.toml, truth/ (+ manifest.json)."""
    fs, ch = sc["fs"], sc["chirp"]
    n_chirp = int(math.floor(ch["duration"] * fs)) + 1
    ref = chirp_signal(np.arange(n_chirp) / fs, ch)
    _write_wav(tmp / "chirp.wav", ref.astype(np.float32), fs, "FLOAT")

    odo = odometry(sc)
    ev = pd.DataFrame({"event": np.arange(len(sc["t_emit"])), "t_emit": sc["t_emit"],
                       "odom_x": odo[:, 0], "odom_y": odo[:, 1], "odom_z": odo[:, 2]})
    cols = EVENTS_COLS
    if sc.get("trajectory") is not None:       # a moving speaker: the robot's velocity at each sweep start
        vel = odometry_velocity(sc)
        ev[VEL_COLS] = vel
        cols = EVENTS_COLS + VEL_COLS
    write_table(ev, tmp / "events.csv", cols, float_format="%.9f")

    # [noise] holds what the "user" knows: the odometry noise the robot was simulated with, plus any
    # priors the scenario states. Invented TDOA/DOA priors would override the frontend's own estimates.
    priors = {**sc["priors"]}
    priors.setdefault("sigma_odo", sc["sigma_odo"] if sc["sigma_odo"] > 0 else 1e-3)
    chirp = {"f0": ch["f0"], "f1": ch["f1"], "duration": ch["duration"], "fade": ch["fade"]}
    if ch["kind"] != "linear":
        chirp["kind"] = ch["kind"]
    write_session_toml(
        tmp / "session.toml", speed_of_sound=sc["speed_of_sound"], reference_array=sc["reference_array"],
        chirp={**chirp, "reference": "chirp.wav"},
        arrays=[{"name": a["name"], "wav": f"{a['name']}.wav", "mics": a["mics"],
                 "doa_hemisphere": a["doa_hemisphere"]} for a in sc["arrays"]],
        noise={k: priors[k] for k in ("sigma_tdoa", "sigma_doa_deg", "sigma_odo") if k in priors})
    manifest = {
        "generator": "calib simulate (pipeline.simulate.roomsim)",
        "versions": {"numpy": np.__version__, "pyroomacoustics": _pra_version()},
        "frame": "room (origin at a room corner, axes along the walls); truth/*.csv are in the reference "
                 "array's frame",
        "clock_model": "L_i(t) = (1 + drift_i) (t - t_emit[0]) + tau_i; WAV sample n at L_i = n / fs",
        "scenario": jsonable(_public(scenario, sc)),
        "derived": _derived(sc, derived, flat),
    }
    extra = {"manifest.json": json.dumps(jsonable(manifest), indent=1, allow_nan=False) + "\n"}
    if sc["model"] == "bands":
        extra["los.csv"] = line_of_sight(sc).to_csv(index=False, float_format="%.6g", lineterminator="\n")
    if sc.get("trajectory") is not None:
        extra["trajectory.csv"] = trajectory_truth(sc).to_csv(index=False, float_format="%.9g",
                                                              lineterminator="\n")
    faulty = clocks.records(sc, sc.get("clock_faults"))
    if faulty:   # each faulty array's clock as a function of time (calib.clock.Clock JSON form)
        extra["clocks.json"] = json.dumps(jsonable(faulty), indent=1, allow_nan=False) + "\n"
    write_truth(tmp / "truth", scenario_truth(sc), extra_files=extra)


def _pra_version():
    import pyroomacoustics as pra

    return pra.__version__


def _derived(sc, derived, flat):
    """The manifest's ``derived`` section (keys of the ``bands`` model only when it is used)."""
    lv, rescale = derived["levels"], derived["rescale"]
    arrivals, mic_arr = arrival_times(sc), arrival_times(sc, mics=True)
    out = {"absorption": flat[0], "max_order": flat[1]} if sc["model"] == "flat" else {}
    out |= {
        "rir_builder_delay_samples": derived["delay"],
        "fractional_delay_length": FDL, "fractional_delay_length_late": FDL_LATE,
        "late_after_direct_s": EARLY}
    if sc["model"] == "flat":
        out["images_dropped_after_direct_s"] = sc["rt60"] or None
    out |= {
        "gain": lv["gain"] * rescale, "rescale": rescale,
        "sensor_noise_std": lv["sigma"] * rescale, "diffuse_noise_std": lv["sigma_diff"] * rescale,
        "direct_power_mean": lv["p_direct"] * rescale ** 2,
        "snr_definition": "10 log10(P / noise variance), P = mean over arrays, mics, events of the "
                          "direct-path chirp power at the mic",
        "n_samples": {a["name"]: int(n) for a, n in zip(sc["arrays"], derived["ends"])},
        "recording_start_true_time": {a["name"]: float(sc["t_emit"][0] - a["tau"] / (1 + a["drift"]))
                                      for a in sc["arrays"]},
        "arrival_times_origin": {a["name"]: arrivals[i].tolist() for i, a in enumerate(sc["arrays"])},
        "arrival_times_mics": {a["name"]: mic_arr[i].tolist() for i, a in enumerate(sc["arrays"])},
    }
    if sc["model"] == "bands":
        out |= _derived_bands(sc, lv, rescale)
    return out


def _derived_bands(sc, lv, rescale):
    ab = sc["acoustic"]
    amp = direct_amplitudes(sc)
    return {
        "band_centers_hz": list(ac.BAND_CENTERS),
        "wall_absorption": {w: ab["alpha"][k].tolist() for k, w in enumerate(ac.WALLS)},
        "air_attenuation_per_m": ab["air"].tolist(), "rt60_bands_s": ab["rt60_bands"].tolist(),
        "hum_std": lv["hum_std"] * rescale,
        "mic_gain_db": {a["name"]: a["mic_gain_db"].tolist() for a in sc["arrays"]},
        "source_axis": sc["source_axis"].tolist(),
        "direct_amplitude": {a["name"]: (lv["gain"] * rescale * x.mean(axis=1)
                                         * 10 ** (sc["event_level_db"] / 20)).tolist()
                             for a, x in zip(sc["arrays"], amp)},
        "early_snr_db": {a["name"]: x.tolist() for a, x in zip(sc["arrays"], early_snr_db(sc))},
    }


def _write_wav(path, data, fs, subtype):
    """soundfile WAV with the PEAK chunk's timestamp zeroed, so equal signals give equal bytes."""
    import soundfile as sf

    sf.write(path, data, fs, subtype=subtype, format="WAV")
    _zero_peak_timestamp(path)


def _zero_peak_timestamp(path):
    with open(path, "r+b") as f:
        f.seek(12)
        while True:
            head = f.read(8)
            if len(head) < 8:
                break
            size = int.from_bytes(head[4:], "little")
            if head[:4] == b"PEAK":
                f.seek(4, 1)                 # version, then the 4-byte timestamp
                f.write(b"\0\0\0\0")
                break
            f.seek(size + (size & 1), 1)


def _public(scenario, sc):
    """The scenario as given (room frame; exactly what reproduces these bytes), defaults filled in; keys
    of the realistic models that keep their default are left out (older manifests stay byte-identical)."""
    out = copy.deepcopy(dict(scenario))
    for k in ("snr", "diffuse_snr", "sigma_odo", "subtype", "tail", "priors", "reference_array", "interferers"):
        out.setdefault(k, sc[k])
    for k, v in NEW_SCENE_DEFAULTS.items():
        if k in out and _same(out[k], v):
            del out[k]
    if isinstance(out.get("generator"), dict):
        out["generator"] = {k: v for k, v in out["generator"].items()
                            if not (k in NEW_GEN_DEFAULTS and _same(v, NEW_GEN_DEFAULTS[k]))}
    return out


def _same(a, b):
    try:
        return a == b or (a is None and b is None)
    except ValueError:
        return False


__all__ = ["make_scenario", "load_scenario", "validate_scenario", "simulate", "arrival_times", "scenario_truth",
           "odometry", "chirp_signal", "circular_array", "local_time", "builder_delay", "impulse_response", "PRESETS"]

