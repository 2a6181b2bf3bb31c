"""A mic geometry declared too large or too small (issue 29): a planar or linear array's delays measure only the
in-plane (axial) part of a source's direction, times the array's size, so they cannot tell a geometry s × too
large from sources s × nearer the normal; the directions to the metric odometry's positions can
(``calib.pipeline.setupcheck.geometry_scale_fit``). A 3-D array's delays measure its size directly
(``calib.frontend.consistency.consensus``).

Fast: hand-made features (plane waves on known arrays, the frontend's SRP answer for a mis-scaled geometry
written analytically, noise). Slow: simulated rooms (3 seeds each of lab3, lab, mixed: circles, a 7-mic circle
with a centre mic, a linear board, a tetrahedron, a pair), each array declared too large and too small.
"""
from __future__ import annotations

import re

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation

from calib.frontend.consistency import consensus
from calib.frontend.doa import cone_vectors
from calib.pipeline.setupcheck import folder_findings, geometry_scale_fit, scale_findings

C = 343.0
CIRCLE = np.c_[0.0463 * np.cos(np.arange(6) * np.pi / 3), 0.0463 * np.sin(np.arange(6) * np.pi / 3), np.zeros(6)]
LINE = np.c_[np.arange(4) * 0.05 - 0.075, np.zeros(4), np.zeros(4)]
SIGMA_T, SIGMA_DOA_DEG, SIGMA_ODO = 2e-5, 1.5, 0.01


def _features(seed, mics, declared_scale, n=16):
    """Features of one array (plus a reference) seeing a two-height loop of ``n`` stops; its DOAs as the SRP of
    a geometry ``declared_scale`` × the true one reports them. Returns (features, the fraction of the sources
    whose projection the declared size clips at the horizon)."""
    rng = np.random.default_rng(seed)
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False) + rng.uniform(0, 0.3)
    odo = np.c_[1.0 + 0.9 * np.cos(ang), 1.0 + 0.7 * np.sin(ang), np.where(np.arange(n) < n // 2, 1.1, 0.7)]
    odo += rng.normal(0, 0.15, odo.shape) * [1, 1, 0]
    t_emit = np.cumsum(rng.uniform(0.8, 1.2, n))
    x = np.array([2.6, 2.2, 0.3]) + rng.normal(0, 0.2, 3)
    R = Rotation.from_rotvec(rng.normal(0, 0.25, 3)).as_matrix()  # roughly upright, as on a table
    d = odo + rng.normal(0, SIGMA_ODO, odo.shape) - x
    r = np.linalg.norm(d, axis=1)
    arr = 0.3 + (1 + 2e-5) * t_emit + r / C + rng.normal(0, SIGMA_T, n)
    v = (d / r[:, None]) @ R  # directions in the array frame
    v = Rotation.from_rotvec(rng.normal(0, np.radians(SIGMA_DOA_DEG), (n, 3))).apply(v)
    u = _measured(v, mics, declared_scale)
    proj = np.abs(v[:, 0]) if np.ptp(mics[:, 1]) == 0 else np.linalg.norm(v[:, :2], axis=1)
    ev = pd.DataFrame({"event": np.arange(n), "t_emit": t_emit, "odom_x": odo[:, 0] - odo[0, 0],
                       "odom_y": odo[:, 1] - odo[0, 1], "odom_z": odo[:, 2] - odo[0, 2]})
    ts = pd.DataFrame({"array": "A2", "from_event": np.arange(n - 1), "to_event": np.arange(1, n),
                       "tdoa": np.diff(arr), "flag": ""})
    doa = pd.DataFrame({"event": np.arange(n), "array": "A2", "ux": u[:, 0], "uy": u[:, 1], "uz": u[:, 2], "flag": ""})
    meta = {"speed_of_sound": C, "reference_array": "A1", "arrays": ["A1", "A2"], "sigma_tdoa": SIGMA_T,
            "sigma_doa_deg": SIGMA_DOA_DEG, "sigma_odo": SIGMA_ODO,
            "mics": {"A2": (np.asarray(mics) * declared_scale).tolist()}}
    feats = {"meta": meta, "events": ev, "tdoa_s": ts, "doa": doa, "tdoa_m": pd.DataFrame()}
    return feats, float(np.mean(proj > 0.98 * declared_scale))


def _measured(v, mics, s):
    """What SRP-PHAT reports with the geometry declared ``s`` × too large: the measured projection (in-plane,
    or on the axis) shrunk by ``s`` and clipped to the unit ball; the rest of the unit vector filled in."""
    if np.ptp(mics[:, 1]) == 0:  # linear along x
        return cone_vectors(np.array([1.0, 0, 0]), np.clip(v[:, 0] / s, -1, 1))
    m = v[:, :2] / s
    m /= np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1.0)
    return np.c_[m, np.sign(v[:, 2]) * np.sqrt(np.maximum(1 - np.sum(m**2, axis=1), 0))]


GRID = [pytest.param(seed, board, s, marks=[] if seed == 1 and s in (1.0, 1.3) else [pytest.mark.slow])
        for seed in (1, 2, 3) for board in ("circle", "line") for s in (0.7, 1.0, 1.3, 2.0)]


@pytest.mark.parametrize("seed, board, s", GRID)
def test_scale_fit_recovers_the_declared_scale(seed, board, s):
    mics = CIRCLE if board == "circle" else LINE
    feats, beyond = _features(seed, mics, s)
    fit = geometry_scale_fit(feats, "A2", np.asarray(mics) * s)
    if s < 1 and beyond >= 0.5:  # most sources beyond what the declared size can show: clipped at the horizon
        assert fit is None and scale_findings(feats) == []  # the delays' |w|·c > 1 tells (fit_geometry)
        return
    if s == 1.0:
        assert scale_findings(feats) == []
        assert fit is None or abs(np.log(fit[0])) < max(4 * fit[1], 0.03), fit
        return
    assert fit is not None
    got, sd, rms, rms1 = fit
    assert sd < 0.06 and abs(np.log(got / s)) < max(4 * sd, 0.03), (got, sd)
    found = scale_findings(feats)
    assert [(f.array, f.check) for f in found] == [("A2", "geometry scale")]
    assert ("larger" in found[0].text) == (s > 1)


def test_a_volume_array_is_left_to_its_delays():
    feats, _ = _features(1, CIRCLE + [[0, 0, 0.03]] * np.r_[0, 1, 0, 1, 0, 1][:, None], 1.3)
    assert geometry_scale_fit(feats, "A2", feats["meta"]["mics"]["A2"]) is None


def _circle_waves(seed):
    """12 plane waves from 3-34° above the plane of CIRCLE: elevations, the mic pairs, the pair delays (s)."""
    rng = np.random.default_rng(seed)
    az, el = rng.uniform(0, 2 * np.pi, 12), rng.uniform(0.05, 0.6, 12)
    u = np.c_[np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]
    t = -(u @ CIRCLE.T) / C + rng.normal(0, 2e-7, (12, 6))
    pairs = np.array([(m, n) for m in range(6) for n in range(m + 1, 6)])
    return el, pairs, t[:, pairs[:, 0]] - t[:, pairs[:, 1]]


def test_delays_of_a_planar_array_declared_too_small():
    """Plane waves from near a circle's plane on a geometry declared 0.7 × the true one: ``|w|·c`` above 1 (no
    plane wave gives that) in every event, and their consensus says 0.7; declared right: no event above 1."""
    from calib.frontend.consistency import PairDelays, fit_geometry

    el, pairs, tau = _circle_waves(29)
    d = PairDelays(pairs, tau, np.ones_like(tau), np.ones_like(tau), np.ones((12, 6)), np.zeros(6), [],
                   np.arange(12.0), 16000.0)
    small = fit_geometry(d, 0.7 * CIRCLE, C)
    assert small.support == 1.0 and abs(small.scale - 0.7) < 0.7 * (1 - np.cos(0.6)) + 0.01
    right = fit_geometry(d, CIRCLE, C)
    assert right.support == 0.0 and right.scale >= 1.0


@pytest.mark.parametrize("bent", [1, 2])
def test_one_reflected_event_does_not_make_a_planar_board_too_small(bent):
    """A clean reverberant room: one or two of 12 events whose delays a reflection stretched (|w|·c 1.9 on a
    circle declared right) are no evidence of a board declared too small; most of the events are (0.7 ×)."""
    from calib.frontend.consistency import PairDelays
    from calib.pipeline.setupcheck import geometry_findings

    el, pairs, tau = _circle_waves(31)
    tau[:bent] *= 1.9 / np.cos(el[:bent, None])    # in-plane |w|·c of those events: 1.9

    def delays(x):
        return PairDelays(pairs, x, np.ones_like(x), np.ones_like(x), np.ones((12, 6)), np.zeros(6), [],
                          np.arange(12.0), 16000.0)
    board = {"name": "A2", "mics": CIRCLE.tolist(), "wav": "A2.wav"}
    assert geometry_findings(board, delays(tau), C) == []
    small = geometry_findings({**board, "mics": (0.7 * CIRCLE).tolist()}, delays(tau), C)
    assert [f.check for f in small] == ["geometry scale"] and "smaller" in small[0].text


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_lone_high_events_do_not_make_a_planar_board_too_small(seed):
    """A board level with the speaker (sources 1-17° from its plane: |w|·c 0.96-1.0) in a noisy reverberant
    hall: about half its events read just above 1 and three read far above it, scattered (reflections): no
    finding, although most events are above 1; declared 0.75 × too small, the same events name it."""
    from calib.frontend.consistency import PairDelays
    from calib.pipeline.setupcheck import geometry_findings

    rng = np.random.default_rng(seed)
    az, el = rng.uniform(0, 2 * np.pi, 12), rng.uniform(0.02, 0.3, 12)
    u = np.c_[np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)]
    t = -(u @ CIRCLE.T) / C * rng.normal(1.02, 0.03, (12, 1))      # delays read ~2 % long, ±3 %
    pairs = np.array([(m, n) for m in range(6) for n in range(m + 1, 6)])
    tau = t[:, pairs[:, 0]] - t[:, pairs[:, 1]]
    tau[:3] *= np.array([[1.28], [1.63], [1.81]]) / np.cos(el[:3, None])   # three bent events, scattered
    d = PairDelays(pairs, tau, np.ones_like(tau), np.ones_like(tau), np.ones((12, 6)), np.zeros(6), [],
                   np.arange(12.0), 16000.0)
    board = {"name": "A2", "mics": CIRCLE.tolist(), "wav": "A2.wav"}
    assert geometry_findings(board, d, C) == []
    small = geometry_findings({**board, "mics": (0.75 * CIRCLE).tolist()}, d, C)
    assert [f.check for f in small] == ["geometry scale"] and "smaller" in small[0].text


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_board_most_of_whose_chirps_arrive_by_reflections_is_not_a_wrong_board(seed):
    """A circle that hears 3 of 12 chirps on the direct path and 9 as reflections (each pair delay bent at
    random, 20-60 % of the largest delay): the 3 fit its geometry, which a wrong board's would not: not failed,
    but suspect (its arrivals are doubtful). Declared as another board (the mics in another order), every chirp
    misfits: failed."""
    from calib.frontend.consistency import PairDelays
    from calib.pipeline.setupcheck import geometry_findings

    rng = np.random.default_rng(seed)
    el, pairs, tau = _circle_waves(40 + seed)
    span = np.max(np.abs(tau))
    tau[3:] += rng.choice([-1, 1], tau[3:].shape) * rng.uniform(0.2, 0.6, tau[3:].shape) * span
    d = PairDelays(pairs, tau, np.ones_like(tau), np.ones_like(tau), np.ones((12, 6)), np.zeros(6), [],
                   np.arange(12.0), 16000.0)
    board = {"name": "A2", "mics": CIRCLE.tolist(), "wav": "A2.wav"}
    assert [(f.status, f.check) for f in geometry_findings(board, d, C)] == [("suspect", "direct path")]
    other = {**board, "mics": CIRCLE[[0, 3, 1, 4, 2, 5]].tolist()}
    clean = PairDelays(pairs, _circle_waves(40 + seed)[2], np.ones_like(tau), np.ones_like(tau), np.ones((12, 6)),
                       np.zeros(6), [], np.arange(12.0), 16000.0)
    assert [f.status for f in geometry_findings(other, clean, C)] == ["failed"]


def test_supported_top_needs_company():
    from calib.frontend.consistency import supported_top

    assert np.isnan(supported_top([1.28, 1.63, 1.81]))
    assert supported_top([1.05, 1.1, 1.2, 1.22, 1.25, 1.9]) == 1.25   # the lone 1.9 spared
    assert np.isnan(supported_top([]))


def test_a_volume_board_s_scale_bound_widens_with_its_events_scatter():
    """A tetrahedron whose events read |w|·c 0.84-1.30 (a small board at a low rate in a reverberant hall: the
    consensus 1.17, beyond the clean bound 1.15) is not named, its events' scatter being 0.09; the same
    consensus with a clean scatter is, and so is a board declared twice too large in the noisy case."""
    from calib.frontend.consistency import PairDelays
    from calib.pipeline.setupcheck import geometry_findings

    tet = 0.02 * np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)
    rng = np.random.default_rng(7)
    u = rng.normal(size=(12, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    pairs = np.array([(m, n) for m in range(4) for n in range(m + 1, 4)])

    def found(wc, mics):
        t = -(u @ tet.T) / C * np.asarray(wc)[:, None]
        tau = t[:, pairs[:, 0]] - t[:, pairs[:, 1]]
        d = PairDelays(pairs, tau, np.ones_like(tau), np.ones_like(tau), np.ones((12, 4)), np.zeros(4), [],
                       np.arange(12.0), 16000.0)
        return geometry_findings({"name": "A3", "mics": mics.tolist(), "wav": "A3.wav"}, d, C)

    noisy = [0.84, 0.96, 1.04, 1.08, 1.11, 1.12, 1.15, 1.18, 1.19, 1.2, 1.25, 1.3]
    assert found(noisy, tet) == []
    clean = 1.17 * rng.normal(1.0, 0.005, 12)
    assert [f.check for f in found(clean, tet)] == ["geometry scale"]
    assert "larger" in found(noisy, 2 * tet)[0].text


def test_a_volume_board_s_events_that_point_away_from_its_doas_do_not_make_it_too_small():
    """A tetrahedron's delays fit any plane wave, so cross-terms of one mic's direct path with another's reflection
    show only as a wrong w: 7 of 16 events at |w|·c 1.50-1.54 pointing 40-90° from the frontend's DOAs (the other
    9 at 0.84-1.35 along them) read as a board 0.66× too small from the delays alone; with the DOAs, not. A board
    truly declared 0.66× too small (every event 1.5 along its DOA) is named with the DOAs too."""
    from calib.frontend.consistency import PairDelays
    from calib.pipeline.setupcheck import geometry_findings

    tet = 0.02 * np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)
    rng = np.random.default_rng(11)
    u = rng.normal(size=(16, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    pairs = np.array([(m, n) for m in range(4) for n in range(m + 1, 4)])
    bent = np.arange(16) >= 9                                          # the last 7 events
    axes = np.cross(u, rng.normal(size=(16, 3)))
    turn = Rotation.from_rotvec(axes / np.linalg.norm(axes, axis=1, keepdims=True)
                                * np.radians(rng.uniform(40, 90, 16))[:, None])
    w = np.where(bent[:, None], turn.apply(u), u)                      # the plane waves the delays say
    wc = np.r_[0.93, 1.01, 1.12, 0.95, 1.08, 1.10, 1.35, 0.84, 1.20, rng.uniform(1.50, 1.54, 7)]

    def found(w, wc, directions):
        t = -(w @ tet.T) / C * wc[:, None]
        tau = t[:, pairs[:, 0]] - t[:, pairs[:, 1]]
        d = PairDelays(pairs, tau, np.ones_like(tau), np.ones_like(tau), np.ones((16, 4)), np.zeros(4), [],
                       np.arange(16.0), 16000.0)
        return [f.check for f in geometry_findings({"name": "A9", "mics": tet.tolist(), "wav": "A9.wav"}, d, C,
                                                   directions=directions)]

    assert found(w, wc, None) == ["geometry scale"]                    # the delays alone: a false alarm
    assert found(w, wc, u) == []
    assert found(u, np.full(16, 1.5), u) == ["geometry scale"]         # a board truly too small


def test_consensus_ignores_the_events_a_reflection_bent():
    rng = np.random.default_rng(29)
    wc = np.r_[rng.normal(1 / 1.3, 0.005, 4), [1.15, 1.4, 1.9, 2.1, 2.7]]  # 5 of 9 events bent, scattered
    val, support = consensus(wc)
    assert abs(val * 1.3 - 1) < 0.01 and abs(support - 4 / 9) < 1e-9
    assert np.median(wc) * 1.3 > 1.4  # what a plain median would say


# ----------------------------------------------------------------------------------------------- slow: rooms
ROOMS = {"lab3": {"n_events": 10, "interval": 0.8, "chirp": {"duration": 0.2}},
         "lab": {"n_events": 10, "interval": 1.0, "chirp": {"duration": 0.2}},
         "mixed": {"n_stops": 10}}
FACTORS = (1.3, 2.0, 0.7)
MIN_CAUGHT = 0.8  # of the mis-scaled arrays (measured 96 % over every array × factor, bench_setup_scale.py)


@pytest.fixture(scope="module")
def rooms(tmp_path_factory):
    from calib.pipeline.simulate.roomsim import make_scenario, simulate

    root = tmp_path_factory.mktemp("rooms")
    return {(p, s): simulate(make_scenario(p, s, **kw), root / f"{p}_{s}")
            for p, kw in ROOMS.items() for s in (1, 2, 3)}


def _findings(folder, target=None, factor=1.0):
    from calib.pipeline.formats.session import read_session

    mics = {a["name"]: np.asarray(a["mics"], float) * factor for a in read_session(folder)["arrays"]
            if a["name"] == target}
    return folder_findings(folder, mics)


@pytest.mark.slow
@pytest.mark.parametrize("preset", list(ROOMS))
def test_mis_scaled_arrays_are_named_in_simulated_rooms(rooms, preset):
    """Each seed's arrays in turn, each factor in turn (array k gets FACTORS[(k + seed) % 3]): most are named,
    none other is, and the clean rooms raise nothing (a note, e.g. the 3-D boards' own speed of sound, is no
    alarm: it changes no verdict)."""
    from calib.pipeline.formats.session import read_session

    caught, total = 0, 0
    for seed in (1, 2, 3):
        folder = rooms[(preset, seed)]
        assert [f for f in _findings(folder) if f.status != "note"] == [], (preset, seed)
        for k, a in enumerate(read_session(folder)["arrays"]):
            f = FACTORS[(k + seed) % len(FACTORS)]
            found = _findings(folder, a["name"], f)
            assert all(x.array in (a["name"], None) for x in found), (preset, seed, a["name"], f, found)
            caught += any(x.array == a["name"] and x.status == "failed" for x in found)
            total += 1
    assert caught >= MIN_CAUGHT * total, f"{preset}: {caught}/{total}"


@pytest.mark.parametrize("seed", [41, 42])
def test_one_pair_off_is_not_a_channel_typo(seed):
    """A wall-mounted octahedron (hall, untuned seed 13): in most chirps the delay between the two mics on the
    wall's normal is off (a reflection), so leaving out either of them fits. No single mic's coordinates explain
    that: a note, not a failed channel. A 3 cm typo in one row still names that row (or the row opposite it,
    which the plane waves cannot tell from it)."""
    from calib.frontend.consistency import PairDelays
    from calib.pipeline.setupcheck import geometry_findings

    octa = 0.05 * np.vstack([np.eye(3), -np.eye(3)])
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(12, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    pairs = np.array([(m, n) for m in range(6) for n in range(m + 1, 6)])

    def delays(mics_true, bad_pair=None):
        t = -(u @ mics_true.T) / C + rng.normal(0, 2e-7, (12, 6))
        tau = t[:, pairs[:, 0]] - t[:, pairs[:, 1]]
        if bad_pair is not None:
            k = np.flatnonzero((pairs[:, 0] == bad_pair[0]) & (pairs[:, 1] == bad_pair[1]))[0]
            tau[:9, k] += rng.choice([-1, 1], 9) * rng.uniform(60e-6, 150e-6, 9)   # 9 of 12 chirps
        return PairDelays(pairs, tau, np.ones_like(tau), np.ones_like(tau), np.ones((12, 6)), np.zeros(6), [],
                          np.arange(12.0), 48000.0)

    board = {"name": "A2", "mics": octa.tolist(), "wav": "A2.wav"}
    found = geometry_findings(board, delays(octa, bad_pair=(2, 5)), C)
    assert [f.status for f in found] == ["note"] and "3 or 6" in found[0].text
    typo = octa.copy()
    typo[2, 0] += 0.03                      # row 3 as typed is 3 cm off the board's mic
    found = geometry_findings({**board, "mics": typo.tolist()}, delays(octa), C)
    assert [f.check for f in found] == ["channel geometry"]
    assert re.search(r"row 3 moved by \(-(2\.[89]|3\.[01]), [+-]0\.0, [+-]0\.0\) cm", found[0].text), found[0].text


@pytest.mark.parametrize("seed", [41, 42])
@pytest.mark.parametrize("centre", [False, True])
def test_one_mic_hearing_a_reflection_is_not_a_channel_typo(seed, centre):
    """A 6-mic circle (with or without a centre mic) whose mic 4 hears a reflection's path in 9 of 12 chirps,
    each late or early by its own 60-150 µs (moving seed 2's A3): leaving that mic out is the only fix, but no
    offset of its coordinates fits every chirp, so it is a note, not a failed channel; the same mic's row typed
    2 cm off is still named, with the offset that fits."""
    from calib.frontend.consistency import PairDelays
    from calib.pipeline.setupcheck import geometry_findings

    ang = np.arange(6) * np.pi / 3
    mics = np.c_[0.0463 * np.cos(ang), 0.0463 * np.sin(ang), np.zeros(6)]
    mics = np.vstack([mics, [[0.0, 0.0, 0.0]]]) if centre else mics
    m = len(mics)
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(12, 3))
    u[:, 2] = np.abs(u[:, 2])
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    pairs = np.array([(a, b) for a in range(m) for b in range(a + 1, m)])

    def delays(bent):
        t = -(u @ mics.T) / C + rng.normal(0, 2e-7, (12, m))
        t[:9, 3] += bent * rng.choice([-1, 1], 9) * rng.uniform(60e-6, 150e-6, 9)
        tau = t[:, pairs[:, 0]] - t[:, pairs[:, 1]]
        return PairDelays(pairs, tau, np.ones_like(tau), np.ones_like(tau), np.ones((12, m)), np.zeros(m), [],
                          np.arange(12.0), 48000.0)

    board = {"name": "A3", "mics": mics.tolist(), "wav": "A3.wav"}
    found = geometry_findings(board, delays(1.0), C)
    assert [f.status for f in found] == ["note"] and "without channel 4 they fit" in found[0].text
    typo = mics.copy()
    typo[3, 1] += 0.02
    found = geometry_findings({**board, "mics": typo.tolist()}, delays(0.0), C)
    assert [f.check for f in found] == ["channel geometry"] and "row 4" in found[0].text, [f.text for f in found]


def test_batch_lm_takes_the_least_norm_step_where_a_start_is_singular(monkeypatch):
    # the set-up check's batched LM: where LAPACK calls a start's damped normal matrix singular (CI's mixed room
    # did), the pseudo-inverse's least-norm step is taken and the fit still reaches the minimum
    from calib.pipeline import setupcheck

    target = np.array([1.0, -2.0])

    def f(X):   # r = x - target, J = I, per start
        return X - target, np.broadcast_to(np.eye(2), (len(X), 2, 2)).copy()

    real = np.linalg.solve

    def singular(a, b):
        raise np.linalg.LinAlgError("Singular matrix")

    monkeypatch.setattr(setupcheck.np.linalg, "solve", singular)
    X, cost = setupcheck._batch_lm(f, np.array([[0.0, 0.0], [5.0, 5.0]]))
    monkeypatch.setattr(setupcheck.np.linalg, "solve", real)
    np.testing.assert_allclose(X, [target, target], atol=1e-6)
    assert np.all(cost < 1e-12)
